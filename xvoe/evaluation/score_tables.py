"""Score files: a scores CSV read, checked and named, one row per test video.

A row holds `index, scenario, setting, pair, member, possible` and one or more score columns
(`score`, `s_img`, `s_dyn`, ...); with the scored split at hand only `index` and `score` are
needed, the labels joined from the split. Every refusal is one line naming the problem.
"""
from __future__ import annotations

import csv
import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import XvoeError
from ..scenes import store
from ..scenes.scenarios import SCENARIOS, TEST_SETTINGS

__all__ = ["REQUIRED", "SCORE_NAMES", "ScoreTable", "model_name", "model_name_problem", "read_columns",
           "read_scores", "score_problem", "scores_digest"]

REQUIRED = ("index", "scenario", "setting", "pair", "member", "possible")
# the settings a row may name: the test scenarios' (S1, S2, S3), a custom scenario's rows too
_SETTINGS = tuple(sorted({setting for _, setting in TEST_SETTINGS}))
SCORE_NAMES = ("score", "paper_score", "s_img", "s_dyn", "s_rec", "excess", "nll", "ess", "p_hidden", "p_two",
               "nll_excess")


def read_scores(path: str | Path, data: str | Path | None = None) -> dict[str, np.ndarray]:
    """A scores CSV as columns of numpy arrays, checked (`score_problem`). With `data`, the
    test split that was scored, the CSV needs only `index` and `score` (any other columns
    too): the labels are joined from the split, and labels the CSV carries must be the
    split's. Every refusal is one line naming the problem."""
    columns = read_columns(Path(path), ("index", "score") if data is not None else (*REQUIRED, "score"),
                            "" if data is not None else " (or give --data, the scored split, to join its labels)")
    if data is not None:
        columns = _join_labels(Path(path), columns, data)
    problem = score_problem(columns)
    if problem:
        raise XvoeError(f"{path}: {problem}")
    return columns


def read_columns(path: Path, needed: tuple[str, ...] = ("index", "score"), hint: str = "") -> dict[str, np.ndarray]:
    """A scores CSV's columns as read, each row's fields and the model's name checked, not yet
    the table as a whole (`score_problem`: a shard's part is not whole, and `xvoe verify` names
    an edited label by its row). UTF-8, with or without a byte-order mark."""
    if path.is_dir():
        raise XvoeError(f"{path} is a directory, not a scores file")
    if not path.is_file():
        raise XvoeError(f"{path}: no such file")
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            rows = list(csv.DictReader(handle))
    except (UnicodeDecodeError, csv.Error):
        raise XvoeError(f"{path} is not a CSV text file") from None
    if not rows or not rows[0]:
        raise XvoeError(f"{path} holds no scores")
    longer = next((number for number, row in enumerate(rows, 1) if None in row), None)
    if longer is not None:
        raise XvoeError(f"{path}: row {longer} (line {longer + 1}) has more fields than the header names")
    missing = [c for c in needed if c not in rows[0]]
    if missing:
        raise XvoeError(f"{path} is not a scores file: no column(s) {', '.join(missing)}{hint}")
    columns: dict[str, np.ndarray] = {}
    for name in rows[0]:
        values = [row[name] if row[name] is not None else "" for row in rows]
        if name in ("scenario", "setting", "model"):
            columns[name] = np.array(values)
        elif name == "possible":
            flags = [v.strip().lower() for v in values]
            unknown = sorted(set(flags) - {"1", "0", "true", "false"})
            if unknown:
                raise XvoeError(f"{path}: possible must be true or false, not {unknown[0]!r}")
            columns[name] = np.array([v in ("1", "true") for v in flags])
        else:
            try:
                columns[name] = np.array(values, dtype=float)
            except ValueError:
                if name in ("index", "pair", "member", "score"):
                    bad = next(v for v in values if not _is_number(v))
                    raise XvoeError(f"{path}: {name} holds {bad!r}, not a number") from None
                columns[name] = np.array(values)
    if "model" in columns:
        _check_one_model(path, columns["model"])
    return columns


def _check_one_model(path: Path, names: np.ndarray) -> None:
    """One model's scores per file, under a usable name (`model_name_problem`): two names in one
    file are refused rather than reported under the first (docs/decisions.md, "Models of
    your own")."""
    for number, name in enumerate(map(str, names), 1):
        problem = model_name_problem(name)
        if problem:
            raise XvoeError(f"{path}: row {number}'s model name {problem}")
        if name != names[0]:
            raise XvoeError(f"{path} holds the scores of two models, {str(names[0])!r} and {name!r} (row {number}); "
                            "give each model a file of its own")


def scores_digest(path: str | Path) -> str:
    """A digest of a scores CSV's columns as read (names, labels and values; not its bytes, so
    that a file saved again with a byte-order mark or other line ends keeps it), which its curves
    file records: curves beside another score file, or beside scores edited since, are told apart."""
    digest = hashlib.sha256()
    for name, values in read_columns(Path(path), ("index", "score")).items():
        digest.update(name.encode() + b"\0")
        if values.dtype.kind in "fb":
            digest.update(np.ascontiguousarray(values, dtype="<f8").tobytes())
        else:
            digest.update("\0".join(map(str, values)).encode() + b"\0")
    return digest.hexdigest()


