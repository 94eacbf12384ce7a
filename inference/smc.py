"""Sequential Monte Carlo over frames, and importance sampling, of the hidden-object model.

Both run `inference.model.HiddenObjectModel` and its guide frame by frame through Pyro's trace
and replay (`ModelSteps`): frame t's draws come from the guide's step, their log-weights from
the model's step replayed on them. The SMC sums the existence of a hidden object and the
explanation of the seen objects (one, or two identical ones) out exactly: without a hidden
object, every latent is masked and one particle gives the exact branch; with one, N particles
carry the trajectory, weighted frame by frame and resampled (systematic resampling) when the
effective sample size falls below a threshold. Importance sampling is the same run never
resampled, the guide proposing existence and the explanation too.

    log p^(x, object, v) = sum over resampling epochs of log mean w      (unbiased in p, not in log p)
    log p^(x) = logsumexp over v of (log p^(x, object, v), log p(x, no object, v))

Both branches are kept frame by frame too: the SMC's normaliser after each frame estimates
p(x_<=t | object) (as unbiased as the whole video's), the branch without one is exact per
frame, and the differences of their mixture are each frame's surprise, -log p^(x_t | x_<t).

Pyro's `SMCFilter` is not used: it keeps float32 weights, renormalises them every step (the
evidence is lost), and resamples from the global random state; here the weights are float64
and a `torch.Generator` makes a score reproducible from a seed. Runs may be batched (`runs`),
so the tests measure the estimator's distribution with thousands of replicates in one pass.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import pyro
import torch
from pyro import poutine
from torch import Tensor

from .model import HiddenObjectModel, InferenceConfig, Proposal, Scene, State


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
    frame_log_evidence: Tensor    # (R, T) float64 log p^(x_<=t): the normaliser after each frame

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
    follows to use the copies), so they stay a weighted sample of the posterior. The evidence
    after every frame, resampled or not, is the epochs' evidence times the carried weights'
    mean (frame t adds log sum_i W_i w_t,i): the last frame's is the whole video's."""
    n = runs * particles
    state = model.start(n)
    log_weights = torch.zeros(runs, particles, dtype=torch.float64, device=device)
    log_evidence = torch.zeros(runs, dtype=torch.float64, device=device)
    origin = torch.arange(particles, device=device).expand(runs, particles).clone()
    ess, resampled, so_far = [], [], []
    base = (torch.arange(runs, device=device) * particles)[:, None]
    target = threshold * particles

    for t in range(model.frames):
        state, increment = model.step(t, state, generator)
        log_weights = log_weights + increment.reshape(runs, particles)
        so_far.append(log_evidence + (torch.logsumexp(log_weights, dim=1) - math.log(particles)))
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
    return SMCRun(log_evidence, log_weights, state, torch.stack(ess, dim=1), torch.stack(resampled, dim=1), origin,
                  torch.stack(so_far, dim=1))


# --- the Pyro model, frame by frame ---------------------------------------------------------

