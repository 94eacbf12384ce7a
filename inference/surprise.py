"""The NLL surprise of a video: -log p(video) under the hidden-object model, by sequential Monte
Carlo over frames (`inference.smc`, the default) or vectorised importance sampling, both with
Transformer 2's proposal; with the effective sample size and the posterior probability that a
hidden object exists. Every estimate comes from a seed (or a torch.Generator): the same seed
gives the same bytes, whatever was drawn before."""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import partial

import torch
from torch import Tensor

from xvoe.evaluation.surprise import DrawnScene, draw_scene
from xvoe.models.perception import ComponentVAE
from xvoe.models.reasoning import never_seen
from xvoe.models.slots import redraw_slots
from xvoe.models.xpl import XPL
from xvoe.resources import check_memory

from .evidence import Evidence, importance_evidence, smc_evidence
from .guide import hidden_proposal, out_of_sight
from .hypotheses import Hypotheses, top_hypotheses
from .identity import Identity, identity_gap, two_objects
from .model import InferenceConfig, Proposal
from .smc import effective_sample_size
from .xpl_scene import XPLScene

__all__ = ["NLLSurprise", "Seed", "video_seed", "check_particles", "nll_surprise", "drawn_surprise",
           "scene_and_proposal", "HiddenPosterior", "hidden_posterior", "Surprise", "explain_surprise"]


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


def video_seed(seed: int | None, frames: Tensor) -> int:
    """The seed of one video's draws under a score's `seed` (None: 0): a hash of the two, so that
    each video draws from a stream of its own, whatever else is scored with it and wherever it
    sits in a split. One seed for every video made one stream good or bad for all similar scenes
    at once: their errors were correlated, and a metric's interval over videos too narrow."""
    digest = hashlib.sha256(str(0 if seed is None else int(seed)).encode())
    digest.update(frames.detach().to("cpu", torch.float32).contiguous().numpy().tobytes())
    return int.from_bytes(digest.digest()[:8], "little") >> 1      # manual_seed takes 63 bits


def _generator_from(seed: Seed, frames: Tensor) -> torch.Generator:
    """A generator of its own for a seed and a video of `frames` (`video_seed`); a generator is
    used as it is. On the CPU whatever the device: the resampling's uniforms are drawn there and
    moved, and Pyro's global state (the CPU's, or the CUDA device's) is seeded from it."""
    if isinstance(seed, torch.Generator):
        return seed
    return torch.Generator().manual_seed(video_seed(seed, frames))


# memory a particle takes through a video's NLL, at the least: the shipped model's run on a
# 32 px test video held 1.0 GB more at 8,192 particles than at 256
_PARTICLE_BYTES = 100_000


def check_particles(particles: int) -> None:
    """Refuse, before any work, a particle count whose run cannot fit in this machine's memory."""
    check_memory(particles * _PARTICLE_BYTES, f"--particles {particles:,}")


@torch.no_grad()
def nll_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, mean: Tensor, visible: Tensor, background: Tensor,
                 occluder: Tensor, config: InferenceConfig, method: str | None = None,
                 seed: Seed = 0, drawn: DrawnScene | None = None) -> NLLSurprise:
    """One video: frames (T, 4, H, W) in [-1, 1]; mean (T, K, D); visible (T, K) bool;
    background (T, D) latents; occluder (K,) bool. `drawn_surprise` of the video as XPL draws
    it: `drawn`, the MSE score's drawing of it (`xvoe.evaluation.surprise.draw_scene`, a batch of
    one), or drawn here without the proposed slot where it is None."""
    if drawn is None:
        drawn = draw_scene(vae, xpl, mean[None], visible[None], background[None], occluder[None], proposed=False)
    return drawn_surprise(vae, xpl, frames, visible, occluder, drawn, config, method, seed)


