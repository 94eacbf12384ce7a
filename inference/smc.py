"""Sequential Monte Carlo over frames for the hidden object's trajectory.

The existence of a hidden object is summed out exactly: without one, every frame is fixed and
its likelihood is computed once; with one, N particles carry the trajectory frame by frame,
each drawn from the guide's per-frame proposal (by default Transformer 2's Gaussian fused with
the dynamics' step, as in `HiddenObjectModel.guide`), weighted by that frame's likelihood, and
resampled (systematic resampling) when the effective sample size falls below a threshold.

    log p^(x | object) = sum over resampling epochs of log mean w      (unbiased in p, not in log p)
    log p^(x) = logsumexp(log p + log p^(x | object), log(1 - p) + log p(x | no object))

Pyro's `SMCFilter` is not used: it keeps float32 weights, renormalises them every step (the
evidence is lost), and draws from the global random state; here the weights are float64 and a
`torch.Generator` makes a score reproducible from a seed. Runs may be batched (`runs`), so the
tests measure the estimator's distribution with thousands of replicates in one pass.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from torch import Tensor

from .model import InferenceConfig, LinearGaussianScene, Proposal, drawing_cost, fuse, pixel_log_normaliser


class SequentialModel(Protocol):
    """What `run_smc` needs: a state for n = runs * particles particles, a step that draws
    frame t for all of them and returns the incremental log-weights (n,) float64, and a way to
    keep the particles `index` (n,) of a state (resampling)."""

    frames: int

    def start(self, particles: int) -> Any: ...

    def step(self, t: int, state: Any, generator: torch.Generator | None) -> tuple[Any, Tensor]: ...

    def select(self, state: Any, index: Tensor) -> Any: ...


def systematic_resample(weights: Tensor, generator: torch.Generator | None = None, count: int | None = None) -> Tensor:
    """Ancestor indices (R, M) from normalised weights (R, N), M = count or N: one uniform per
    row, M evenly spaced points through the cumulative weights. Particle i is kept floor(M w_i)
    or ceil(M w_i) times, M w_i in expectation: the weights' mean is kept, with less noise than
    multinomial draws."""
    runs, particles = weights.shape
    count = particles if count is None else count
    # drawn from the CPU generator and moved: one seed, the same draws on every device
    offset = torch.rand(runs, 1, generator=generator, dtype=torch.float64).to(weights.device)
    points = (offset + torch.arange(count, dtype=torch.float64, device=weights.device)) / count
    cumulative = weights.to(torch.float64).cumsum(dim=1)
    cumulative = cumulative / cumulative[:, -1:]           # a sum of 1 - 1e-16 must not leave a point past the end
    return torch.searchsorted(cumulative, points).clamp_max(particles - 1)


def effective_sample_size(log_weights: Tensor) -> Tensor:
    """(sum w)^2 / sum w^2 along the last dimension."""
    normalised = torch.softmax(log_weights, dim=-1)
    return 1.0 / normalised.square().sum(dim=-1)


@dataclass
class SMCRun:
    log_evidence: Tensor          # (R,) float64
    log_weights: Tensor           # (R, N) float64, since the last resampling
    state: Any                    # the final particles
    ess: Tensor                   # (R, T) before each frame's resampling decision
    resampled: Tensor             # (R, T) bool
    origin: Tensor                # (R, N) the first-frame particle each final particle descends from

    @property
    def final_ess(self) -> Tensor:
        return self.ess[:, -1]

    @property
    def lineages(self) -> Tensor:
        """(R,) distinct first-frame ancestors among the final particles."""
        return torch.tensor([len(torch.unique(row)) for row in self.origin])


def run_smc(model: SequentialModel, particles: int, runs: int = 1, threshold: float = 0.5,
            generator: torch.Generator | None = None, device: torch.device | str = "cpu") -> SMCRun:
    """`runs` independent particle filters of `particles` particles each, stepped together, their
    weights on `device` (the model's).

    After frame t, a run whose ESS is under threshold * particles is resampled and its mean
    weight moved into its evidence; the last frame's weights are never resampled (nothing
    follows to use the copies), so they stay a weighted sample of the posterior."""
    n = runs * particles
    state = model.start(n)
    log_weights = torch.zeros(runs, particles, dtype=torch.float64, device=device)
    log_evidence = torch.zeros(runs, dtype=torch.float64, device=device)
    origin = torch.arange(particles, device=device).expand(runs, particles).clone()
    ess, resampled = [], []
    base = (torch.arange(runs, device=device) * particles)[:, None]
    target = threshold * particles

    for t in range(model.frames):
        state, increment = model.step(t, state, generator)
        log_weights = log_weights + increment.reshape(runs, particles)
        current = effective_sample_size(log_weights)
        ess.append(current)
        due = current < target if t < model.frames - 1 else torch.zeros(runs, dtype=torch.bool, device=device)
        resampled.append(due)
        if due.any():
            log_evidence[due] += torch.logsumexp(log_weights[due], dim=1) - math.log(particles)
            ancestors = torch.arange(particles, device=device).expand(runs, particles).clone()
            ancestors[due] = systematic_resample(torch.softmax(log_weights[due], dim=1), generator)
            state = model.select(state, (base + ancestors).reshape(-1))
            log_weights = log_weights.clone()
            log_weights[due] = 0.0
            origin = origin.gather(1, ancestors)
    log_evidence += torch.logsumexp(log_weights, dim=1) - math.log(particles)
    return SMCRun(log_evidence, log_weights, state, torch.stack(ess, dim=1), torch.stack(resampled, dim=1), origin)


# --- the hidden object's trajectory as a sequential model ---------------------------------

@dataclass
class Particles:
    trajectory: Tensor                    # (n, t, D) the frames drawn so far
    loc: Tensor | None = None             # (n, D) the dynamics' mean of the next frame
    carried: Any = None                   # the scene's own state after the last frame (the dynamics' memory)
    increment: Tensor | None = None       # (n,) float64 its log-weight: transition + likelihood - proposal


class HiddenTrajectory:
    """The hidden object's trajectory given that it exists, for `run_smc`: frame t's draw
    from the guide's proposal, weighted by the transition density over the proposal density,
    the frame's pixel likelihood, and whatever else the scene observes from frames <= t (XPL:
    the seen objects' motion at t + 1). `proposal` None draws from the dynamics alone (the
    bootstrap filter)."""

    def __init__(self, steps: SceneSteps, config: InferenceConfig, proposal: Proposal | None):
        self.steps, self.config, self.proposal = steps, config, proposal
        self.frames = steps.frames

    def start(self, particles: int) -> Particles:
        return Particles(self.steps.initial_trajectory(particles), None, self.steps.start(particles))

    def step(self, t: int, state: Particles, generator: torch.Generator | None) -> tuple[Particles, Tensor]:
        n = len(state.trajectory)
        if t == 0:
            prior_loc, prior_scale = self.steps.initial(n)
        else:
            prior_loc, prior_scale = state.loc, torch.full_like(state.loc, self.config.transition_sigma)
        locs, scales = self.proposal_at(t, prior_loc, prior_scale)
        # drawn from the CPU generator and moved: one seed, the same draws on every device
        chosen = torch.randint(locs.shape[1], (n,), generator=generator).to(locs.device)
        rows = torch.arange(n, device=locs.device)
        loc, scale = locs[rows, chosen], scales[rows, chosen]
        z = loc + scale * torch.randn(loc.shape, generator=generator, dtype=loc.dtype).to(loc.device)
        drawn = self.evaluate(t, z, (prior_loc, prior_scale), (locs, scales), state.carried)
        drawn.trajectory = torch.cat([state.trajectory, z[:, None]], dim=1)
        return drawn, drawn.increment

    def evaluate(self, t: int, z: Tensor, prior: tuple[Tensor, Tensor], guide: tuple[Tensor, Tensor],
                 before: Any) -> Particles:
        """Frame t's draws z (n, D) weighed: their log-weights and the scene's state after them.
        guide: the proposal's components' means and scales (n, C, D), an equal-weight mixture."""
        log_q = mixture_log_density(z, *guide)
        increment = normal_log_density(z, *prior) - log_q + self.steps.frame_log_likelihood(t, z)
        next_loc, carried = None, before
        if t < self.frames - 1:
            next_loc, carried, extra = self.steps.advance(t, z, before)
            increment = increment + extra
        return Particles(z[:, None], next_loc, carried, increment)

    def proposal_at(self, t: int, prior_loc: Tensor, prior_scale: Tensor) -> tuple[Tensor, Tensor]:
        """Means and scales (n, C, D) of the proposal's C components for frame t: the
        dynamics' step fused with Transformer 2's marginal widened by each of
        `smc_proposal_widening` (an equal-weight mixture: every component is a function of the
        particle's past, so the mixture's density is the one each draw came from)."""
        if self.proposal is None:
            return prior_loc[:, None], prior_scale[:, None]
        loc, scale = self.proposal.loc[t].expand_as(prior_loc), self.proposal.scale[t].expand_as(prior_loc)
        if not self.config.guide_follows_dynamics:
            components = [(loc, scale)]
        else:
            widenings = self.config.smc_proposal_widening
            if widenings is None:
                widenings = (self.config.proposal_widening,)
            elif isinstance(widenings, (int, float)):
                widenings = (widenings,)
            components = [fuse(prior_loc, prior_scale, loc, scale * widening) for widening in widenings]
        return torch.stack([c[0] for c in components], dim=1), torch.stack([c[1] for c in components], dim=1)

    def select(self, state: Particles, index: Tensor) -> Particles:
        def pick(value):
            return None if value is None else value[index]

        return Particles(state.trajectory[index], pick(state.loc), self.steps.select(state.carried, index),
                         pick(state.increment))


def mixture_log_density(x: Tensor, locs: Tensor, scales: Tensor) -> Tensor:
    """Log-density (n,) of x (n, D) under the equal-weight mixture of diagonal Gaussians (n, C, D)."""
    components = normal_log_density(x[:, None], locs, scales)            # (n, C)
    return torch.logsumexp(components, dim=1) - math.log(locs.shape[1])


def normal_log_density(x: Tensor, loc: Tensor, scale: Tensor) -> Tensor:
    """Diagonal Gaussian log-density (n,) of x (n, D), summed in float64."""
    scale = scale.to(torch.float64)
    z = (x.to(torch.float64) - loc.to(torch.float64)) / scale
    return (-0.5 * z.square() - scale.log() - 0.5 * math.log(2 * math.pi)).sum(dim=-1)


class SceneSteps(Protocol):
    """A scene taken frame by frame (the sequential face of `inference.model.Scene`)."""

    frames: int

    def initial(self, particles: int) -> tuple[Tensor, Tensor]: ...

    def initial_trajectory(self, particles: int) -> Tensor: ...

    def start(self, particles: int) -> Any: ...

    def frame_log_likelihood(self, t: int, z: Tensor) -> Tensor: ...

    def advance(self, t: int, z: Tensor, carried: Any) -> tuple[Tensor, Any, Tensor]: ...

    def select(self, carried: Any, index: Tensor) -> Any: ...

    def empty_log_likelihood(self) -> float: ...


def pixel_frame_log_density(expected: Tensor, observed: Tensor, sigma: float) -> Tensor:
    """log N(observed | expected, sigma^2) of each leading entry of expected (n, ...) against
    one observed frame, summed in float64."""
    squares = ((expected - observed) / sigma).square().flatten(start_dim=1)
    return -0.5 * squares.sum(dim=1, dtype=torch.float64) - pixel_log_normaliser(observed.numel(), sigma)


class LinearSteps:
    """`LinearGaussianScene` frame by frame (the closed-form check)."""

    def __init__(self, scene: LinearGaussianScene, frames: Tensor, config: InferenceConfig):
        self.scene, self.observed, self.sigma = scene, frames, config.pixel_sigma
        self.frames = scene.frames

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        return self.scene.initial(particles)

    def initial_trajectory(self, particles: int) -> Tensor:
        return self.scene.initial_mean.new_zeros(particles, 0, len(self.scene.initial_mean))

    def start(self, particles: int) -> None:
        return None

    def frame_log_likelihood(self, t: int, z: Tensor) -> Tensor:
        return pixel_frame_log_density(self.scene.background + z @ self.scene.H.T, self.observed[t], self.sigma)

    def advance(self, t: int, z: Tensor, carried: None) -> tuple[Tensor, None, Tensor]:
        return z @ self.scene.A.T, None, torch.zeros(len(z), dtype=torch.float64, device=z.device)

    def select(self, carried: None, index: Tensor) -> None:
        return None

    def empty_log_likelihood(self) -> float:
        return float(pixel_frame_log_density(self.scene.empty()[None], self.observed, self.sigma)[0])


class XPLSteps:
    """An `XPLScene` frame by frame: the dynamics stepped once per frame on every particle's
    scene (the hidden slot from the particle), its memory carried and resampled with the
    particles; frame t's picture of the hidden object composited with the fixed layers; the
    seen objects' motion at t + 1 observed once frame t is drawn."""

    def __init__(self, scene, frames: Tensor, config: InferenceConfig):
        self.scene, self.observed, self.config = scene, frames, config
        self.frames = scene.frames
        self.moving = scene.moving
        self.seen = scene.refined[1:, self.moving]            # (T-1, M, D)

    def initial(self, particles: int) -> tuple[Tensor, Tensor]:
        return self.scene.initial(particles)

    def initial_trajectory(self, particles: int) -> Tensor:
        return self.scene.refined.new_zeros(particles, 0, self.scene.dim)

    def start(self, particles: int) -> None:
        return None

    def frame_log_likelihood(self, t: int, z: Tensor) -> Tensor:
        chosen = torch.full((len(z),), t, dtype=torch.long, device=z.device)
        drawing = self.scene.draw_frames(z, chosen)
        pixels = pixel_frame_log_density(drawing.frames, self.observed[t], self.config.pixel_sigma)
        return pixels - drawing_cost(self.config, drawing)

    def advance(self, t: int, z: Tensor, carried: Any) -> tuple[Tensor, Any, Tensor]:
        scene = self.scene.refined[t].expand(len(z), *self.scene.refined.shape[1:]).clone()
        scene[:, self.scene.hidden] = z
        prediction, carried = self.scene.xpl.dynamics.step(scene, carried, self.scene.inert())
        return prediction[:, self.scene.hidden], carried, self.motion_log_likelihood(t, prediction[:, self.moving])

    def motion_log_likelihood(self, t: int, predicted: Tensor) -> Tensor:
        """log N(seen latents at t + 1 | predicted (n, M, D), motion_sigma^2) where the encoder saw them."""
        seen = self.observed_motion[t]
        density = torch.distributions.Normal(predicted, self.config.motion_sigma).log_prob(self.seen[t])
        return (density * seen[:, None]).sum(dim=(1, 2), dtype=torch.float64)

    @property
    def observed_motion(self) -> Tensor:
        return self.scene.observed                           # (T-1, M) bool

    def select(self, carried: Any, index: Tensor) -> Any:
        if carried is None:
            return None
        slots = self.scene.slots

        def pick(tensor: Tensor) -> Tensor:
            shaped = tensor.reshape(-1, slots, *tensor.shape[1:])[index]
            return shaped.reshape(-1, *tensor.shape[1:])

        return type(carried)(*(pick(part) for part in carried))

    def empty_log_likelihood(self) -> float:
        """log p(frames, seen motion | no hidden object): the free slot holds what the encoder
        made of its empty pixels, as in `XPLScene.seen_motion`."""
        pixels = pixel_frame_log_density(self.scene.empty()[None], self.observed, self.config.pixel_sigma)[0]
        predicted = self.scene.xpl.predict(self.scene.refined[None], self.scene.occluder)[0, :, self.moving]
        density = torch.distributions.Normal(predicted, self.config.motion_sigma).log_prob(self.seen)
        motion = (density * self.observed_motion[..., None]).sum(dtype=torch.float64)
        return float(pixels + motion)