class ModelSteps:
    """`HiddenObjectModel` and its guide taken frame by frame, for `run_smc`: frame t's draws are
    a trace of the guide's step, and their log-weights the model's step replayed on them (log p
    less log q of every site, summed per particle in float64); the first frame runs `init` too.
    `fixed` holds the first frame's discrete sites (`exists`, `two`) the SMC sums out by running
    each value; a site it leaves out the guide proposes (importance sampling)."""

    def __init__(self, model: HiddenObjectModel, frames: Tensor, proposal: Proposal | None,
                 widenings: tuple[float, ...], fixed: dict[str, float] | None = None):
        self.model, self.observed, self.proposal, self.widenings = model, frames, proposal, widenings
        self.frames, self.fixed = model.frames, fixed or {}

    def start(self, particles: int) -> State:
        return {"particles": particles}

    def step(self, t: int, state: State, generator: torch.Generator | None) -> tuple[State, Tensor]:
        """Pyro draws from the global random state: the caller seeds it (`seeded`)."""
        n = state["particles"]

        def guide() -> None:
            with pyro.plate("particles", n, dim=-1):
                if t == 0:
                    self.model.guide_init(state, n, self.proposal)
                self.model.guide_step(state, t, self.proposal, self.widenings)

        def model() -> None:
            with pyro.plate("particles", n, dim=-1):
                if t == 0:
                    self.model.init(state, n)
                self.model.step(state, t, self.observed[t])

        if self.fixed and t == 0:     # the only frame with discrete sites
            fixed = {name: torch.full((n,), float(value), device=self.observed.device)
                     for name, value in self.fixed.items()}
            guide, model = poutine.condition(guide, data=fixed), poutine.condition(model, data=fixed)
        guide_trace = poutine.trace(guide).get_trace()
        model_trace = poutine.trace(poutine.replay(model, trace=guide_trace)).get_trace()
        return state, site_log_probs(model_trace, n) - site_log_probs(guide_trace, n, sampled_only=True)

    def select(self, state: State, index: Tensor) -> State:
        chosen = {name: value[index] if isinstance(value, Tensor) else value for name, value in state.items()}
        chosen["memory"] = self.model.scene.select(state["memory"], index)
        return chosen


def site_log_probs(trace: poutine.Trace, particles: int, sampled_only: bool = False) -> Tensor:
    """Per-particle sum (particles,) float64 of every sample site's log-density, masks applied;
    `sampled_only`: without the observed sites (a guide's conditioned ones are no proposal)."""
    trace.compute_log_prob()
    sites = [node for node in trace.nodes.values()
             if node["type"] == "sample" and not (sampled_only and node["is_observed"])]
    total = torch.zeros(particles, dtype=torch.float64, device=sites[0]["log_prob"].device if sites else None)
    for node in sites:
        log_prob = node["log_prob"].to(torch.float64)
        if log_prob.shape not in ((), (particles,)):
            raise ValueError(f"site {node['name']!r} has log_prob shape {tuple(log_prob.shape)}; "
                             f"put it inside the particles plate (expected ({particles},))")
        total = total + log_prob
    return total


def empty_branch(model: HiddenObjectModel, frames: Tensor, version: int = 0) -> Tensor:
    """log p(x, no hidden object, version) frame by frame (T,) float64, exact: the whole-video
    model traced once with `exists` fixed to 0, `two` to the version, and one particle, every
    latent masked. Frame t holds the terms its step adds (x_t and motion_{t+1}; `exists` and
    `two` at frame 0), as the SMC's weights do."""
    absent = {"exists": torch.zeros(1, device=frames.device), "two": torch.full((1,), float(version),
                                                                                device=frames.device)}
    trace = poutine.trace(poutine.condition(model.model, data=absent)).get_trace(frames)
    trace.compute_log_prob()
    per_frame = torch.zeros(model.frames, dtype=torch.float64, device=frames.device)
    for name, node in trace.nodes.items():
        if node["type"] == "sample" and name != "particles":
            per_frame[site_frame(name)] += node["log_prob"].to(torch.float64).sum()
    return per_frame


def site_frame(name: str) -> int:
    """The frame whose step holds a site of `HiddenObjectModel`: exists and two at 0, z_t and x_t
    at t, motion_t at t - 1 (observed once frame t - 1 is drawn)."""
    if name in ("exists", "two"):
        return 0
    kind, frame = name.rsplit("_", 1)
    return int(frame) - (kind == "motion")


@contextmanager
def seeded(generator: torch.Generator | None, device: torch.device | None = None) -> Iterator[None]:
    """The global random state, which Pyro draws from, seeded from `generator` and put back
    after: an estimate is a function of its seed, whatever was drawn before. On CUDA Pyro draws
    from that device's state: seeded from the same seed, it is put back too."""
    with torch.random.fork_rng(devices=[device] if device is not None and device.type == "cuda" else []):
        torch.manual_seed(int(torch.randint(2 ** 62, (1,), generator=generator)))
        yield


