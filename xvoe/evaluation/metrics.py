"""The paper's metrics over surprise scores, with 95% intervals and the counts they rest on.

Scores are one row per test video (`index, scenario, setting, pair, member, possible` and
one or more score columns: `score`, `s_img`, `s_dyn`, ...). A higher score means more
surprise. s+ is an impossible video's score, s- a possible one's; a tie counts one half.
`score` is the default verdict; `paper_score`, where a file has it, the paper's score (always
Transformer 2's proposal), measured beside it under its own column name.

- comparative, per setting: over pairs, 1[s(member 1) > s(member 0)]. Ideal: 1 for S1 and
  S3 (member 1 is the impossible one), 0.5 for S2 (both possible). With it, `p`: the
  permutation test's p-value that it differs from 50% (resampling.chance_p).
- holistic, per scenario: over all (impossible, possible) pairs of videos of the scenario,
  1[s+ > s-]: the ROC AUC of the score as a detector of impossible videos, the Mann-Whitney
  U statistic over n+ n-.
- relative: each video against the mean score of the S1 pair of its scenario and pair index
  (the same scene in every setting): judged impossible when above it. Accuracy per setting.

Intervals: the comparative and relative metrics and the onset's timely share are shares of
pairs (videos for the relative one), with Wilson's interval (resampling.wilson), right for a
few pairs and at 0% or 100%. The holistic AUC, whose comparisons share videos, gets the wider
of a bootstrap interval that resamples pair indices (the unit the settings of a scenario
share; resampling.interval, seeded) and Wilson's over the pairs it rests on, so that four
pairs never give an interval of zero width. Every row says how many units it rests on (`count`).
"""
from __future__ import annotations

import csv
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from ..errors import XvoeError
from ..scenes import store
from ..scenes.scenarios import SCENARIOS
from .resampling import chance_p, interval, pairwise_win, wilson

REQUIRED = ("index", "scenario", "setting", "pair", "member", "possible")
SCORE_NAMES = ("score", "paper_score", "s_img", "s_dyn", "s_rec", "excess", "nll", "ess", "p_hidden", "p_two",
               "nll_excess")
IDEAL_COMPARATIVE = {"S1": 1.0, "S2": 0.5, "S3": 1.0}


