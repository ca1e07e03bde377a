"""The notebooks run top to bottom (executed, not just parsed)."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))
#: Notebooks that take a minute or more beyond what the default run covers (a shared real recording fitted;
#: the learning API, which tests/test_functional.py checks): run with ``-m extended``. The quickstart runs by default.
SLOW = {"joint_angles.ipynb", "learning_through_the_fit.ipynb"}


@pytest.mark.parametrize(
    "path", [pytest.param(p, marks=pytest.mark.extended) if p.name in SLOW else p for p in NOTEBOOKS],
    ids=[p.name for p in NOTEBOOKS],
)
def test_notebook_executes(path, tmp_path):
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors


def test_there_is_a_quickstart():
    assert any(p.name == "quickstart.ipynb" for p in NOTEBOOKS)
