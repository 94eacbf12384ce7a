"""The paper's metrics over surprise scores, with bootstrap 95% intervals.

Scores are one row per test video (`index, scenario, setting, pair, member, possible` and
one or more score columns: `score`, `s_img`, `s_dyn`, ...). A higher score means more
surprise. s+ is an impossible video's score, s- a possible one's; a tie counts one half.

- comparative, per setting: over pairs, 1[s(member 1) > s(member 0)]. Ideal: 1 for S1 and
  S3 (member 1 is the impossible one), 0.5 for S2 (both possible).
- holistic, per scenario: over all (impossible, possible) pairs of videos of the scenario,
  1[s+ > s-]: the ROC AUC of the score as a detector of impossible videos.
- relative: each video against the mean score of the S1 pair of its scenario and pair index
  (the same scene in every setting): judged impossible when above it. Accuracy per setting.

Intervals resample pair indices with replacement (the unit that the settings of a scenario
share), from a seeded generator.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

from ..errors import XvoeError

REQUIRED = ("index", "scenario", "setting", "pair", "member", "possible")
IDEAL_COMPARATIVE = {"S1": 1.0, "S2": 0.5, "S3": 1.0}


@dataclass
class Estimate:
    value: float
    low: float
    high: float


def read_scores(path: str | Path) -> dict[str, np.ndarray]:
    """A scores CSV as columns of numpy arrays; refuses a file without the label columns."""
    path = Path(path)
    if not path.is_file():
        raise XvoeError(f"{path}: no such file")
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    if not rows:
        raise XvoeError(f"{path} holds no scores")
    missing = [c for c in REQUIRED if c not in rows[0]]
    if missing:
        raise XvoeError(f"{path} is not a scores file: no column(s) {', '.join(missing)}")
    columns: dict[str, np.ndarray] = {}
    for name in rows[0]:
        values = [row[name] for row in rows]
        if name in ("scenario", "setting", "model"):
            columns[name] = np.array(values)
        elif name == "possible":
            columns[name] = np.array([v.strip().lower() in ("1", "true") for v in values])
        else:
            try:
                columns[name] = np.array(values, dtype=float)
            except ValueError:
                columns[name] = np.array(values)
    return columns


def pairwise_win(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """1 where a > b, 0.5 where equal, 0 where below."""
    return (a > b) + 0.5 * (a == b)


def auc(positive: np.ndarray, negative: np.ndarray) -> float:
    """P(s+ > s-) + P(s+ = s-)/2 from ranks (Mann-Whitney U, ties given average ranks)."""
    positive, negative = np.asarray(positive, float), np.asarray(negative, float)
    if len(positive) == 0 or len(negative) == 0:
        return float("nan")
    values = np.concatenate([positive, negative])
    order = np.argsort(values, kind="mergesort")
    sorted_values = values[order]
    # each run of equal values gets the average of its ranks
    run = np.cumsum(np.r_[True, sorted_values[1:] != sorted_values[:-1]]) - 1
    average = np.bincount(run, np.arange(1, len(values) + 1)) / np.bincount(run)
    ranks = np.empty(len(values))
    ranks[order] = average[run]
    u = ranks[: len(positive)].sum() - len(positive) * (len(positive) + 1) / 2.0
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
    """Per setting: the share of pairs whose member 1 is more surprising than member 0."""
    out = {}
    for scenario, setting in _settings(scores):
        _, first, second = pairs_table(scores, scenario, setting, column)
        out[scenario, setting] = _mean_by_unit(pairwise_win(second, first), np.arange(len(first)), rounds, seed)
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
        pairs_s1, first, second = pairs_table(scores, scenario, "S1", column)
        threshold = dict(zip(pairs_s1, (first + second) / 2))
        mask = (scores["scenario"] == scenario) & (scores["setting"] == setting)
        pair = scores["pair"][mask].astype(int)
        known = np.array([p in threshold for p in pair], dtype=bool)
        value, possible, pair = scores[column][mask][known], scores["possible"][mask][known], pair[known]
        limit = np.array([threshold[p] for p in pair])
        right = np.where(possible, pairwise_win(limit, value), pairwise_win(value, limit))
        out[scenario, setting] = _mean_by_unit(right, pair, rounds, seed)
    return out


def _mean_by_unit(values: np.ndarray, unit: np.ndarray, rounds: int, seed: int) -> Estimate:
    """Mean of `values`, with an interval from resampling the units they belong to."""
    if len(values) == 0:
        return Estimate(float("nan"), float("nan"), float("nan"))
    units, slot = np.unique(unit, return_inverse=True)
    total, count = np.bincount(slot, values, len(units)), np.bincount(slot, minlength=len(units))
    low, high = _bootstrap(lambda chosen: total[chosen].sum() / count[chosen].sum(), len(units), rounds, seed)
    return Estimate(float(values.mean()), low, high)


def _auc_by_unit(values: np.ndarray, possible: np.ndarray, unit: np.ndarray, rounds: int, seed: int) -> Estimate:
    """AUC of impossible against possible videos, with an interval from resampling units."""
    units, slot = np.unique(unit, return_inverse=True)
    by_unit = np.argsort(slot, kind="stable")
    bounds = np.searchsorted(slot[by_unit], np.arange(len(units) + 1))

    def statistic(chosen: np.ndarray) -> float:
        starts, sizes = bounds[chosen], bounds[chosen + 1] - bounds[chosen]
        offsets = np.arange(sizes.sum()) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        rows = by_unit[np.repeat(starts, sizes) + offsets]
        return auc(values[rows][~possible[rows]], values[rows][possible[rows]])

    return Estimate(auc(values[~possible], values[possible]), *_bootstrap(statistic, len(units), rounds, seed))


def _bootstrap(statistic, units: int, rounds: int, seed: int) -> tuple[float, float]:
    """95% percentile interval of statistic(a resample of range(units) with replacement)."""
    rng = np.random.default_rng(seed)
    draws = [statistic(rng.integers(0, units, units)) for _ in range(rounds)]
    low, high = np.nanpercentile(draws, [2.5, 97.5])
    return float(low), float(high)


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
COMPONENTS = ("score", "s_img", "s_dyn", "excess", "nll", "nll_excess")    # the last three: when scored

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
            "value": estimate.value, "low": estimate.low, "high": estimate.high, "ideal": ideal}


def model_name(path: str | Path, scores: dict[str, np.ndarray]) -> str:
    """The `model` column of a scores file if it has one, else the file's name."""
    if "model" in scores and len(scores["model"]):
        return str(scores["model"][0])
    return Path(path).stem