@dataclass(frozen=True)
class ScoreTable:
    """A score file as `xvoe.score` returns it: its path (the table stands for it wherever a
    path is taken: `open`, `Path`, `xvoe.report`) and its columns as read, one row per video."""

    path: Path

    def __fspath__(self) -> str:
        return str(self.path)

    def __str__(self) -> str:
        return str(self.path)

    @property
    def columns(self) -> dict[str, np.ndarray]:
        """name -> (N,) values, as `read_scores` reads them (a shard's part too: not checked whole)."""
        return read_columns(self.path, ("index", "score"))

    @property
    def rows(self) -> list[dict]:
        """One dict per video, the columns' values as Python numbers (index, pair and member whole) and text."""
        columns = self.columns
        whole = {name for name in ("index", "pair", "member") if name in columns}
        return [{name: int(values[i]) if name in whole else values[i].item() for name, values in columns.items()}
                for i in range(len(columns["index"]))]


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _join_labels(path: Path, columns: dict[str, np.ndarray], data: str | Path) -> dict[str, np.ndarray]:
    """The split's labels for the CSV's rows; an error for an index outside the split, a
    missing video, or a label that differs from the split's (scores of another split)."""
    index = columns["index"]
    with store.open_dataset(data, split="test") as file:
        count = file["rgbd"].shape[0]
        labels = store.labels(file, REQUIRED[1:])
    if np.any(index != np.round(index)) or np.any(index < 0) or np.any(index >= count):
        raise XvoeError(f"{data} does not hold the videos these scores were made from: {path} names videos "
                        f"{int(index.min())}..{int(index.max())}, the split holds 0..{count - 1}")
    rows = index.astype(int)
    if len(np.unique(rows)) != len(rows):
        raise XvoeError(f"{path}: video {_first_duplicate(rows)} has more than one row")
    if len(rows) != count:
        absent = np.setdiff1d(np.arange(count), rows)
        raise XvoeError(f"{path} scores {len(rows)} of the {count} videos of {data} (video {absent[0]} is missing)")
    for name, values in labels.items():
        joined = values[rows]
        if name in columns and not np.array_equal(columns[name].astype(joined.dtype), joined):
            raise XvoeError(f"{data} does not hold the videos these scores were made from: the {name} labels "
                            f"of {path} differ")
        columns[name] = joined.astype(float) if name in ("pair", "member") else joined    # as read from a CSV
    return columns


def _first_duplicate(values: np.ndarray) -> int:
    found, counts = np.unique(values, return_counts=True)
    return int(found[counts > 1][0])


def score_problem(scores: dict[str, np.ndarray]) -> str | None:
    """What makes a scores table unusable by the metrics, in a few words, or None: indices
    whole and unique, finite numeric scores, members 0 and 1 of every pair exactly once,
    known settings."""
    index = scores["index"]
    if index.dtype.kind != "f" or np.any(index != np.round(index)):
        return "index must hold whole numbers"
    if len(np.unique(index)) != len(index):
        return f"video {_first_duplicate(index.astype(int))} has more than one row"
    for name in (c for c in scores if c in SCORE_NAMES):
        values = scores[name]
        if values.dtype.kind != "f":
            return f"{name} must hold numbers"
        if not np.all(np.isfinite(values)):
            return f"{name} of video {int(index[np.flatnonzero(~np.isfinite(values))[0]])} is not a finite number"
    unknown = sorted(set(scores["scenario"]) - set(SCENARIOS) - {"custom"})
    if unknown:
        return f"unknown scenario {unknown[0]!r} (the scenarios are {', '.join(SCENARIOS)}, and custom)"
    unknown = sorted(set(scores["setting"]) - set(_SETTINGS))
    if unknown:
        return f"unknown setting {unknown[0]!r} (the settings are {', '.join(_SETTINGS)})"
    members = scores["member"]
    if members.dtype.kind != "f" or not set(np.unique(members)) <= {0.0, 1.0}:
        return "member must be 0 or 1"
    keys = list(zip(scores["scenario"], scores["setting"], scores["pair"], members))
    if len(set(keys)) != len(keys):
        return "a pair holds the same member twice"
    groups: dict[tuple, int] = {}
    for scenario, setting, pair, _ in keys:
        groups[scenario, setting, pair] = groups.get((scenario, setting, pair), 0) + 1
    lonely = next((group for group, size in groups.items() if size != 2), None)
    if lonely is not None:
        return f"{lonely[0]} {lonely[1]} pair {int(lonely[2])} has one member; every pair needs both"
    return None


def model_name_problem(name: str) -> str | None:
    """What makes `name` unusable as a model's name, in a few words, or None: a name is a CSV
    field, a line of a report and part of its figures' file names (components-NAME.png), so it
    is one line of printable text, not empty, with no path separator."""
    if not name.strip():
        return "is empty"
    if not name.isprintable():
        return f"holds a control character ({name!r}); a name is one line of printable text"
    if "/" in name or "\\" in name:
        return f"holds a path separator ({name!r}); a name is part of a report's file names"
    return None


def model_name(path: str | Path, scores: dict[str, np.ndarray]) -> str:
    """The `model` column of a scores file if it has one, else the file's name."""
    if "model" in scores and len(scores["model"]):
        return str(scores["model"][0])
    return Path(path).stem
