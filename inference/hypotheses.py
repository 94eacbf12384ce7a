"""Explanations, plural: the distinct weighted hypotheses of a hidden object in an estimate."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from .evidence import Evidence

__all__ = ["Hypotheses", "top_hypotheses"]


@dataclass
class Hypotheses:
    """The distinct weighted hypotheses of a hidden object, heaviest first: its trajectory and
    the explanation of the seen objects it goes with."""

    trajectories: Tensor          # (H, T, D)
    version: Tensor               # (H,) long: 1 where a seen object is two identical ones
    weights: Tensor               # (H,) their share of the posterior given an object (sum <= 1)
    copies: Tensor                # (H,) how many particles carry each
    spread: Tensor                # (T,) weighted standard deviation between them per frame (RMS over D)
    disagree: list[int] = field(default_factory=list)   # frames where they differ most, most first


def top_hypotheses(estimate: Evidence, top: int = 4) -> Hypotheses | None:
    """The `top` heaviest distinct hypotheses after resampling (copies of one particle are
    merged and their weights added), and where they disagree: the weighted spread between their
    trajectories per frame, and the frames in order of that spread. None where no object can be
    placed."""
    held = estimate.holding()
    if held is None:
        return None
    held_trajectories, log_weights = held
    versions = estimate.holding_versions().to(held_trajectories)
    keys = torch.cat([held_trajectories.flatten(1), versions[:, None]], dim=1)
    unique, inverse = torch.unique(keys, dim=0, return_inverse=True)
    weights = torch.zeros(len(unique), dtype=torch.float64, device=unique.device).index_add_(
        0, inverse, torch.softmax(log_weights, 0))
    copies = torch.zeros(len(unique), dtype=torch.long, device=unique.device).index_add_(0, inverse,
                                                                                         torch.ones_like(inverse))
    order = weights.argsort(descending=True)[:top]
    trajectories = unique[order, :-1].reshape(len(order), *held_trajectories.shape[1:])
    chosen = weights[order]
    share = chosen / chosen.sum()
    mean = (share[:, None, None] * trajectories.double()).sum(0)
    variance = (share[:, None, None] * (trajectories.double() - mean).square()).sum(0)   # (T, D)
    spread = variance.mean(dim=1).sqrt()
    disagree = [int(t) for t in spread.argsort(descending=True) if spread[t] > 1e-6]
    return Hypotheses(trajectories, unique[order, -1].long(), chosen, copies[order], spread, disagree)
