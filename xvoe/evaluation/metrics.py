"""The paper's metrics over surprise scores, with 95% intervals and the counts they rest on.

Scores are one row per test video (`index, scenario, setting, pair, member, possible` and
one or more score columns: `score`, `s_img`, `s_dyn`, ...), read and checked by
`score_tables`. A higher score means more surprise. s+ is an impossible video's score, s- a
possible one's; a tie counts one half.
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

from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from .resampling import chance_p, interval, pairwise_win, wilson

__all__ = ["COMPONENTS", "IDEAL_COMPARATIVE", "METRICS", "OFFICIAL_RELATIVE", "Estimate", "auc", "comparative",
           "excess", "holistic", "metric_rows", "pairs_table", "pairwise_win", "relative", "relative_members",
           "scenario_settings", "share_of"]

IDEAL_COMPARATIVE = {"S1": 1.0, "S2": 0.5, "S3": 1.0}


@dataclass
class Estimate:
    value: float
    low: float
    high: float
    p: float = float("nan")     # comparative only: the p-value that the accuracy differs from 50%
    count: int = 0              # the units it rests on: pairs (videos for the relative metric)


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
    for scenario, setting in scenario_settings(scores):
        _, first, second = pairs_table(scores, scenario, setting, column)
        found = share_of(pairwise_win(second, first))
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
    for scenario, setting in scenario_settings(scores):
        right, _, _ = _relative_right(scores, scenario, setting, column)
        out[scenario, setting] = share_of(right)
    return out


# the reference's relative metric, one row per member of S2 and S3 (utils/metrix_ds.py): each the
# share of one block of videos judged rightly against its S1 pair's mean; `relative` is their mean
OFFICIAL_RELATIVE = {("S2", 0): "S2-ext1", ("S2", 1): "S2-ext2", ("S3", 0): "S3-ext", ("S3", 1): "S3-sur"}


def relative_members(scores: dict[str, np.ndarray], column: str = "score") -> dict[tuple[str, str], Estimate]:
    """The reference's relative sub-rows: per scenario and OFFICIAL_RELATIVE name, the share of
    that member's videos judged rightly against the mean of their S1 pair."""
    out = {}
    for scenario, setting in scenario_settings(scores):
        right, _, member = _relative_right(scores, scenario, setting, column)
        for which in (0, 1):
            name = OFFICIAL_RELATIVE.get((setting, which))
            if name is not None:
                out[scenario, name] = share_of(right[member == which])
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


def share_of(values: np.ndarray) -> Estimate:
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


def scenario_settings(scores: dict[str, np.ndarray]) -> list[tuple[str, str]]:
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
