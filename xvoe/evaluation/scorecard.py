"""The scorecard: every goal of docs/design.md, "Goals" that a model can be measured on, one line
each, and the shipping rule of docs/design.md, "Recipes, choosing and shipping" that compares two
cards.

A line is a goal line when it has a target (`>=`, `<=`, or `within`: the target lies inside the
line's interval), else a reported line. Intervals are 95% bootstrap intervals (resampling) over
pairs or videos. The shipping rule (`compare`): a candidate ships when, on the validation
splits, it meets every goal that the shipped model meets and no goal line is worse than the
shipped model's beyond its interval (its whole interval on the worse side of the shipped
value). Reported lines never block: with dozens of lines some move beyond their interval by
chance alone.

The lines are built from a model's scores files (`read_scores`; the NLL's columns come from a
file scored with `--surprise both`), the split, and the model itself for the explanation and
perception lines; scoring and timing are the caller's (benchmarks/scorecard.py).
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import h5py
import numpy as np

from ..errors import XvoeError
from ..models.perception import ComponentVAE
from ..scenes.scenarios import SCENARIOS
from ..training.stages import BASELINE, CHANCE, MODEL_ROLES, ROLES, XPL
from .disagreements import VERDICTS, has_both_surprises
from .explanation_quality import expected_videos, ground_truth, hidden_explanations, mae_iou, pick
from .metrics import Estimate, comparative, holistic, pairs_table, pairwise_win
from .perception_quality import (
    POOLED,
    PROBE_GOALS,
    PositionProbe,
    latent_positions,
    position_probes,
    read_held_out,
    reconstruction,
)
from .resampling import values_interval
from .scorer import Scorer

__all__ = ["LABELS", "ROLES", "PSNR", "PROBE_R2", "MSE_SPEED", "NLL_SPEED", "TWO_SAID", "TWO_DENIED", "Line",
           "Decision", "compare", "role_of", "score_lines", "lead_lines", "nll_lines", "repeat_lines",
           "identity_lines", "hypotheses_in_s2", "explanation_lines", "perception_lines", "probe_lines",
           "speed_line", "format_line", "write_card", "read_card"]

LABELS = {"score": "MSE verdict", "paper_score": "paper's MSE score", "excess": "MSE excess", "nll": "NLL",
          "nll_excess": "NLL excess"}
GAP_PREFIX = {"score": "", "nll": "NLL "}     # the paper's "gap", under the default verdict and the NLL
XPL_ACCURACY, BASELINE_ACCURACY, LEAD = 97.0, 90.0, 20.0      # percent
LEAD_SCENARIOS = ("collision", "blocking")
NLL_EXCESS_AUC, HIDDEN_IOU, PSNR, PROBE_R2 = 0.9, 0.6, 26.0, 0.95
MSE_SPEED, NLL_SPEED = 10.0, 8.0        # videos per second
REPEAT_MEDIAN, REPEAT_P99 = 0.5, 5.0    # nats
TWO_SAID, TWO_DENIED = 90.0, 95.0       # percent: p(two objects) > 0.5 where only two explain, < 0.5 where one must


@dataclass
class Line:
    """One measured figure; a goal line when it has a target."""

    name: str
    value: float
    low: float = float("nan")
    high: float = float("nan")
    target: float | None = None
    direction: str = ">="       # >= or <=: which way is better; within: the target inside the interval
    p: float = float("nan")     # comparative lines: the p-value that the accuracy differs from 50%
    note: str = ""              # why the value is nan, where it could not be measured

    @property
    def has_interval(self) -> bool:
        return math.isfinite(self.low) and math.isfinite(self.high)

    @property
    def met(self) -> bool | None:
        """Whether the goal is met; None for a reported line."""
        if self.target is None:
            return None
        if self.direction == "within":
            return bool(self.low <= self.target <= self.high) if self.has_interval else self.value == self.target
        return bool(self.value >= self.target) if self.direction == ">=" else bool(self.value <= self.target)

    def worse_than(self, reference: Line) -> bool:
        """Whether this line's whole interval lies on the worse side of the reference's value
        (never, without an interval)."""
        if not self.has_interval:
            return False
        if self.direction == ">=":
            return self.high < reference.value
        if self.direction == "<=":
            return self.low > reference.value
        if self.low <= self.target <= self.high:
            return False
        return min(abs(self.low - self.target), abs(self.high - self.target)) > abs(reference.value - self.target)


@dataclass
class Decision:
    """The shipping rule's verdict on a candidate's card against the shipped model's."""

    ships: bool
    unmet: list[str]        # goals the shipped model meets that the candidate does not (or has no line for)
    worse: list[str]        # goal lines worse than the shipped model's beyond the candidate's interval


