"""`xvoe verify`: does a score file hold what its model gives? Every row is checked against the
curves stored beside it (they reduce to its scores, so this costs nothing) and its labels
against the split's; then a seeded sample of its rows is scored again, by the model and on the
split its header names, and compared with the file. An edit of any row is so named.

A number in a paper made with xvoe can so be checked later: the header says what to load
(xvoe.evaluation.score_headers, `score_header`), and the hashes say whether it is still the same. A
header decides only which weights are read, never which code runs: a model of your own is
loaded from the `model` its user names, and its file's hash must be the one recorded.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from xvoe.inference.score import NLLRun, nll_run

from ..errors import XvoeError
from ..evaluation.score_curves import curve_columns
from ..evaluation.score_headers import check_same_split, check_scored_by, curves_arrays, score_header, scored_nll
from ..evaluation.score_tables import read_columns, scores_digest
from ..evaluation.scorer import Scorer, load_model, names_code
from ..fingerprints import split_identity
from ..models.config import to_dict
from ..scenes import store
from .verbs import score_batch, score_columns

__all__ = ["Verification", "verify"]

# a video scored alone against the batch it was scored in: the float sums differ in the last digits
TOLERANCE = {"rtol": 1e-4, "atol": 1e-6}
# a column against the curves it was summed from when written: the same numbers, summed again
STORED = {"rtol": 1e-9, "atol": 0.0}
SHOWN = 3           # rows named of those whose values or labels differ


@dataclass
class Verification:
    """What `verify` found: a line per video rescored, and whether every one matched."""

    lines: list[str] = field(default_factory=list)
    matches: bool = True


def verify(path: str | Path, rows: int = 5, data: str | Path | None = None, seed: int = 0,
           model: str | None = None) -> Verification:
    """Check every row of a scores file, or of every scores file a report of `xvoe metrics` names
    (its headers.json), against its stored curves and the split's labels (`_check_rows`), then
    score again `rows` rows (drawn from `seed`) and compare them with the file, values and
    per-frame curves, within `TOLERANCE`. `data`: the split, where it is not where the
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
    header = score_header(path, check=False)       # edited scores are named row by row below
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
    table = read_columns(path)
    scorer = load_model(source)
    check_scored_by(path, scorer, header)
    nll = _nll_run(path, header, scorer)
    picked = np.sort(np.random.default_rng(seed).choice(len(table["index"]), min(rows, len(table["index"])),
                                                        replace=False))
    saved = curves_arrays(path.with_suffix(".curves.npz"))
    with store.open_dataset(data, split="test") as file:
        check_same_split(path, split_identity(file), data, header)
        _check_rows(path, table, saved, header, store.labels(file, REQUIRED_LABELS), found)
        for row in picked:
            video = int(table["index"][row])
            curves, values = score_batch(scorer, file, video, video + 1, nll)
            again = score_columns(scorer, curves, values, header["aggregate"], header["score"], nll,
                                  file["rgbd"].shape[2])
            again |= {f"curve {name}": curve[0] for name, curve in curves.items() if name in saved}
            held = {name: table[name][row] for name in again if name in table}
            held |= {name: saved[name.removeprefix("curve ")][row] for name in again if name.startswith("curve ")}
            differ = [name for name in held if not np.allclose(held[name], again[name], **TOLERANCE)]
            found.matches &= not differ
            found.lines.append(f"{path.name} video {video}: " + ("matches" if not differ else "differs in " + ", ".join(
                f"{name} ({_shown(held[name])} in the file, {_shown(again[name])} scored again)" for name in differ)))


REQUIRED_LABELS = ("scenario", "setting", "pair", "member", "possible")


def _check_rows(path: Path, table: dict[str, np.ndarray], saved: dict[str, np.ndarray], header: dict,
                labels: dict[str, np.ndarray], found: Verification) -> None:
    """Every row of a scores file against what it was written from: its values against the
    columns its curves reduce to (`_stored_columns`), its model against the header's, its labels
    against the split's video of its index; one line, naming the first rows that differ. Scores
    that match all these but not the digest the curves record were edited in a column the
    curves do not hold (the NLL's): said too."""
    index = table["index"].astype(int)
    if index.min() < 0 or index.max() >= len(labels["pair"]):
        raise XvoeError(f"{path} names videos {index.min()}..{index.max()}, which its split does not hold")
    expected = {name: values for name, values in _stored_columns(saved, header).items() if name in table}
    expected |= {name: values[index] for name, values in labels.items() if name in table}
    if "model" in table and "model" in header:
        expected["model"] = np.full(len(index), header["model"])
    differ = np.zeros(len(index), bool)
    for name, values in expected.items():
        same = np.isclose(table[name], values, **STORED) if values.dtype.kind == "f" else table[name] == values
        differ |= ~same
    rows = np.flatnonzero(differ)
    found.matches &= not len(rows)
    recorded = header.get("scores_digest")
    if len(rows):
        named = "; ".join(f"row {row + 1} (video {index[row]}): {_differences(table, expected, row)}"
                          for row in rows[:SHOWN])
        more = f" (and {len(rows) - SHOWN} more rows)" if len(rows) > SHOWN else ""
        found.lines.append(f"{path.name}: {len(rows)} of {len(index)} rows differ from what was written: {named}{more}")
    elif recorded is not None and recorded != scores_digest(path):
        found.matches = False
        found.lines.append(f"{path.name}: the scores differ from those the curves were written with, in a column "
                           "the curves do not hold")
    else:
        found.lines.append(f"{path.name}: all {len(index)} rows match their curves and the split's labels")


def _differences(table: dict[str, np.ndarray], expected: dict[str, np.ndarray], row: int) -> str:
    """What of one row differs from what was written, value by value."""
    return ", ".join(f"{name} {_value(table[name][row])} in the file, {_value(values[row])} written"
                     for name, values in expected.items() if _differ(table[name][row], values[row]))


def _differ(held, written) -> bool:
    """Whether one value of a row differs from the value written (numbers within `STORED`)."""
    try:
        return not np.isclose(float(held), float(written), **STORED)
    except (TypeError, ValueError):
        return str(held) != str(written)


def _value(value) -> str:
    return _shown(value) if isinstance(value, (float, np.floating)) else repr(str(value))


def _stored_columns(saved: dict[str, np.ndarray], header: dict) -> dict[str, np.ndarray]:
    """The columns of a score file that its stored curves (`curves_arrays`) reduce to, as they were
    written (`curve_columns`, by the aggregation its header records), and nll, -log p(video), the
    sum of its curve whatever the aggregation (the SMC's; importance sampling stores none); score
    is the header's score column. The NLL's other columns are not sums of curves: rescored."""
    curves = {name: values for name, values in saved.items() if name != "header"}
    own = header.get("curve") if header.get("curve") in curves else None
    found = curve_columns(curves, header.get("aggregate", "sum"), own)
    if "nll" in curves:
        found["nll"] = np.asarray(curves["nll"], float).sum(axis=1)
    score = header.get("score", "score")
    if score != "score":
        found.pop("score", None)
        if score in found:
            found["score"] = found[score]
    return found


def _nll_run(path: Path, header: dict, scorer: Scorer) -> NLLRun | None:
    """The NLL's settings and seed as the file was made with them (each checked as `--nll-set`
    would be), if it has the NLL's columns."""
    if "nll" not in header:
        return None
    return nll_run(scorer, None, header["nll_seed"], to_dict(scored_nll(path, header)))


def _shown(value) -> str:
    value = np.asarray(value, dtype=float)
    return f"{float(value):.6g}" if value.ndim == 0 else "[" + ", ".join(f"{v:.4g}" for v in value) + "]"
