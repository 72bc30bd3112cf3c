"""notebooks/cruise_control_walkthrough.ipynb executes as it stands (nbclient)."""

from pathlib import Path

import pytest

from ampc_jax.testing.budget import budget

pytestmark = pytest.mark.timeout(300)

NOTEBOOK = Path(__file__).parents[2] / "notebooks" / "cruise_control_walkthrough.ipynb"


def test_walkthrough_notebook_executes(tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")

    nb = nbformat.read(NOTEBOOK, as_version=4)
    # its first code cell sets XLA_FLAGS and x64 before any other import
    first = next(c for c in nb.cells if c.cell_type == "code").source
    assert first.startswith("import os\n") and "XLA_FLAGS" in first
    assert first.index("jax_enable_x64") < first.index("from ampc_jax")
    # run where its figures may be written (notebook_output/ in the working directory)
    nbclient.NotebookClient(nb, timeout=budget(240), kernel_name="python3").execute(
        cwd=str(tmp_path)
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notebook_output"]  # nothing else
    text = "".join(
        o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
    )
    assert "e_sub_p95" in text and "yaw_rms_focus" in text
    figures = sorted(p.name for p in (tmp_path / "notebook_output" / "walkthrough").glob("*.png"))
    assert figures == [
        "convergence.png",
        "vehicle_response.png",
        "wheel_torques.png",
        "yaw_error.png",
    ]
