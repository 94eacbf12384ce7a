"""The NLL surprise of a video: -log p(video) under the hidden-object model, by sequential Monte
Carlo over frames (`inference.smc`, the default) or vectorised importance sampling, both with
Transformer 2's proposal; with the effective sample size and the posterior probability that a
hidden object exists. Every estimate comes from a seed (or a torch.Generator): the same seed
gives the same bytes, whatever was drawn before."""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from xvoe.evaluation.surprise import DrawnScene, draw_scene
from xvoe.models.perception import ComponentVAE
from xvoe.models.reasoning import never_seen
from xvoe.models.slots import redraw_slots
from xvoe.models.xpl import XPL
from xvoe.resources import check_memory

from .evidence import Evidence, importance_evidence, smc_evidence
from .hypotheses import Hypotheses, top_hypotheses
from .identity import Identity, identity_gap, two_objects
from .model import InferenceConfig, Proposal, drawing_cost
from .smc import effective_sample_size
from .xpl_scene import XPLScene

__all__ = ["NLLSurprise", "Seed", "check_particles", "nll_surprise", "HiddenPosterior", "hidden_posterior",
           "Surprise", "explain_surprise"]


@dataclass
class NLLSurprise:
    nll: float            # -log p(video), nats
    ess: float            # effective sample size of the weights (SMC: of the particles, all holding an object)
    p_hidden: float       # posterior probability that a hidden object exists
    hidden_slot: int      # the free slot the hidden object was given (-1: none was free)
    estimate: Evidence
    holding_ess: float = 0.0   # effective sample size among the particles that hold an object
    method: str = "importance"
    identity: Identity | None = None    # the seen object that may be two identical ones, None where none may

    @property
    def p_two(self) -> float:
        """Posterior probability that the seen object of `identity` is two identical ones."""
        return self.estimate.p_two

    @property
    def frame_nll(self) -> Tensor | None:
        """-log p(x_t | x_<t) (T,) float64, summing to nll: the SMC's; importance sampling keeps none."""
        return self.estimate.frame_nll


Seed = int | torch.Generator | None


def _generator_from(seed: Seed) -> torch.Generator:
    """A generator of its own for a seed (None: 0); a generator is used as it is. On the CPU
    whatever the device: the resampling's uniforms are drawn there and moved, and Pyro's global
    state (the CPU's, or the CUDA device's) is seeded from it."""
    if isinstance(seed, torch.Generator):
        return seed
    return torch.Generator().manual_seed(0 if seed is None else int(seed))


_BRANCH_SAMPLES = 8     # particles each value of `exists` expects at the least
# memory a particle takes through a video's NLL, at the least: the shipped model's run on a
# 32 px test video held 1.0 GB more at 8,192 particles than at 256
_PARTICLE_BYTES = 100_000


def check_particles(particles: int) -> None:
    """Refuse, before any work, a particle count whose run cannot fit in this machine's memory."""
    check_memory(particles * _PARTICLE_BYTES, f"--particles {particles:,}")



def _defensive(p_exists: Tensor, particles: int) -> Tensor:
    """The guide's existence probability, kept off 0 and 1 so that each branch expects at
    least BRANCH_SAMPLES particles. Every particle without a hidden object has the same,
    exactly computed weight, and the two branches' likelihoods differ by thousands of nats: a
    run that draws no particle of one branch misses it whole (with a 0.98 clamp and 64
    particles, one run in four did), and its NLL and p_hidden swing with the seed."""
    floor = min(0.5, _BRANCH_SAMPLES / particles)
    return p_exists.clamp(floor, 1.0 - floor)


@torch.no_grad()
def nll_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor, background: Tensor,
                 occluder: Tensor, config: InferenceConfig, method: str | None = None,
                 seed: Seed = 0, drawn: DrawnScene | None = None) -> NLLSurprise:
    """One video: frames (T, 4, H, W) in [-1, 1]; mean (T, K, D); visible (T, K) bool;
    background (T, D) latents; occluder (K,) bool. The guide proposes the hidden object's
    trajectory from Transformer 2's mean (moved out of sight, `_refine_out_of_sight`) and scale,
    and (importance sampling) its existence from XPL's amortised existence probability.

    method: "smc" or "importance" (None: config.method). seed: an int or a torch.Generator;
    the global random state is neither read nor changed. drawn: this video's scene as the MSE
    score drew it (`_hidden_object_scene`)."""
    method = config.method if method is None else method
    if method not in ("smc", "importance"):
        raise ValueError(f"method must be smc or importance, not {method!r}")
    generator = _generator_from(seed)
    scene, loc, spread, free = _hidden_object_scene(vae, xpl, mean, visible, background, occluder, config, drawn)
    hidden = scene.hidden
    p_exists = torch.sigmoid(xpl.existence_logit(loc[None], spread[None]))[0] if free else mean.new_zeros(())
    if free and config.refine_steps:
        loc = _refine_out_of_sight(scene, loc, frames, config)
    proposal = Proposal(_defensive(p_exists, config.particles) if free else p_exists, loc, spread)
    if method == "smc":
        found = smc_evidence(scene, frames, config, proposal, generator, free)
        return NLLSurprise(found.nll, found.ess, found.p_hidden, hidden if free else -1, found,
                           found.ess if free else 0.0, "smc", scene.identity)
    found = importance_evidence(scene, frames, config, proposal, generator)
    held = found.holding()
    holding = float(effective_sample_size(held[1])) if held is not None else 0.0
    return NLLSurprise(found.nll, found.ess, found.p_hidden, hidden if free else -1, found, holding, "importance",
                       scene.identity)