# --- the two surprise definitions, compared -------------------------------------------------

SURPRISES = ("score", "nll")     # the MSE score (`xvoe score --surprise both`) and the NLL
DISAGREEMENT_FIELDS = ("scenario", "setting", "pair", "index_0", "index_1", "score_0", "score_1", "nll_0", "nll_1",
                       "score_says", "nll_says", "right")


def has_both_surprises(scores: dict[str, np.ndarray]) -> bool:
    """True when the scores hold the MSE score and the NLL as two different columns (with
    `--surprise nll` the score column is the NLL itself)."""
    return all(c in scores for c in SURPRISES) and not np.array_equal(scores["score"], scores["nll"])


def verdict(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Which member of each pair a score finds more surprising: 1, 0, or -1 on a tie."""
    return np.where(second > first, 1, np.where(first > second, 0, -1))


def disagreements(scores: dict[str, np.ndarray], columns: tuple[str, str] = SURPRISES) -> list[dict]:
    """Per setting, the pairs whose verdict (which member is more surprising) differs between
    two surprise columns; `right` names the column that picked the impossible member, where
    a pair holds one (S1, S3), "neither" when both missed it (a tie), "" in S2."""
    a, b = columns
    rows = []
    for scenario, setting in _settings(scores):
        pairs, index_0, index_1 = pairs_table(scores, scenario, setting, "index")
        _, a_0, a_1 = pairs_table(scores, scenario, setting, a)
        _, b_0, b_1 = pairs_table(scores, scenario, setting, b)
        _, possible_0, possible_1 = pairs_table(scores, scenario, setting, "possible")
        says_a, says_b = verdict(a_0, a_1), verdict(b_0, b_1)
        truth = np.where(possible_0 == possible_1, -2, np.where(possible_0, 1, 0))    # -2: no right answer
        for i in np.flatnonzero(says_a != says_b):
            right = "" if truth[i] == -2 else a if says_a[i] == truth[i] else b if says_b[i] == truth[i] else "neither"
            rows.append(dict(zip(DISAGREEMENT_FIELDS, (
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
