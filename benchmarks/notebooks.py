"""How long each notebook takes run fresh at its defaults, and whether it shows a red box.

    python benchmarks/notebooks.py [--only 02_surprise_definitions.ipynb] [--save] [--timeout 900]

Runs every notebook in notebooks/ top to bottom in a new kernel (nbclient, as
tests/test_notebooks.py does, but with the notebooks' own parameters), in the notebooks'
folder, so that their files go where a user's would (notebooks/notebook-data/). Prints per
notebook its wall time and its count of error outputs and stderr outputs (a red box in
Jupyter); the design's goal is 0 of either and <= 2 minutes each on 2 idle cores. --save
writes each notebook back with the outputs of this run, for a reader without a kernel.
Last line: NAME=SECONDSs stderr=N errors=N, per notebook.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient
from nbclient.exceptions import CellExecutionError

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"


def run(path: Path, timeout: int) -> tuple[nbformat.NotebookNode, float, list[str]]:
    """The notebook at `path` executed in its folder, its wall time in seconds, and the problem
    that stopped it, if one did."""
    notebook = nbformat.read(path, as_version=4)
    client = NotebookClient(notebook, timeout=timeout, kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}})
    start = time.perf_counter()
    stopped = []
    try:
        client.execute()
    except CellExecutionError as error:
        stopped.append(str(error).splitlines()[0])
    return notebook, time.perf_counter() - start, stopped


def red_boxes(notebook: nbformat.NotebookNode) -> tuple[int, int]:
    """(stderr outputs, error outputs) of an executed notebook's code cells."""
    outputs = [o for cell in notebook.cells if cell.cell_type == "code" for o in cell.outputs]
    return (sum(o.output_type == "stream" and o.name == "stderr" for o in outputs),
            sum(o.output_type == "error" for o in outputs))


def coalesced(notebook: nbformat.NotebookNode) -> nbformat.NotebookNode:
    """The notebook with each cell's consecutive stream outputs of one name joined, and a line
    redrawn with carriage returns (a progress bar) kept as last drawn, as Jupyter shows them."""
    for cell in (c for c in notebook.cells if c.cell_type == "code"):
        joined: list = []
        for output in cell.outputs:
            if (output.output_type == "stream" and joined and joined[-1].output_type == "stream"
                    and joined[-1].name == output.name):
                joined[-1].text += output.text
            else:
                joined.append(output)
        for output in joined:
            if output.output_type == "stream":
                output.text = "\n".join(line.rstrip("\r").rsplit("\r", 1)[-1] for line in output.text.split("\n"))
        cell.outputs = joined
    return notebook


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--only", action="append", help="a notebook's file name (default: all)")
    parser.add_argument("--save", action="store_true", help="write each notebook back with this run's outputs")
    parser.add_argument("--timeout", type=int, default=900, help="seconds a cell may take")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")       # the kernel inherits it
    os.environ.setdefault("MPLBACKEND", "module://matplotlib_inline.backend_inline")
    paths = [NOTEBOOKS / name for name in args.only] if args.only else sorted(NOTEBOOKS.glob("*.ipynb"))
    summary = []
    for path in paths:
        notebook, seconds, stopped = run(path, args.timeout)
        stderr, errors = red_boxes(notebook)
        print(f"{path.name}: {seconds:.0f} s, {stderr} stderr outputs, {errors} errors"
              + (f"; stopped: {stopped[0]}" if stopped else ""), flush=True)
        if args.save and not stopped:
            nbformat.write(coalesced(notebook), path)
        summary.append(f"{path.stem}={seconds:.0f}s stderr={stderr} errors={errors}")
    print(" ".join(summary))


if __name__ == "__main__":
    main()
