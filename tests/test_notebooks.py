"""The notebooks run top to bottom (nbclient), with their smallest parameters.

Each notebook's first code cell is tagged `parameters`; a cell inserted after it overrides
them (as papermill does), so the notebooks run here on one pair per setting with few
particles and bootstrap rounds. The kernel is this Python's (`python3`), started in a
temporary directory where the notebooks write their files.
"""
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

from xvoe.apps import zoo

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
SMALLEST = {
    "01_explanations.ipynb": "PAIRS = 1\nPARTICLES = 8",
    "02_surprise_definitions.ipynb": "PAIRS = 1\nPARTICLES = 4\nROUNDS = 50",
    "03_teaching_voe.ipynb": "PAIRS = 1\nROUNDS = 50",
}


def test_every_notebook_is_tested():
    assert sorted(p.name for p in NOTEBOOKS.glob("*.ipynb")) == sorted(SMALLEST)


@pytest.mark.parametrize("name", sorted(SMALLEST))
def test_notebook_is_stored_without_outputs(name):
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    nbformat.validate(notebook)
    for cell in notebook.cells:
        if cell.cell_type == "code":
            assert not cell.outputs and cell.execution_count is None, cell.source[:60]
    assert "parameters" in next(c for c in notebook.cells if c.cell_type == "code").metadata.get("tags", [])


@pytest.mark.parametrize("name", sorted(SMALLEST))
def test_notebook_runs_top_to_bottom(name, tmp_path, monkeypatch):
    assert "xpl" in zoo.available_models(), "the notebooks need xvoe/weights/xpl.pt (xvoe ship RUN_DIR)"
    monkeypatch.setenv("OMP_NUM_THREADS", "1")       # the kernel inherits it: one core per notebook
    monkeypatch.setenv("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    first = next(i for i, c in enumerate(notebook.cells) if "parameters" in c.metadata.get("tags", []))
    notebook.cells.insert(first + 1, nbformat.v4.new_code_cell(SMALLEST[name]))
    client = NotebookClient(notebook, timeout=240, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}})
    try:
        client.execute()
    except CellExecutionError as error:
        pytest.fail(f"{name} failed in a cell:\n{error}", pytrace=False)
    errors = [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs if o.output_type == "error"]
    assert not errors
    assert (tmp_path / "notebook-data" / "test.h5").is_file()
