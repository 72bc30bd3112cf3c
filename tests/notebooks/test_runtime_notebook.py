"""notebooks/runtime_over_the_bus.ipynb executes as it stands (nbclient), on a 6 s run."""

import os
from pathlib import Path

import pytest

from ampc_jax.testing.budget import budget

# a closed loop, a simulation and a replay (about a minute): `pytest -m slow`
pytestmark = [pytest.mark.timeout(300), pytest.mark.both_cores, pytest.mark.slow]

ROOT = Path(__file__).parents[2]
NOTEBOOK = ROOT / "notebooks" / "runtime_over_the_bus.ipynb"


def test_runtime_notebook_executes(tmp_path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")

    nb = nbformat.read(NOTEBOOK, as_version=4)
    first = next(c for c in nb.cells if c.cell_type == "code").source
    assert first.startswith("import os\n") and "XLA_FLAGS" in first
    monkeypatch.setenv("AMPC_NOTEBOOK_RUN_SECONDS", "6")
    monkeypatch.setenv("PYTHONPATH", str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    nbclient.NotebookClient(nb, timeout=budget(240), kernel_name="python3").execute(
        cwd=str(tmp_path)
    )
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    # (no missed deadline is the end-to-end test's check, under real-time priority)
    assert "'misses':" in text and "identical bit for bit" in text
    assert "speed RMS difference" in text
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notebook_output"]  # nothing else
    out = tmp_path / "notebook_output" / "runtime"
    figures = sorted(p.name for p in (out / "figures").glob("*.png"))
    assert figures == ["response.png", "tick_timing.png"]