@torch.no_grad()
def drawn_surprise(vae: ComponentVAE, xpl: XPL, frames: Tensor, visible: Tensor, occluder: Tensor,
                   drawn: DrawnScene, config: InferenceConfig, method: str | None = None,
                   seed: Seed = 0) -> NLLSurprise:
    """The NLL surprise of one video of frames (T, 4, H, W) in [-1, 1], visible (T, K) and
    occluder (K,) bool, that XPL has drawn (`drawn`, a batch of one: its refined latents,
    Transformer 2's proposal and the pictures): its scene for the Pyro model and the guide's
    proposal of a hidden object (`scene_and_proposal`), then the evidence (`smc_evidence`, or
    `importance_evidence`).

    method: "smc" or "importance" (None: config.method). seed: an int, mixed with the video's
    pixels (`video_seed`), or a torch.Generator, used as it is; the global random state is
    neither read nor changed."""
    method = config.method if method is None else method
    if method not in ("smc", "importance"):
        raise ValueError(f"method must be smc or importance, not {method!r}")
    generator = _generator_from(seed, frames)
    scene, proposal, free = scene_and_proposal(vae, xpl, visible, occluder, drawn, config)
    slot = scene.hidden if free else -1
    refine = partial(out_of_sight, scene, frames=frames, config=config)
    if method == "smc":
        found = smc_evidence(scene, frames, config, proposal, generator, free, refine)
        return NLLSurprise(found.nll, found.ess, found.p_hidden, slot, found, found.ess if free else 0.0, "smc",
                           scene.identity)
    found = importance_evidence(scene, frames, config, refine(proposal) if free else proposal, generator)
    held = found.holding()
    holding = float(effective_sample_size(held[1])) if held is not None else 0.0
    return NLLSurprise(found.nll, found.ess, found.p_hidden, slot, found, holding, "importance", scene.identity)


def scene_and_proposal(vae: ComponentVAE, xpl: XPL, visible: Tensor, occluder: Tensor, drawn: DrawnScene,
                       config: InferenceConfig) -> tuple[XPLScene, Proposal, bool]:
    """What the estimators of one video start from (arguments as `drawn_surprise`'s): its scene for
    the Pyro model, the guide's proposal of a hidden object as a pilot draws from it (the full run
    moves it out of sight first: `inference.guide.out_of_sight`), and whether a slot is free for one."""
    hidden, free = _hidden_slot(drawn, visible)
    scene = _hidden_object_scene(vae, xpl, visible, occluder, hidden, config, drawn)
    proposal = hidden_proposal(xpl, drawn.proposal[0, :, hidden], drawn.scale[0, :, hidden], config, free)
    return scene, proposal, free


def _hidden_slot(drawn: DrawnScene, visible: Tensor) -> tuple[int, bool]:
    """The slot a hidden object would take: the one Transformer 2 explained, else the first
    never-seen one; and whether any slot is free for it."""
    unseen = never_seen(visible[None])[0]
    hidden = int(drawn.slot[0]) if drawn.slot[0] >= 0 else int(unseen.float().argmax())
    return hidden, bool(unseen.any())


def _hidden_object_scene(vae: ComponentVAE, xpl: XPL, visible: Tensor, occluder: Tensor, hidden: int,
                         config: InferenceConfig, drawn: DrawnScene) -> XPLScene:
    """One video's scene for the Pyro model (arguments as `drawn_surprise`'s), its free slot
    `hidden`: what was seen, as the MSE score drew it (the proposed slot left blank), and the
    two-object explanation as its second version where a seen object goes out of sight and comes
    back (and config.prior_two > 0), which decodes only the two slots it changes."""
    identity = identity_gap(visible, occluder, hidden) if config.prior_two > 0 else None
    latents, seen, layers = drawn.refined, visible[None], drawn.seen_layers(vae.blank()[0])
    if identity is not None:
        two, two_seen = two_objects(drawn.refined[0], visible, identity)
        changed = torch.zeros_like(occluder)
        changed[[identity.slot, identity.second]] = True
        two_layers = redraw_slots(vae, layers, two[None], changed[None], two_seen[None], occluder[None])
        latents, seen = torch.stack([drawn.refined[0], two]), torch.stack([visible, two_seen])
        layers = torch.cat([layers, two_layers])
    return XPLScene(vae, xpl, latents, drawn.background[0], seen, occluder, hidden, layers, drawn.walls[0, :, 0],
                    identity)


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