def compare(candidate: list[Line], shipped: list[Line]) -> Decision:
    """The shipping rule: goal lines only; reported lines never block."""
    mine = {line.name: line for line in candidate}
    unmet, worse = [], []
    for reference in (line for line in shipped if line.target is not None):
        own = mine.get(reference.name)
        if reference.met and (own is None or not own.met):
            unmet.append(reference.name)
        if own is not None and own.target is not None and own.worse_than(reference):
            worse.append(reference.name)
    return Decision(not unmet and not worse, unmet, worse)


def role_of(model: str) -> str:
    """The goals a model known by name carries (its entry in `MODEL_ROLES` of
    xvoe.training.stages); anything else (a run directory) is a candidate XPL."""
    return MODEL_ROLES.get(Path(model).name, XPL)


def _percent(name: str, estimate: Estimate, target: float | None = None, direction: str = ">=") -> Line:
    return Line(name, 100 * estimate.value, 100 * estimate.low, 100 * estimate.high, target, direction, estimate.p)


def _accuracy_goal(role: str, column: str, setting: str) -> tuple[float | None, str]:
    """The comparative goal of a line: (target, direction), or (None, ...) when it is reported."""
    if column != "score" or setting == "S2":
        return None, ">="
    if role == XPL:
        return XPL_ACCURACY, ">="
    if role == BASELINE and setting == "S1":
        return BASELINE_ACCURACY, ">="
    if role == CHANCE:
        return 50.0, "within"
    return None, ">="


def score_lines(scores: dict[str, np.ndarray], role: str = XPL, rounds: int = 1000, seed: int = 0) -> list[Line]:
    """The lines of one scores table: comparative accuracy (%) of S1 and S3 per scenario under
    every score column it holds (the default verdict carries the goals; the paper's score where
    it differs from it), the S3 - S2 gap, and the holistic AUC per scenario (the NLL excess's
    carries its goal for XPL)."""
    lines = []
    same = not has_both_surprises(scores, VERDICTS)     # a model with no choice of explanation
    for column in (c for c in LABELS if c in scores and not (c == "paper_score" and same)):
        accuracy = comparative(scores, column, rounds, seed)
        for (scenario, setting), estimate in accuracy.items():
            if setting != "S2":
                target, direction = _accuracy_goal(role, column, setting)
                lines.append(_percent(f"{LABELS[column]} {scenario} {setting} comparative (%)", estimate, target,
                                      direction))
        if column in GAP_PREFIX:
            for scenario in (s for s in SCENARIOS if (s, "S3") in accuracy and (s, "S2") in accuracy):
                gap = 100 * (accuracy[scenario, "S3"].value - accuracy[scenario, "S2"].value)
                lines.append(Line(f"{GAP_PREFIX[column]}S3 - S2 gap {scenario} (points)", gap))
        target = NLL_EXCESS_AUC if column == "nll_excess" and role == XPL else None
        for scenario, estimate in holistic(scores, column, rounds, seed).items():
            lines.append(Line(f"{LABELS[column]} {scenario} holistic AUC", estimate.value, estimate.low,
                              estimate.high, target))
    return lines


def lead_lines(xpl: dict[str, np.ndarray], baselines: dict[str, dict[str, np.ndarray]], rounds: int = 1000,
               seed: int = 0) -> list[Line]:
    """XPL's S3 comparative accuracy less each baseline's (points) in collision and blocking,
    on the same pairs of one split, with an interval from resampling those pairs."""
    lines = []
    for name, other in baselines.items():
        for scenario in LEAD_SCENARIOS:
            pairs, first, second = pairs_table(xpl, scenario, "S3", "score")
            other_pairs, other_first, other_second = pairs_table(other, scenario, "S3", "score")
            if len(pairs) == 0 or not np.array_equal(pairs, other_pairs):
                continue
            lead = 100 * (pairwise_win(second, first) - pairwise_win(other_second, other_first))
            lines.append(Line(f"XPL S3 lead over {name} {scenario} (points)", float(lead.mean()),
                              *values_interval(lead, rounds=rounds, seed=seed), target=LEAD))
    return lines


