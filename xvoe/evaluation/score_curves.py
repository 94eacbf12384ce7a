"""A score file's columns and its per-frame curves, by name: the columns the curves reduce to
(`curve_columns`: what `xvoe score` writes and what `xvoe verify` checks a file's rows against),
and the curves read back as figures draw them (`read_curves`).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import XvoeError
from .metrics import excess
from .score_headers import check_curves_of, curves_arrays, header_of
from .scorer import MSE_LABEL
from .surprise import aggregate

__all__ = ["LABEL_COLUMNS", "SCORE_COLUMNS", "Curves", "curve_columns", "read_curves"]

# a score file's first columns: the video's row in the split and its labels
LABEL_COLUMNS = ("index", "model", "scenario", "setting", "pair", "member", "possible")
# then score, s_img and s_dyn: the default verdict (for XPL, the better of two explanations); paper_score:
# the paper's (XPL: always Transformer 2's proposal), the same for a model with no such choice
SCORE_COLUMNS = (*LABEL_COLUMNS, "score", "s_img", "s_dyn", "paper_score")


def curve_columns(curves: Mapping[str, np.ndarray], how: str, own: str | None = None) -> dict[str, np.ndarray]:
    """The columns (N,) that per-frame curves (N, T) reduce to by `how` (sum or max over frames),
    each where its curves are given, in a score file's order: score (the model's `own` curve
    where it has one, else s_img + s_dyn), s_img, s_dyn, paper_score (paper_s_img +
    paper_s_dyn), s_rec and excess (s_img - s_rec + s_dyn). The NLL's columns are not sums of
    curves, but for nll with the sequential Monte Carlo's curve (`xvoe verify` sums it)."""
    def reduced(curve: np.ndarray) -> np.ndarray:
        return aggregate(torch.from_numpy(np.asarray(curve, float)), how).numpy()

    given = set(curves)
    found = {}
    if own is not None:
        found["score"] = reduced(curves[own])
    elif {"s_img", "s_dyn"} <= given:
        found["score"] = reduced(curves["s_img"] + curves["s_dyn"])
    found |= {name: reduced(curves[name]) for name in ("s_img", "s_dyn") if name in given}
    if {"paper_s_img", "paper_s_dyn"} <= given:
        found["paper_score"] = reduced(curves["paper_s_img"] + curves["paper_s_dyn"])
    if {"s_img", "s_dyn", "s_rec"} <= given:
        found["s_rec"] = reduced(curves["s_rec"])
        found["excess"] = reduced(excess(curves["s_img"], curves["s_dyn"], curves["s_rec"]))
    return found


@dataclass
class Curves:
    """A score file's per-frame curves as figures draw them: the MSE's terms (s_img, s_dyn, and
    s_rec for a model with a perception module), or a model's own curve alone."""

    arrays: dict[str, np.ndarray]   # name -> (N, T), one row per row of the score file
    own: str | None                 # the name of a model's own curve (`curve_of`); None: the MSE's terms
    label: str                      # what the axis measures

    @property
    def total(self) -> np.ndarray:
        """(N, T): the per-frame surprise whose sum over frames is the score."""
        return self.arrays[self.own] if self.own else self.arrays["s_img"] + self.arrays["s_dyn"]


def read_curves(path: str | Path, videos: int, scores: str | Path | None = None) -> Curves:
    """The curves file `path` (.curves.npz) of a score file of `videos` rows (`scores`, where
    known, whose digest it must record: `check_curves_of`); a one-line error for a missing
    file, one that is not a curves file or one of another score file."""
    path = Path(path)
    if not path.is_file():
        raise XvoeError(f"{path}: no such file; xvoe score writes the curves beside the CSV")
    saved = curves_arrays(path)
    header = header_of(path, saved)
    if scores is not None:
        check_curves_of(scores, path, header)
    own = header.get("curve")
    needed = {own} if own else {"s_img", "s_dyn"}
    if not needed <= set(saved):
        raise XvoeError(f"{path} is not a curves file (it holds {', '.join(saved)})")
    arrays = {name: values for name, values in saved.items() if name != "header"}
    if any(len(values) != videos for values in arrays.values()):
        raise XvoeError(f"{path} does not hold the curves of its score file ({videos} videos): "
                        "they were not written together")
    return Curves(arrays, own, header.get("curve_label", MSE_LABEL) if own else MSE_LABEL)
