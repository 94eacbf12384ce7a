"""The guide's proposal for a video's hidden object (`hidden_proposal`): Transformer 2's mean
trajectory for the free slot, its scale, and XPL's amortised probability that the object exists,
kept off 0 and 1 so that both values of `exists` draw particles (`_defensive`); for the full run,
the mean moved out of sight where it spoils the frames (`out_of_sight`) and, where that
probability is sure of an object, up the model's own log joint (`toward_mode`)."""
from __future__ import annotations

import math

import torch
from torch import Tensor

from xvoe.models.xpl import XPL

from .model import HiddenObjectModel, InferenceConfig, Proposal, drawing_cost
from .xpl_scene import XPLScene

__all__ = ["hidden_proposal", "out_of_sight", "toward_mode"]

_BRANCH_SAMPLES = 8     # particles each value of `exists` expects at the least


def hidden_proposal(xpl: XPL, loc: Tensor, scale: Tensor, config: InferenceConfig, free: bool) -> Proposal:
    """The guide's parameters for one video: Transformer 2's mean (T, D) for the hidden slot and
    its scale (T, D), floored at the reasoning module's min_scale; the probability that the object
    exists from XPL's existence head, 0 where no slot is `free` for it. What a pilot draws from;
    the full run's mean is first moved out of sight (`out_of_sight`)."""
    spread = scale.clamp_min(xpl.config.reasoning.min_scale)
    if not free:
        return Proposal(loc.new_zeros(()), loc, spread)
    p_exists = torch.sigmoid(xpl.existence_logit(loc[None], spread[None]))[0]
    return Proposal(_defensive(p_exists, config.particles), loc, spread)


def out_of_sight(scene: XPLScene, proposal: Proposal, frames: Tensor, config: InferenceConfig) -> Proposal:
    """The proposal with its mean moved out of sight where it spoils `frames` (T, 4, H, W)
    (`_refine_out_of_sight`, where `config.refine_steps`). Left to the full run: a pilot stops as
    surely without it (docs/decisions.md, "The NLL's settings", row `refine_steps`)."""
    if not config.refine_steps:
        return proposal
    return Proposal(proposal.p_exists, _refine_out_of_sight(scene, proposal.loc, frames, config), proposal.scale)


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


def toward_mode(model: HiddenObjectModel, frames: Tensor, proposal: Proposal, config: InferenceConfig) -> Proposal:
    """The proposal with its mean trajectory (T, D) moved by `config.mode_steps` Adam steps up
    the model's log joint log p(x, object, one object for each seen one, z = mean)
    (`HiddenObjectModel.log_joint`), the best mean met kept, and its scale narrowed to the log
    joint's curvature there where that is sharper (`_shift_scale`). Where a never-seen cube
    stops the ball, one frame's likelihood is so narrow that the estimate turns on whether
    particles already hold the cube there when it comes, in the one or two latent directions
    that frame pins down (a scale of 0.03-0.05 where Transformer 2 gives 0.2, widened 3 and 10
    times). The mean alone, or the scale alone, left the two-seed spread where it was.
    Deterministic in the video: the guide stays a proper proposal, the same for every seed."""
    adam = _AdamSteps(config.mode_rate)
    mean, best, best_value = proposal.loc, proposal.loc, -math.inf
    for step in range(config.mode_steps + 1):
        with torch.enable_grad():
            latents = mean.detach().requires_grad_(True)
            value = model.log_joint(frames, latents[None])[0]
            gradient, = torch.autograd.grad(value, latents)     # not the networks' weights
        if float(value.detach()) > best_value:
            best, best_value = mean.detach(), float(value.detach())
        if step < config.mode_steps:
            mean = adam.step(mean.detach(), -gradient)
    scale = proposal.scale
    if config.mode_shift:
        scale = torch.minimum(scale, _shift_scale(model, frames, best, config.mode_shift))
    return Proposal(proposal.p_exists, best, scale)


@torch.no_grad()
def _shift_scale(model: HiddenObjectModel, frames: Tensor, mean: Tensor, shift: float) -> Tensor:
    """Each latent dimension's scale (D,) under the log joint around `mean` (T, D) when the whole
    trajectory moves along it (a still cube's place moves every frame's latent alike):
    1/sqrt of the log joint's curvature, from second differences at +-shift, the 2D + 1
    trajectories traced as one batch (a flat or convex direction: no limit)."""
    dims = mean.shape[1]
    offsets = torch.cat([mean.new_zeros(1, dims), shift * torch.eye(dims, dtype=mean.dtype, device=mean.device),
                         -shift * torch.eye(dims, dtype=mean.dtype, device=mean.device)])
    values = model.log_joint(frames, mean[None] + offsets[:, None])
    curvature = (2 * values[0] - values[1:dims + 1] - values[dims + 1:]) / shift ** 2
    return torch.where(curvature > 0, curvature.clamp_min(1e-12).rsqrt(), math.inf).to(mean.dtype)


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