def scene_steps(scene, frames: Tensor, config: InferenceConfig) -> SceneSteps:
    if isinstance(scene, LinearGaussianScene):
        return LinearSteps(scene, frames, config)
    return XPLSteps(scene, frames, config)


# --- the evidence of a video ---------------------------------------------------------------

@dataclass
class SMCEstimate:
    """The SMC estimate of one video (the existence of a hidden object summed out exactly)."""

    log_evidence: float           # log p^(x)
    log_evidence_hidden: float    # log p^(x | a hidden object), -inf where none can be placed
    log_evidence_empty: float     # log p(x | no hidden object), exact
    p_hidden: float               # posterior probability of a hidden object
    ess: float                    # ESS of the final weights (all particles hold an object)
    min_ess: float                # the lowest ESS over frames, before resampling
    lineages: int                 # distinct first-frame ancestors of the final particles
    resamplings: int
    particles: int
    trajectories: Tensor | None   # (N, T, D) final particles, None where no object can be placed
    log_weights: Tensor | None    # (N,) float64 final log-weights

    @property
    def nll(self) -> float:
        return -self.log_evidence

    @property
    def weights(self) -> Tensor:
        return torch.softmax(self.log_weights, dim=0)


def mixture(prior_hidden: float, log_hidden: float, log_empty: float) -> tuple[float, float]:
    """log p(x) and p(object | x) from the two branches' evidence."""
    a = math.log(prior_hidden) + log_hidden if prior_hidden > 0 else -math.inf
    b = math.log1p(-prior_hidden) + log_empty if prior_hidden < 1 else -math.inf
    total = max(a, b) + math.log(math.exp(a - max(a, b)) + math.exp(b - max(a, b)))
    return total, math.exp(a - total)