def nll_lines(scores: dict[str, np.ndarray], file: h5py.File, repeat: dict[str, np.ndarray] | None = None,
              rounds: int = 1000, seed: int = 0) -> list[Line]:
    """The NLL's own lines from a file scored with `--surprise both`: p_hidden on videos with a
    never-seen object and on all-seen ones, the ESS on the former, p_two where only two objects
    explain the video and where a wall shows one (`identity_lines`), and, with the same split
    scored with another seed (`repeat`), |NLL difference| per video (median, 99th percentile)."""
    kinds = np.array([ground_truth(file, int(i)) for i in scores["index"]])
    hidden, seen = kinds == "hidden", kinds == "seen"
    lines = []
    if hidden.any():
        said = scores["p_hidden"][hidden] > 0.5
        lines.append(Line("p_hidden > 0.5 on never-seen-object videos (%)", 100 * said.mean(),
                          *(100 * np.array(values_interval(said, rounds=rounds, seed=seed)))))
        ess = scores["ess"][hidden]
        lines.append(Line("ESS of all particles, never-seen-object videos (median)", float(np.median(ess)),
                          *values_interval(ess, np.median, rounds, seed)))
    if seen.any():
        denied = scores["p_hidden"][seen] < 0.5
        lines.append(Line("p_hidden < 0.5 on all-seen videos (%)", 100 * denied.mean(),
                          *(100 * np.array(values_interval(denied, rounds=rounds, seed=seed)))))
    if "p_two" in scores:
        lines += identity_lines(scores, rounds, seed) + hypotheses_in_s2(scores)
    if repeat is not None:
        lines += repeat_lines(scores, repeat, rounds, seed)
    return lines


def repeat_lines(scores: dict[str, np.ndarray], repeat: dict[str, np.ndarray], rounds: int = 1000,
                 seed: int = 0) -> list[Line]:
    """|NLL difference| between two seeds per video (median, 99th percentile), on the videos both
    tables hold: the second seed may cover part of the split, since it costs a whole NLL run."""
    _, mine, theirs = np.intersect1d(scores["index"], repeat["index"], return_indices=True)
    if len(mine) == 0:
        raise XvoeError("the repeat scores share no video with the scores")
    difference = np.abs(scores["nll"][mine] - repeat["nll"][theirs])
    return [Line("NLL repeatability, two seeds, median (nats)", float(np.median(difference)),
                 *values_interval(difference, np.median, rounds, seed), REPEAT_MEDIAN, "<="),
            Line("NLL repeatability, two seeds, 99th percentile (nats)", float(_p99(difference)),
                 *values_interval(difference, _p99, rounds, seed), REPEAT_P99, "<=")]


def identity_lines(scores: dict[str, np.ndarray], rounds: int = 1000, seed: int = 0) -> list[Line]:
    """p_two > 0.5 on continuity S2's not-seen-in-window videos (the generator moved one ball:
    only two identical ones explain them), and p_two < 0.5 on the possible videos of S1 and S3,
    whose lifted walls show one ball."""
    scenario, setting = scores["scenario"].astype(str), scores["setting"].astype(str)
    lines = []
    unseen = (scenario == "continuity") & (setting == "S2") & (scores["member"] == 1)
    if unseen.any():
        said = scores["p_two"][unseen] > 0.5
        lines.append(Line("p_two > 0.5 on continuity S2 not-seen-in-window videos (%)", 100 * said.mean(),
                          *(100 * np.array(values_interval(said, rounds=rounds, seed=seed))), TWO_SAID))
    one = np.isin(setting, ("S1", "S3")) & scores["possible"].astype(bool)
    if one.any():
        denied = scores["p_two"][one] < 0.5
        lines.append(Line("p_two < 0.5 on S1 and S3 possible videos (%)", 100 * denied.mean(),
                          *(100 * np.array(values_interval(denied, rounds=rounds, seed=seed))), TWO_DENIED))
    return lines


def hypotheses_in_s2(scores: dict[str, np.ndarray]) -> list[Line]:
    """What the NLL's hypotheses make of each S2 setting, member by member (reported, no goal):
    the share of videos it explains by a hidden object and by two identical objects."""
    lines, in_s2 = [], scores["setting"].astype(str) == "S2"
    scenarios = scores["scenario"].astype(str)
    for scenario in SCENARIOS:
        for member in (0, 1):
            chosen = in_s2 & (scenarios == scenario) & (scores["member"] == member)
            if chosen.any():
                for column, what in (("p_hidden", "a hidden object"), ("p_two", "two objects")):
                    share = 100 * float((scores[column][chosen] > 0.5).mean())
                    lines.append(Line(f"S2 {scenario} member {member}: {what} (% of videos)", share))
    return lines


