"""notebooks/sweeps_and_tuning.ipynb executes as it stands (nbclient): a small
sweep on two CPU devices, a tuning run, the tuned file in a closed loop."""

from pathlib import Path

import pytest

from ampc_jax.testing.budget import budget

pytestmark = [pytest.mark.timeout(400), pytest.mark.slow, pytest.mark.both_cores]

NOTEBOOK = Path(__file__).parents[2] / "notebooks" / "sweeps_and_tuning.ipynb"


def test_sweeps_notebook_executes(tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(NOTEBOOK, as_version=4)
    first = next(c for c in nb.cells if c.cell_type == "code").source
    assert first.index("XLA_FLAGS") < first.index("import jax")
    nbclient.NotebookClient(nb, timeout=budget(300), kernel_name="python3").execute(
        cwd=str(tmp_path)
    )
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "2700 rows" in text and "tuned rho scales" in text and "eq.opt_ro" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notebook_output"]  # nothing else
    out = tmp_path / "notebook_output" / "sweeps_and_tuning"
    for name in ("sweep/iterations_vs_rho.png", "sweep/best_rho.png", "loss.png", "params.json"):
        assert (out / name).exists(), name
