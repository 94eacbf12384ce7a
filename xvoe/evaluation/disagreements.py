"""Two score columns compared: the pairs whose more surprising member they disagree on, and
every metric of one model under both side by side (the MSE score and the NLL of
`xvoe score --surprise both`, or the default verdict and the paper's score)."""
from __future__ import annotations

import numpy as np

from .metrics import pairs_table, scenario_settings

__all__ = ["DISAGREEMENT_FIELDS", "SURPRISES", "TIE_TOLERANCE", "VERDICTS", "disagreement_fields", "disagreements",
           "has_both_surprises", "side_by_side", "verdict"]

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
    for scenario, setting in scenario_settings(scores):
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
