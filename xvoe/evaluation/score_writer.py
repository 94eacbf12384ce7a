"""Writing a score file and its curves as one result: the CSV of one row per video, and the
per-frame curves beside it (.curves.npz) with the header that records how they were made and
the digest of the scores written. The CSV, which names the curves, is renamed into place last.
"""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from ..outputs import atomic_paths
from .score_curves import LABEL_COLUMNS
from .score_tables import scores_digest

__all__ = ["score_lines", "write_score_files"]


def score_lines(model: str, labels: dict[str, np.ndarray], first: int, columns: dict[str, np.ndarray]) -> str:
    """The CSV text of videos first.. of a split: a row each of its index, `model`, its `labels`
    (scenario, setting, pair, member, possible: the split's whole columns) and the `columns` (N,)."""
    text = io.StringIO(newline="")
    writer = csv.writer(text)
    writer.writerow(LABEL_COLUMNS + tuple(columns))
    for row in range(len(next(iter(columns.values())))):
        i = first + row
        writer.writerow([i, model, labels["scenario"][i], labels["setting"][i], int(labels["pair"][i]),
                         int(labels["member"][i]), bool(labels["possible"][i])]
                        + [float(values[row]) for values in columns.values()])
    return text.getvalue()


def write_score_files(out: Path, curves_path: Path, text: str, header: dict, curves: dict[str, np.ndarray]) -> None:
    """The CSV `text` at `out` and, at `curves_path`, the `curves` by name with `header` and the
    digest of the CSV as written; both appear together or neither does."""
    with atomic_paths(curves_path, out) as (curves_tmp, tmp):
        with open(tmp, "w", newline="") as handle:
            handle.write(text)
        header = header | {"scores_digest": scores_digest(tmp)}
        with open(curves_tmp, "wb") as curves_file:
            np.savez_compressed(curves_file, header=np.array(json.dumps(header, sort_keys=True)), **curves)
