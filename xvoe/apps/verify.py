"""`xvoe verify`: does a score file hold what its model gives? A seeded sample of its rows is
scored again, by the model and on the split its header names, and compared with the file.

A number in a paper made with xvoe can so be checked later: the header says what to load
(xvoe.evaluation.score, `score_header`), and the hashes say whether it is still the same. A
header decides only which weights are read, never which code runs: a model of your own is
loaded from the `model` its user names, and its file's hash must be the one recorded.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from xvoe.inference.score import NLLColumns

from ..benchmark import store
from ..errors import XvoeError
from ..evaluation.metrics import read_scores
from ..evaluation.score import (
    CURVES,
    check_same_split,
    check_scored_by,
    curves_arrays,
    load_model,
    names_code,
    row_columns,
    score_header,
    score_rows,
)
from ..identity import split_identity
from ..models.config import from_dict, to_dict
from ..models.nll import InferenceConfig

# a video scored alone against the batch it was scored in: the float sums differ in the last digits
TOLERANCE = {"rtol": 1e-4, "atol": 1e-6}


@dataclass
class Verification:
    """What `verify` found: a line per video rescored, and whether every one matched."""

    lines: list[str] = field(default_factory=list)
    matches: bool = True


def verify(path: str | Path, rows: int = 5, data: str | Path | None = None, seed: int = 0,
           model: str | None = None) -> Verification:
    """Score again `rows` rows (drawn from `seed`) of a scores file, or of every scores file a
    report of `xvoe metrics` names (its headers.json), and compare them with the file, values
    and per-frame curves, within `TOLERANCE`. `data`: the split, where it is not where the
    header says it was read from. `model`: the model to score with (as `xvoe score --model`
    takes it), which a model of your own needs: a header never names code to run."""
    path = Path(path)
    found = Verification()
    for scores in _scores_files(path):
        _verify_file(scores, rows, data, seed, model, found)
    return found


def _scores_files(path: Path) -> list[Path]:
    """A scores file, or the scores files a report directory's headers.json names."""
    if not path.is_dir():
        return [path]
    headers = path / "headers.json"
    if not headers.is_file():
        raise XvoeError(f"{path} holds no headers.json: give a scores file or a report of xvoe metrics")
    return [Path(entry["scores"]) for entry in json.loads(headers.read_text())]


def _verify_file(path: Path, rows: int, data: str | Path | None, seed: int, model: str | None,
                 found: Verification) -> None:
    header = score_header(path)
    if "split" not in header or "model_identity" not in header:
        raise XvoeError(f"{path} does not record the model and split it was made with (an older xvoe's, or made "
                        "elsewhere): rescore it with this xvoe to verify it")
    source = model or header["model_identity"].get("source")
    if not isinstance(source, str):
        raise XvoeError(f"{path} was scored by a model made in memory: name it with --model to verify the file")
    if model is None and names_code(source):
        raise XvoeError(f"{path} was scored by a model of your own, {source}; verify runs no code a file names: "
                        "pass --model with the model you trust")
    data = data or header["data"]
    table = read_scores(path)
    scorer = load_model(source)
    check_scored_by(path, scorer)
    extra = _extra_columns(header)
    if extra is not None:
        extra.check(scorer)
    picked = np.sort(np.random.default_rng(seed).choice(len(table["index"]), min(rows, len(table["index"])),
                                                        replace=False))
    saved = curves_arrays(path.with_suffix(".curves.npz"))
    with store.open_dataset(data, split="test") as file:
        check_same_split(path, split_identity(file), data)
        for row in picked:
            video = int(table["index"][row])
            curves, added, extra_curves = score_rows(scorer, file, video, video + 1, 1, extra)
            again = row_columns(scorer, curves, added, header["aggregate"], extra, header["score"])
            again |= {f"curve {name}": curves[i, 0] for i, name in enumerate(CURVES) if name in saved}
            again |= {f"curve {name}": values[0] for name, values in extra_curves.items() if name in saved}
            held = {name: table[name][row] for name in again if name in table}
            held |= {name: saved[name.removeprefix("curve ")][row] for name in again if name.startswith("curve ")}
            differ = [name for name in held if not np.allclose(held[name], again[name], **TOLERANCE)]
            found.matches &= not differ
            found.lines.append(f"{path.name} video {video}: " + ("matches" if not differ else "differs in " + ", ".join(
                f"{name} ({_shown(held[name])} in the file, {_shown(again[name])} scored again)" for name in differ)))


def _extra_columns(header: dict) -> NLLColumns | None:
    """The NLL's columns with the settings and seed the file was made with, if it has them."""
    if "nll" not in header:
        return None
    settings = to_dict(from_dict(InferenceConfig, header["nll"]))
    return NLLColumns(None, header["nll_seed"], settings)


def _shown(value) -> str:
    value = np.asarray(value, dtype=float)
    return f"{float(value):.6g}" if value.ndim == 0 else "[" + ", ".join(f"{v:.4g}" for v in value) + "]"