@torch.no_grad()
def smc_evidence(scene, frames: Tensor, config: InferenceConfig, proposal: Proposal | None,
                 generator: torch.Generator | None = None, free: bool = True) -> SMCEstimate:
    """One video's evidence by SMC over `config.particles` particles holding a hidden object,
    plus the exact branch without one. `free` False: no slot is left for a hidden object, and
    the evidence is that of the branch without one, weighted by its prior (as the importance
    sampler's guide, which then never proposes an object, gives it)."""
    steps = scene_steps(scene, frames, config)
    log_empty = steps.empty_log_likelihood()
    particles = config.particles
    if not free:
        return SMCEstimate(math.log1p(-config.prior_hidden) + log_empty, -math.inf, log_empty, 0.0,
                           float(particles), float(particles), 0, 0, particles, None, None)
    model = HiddenTrajectory(steps, config, proposal)
    run = None
    sure = proposal is not None and float(proposal.p_exists) > config.smc_pilot_skip_exists
    for size in () if sure else pilot_sizes(config):
        pilot = run_smc(model, size, threshold=config.resample_threshold, generator=generator, device=frames.device)
        gap = ((math.log1p(-config.prior_hidden) + log_empty)
               - (math.log(config.prior_hidden) + float(pilot.log_evidence[0])))
        if gap > config.smc_pilot_margin:
            run, particles = pilot, size
            break
    if run is None:
        run = run_smc(model, particles, threshold=config.resample_threshold, generator=generator,
                      device=frames.device)
    log_hidden = float(run.log_evidence[0])
    total, p_hidden = mixture(config.prior_hidden, log_hidden, log_empty)
    return SMCEstimate(total, log_hidden, log_empty, p_hidden, float(run.final_ess[0]), float(run.ess[0].min()),
                       int(run.lineages[0]), int(run.resampled[0].sum()), particles,
                       run.state.trajectory,
                       run.log_weights[0])