# --- the evidence of a video ---------------------------------------------------------------

@dataclass
class Evidence:
    """The NLL estimate of one video, by SMC (existence and identity summed out exactly) or by
    importance sampling (both proposed by the guide)."""

    log_evidence: float           # log p^(x)
    log_evidence_hidden: float    # log p^(x, a hidden object) (SMC; nan by importance sampling), -inf where none fits
    log_evidence_empty: float     # log p(x, no hidden object), exact (SMC; nan by importance sampling)
    p_hidden: float               # posterior probability of a hidden object
    ess: float                    # ESS of the final weights (SMC: the likelier explanation's run, all holding one)
    min_ess: float                # the lowest ESS over frames, before resampling
    lineages: int                 # distinct first-frame ancestors of the final particles
    resamplings: int
    particles: int
    trajectories: Tensor | None   # (N, T, D) final particles, None where no object can be placed
    log_weights: Tensor | None    # (N,) float64 final log-weights, of the posterior over all of them
    exists: Tensor | None = None  # (N,) bool: which final particles hold an object (None: all)
    frame_nll: Tensor | None = None   # (T,) float64 -log p^(x_t | x_<t), existence summed out; sums to nll
    p_two: float = 0.0            # posterior probability that a seen object is two identical ones
    version: Tensor | None = None     # (N,) long: each final particle's explanation (1: two objects)

    @property
    def nll(self) -> float:
        return -self.log_evidence

    @property
    def weights(self) -> Tensor:
        return torch.softmax(self.log_weights, dim=0)

    def holding(self) -> tuple[Tensor, Tensor] | None:
        """The trajectories (H, T, D) of the particles that hold an object and their log-weights
        (H,); None where none does."""
        if self.trajectories is None:
            return None
        if self.exists is None:
            return self.trajectories, self.log_weights
        return (self.trajectories[self.exists], self.log_weights[self.exists]) if self.exists.any() else None

    def holding_versions(self) -> Tensor | None:
        """The explanation (H,) of each particle `holding` returns."""
        if self.trajectories is None:
            return None
        version = self.version if self.version is not None else torch.zeros(
            len(self.trajectories), dtype=torch.long, device=self.trajectories.device)
        return version if self.exists is None else version[self.exists]


def widenings_of(config: InferenceConfig) -> tuple[float, ...]:
    """The SMC proposal's widenings (`smc_proposal_widening`; None: `proposal_widening`)."""
    widenings = config.smc_proposal_widening
    if widenings is None:
        return (config.proposal_widening,)
    return (widenings,) if isinstance(widenings, (int, float)) else tuple(widenings)


def frame_surprise(branches: list[Tensor]) -> Tensor:
    """-log p(x_t | x_<t) (T,) float64 from each branch's log p(x_<=t, branch) after every frame
    (T,): the differences of their sum over frames."""
    so_far = torch.logsumexp(torch.stack(branches), dim=0)
    return -torch.diff(so_far, prepend=so_far.new_zeros(1))


def log_sum(values: list[float]) -> float:
    """log sum exp of a list of float64 log-values (-inf where it is empty)."""
    return float(torch.logsumexp(torch.tensor(values, dtype=torch.float64), dim=0)) if values else -math.inf


