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


@torch.no_grad()
def nll_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor, background: Tensor,
                 occluder: Tensor, config: InferenceConfig) -> NLLSurprise:
    """One video: frames (T, 4, H, W) in [-1, 1]; mean (T, K, D); visible (T, K) bool;
    background (T, D) latents; occluder (K,) bool. The guide proposes the hidden object's
    trajectory from Transformer 2's mean and scale and its existence from XPL's amortised
    existence probability."""
    refined = xpl.refine(mean[None], visible[None])
    explained, scale, slot = xpl.explain(refined, visible[None])
    unseen = never_seen(visible[None])[0]
    hidden = int(slot[0]) if slot[0] >= 0 else int(unseen.float().argmax())
    free = bool(unseen.any())
    background_pictures = vae.decode(background)
    occupied = visible.any(0)
    scene = XPLScene(vae, xpl, refined[0], background_pictures, occupied, hidden, occupied & ~occluder)
    model = HiddenObjectModel(scene, config)
    loc, spread = explained[0, :, hidden], scale[0, :, hidden].clamp_min(xpl.config.reasoning.min_scale)
    p_exists = torch.sigmoid(xpl.existence_logit(loc[None], spread[None]))[0] if free else torch.tensor(0.0)
    proposal = Proposal(p_exists.clamp(0.02, 0.98) if free else p_exists, loc, spread)
    estimate = importance(model.model, model.guide, frames, proposal=proposal, particles=config.particles)
    return NLLSurprise(estimate.nll, estimate.ess, float(estimate.posterior_mean("exists")),
                       hidden if free else -1, estimate)