def _hidden_object_scene(vae: ComponentVAE, xpl: XPL, mean: Tensor, visible: Tensor, background: Tensor,
                        occluder: Tensor, config: InferenceConfig,
                        drawn: DrawnScene | None = None) -> tuple[XPLScene, Tensor, Tensor, bool]:
    """One video's scene for the Pyro model (arguments as `nll_surprise`'s), with the
    two-object explanation as its second version where a seen object goes out of sight and comes
    back (and config.prior_two > 0); Transformer 2's mean and scale (T, D) for the hidden slot
    (the one it explained, else the first never-seen one), and whether any slot is free for a
    hidden object. drawn: the video's refined latents, proposal and pictures as the MSE score
    drew them (`xvoe.evaluation.surprise.draw_scene`, a batch of one), drawn here where absent;
    the second version decodes only the two slots it changes."""
    if drawn is None:
        drawn = draw_scene(vae, xpl, mean[None], visible[None], background[None], occluder[None], proposed=False)
    unseen = never_seen(visible[None])[0]
    hidden = int(drawn.slot[0]) if drawn.slot[0] >= 0 else int(unseen.float().argmax())
    identity = identity_gap(visible, occluder, hidden) if config.prior_two > 0 else None
    latents, seen, layers = drawn.refined, visible[None], drawn.seen_layers(vae.blank()[0])
    if identity is not None:
        two, two_seen = two_objects(drawn.refined[0], visible, identity)
        changed = torch.zeros_like(occluder)
        changed[[identity.slot, identity.second]] = True
        two_layers = redraw_slots(vae, layers, two[None], changed[None], two_seen[None], occluder[None])
        latents, seen = torch.stack([drawn.refined[0], two]), torch.stack([visible, two_seen])
        layers = torch.cat([layers, two_layers])
    scene = XPLScene(vae, xpl, latents, drawn.background[0], seen, occluder, hidden, identity, layers)
    loc, spread = drawn.proposal[0, :, hidden], drawn.scale[0, :, hidden].clamp_min(xpl.config.reasoning.min_scale)
    return scene, loc, spread, bool(unseen.any())


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
    held = result.estimate.holding() if result.hidden_slot >= 0 else None
    if held is None:
        return None
    trajectories, log_weights = held
    weights = torch.softmax(log_weights, dim=0)
    mean = (weights[:, None, None] * trajectories.to(torch.float64)).sum(0).to(trajectories.dtype)
    best = int(weights.argmax())
    return HiddenPosterior(mean, trajectories[best], float(weights[best]), len(trajectories),
                           float(effective_sample_size(log_weights)))


@dataclass
class Surprise:
    """What the application layer shows of one video's NLL surprise."""

    nll: float
    ess: float                 # ESS among the particles that hold an object
    p_hidden: float
    hidden_slot: int
    method: str
    hypotheses: Hypotheses | None   # the heaviest distinct trajectories (SMC), None where no object was placed
    result: NLLSurprise


def explain_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor, background: Tensor,
                     occluder: Tensor, config: InferenceConfig | None = None, method: str | None = None,
                     seed: Seed = 0, top: int = 4) -> Surprise:
    """`nll_surprise` with the plural explanation: the `top` heaviest distinct hidden-object
    trajectories after resampling, their weights, and the frames where they disagree
    (`inference.hypotheses.top_hypotheses`). With importance sampling, the particles that hold an
    object stand in for them, weighted among themselves."""
    config = config or InferenceConfig()
    result = nll_surprise(vae, xpl, frames, mean, visible, background, occluder, config, method, seed)
    hypotheses = top_hypotheses(result.estimate, top) if result.hidden_slot >= 0 else None
    return Surprise(result.nll, result.holding_ess, result.p_hidden, result.hidden_slot, result.method, hypotheses,
                    result)
