"""The NLL surprise of a video: -log p(video) under the hidden-object model, by vectorised
importance sampling with Transformer 2's proposal; with the effective sample size and the
posterior probability that a hidden object exists."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from xvoe.models.perception import ComponentVAE
from xvoe.models.reasoning import never_seen
from xvoe.models.xpl import XPL

from .importance import Estimate, importance
from .model import HiddenObjectModel, InferenceConfig, Proposal
from .xpl_scene import XPLScene


@dataclass
class NLLSurprise:
    nll: float            # -log p(video), nats
    ess: float            # effective sample size of the importance weights
    p_hidden: float       # posterior probability that a hidden object exists
    hidden_slot: int      # the free slot the hidden object was given (-1: none was free)
    estimate: Estimate


BRANCH_SAMPLES = 8     # particles each value of `exists` expects at the least


def defensive(p_exists: Tensor, particles: int) -> Tensor:
    """The guide's existence probability, kept off 0 and 1 so that each branch expects at
    least BRANCH_SAMPLES particles. Every particle without a hidden object has the same,
    exactly computed weight, and the two branches' likelihoods differ by thousands of nats: a
    run that draws no particle of one branch misses it whole (with a 0.98 clamp and 64
    particles, one run in four did), and its NLL and p_hidden swing with the seed."""
    floor = min(0.5, BRANCH_SAMPLES / particles)
    return p_exists.clamp(floor, 1.0 - floor)


@torch.no_grad()
def nll_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor, background: Tensor,
                 occluder: Tensor, config: InferenceConfig) -> NLLSurprise:
    """One video: frames (T, 4, H, W) in [-1, 1]; mean (T, K, D); visible (T, K) bool;
    background (T, D) latents; occluder (K,) bool. The guide proposes the hidden object's
    trajectory from Transformer 2's mean (moved out of sight, `refine_out_of_sight`) and scale,
    and its existence from XPL's amortised existence probability."""
    refined = xpl.refine(mean[None], visible[None])
    explained, scale, slot = xpl.explain(refined, visible[None])
    unseen = never_seen(visible[None])[0]
    hidden = int(slot[0]) if slot[0] >= 0 else int(unseen.float().argmax())
    free = bool(unseen.any())
    background_pictures = vae.decode(background)
    scene = XPLScene(vae, xpl, refined[0], background_pictures, visible, occluder, hidden)
    model = HiddenObjectModel(scene, config)
    loc, spread = explained[0, :, hidden], scale[0, :, hidden].clamp_min(xpl.config.reasoning.min_scale)
    p_exists = torch.sigmoid(xpl.existence_logit(loc[None], spread[None]))[0] if free else torch.tensor(0.0)
    if free and config.refine_steps:
        loc = refine_out_of_sight(scene, loc, frames, config)
    proposal = Proposal(defensive(p_exists, config.particles) if free else p_exists, loc, spread)
    estimate = importance(model.model, model.guide, frames, proposal=proposal, particles=config.particles)
    p_hidden = float(estimate.posterior_mean("exists").clamp(0.0, 1.0))   # a weighted mean can round past 1
    return NLLSurprise(estimate.nll, estimate.ess, p_hidden, hidden if free else -1, estimate)


def refine_out_of_sight(scene: XPLScene, loc: Tensor, frames: Tensor, config: InferenceConfig) -> Tensor:
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
    every = torch.arange(len(loc))

    def extra_cost(latents: Tensor, chosen: Tensor) -> Tensor:
        """Nats (F,) the hidden object's pictures add in the frames `chosen`."""
        extra = (scene.render_frames(latents, chosen) - frames[chosen]).square() - without[chosen]
        return extra.clamp_min(0.0).sum(dim=(1, 2, 3)) / (2 * config.pixel_sigma ** 2)

    chosen = every[extra_cost(loc, every) > config.refine_tolerance]
    if len(chosen) == 0:
        return loc
    with torch.enable_grad():
        moved = loc[chosen].clone().requires_grad_(True)
        optimiser = torch.optim.Adam([moved], lr=config.refine_rate)
        for _ in range(config.refine_steps):
            cost = extra_cost(moved, chosen)
            if float(cost.detach().max()) <= config.refine_tolerance:
                break
            moved.grad, = torch.autograd.grad(cost.sum(), moved)    # not the networks' weights
            optimiser.step()
    refined = loc.clone()
    refined[chosen] = moved.detach()
    return refined


@dataclass
class HiddenPosterior:
    """The hidden object as the importance weights see it, given that it exists."""

    mean: Tensor          # (T, D) importance-weighted mean trajectory of the particles holding an object
    best: Tensor          # (T, D) the trajectory of the highest-weight such particle
    best_weight: float    # its weight among them
    holding: int          # how many particles held an object
    ess: float            # the effective sample size among them


def hidden_posterior(result: NLLSurprise) -> HiddenPosterior | None:
    """The explanation posterior of one video, or None when no particle held an object.

    Weights are renormalised over the particles that hold an object, from the float64
    log-weights: where p_hidden is tiny their plain normalised weights underflow to zero, yet
    what the model would believe if there were an object is still worth drawing."""
    nodes = result.estimate.guide_trace.nodes
    alive = nodes["exists"]["value"].bool()
    if result.hidden_slot < 0 or not alive.any():
        return None
    frames = sum(1 for name in nodes if name.startswith("z_"))
    trajectories = torch.stack([nodes[f"z_{t}"]["value"] for t in range(frames)], dim=1)[alive]
    weights = torch.softmax(result.estimate.log_weights[alive], dim=0)
    mean = (weights[:, None, None] * trajectories.to(torch.float64)).sum(0).to(trajectories.dtype)
    best = int(weights.argmax())
    return HiddenPosterior(mean, trajectories[best], float(weights[best]), int(alive.sum()),
                           float(1.0 / (weights ** 2).sum()))