@dataclass
class Estimate:
    value: float
    low: float
    high: float
    p: float = float("nan")     # comparative only: the p-value that the accuracy differs from 50%
    count: int = 0              # the units it rests on: pairs (videos for the relative metric)


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
    file are refused rather than reported under the first (docs/decisions.md, "One model per
    score file")."""
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
    unknown = sorted(set(scores["setting"]) - set(IDEAL_COMPARATIVE))
    if unknown:
        return f"unknown setting {unknown[0]!r} (the settings are S1, S2, S3)"
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


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """P(s+ > s-) + P(s+ = s-)/2: the Mann-Whitney U of s+ over n+ n-, counted by binary search
    in the sorted s- (scipy's rankdata gives the same U at ten times the cost per call, and the
    bootstrap calls this a thousand times per scenario)."""
    positive, negative = np.asarray(positive, float), np.asarray(negative, float)
    if len(positive) == 0 or len(negative) == 0:
        return float("nan")
    ordered = np.sort(negative)
    below, not_above = np.searchsorted(ordered, positive, "left"), np.searchsorted(ordered, positive, "right")
    u = below.sum() + 0.5 * (not_above - below).sum()
    return float(u / (len(positive) * len(negative)))


def pairs_table(scores: dict[str, np.ndarray], scenario: str, setting: str, column: str):
    """Scores of member 0 and member 1 by pair index, for one setting."""
    mask = (scores["scenario"] == scenario) & (scores["setting"] == setting)
    pair, member, value = scores["pair"][mask].astype(int), scores["member"][mask].astype(int), scores[column][mask]
    first = {p: v for p, m, v in zip(pair, member, value) if m == 0}
    second = {p: v for p, m, v in zip(pair, member, value) if m == 1}
    common = sorted(set(first) & set(second))
    return np.array(common), np.array([first[p] for p in common]), np.array([second[p] for p in common])


def comparative(scores: dict[str, np.ndarray], column: str = "score", rounds: int = 1000,
                seed: int = 0) -> dict[tuple[str, str], Estimate]:
    """Per setting: the share of pairs whose member 1 is more surprising than member 0, and
    the p-value that it differs from 50% (`rounds` permutations from `seed`)."""
    out = {}
    for scenario, setting in _settings(scores):
        _, first, second = pairs_table(scores, scenario, setting, column)
        found = _share(pairwise_win(second, first))
        found.p = chance_p(first, second, rounds, seed)
        out[scenario, setting] = found
    return out


def holistic(scores: dict[str, np.ndarray], column: str = "score", rounds: int = 1000,
             seed: int = 0) -> dict[str, Estimate]:
    """Per scenario: the AUC of impossible against possible videos, resampling pair indices."""
    out = {}
    for scenario in _unique(scores["scenario"]):
        mask = scores["scenario"] == scenario
        out[scenario] = _auc_by_unit(scores[column][mask], scores["possible"][mask], scores["pair"][mask],
                                     rounds, seed)
    return out


def relative(scores: dict[str, np.ndarray], column: str = "score", rounds: int = 1000,
             seed: int = 0) -> dict[tuple[str, str], Estimate]:
    """Per setting: videos judged impossible when their score is above the mean of the S1 pair
    of the same scenario and pair index; the share judged rightly."""
    out = {}
    for scenario, setting in _settings(scores):
        right, _, _ = _relative_right(scores, scenario, setting, column)
        out[scenario, setting] = _share(right)
    return out


# the reference's relative metric, one row per member of S2 and S3 (utils/metrix_ds.py): each the
# share of one block of videos judged rightly against its S1 pair's mean; `relative` is their mean
OFFICIAL_RELATIVE = {("S2", 0): "S2-ext1", ("S2", 1): "S2-ext2", ("S3", 0): "S3-ext", ("S3", 1): "S3-sur"}


def relative_members(scores: dict[str, np.ndarray], column: str = "score") -> dict[tuple[str, str], Estimate]:
    """The reference's relative sub-rows: per scenario and OFFICIAL_RELATIVE name, the share of
    that member's videos judged rightly against the mean of their S1 pair."""
    out = {}
    for scenario, setting in _settings(scores):
        right, _, member = _relative_right(scores, scenario, setting, column)
        for which in (0, 1):
            name = OFFICIAL_RELATIVE.get((setting, which))
            if name is not None:
                out[scenario, name] = _share(right[member == which])
    return out


def _relative_right(scores: dict[str, np.ndarray], scenario: str, setting: str,
                    column: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each video of a setting whose S1 pair is scored: 1 if judged rightly against the S1
    pair's mean (a tie one half), with its pair index and member."""
    pairs_s1, first, second = pairs_table(scores, scenario, "S1", column)
    threshold = dict(zip(pairs_s1, first / 2 + second / 2))    # halved first: 1e308 + 1e308 overflows
    mask = (scores["scenario"] == scenario) & (scores["setting"] == setting)
    pair, member = scores["pair"][mask].astype(int), scores["member"][mask].astype(int)
    known = np.array([p in threshold for p in pair], dtype=bool)
    value, possible, pair, member = scores[column][mask][known], scores["possible"][mask][known], pair[known], \
        member[known]
    limit = np.array([threshold[p] for p in pair])
    right = np.where(possible, pairwise_win(limit, value), pairwise_win(value, limit))
    return right, pair, member


def _share(values: np.ndarray) -> Estimate:
    """The share of units judged rightly (`values` 1, 0 or one half for a tie), with Wilson's
    interval over their count."""
    if len(values) == 0:
        return Estimate(float("nan"), float("nan"), float("nan"))
    return Estimate(float(values.mean()), *wilson(float(values.sum()), len(values)), count=len(values))


def _auc_by_unit(values: np.ndarray, possible: np.ndarray, unit: np.ndarray, rounds: int, seed: int) -> Estimate:
    """AUC of impossible against possible videos, with the wider of a bootstrap interval over
    units and Wilson's over their count (a bootstrap of four units is often of zero width)."""
    units, slot = np.unique(unit, return_inverse=True)
    by_unit = np.argsort(slot, kind="stable")
    bounds = np.searchsorted(slot[by_unit], np.arange(len(units) + 1))

    def statistic(chosen: np.ndarray) -> float:
        starts, sizes = bounds[chosen], bounds[chosen + 1] - bounds[chosen]
        offsets = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        rows = by_unit[np.repeat(starts, sizes) + offsets]
        return auc(values[rows][~possible[rows]], values[rows][possible[rows]])

    value = auc(values[~possible], values[possible])
    low, high = interval(statistic, len(units), rounds, seed)
    floor, ceiling = wilson(value * len(units), len(units))
    return Estimate(value, min(low, floor), max(high, ceiling), count=len(units))


def _unique(values: np.ndarray) -> list[str]:
    """Distinct values in order of first appearance."""
    seen: dict[str, None] = {}
    for v in values:
        seen.setdefault(str(v), None)
    return list(seen)


def _settings(scores: dict[str, np.ndarray]) -> list[tuple[str, str]]:
    """(scenario, setting) keys in order of first appearance."""
    keys = _unique(np.array([f"{a}/{b}" for a, b in zip(scores["scenario"], scores["setting"])]))
    return [tuple(key.split("/")) for key in keys]


METRICS = ("comparative", "holistic", "relative")
COMPONENTS = ("score", "paper_score", "s_img", "s_dyn", "excess", "nll", "nll_excess")    # each where scored

Curve = TypeVar("Curve")    # numpy arrays or torch tensors


def excess(s_img: Curve, s_dyn: Curve, s_rec: Curve) -> Curve:
    """Per-frame surprise beyond the perception's reconstruction of what it saw: s_img - s_rec
    + s_dyn (the `excess` component). Here, without torch, so that curves saved by `xvoe score`
    use it as the scorer does."""
    return s_img - s_rec + s_dyn


def metric_rows(scores: dict[str, np.ndarray], model: str, columns: tuple[str, ...] = COMPONENTS,
                rounds: int = 1000, seed: int = 0) -> list[dict]:
    """Every metric of one model's scores as flat rows (one per metric, column and group)."""
    rows = []
    for column in (c for c in columns if c in scores):
        for (scenario, setting), estimate in comparative(scores, column, rounds, seed).items():
            rows.append(_row(model, "comparative", column, scenario, setting, estimate, IDEAL_COMPARATIVE[setting]))
        for scenario, estimate in holistic(scores, column, rounds, seed).items():
            rows.append(_row(model, "holistic", column, scenario, "", estimate, 1.0))
        for (scenario, setting), estimate in relative(scores, column, rounds, seed).items():
            rows.append(_row(model, "relative", column, scenario, setting, estimate, 1.0))
    return rows


def _row(model, metric, column, scenario, setting, estimate: Estimate, ideal: float) -> dict:
    return {"model": model, "metric": metric, "column": column, "scenario": scenario, "setting": setting,
            "value": estimate.value, "low": estimate.low, "high": estimate.high, "count": estimate.count,
            "ideal": ideal, "p": estimate.p}


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


# --- two score columns compared (surprise definitions, or verdicts) ------------------------

SURPRISES = ("score", "nll")     # the MSE score (`xvoe score --surprise both`) and the NLL
VERDICTS = ("score", "paper_score")     # the default verdict and the paper's score, where a file has both


def disagreement_fields(columns: tuple[str, str] = SURPRISES) -> tuple[str, ...]:
    """The columns of `disagreements` between two score columns, named after them."""
    a, b = columns
    return ("scenario", "setting", "pair", "index_0", "index_1", f"{a}_0", f"{a}_1", f"{b}_0", f"{b}_1",
            f"{a}_says", f"{b}_says", "right")


DISAGREEMENT_FIELDS = disagreement_fields()


def has_both_surprises(scores: dict[str, np.ndarray], columns: tuple[str, str] = SURPRISES) -> bool:
    """True when the scores hold both columns and they differ (with `--surprise nll` the score
    column is the NLL itself; a model with no choice of explanation writes its score twice)."""
    return all(c in scores for c in columns) and not np.array_equal(scores[columns[0]], scores[columns[1]])


TIE_TOLERANCE = 1e-3     # members whose scores differ by less than this share of the larger are too close to call


def verdict(first: np.ndarray, second: np.ndarray, tolerance: float = 0.0) -> np.ndarray:
    """Which member of each pair a score finds more surprising: 1, 0, or -1 on a tie, which
    within `tolerance` (a share of the larger magnitude of the two) includes near ties."""
    close = np.abs(second - first) <= tolerance * np.maximum(np.abs(first), np.abs(second))
    return np.where(close, -1, np.where(second > first, 1, 0))


def disagreements(scores: dict[str, np.ndarray], columns: tuple[str, str] = SURPRISES) -> list[dict]:
    """Per setting, the pairs in which two surprise columns pick different members as the more
    surprising one, each by more than TIE_TOLERANCE (787.3 against 787.5 nats picks no member:
    such a pair is no disagreement); `right` names the column that picked the impossible member,
    where a pair holds one (S1, S3), "" in S2."""
    a, b = columns
    rows = []
    for scenario, setting in _settings(scores):
        pairs, index_0, index_1 = pairs_table(scores, scenario, setting, "index")
        _, a_0, a_1 = pairs_table(scores, scenario, setting, a)
        _, b_0, b_1 = pairs_table(scores, scenario, setting, b)
        _, possible_0, possible_1 = pairs_table(scores, scenario, setting, "possible")
        says_a, says_b = verdict(a_0, a_1, TIE_TOLERANCE), verdict(b_0, b_1, TIE_TOLERANCE)
        truth = np.where(possible_0 == possible_1, -2, np.where(possible_0, 1, 0))    # -2: no right answer
        for i in np.flatnonzero((says_a != says_b) & (says_a >= 0) & (says_b >= 0)):
            right = "" if truth[i] == -2 else a if says_a[i] == truth[i] else b
            rows.append(dict(zip(disagreement_fields(columns), (
                scenario, setting, int(pairs[i]), int(index_0[i]), int(index_1[i]), float(a_0[i]), float(a_1[i]),
                float(b_0[i]), float(b_1[i]), _said(says_a[i]), _said(says_b[i]), right))))
    return rows


def _said(value: int) -> str:
    return "tie" if value < 0 else f"member {value}"


def side_by_side(scores: dict[str, np.ndarray], rows: list[dict], model: str,
                 columns: tuple[str, str] = SURPRISES) -> list[dict]:
    """Every metric of one model under the two surprise columns, one row per metric and group,
    with the difference (second minus first) and, per setting, how many pairs they judge
    differently."""
    a, b = columns
    index = {(r["metric"], r["scenario"], r["setting"], r["column"]): r for r in rows if r["model"] == model}
    differ: dict[tuple[str, str], int] = {}
    for row in disagreements(scores, columns):
        differ[row["scenario"], row["setting"]] = differ.get((row["scenario"], row["setting"]), 0) + 1
    table = []
    for (metric, scenario, setting, column), first in index.items():
        second = index.get((metric, scenario, setting, b))
        if column != a or second is None:
            continue
        pairs = len(pairs_table(scores, scenario, setting, a)[0]) if setting else ""
        table.append({"model": model, "metric": metric, "scenario": scenario, "setting": setting,
                      a: first["value"], f"{a}_low": first["low"], f"{a}_high": first["high"],
                      b: second["value"], f"{b}_low": second["low"], f"{b}_high": second["high"],
                      "difference": second["value"] - first["value"], "ideal": first["ideal"],
                      "pairs": pairs, "disagreeing_pairs": differ.get((scenario, setting), 0) if setting else ""})
    return table


# --- violation onset: is the model surprised at the right moment? ------------------------------

ONSET_SHARE = 0.1       # of the peak difference: where the surprise "rises"
ONSET_FIELDS = ("model", "surprise", "scenario", "setting", "pairs", "timely", "timely_low", "timely_high",
                "median_peak_offset")


def onset_pairs(scores: dict[str, np.ndarray], per_frame: np.ndarray, event_frame: np.ndarray) -> list[dict]:
    """For every S1/S3 pair with an event frame: the impossible member's per-frame surprise less
    the possible one's (rows of `per_frame` (N, T) follow the scores' rows; `event_frame` by
    row too); `timely`, whether that difference first rises above a tenth of its peak at or
    after the event frame; `peak_offset`, how many frames after it the difference peaks
    (negative: before)."""
    found = []
    for scenario, setting in _settings(scores):
        if setting not in ("S1", "S3"):
            continue
        mask = (scores["scenario"] == scenario) & (scores["setting"] == setting)
        rows = np.flatnonzero(mask)
        by_pair: dict[int, dict[bool, int]] = {}
        for row in rows:
            by_pair.setdefault(int(scores["pair"][row]), {})[bool(scores["possible"][row])] = row
        for pair, members in sorted(by_pair.items()):
            if set(members) != {True, False} or event_frame[members[False]] < 0:
                continue
            event = int(event_frame[members[False]])
            difference = per_frame[members[False]] - per_frame[members[True]]
            # a rise is a tenth of the peak: a model that reads the whole video (as Transformer 1
            # does) differs a little before the event in every pair, which is no verdict
            positive = np.flatnonzero(difference > ONSET_SHARE * difference.max()) if difference.max() > 0 \
                else np.array([], dtype=int)
            found.append({"scenario": scenario, "setting": setting, "pair": pair, "event_frame": event,
                          "first_positive": int(positive[0]) if len(positive) else -1,
                          "timely": bool(len(positive) and positive[0] >= event),
                          "peak_offset": int(np.argmax(difference)) - event})
    return found


def onset(scores: dict[str, np.ndarray], per_frame: np.ndarray, event_frame: np.ndarray, model: str,
          rounds: int = 1000, seed: int = 0, surprise: str = "mse") -> list[dict]:
    """Per S1/S3 setting: the share of pairs whose surprise rises at or after the event (with a
    Wilson interval over pairs) and the median frame of its peak after the event. surprise:
    the definition whose curves `per_frame` are ("mse": s_img + s_dyn; "nll": -log p(x_t | x_<t))."""
    pairs = onset_pairs(scores, per_frame, event_frame)
    rows = []
    for scenario, setting in dict.fromkeys((p["scenario"], p["setting"]) for p in pairs):
        chosen = [p for p in pairs if (p["scenario"], p["setting"]) == (scenario, setting)]
        timely = np.array([p["timely"] for p in chosen], dtype=float)
        estimate = _share(timely)
        rows.append(dict(zip(ONSET_FIELDS, (model, surprise, scenario, setting, len(chosen), estimate.value,
                                            estimate.low, estimate.high,
                                            float(np.median([p["peak_offset"] for p in chosen]))))))
    return rows
