"""The notebooks run top to bottom (nbclient), with their smallest parameters, with no error
and nothing on stderr (a red box in Jupyter), and are stored with the outputs of a clean run.

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


STORED_BYTES = 3_000_000     # the saved outputs (figures, one player) of a notebook at its defaults


def red_boxes(notebook) -> list:
    """The outputs Jupyter draws red: errors and anything written to stderr."""
    return [o for c in notebook.cells if c.cell_type == "code" for o in c.outputs
            if o.output_type == "error" or (o.output_type == "stream" and o.name == "stderr")]


@pytest.mark.parametrize("name", sorted(SMALLEST))
def test_notebook_is_stored_run_and_clean(name):
    """Stored with the outputs of a run at its defaults (`python benchmarks/notebooks.py
    --save`), for a reader without a kernel: every code cell run in order, no red box."""
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    nbformat.validate(notebook)
    code = [c for c in notebook.cells if c.cell_type == "code"]
    assert [c.execution_count for c in code] == list(range(1, len(code) + 1))
    assert not red_boxes(notebook)
    assert (NOTEBOOKS / name).stat().st_size < STORED_BYTES
    assert "parameters" in code[0].metadata.get("tags", [])


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
    assert not red_boxes(notebook), [o.get("text", o.get("ename"))[:200] for o in red_boxes(notebook)]
    assert (tmp_path / "notebook-data" / "test.h5").is_file()
