"""Every notebook writes its files into ``notebook_output/`` of its working
directory (beside the notebook when Jupyter runs it), and git ignores that folder
there, so running a notebook leaves no untracked files in ``notebooks/``."""

import json
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(60)

ROOT = Path(__file__).parents[2]
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


def _code(path: Path) -> str:
    nb = json.loads(path.read_text())
    return "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_notebook_writes_under_notebook_output(path):
    code = _code(path)
    assert 'Path("notebook_output") / ' in code
    # no other relative output folder: every Path(...) literal is the output root
    literals = {part.split(")")[0] for part in code.split("Path(")[1:] if part.startswith('"')}
    assert literals == {'"notebook_output"'}, literals


def test_git_ignores_notebook_output_beside_the_notebooks():
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    probe = ["notebooks/notebook_output/walkthrough/convergence.png", "notebook_output/x"]
    res = subprocess.run(
        ["git", "check-ignore", "--no-index", *probe], cwd=ROOT, capture_output=True, text=True
    )
    assert res.stdout.split() == probe, res