def _p99(values: np.ndarray) -> float:
    return float(np.percentile(values, 99))


def explanation_lines(scorer: Scorer, file: h5py.File, pairs: int, rounds: int = 1000, seed: int = 0) -> list[Line]:
    """hidden_iou (goal) on blocking S2's never-seen cubes, why it falls short, and mae_iou."""
    explained = hidden_explanations(scorer, file, pick(file, "blocking", "S2", 0, pairs))
    rebuilt = mae_iou(scorer, file, expected_videos(file, pairs))
    return [Line("hidden_iou", explained["iou"], *values_interval(explained["per_video"], rounds=rounds, seed=seed),
                 HIDDEN_IOU),
            Line("hidden cube's decoded centre off by (px, median)", explained["centre_px"], direction="<="),
            Line("hidden cube proposed farther from the ball by (px, median)", explained["away_px"], direction="<="),
            Line("mae_iou", float(np.mean(rebuilt)), *values_interval(rebuilt, rounds=rounds, seed=seed))]


def perception_lines(vae: ComponentVAE, data: str | Path, videos: int = 300, rounds: int = 1000,
                     seed: int = 0) -> list[Line]:
    """The perception's goals on held-out frames: RGB PSNR and the position probe's R^2 of the
    kinds and axes of `PROBE_GOALS`; beside them (reported) depth PSNR, PSNR on object pixels,
    one probe for every visible object, and the probes' other lines."""
    held = read_held_out(data, videos, vae.config.image_size)
    quality = reconstruction(vae, held, rounds, seed)
    lines = [Line("perception RGB PSNR (dB)", *quality["rgb"], PSNR),
             Line("perception depth PSNR (dB)", *quality["depth"]),
             Line("perception RGB PSNR on object pixels (dB)", *quality["objects"])]
    return lines + probe_lines(position_probes(*latent_positions(vae, held), held.kind, held.kind_names, rounds,
                                               seed))


def probe_lines(probes: dict[str, PositionProbe]) -> list[Line]:
    """The lines of `position_probes`: R^2 x and y of the probe for every visible object, then
    of each kind's, named "(kind)"; those of `PROBE_GOALS` carry the goal."""
    lines = []
    for name, found in probes.items():
        suffix = "" if name == POOLED else f" ({name})"
        lines += [Line(f"perception position probe R^2 {axis}{suffix}", *value,
                       PROBE_R2 if axis in PROBE_GOALS.get(name, ()) else None,
                       note=found.reason if math.isnan(value[0]) else "")
                  for axis, value in (("x", found.x), ("y", found.y))]
    return lines


def speed_line(name: str, videos: int, seconds: float, target: float | None) -> Line:
    """Videos per second of a scoring run (no interval: one run)."""
    return Line(f"{name}, videos per second", videos / seconds, target=target)


def format_line(line: Line, reference: Line | None = None) -> str:
    """One printed line: value, interval, p-value, goal, met or not, and the reference beside."""
    text = f"{line.name}: {line.value:.3f}"
    if line.has_interval:
        text += f" [{line.low:.3f}, {line.high:.3f}]"
    if math.isfinite(line.p):
        text += f" p(50%)={line.p:.3g}"
    if line.note:
        text += f" ({line.note})"
    if line.target is not None:
        text += f" (goal {line.direction} {line.target:g}) {'met' if line.met else 'NOT MET'}"
    if reference is not None:
        text += f"  | shipped {reference.value:.3f}"
        if line.target is not None and line.worse_than(reference):
            text += "  WORSE BEYOND ITS INTERVAL"
    return text


def write_card(path: str | Path, lines: list[Line], **about) -> Path:
    """A card as JSON: `about` (model, data, ...) and its lines."""
    path = Path(path)
    path.write_text(json.dumps({**about, "card": [asdict(line) | {"met": line.met} for line in lines]}, indent=1))
    return path


def read_card(path: str | Path) -> list[Line]:
    """The lines of a card written by `write_card`."""
    names = {f.name for f in fields(Line)}
    return [Line(**{k: v for k, v in row.items() if k in names}) for row in json.loads(Path(path).read_text())["card"]]

