"""The guide's proposal for a video's hidden object (`hidden_proposal`): Transformer 2's mean
trajectory for the free slot, its scale, and XPL's amortised probability that the object exists,
kept off 0 and 1 so that both values of `exists` draw particles (`_defensive`); for the full run,
the mean moved out of sight where it spoils the frames (`out_of_sight`)."""
from __future__ import annotations

import math
from dataclasses import replace

import torch
from torch import Tensor

from xvoe.models.xpl import XPL

from .model import InferenceConfig, Proposal, drawing_cost
from .xpl_scene import XPLScene

__all__ = ["hidden_proposal", "out_of_sight"]

_BRANCH_SAMPLES = 8     # particles each value of `exists` expects at the least


def hidden_proposal(xpl: XPL, loc: Tensor, scale: Tensor, config: InferenceConfig, free: bool) -> Proposal:
    """The guide's parameters for one video: Transformer 2's mean (T, D) for the hidden slot and
    its scale (T, D), floored at the reasoning module's min_scale; the probability that the object
    exists from XPL's existence head, 0 where no slot is `free` for it. What a pilot draws from;
    the full run's mean is first moved out of sight (`out_of_sight`)."""
    spread = scale.clamp_min(xpl.config.reasoning.min_scale)
    if not free:
        return Proposal(loc.new_zeros(()), loc, spread, loc.new_zeros(()))
    p_exists = torch.sigmoid(xpl.existence_logit(loc[None], spread[None]))[0]
    return Proposal(_defensive(p_exists, config.particles), loc, spread, p_exists)


def out_of_sight(scene: XPLScene, proposal: Proposal, frames: Tensor, config: InferenceConfig) -> Proposal:
    """The proposal with its mean moved out of sight where it spoils `frames` (T, 4, H, W)
    (`_refine_out_of_sight`, where `config.refine_steps`). Left to the full run: a pilot stops as
    surely without it (docs/decisions.md, "The NLL's settings", row `refine_steps`)."""
    if not config.refine_steps:
        return proposal
    return replace(proposal, loc=_refine_out_of_sight(scene, proposal.loc, frames, config))


def _defensive(p_exists: Tensor, particles: int) -> Tensor:
    """The guide's existence probability, kept off 0 and 1 so that each branch expects at
    least BRANCH_SAMPLES particles. Every particle without a hidden object has the same,
    exactly computed weight, and the two branches' likelihoods differ by thousands of nats: a
    run that draws no particle of one branch misses it whole (with a 0.98 clamp and 64
    particles, one run in four did), and its NLL and p_hidden swing with the seed."""
    floor = min(0.5, _BRANCH_SAMPLES / particles)
    return p_exists.clamp(floor, 1.0 - floor)


def _refine_out_of_sight(scene: XPLScene, loc: Tensor, frames: Tensor, config: InferenceConfig) -> Tensor:
    """Transformer 2's mean trajectory (T, D), moved by a few gradient steps that take its
    pictures out of sight where they spoil the frames. Transformer 2 learned the latents of
    objects that were partly seen, and its mean for a never-seen one can show where no wall
    covers it (the scene keeps it behind the walls, `XPLScene.render`); every particle drawn
    around it then pays hundreds of nats. The steps descend only the pixels' extra cost over the
    scene without the object (clipped at zero), so they hide the object and never reward it for
    patching what the seen slots reconstruct badly; frames where it costs under
    `refine_tolerance` nats are left as they are. A deterministic function of the video: the
    guide stays a proper proposal."""
    without = (scene.empty() - frames).square()
    every = torch.arange(len(loc), device=loc.device)

    def extra_cost(latents: Tensor, chosen: Tensor) -> Tensor:
        """Nats (F,) the hidden object's pictures and its drawing (`drawing_cost`) add in the
        frames `chosen`. The drawing's shortfall counts too: without it, fading to a blank was the
        steepest way out of sight, and a cube behind the wall came out of the steps a ghost."""
        drawing = scene.draw_frames(latents, chosen)
        extra = (drawing.frames - frames[chosen]).square() - without[chosen]
        pixels = extra.clamp_min(0.0).sum(dim=(1, 2, 3)) / (2 * config.pixel_sigma ** 2)
        return pixels + drawing_cost(config, drawing)

    chosen = every[extra_cost(loc, every) > config.refine_tolerance]
    if len(chosen) == 0:
        return loc
    moved = loc[chosen].clone()
    adam = _AdamSteps(config.refine_rate)
    for _ in range(config.refine_steps):
        with torch.enable_grad():
            latents = moved.requires_grad_(True)
            cost = extra_cost(latents, chosen)
            if float(cost.detach().max()) <= config.refine_tolerance:
                break
            gradient, = torch.autograd.grad(cost.sum(), latents)    # not the networks' weights
        moved = adam.step(moved.detach(), gradient)
    refined = loc.clone()
    refined[chosen] = moved.detach()
    return refined


class _AdamSteps:
    """Adam's update (torch.optim.Adam's defaults) of one tensor. Written out because the first
    torch.optim optimiser of a process imports torch._dynamo, which the first NLL score or
    explanation of a notebook would wait for, for five small steps (measured in
    docs/log/decisions-2026-11.md, "The NLL's pilot stays at 16 particles")."""

    def __init__(self, rate: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.rate, self.betas, self.eps = rate, betas, eps
        self.count, self.first, self.second = 0, None, None

    def step(self, value: Tensor, gradient: Tensor) -> Tensor:
        (b1, b2), self.count = self.betas, self.count + 1
        if self.first is None:
            self.first, self.second = torch.zeros_like(value), torch.zeros_like(value)
        self.first = b1 * self.first + (1 - b1) * gradient
        self.second = b2 * self.second + (1 - b2) * gradient.square()
        denominator = (self.second.sqrt() / math.sqrt(1 - b2 ** self.count)) + self.eps
        return value - (self.rate / (1 - b1 ** self.count)) * self.first / denominator