@torch.no_grad()
def smc_evidence(scene: Scene, frames: Tensor, config: InferenceConfig, proposal: Proposal | None,
                 generator: torch.Generator | None = None, free: bool = True) -> Evidence:
    """One video's evidence, summed over the scene's explanations of what was seen (its
    versions): each run once without a hidden object (one particle: every latent is masked, so
    it is exact) and by SMC over `config.particles` particles with one. `free` False: no slot is
    left for a hidden object, and the evidence is that of the branches without one."""
    model = HiddenObjectModel(scene, config)
    device, versions = frames.device, range(scene.versions)
    with seeded(generator, device):
        empty = [empty_branch(model, frames, version).cumsum(0) for version in versions]
        empty_end = [float(branch[-1]) for branch in empty]
        known = log_sum(empty_end)
        runs = [hidden_run(model, frames, config, proposal, version, known, generator) for version in versions] \
            if free else []
    hidden_end = [float(run.log_evidence[0]) for run in runs]
    total = log_sum(empty_end + hidden_end)
    p_two = math.exp(log_sum(empty_end[1:] + hidden_end[1:]) - total) if scene.versions > 1 else 0.0
    frame_nll = frame_surprise(empty + [run.frame_log_evidence[0] for run in runs])
    if not free:
        particles = config.particles
        return Evidence(total, -math.inf, total, 0.0, float(particles), float(particles), 0, 0, particles,
                        None, None, frame_nll=frame_nll, p_two=p_two)
    hidden = log_sum(hidden_end)
    likelier = runs[max(versions, key=lambda version: hidden_end[version])]
    # every run's particles, each run's weights scaled to its share of p(x, object): one posterior
    log_weights = torch.cat([torch.log_softmax(run.log_weights[0], 0) + float(run.log_evidence[0]) for run in runs])
    version = torch.cat([torch.full((run.log_weights.shape[1],), v, dtype=torch.long, device=device)
                         for v, run in zip(versions, runs)])
    return Evidence(total, hidden, known, math.exp(hidden - total), float(likelier.final_ess[0]),
                    float(likelier.ess[0].min()), int(likelier.lineages[0]), int(likelier.resampled[0].sum()),
                    likelier.log_weights.shape[1], torch.cat([run.state["trajectory"] for run in runs]),
                    log_weights, frame_nll=frame_nll, p_two=p_two, version=version)


def hidden_run(model: HiddenObjectModel, frames: Tensor, config: InferenceConfig, proposal: Proposal | None,
               version: int, known: float, generator: torch.Generator | None) -> SMCRun:
    """The SMC of the branch with a hidden object under one explanation of what was seen. A
    pilot of fewer particles is kept where it trails `known` (the exact branches' log p(x, no
    object) summed) by more than smc_pilot_margin nats: the branch then changes log p(x) by
    less than exp(-margin)."""
    steps = ModelSteps(model, frames, proposal, widenings_of(config), {"exists": 1.0, "two": float(version)})
    sure = proposal is not None and float(proposal.p_exists) > config.smc_pilot_skip_exists
    for size in () if sure else pilot_sizes(config):
        pilot = run_smc(steps, size, threshold=config.resample_threshold, generator=generator, device=frames.device)
        if known - float(pilot.log_evidence[0]) > config.smc_pilot_margin:
            return pilot
    return run_smc(steps, config.particles, threshold=config.resample_threshold, generator=generator,
                   device=frames.device)


@torch.no_grad()
def importance_evidence(scene: Scene, frames: Tensor, config: InferenceConfig, proposal: Proposal,
                        generator: torch.Generator | None = None) -> Evidence:
    """One video's evidence by importance sampling: the same frame-by-frame model and guide,
    never resampled, the guide proposing the existence of a hidden object and the explanation
    of the seen objects too."""
    model = HiddenObjectModel(scene, config)
    particles = config.particles
    with seeded(generator, frames.device):
        run = run_smc(ModelSteps(model, frames, proposal, (config.proposal_widening,)), particles,
                      threshold=0.0, generator=generator, device=frames.device)
    log_weights, exists, version = run.log_weights[0], run.state["exists"], run.state["version"]
    weights = torch.softmax(log_weights, dim=0)
    p_hidden = float((weights * exists).sum().clamp(0.0, 1.0))      # a weighted sum can round past 1
    p_two = float((weights * version).sum().clamp(0.0, 1.0))
    return Evidence(float(run.log_evidence[0]), math.nan, math.nan, p_hidden, float(run.final_ess[0]),
                    float(run.ess[0].min()), int(run.lineages[0]), 0, particles, run.state["trajectory"],
                    log_weights, exists, p_two=p_two, version=version)


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