def pilot_sizes(config: InferenceConfig) -> tuple[int, ...]:
    """The pilot runs' particle counts, smallest first: those of config.smc_pilot between 0 and
    config.particles."""
    sizes = (config.smc_pilot,) if isinstance(config.smc_pilot, int) else tuple(config.smc_pilot)
    if list(sizes) != sorted(sizes):
        raise ValueError(f"smc_pilot's runs go smallest first, not {sizes}")
    return tuple(size for size in sizes if 0 < size < config.particles)


# --- explanations, plural -----------------------------------------------------------------

@dataclass
class Hypotheses:
    """The distinct weighted trajectories of a hidden object, heaviest first."""

    trajectories: Tensor          # (H, T, D)
    weights: Tensor               # (H,) their share of the posterior given an object (sum <= 1)
    copies: Tensor                # (H,) how many particles carry each
    spread: Tensor                # (T,) weighted standard deviation between them per frame (RMS over D)
    disagree: list[int] = field(default_factory=list)   # frames where they differ most, most first


def top_hypotheses(estimate: SMCEstimate, top: int = 4) -> Hypotheses | None:
    """The `top` heaviest distinct trajectories after resampling (copies of one particle are
    merged and their weights added), and where they disagree: the weighted spread between them
    per frame, and the frames in order of that spread. None where no object can be placed."""
    if estimate.trajectories is None:
        return None
    unique, inverse = torch.unique(estimate.trajectories.flatten(1), dim=0, return_inverse=True)
    weights = torch.zeros(len(unique), dtype=torch.float64, device=unique.device).index_add_(0, inverse,
                                                                                             estimate.weights)
    copies = torch.zeros(len(unique), dtype=torch.long, device=unique.device).index_add_(0, inverse,
                                                                                         torch.ones_like(inverse))
    order = weights.argsort(descending=True)[:top]
    trajectories = unique[order].reshape(len(order), *estimate.trajectories.shape[1:])
    chosen = weights[order]
    share = chosen / chosen.sum()
    mean = (share[:, None, None] * trajectories.double()).sum(0)
    variance = (share[:, None, None] * (trajectories.double() - mean).square()).sum(0)   # (T, D)
    spread = variance.mean(dim=1).sqrt()
    disagree = [int(t) for t in spread.argsort(descending=True) if spread[t] > 1e-6]
    return Hypotheses(trajectories, chosen, copies[order], spread, disagree)
