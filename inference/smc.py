"""Sequential Monte Carlo over frames: the estimator, for any model stepped frame by frame.

`run_smc` steps `runs` independent filters of N particles together through a `SequentialModel`:
at frame t each particle is drawn and weighted (the model's `step`), and a run whose effective
sample size falls below a threshold is resampled (systematic resampling) and its mean weight
moved into its evidence. Importance sampling is the same run never resampled (threshold 0).

    log p^(x) = sum over resampling epochs of log mean w      (unbiased in p, not in log p)

The normaliser after each frame estimates p(x_<=t) the same way, so the evidence is kept
frame by frame too (`SMCRun.frame_log_evidence`).
Independent runs of one target pool into one estimate, the mean of their evidence (`pooled`).

Pyro's `SMCFilter` is not used: it keeps float32 weights, renormalises them every step (the
evidence is lost), and resamples from the global random state; here the weights are float64
and a `torch.Generator` makes a score reproducible from a seed. Runs may be batched (`runs`),
so the tests measure the estimator's distribution with thousands of replicates in one pass.
The hidden-object model's steps are `inference.model_steps.ModelSteps`; one video's evidence,
existence and explanation summed out, is `inference.evidence`.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from itertools import accumulate
from typing import Any, Protocol

import torch
from torch import Tensor

__all__ = ["SMCRun", "SequentialModel", "effective_sample_size", "pooled", "run_smc", "systematic_resample"]


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

    def one(self, run: int, model: SequentialModel) -> SMCRun:
        """Run `run` of a batch alone, a batch of one: its rows, and its particles of the final
        state (`model.select`: runs lie one after another)."""
        particles = self.log_weights.shape[1]
        rows = slice(run, run + 1)
        state = model.select(self.state, torch.arange(run * particles, (run + 1) * particles,
                                                      device=self.log_weights.device))
        return SMCRun(self.log_evidence[rows], self.log_weights[rows], state, self.ess[rows], self.resampled[rows],
                      self.origin[rows], self.frame_log_evidence[rows])

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


def pooled(runs: list[SMCRun], join: Callable[[list[Any]], Any]) -> SMCRun:
    """Independent runs of one target (batches of one, as `SMCRun.one` gives them) as one
    estimate: the mean of their evidence after every frame, which is unbiased as each run's is,
    so that a run that misses a narrow mode costs log K nats rather than the mode; and their
    particles together, each run's weights scaled to its share of that mean. The ESS is the
    pooled weights': 1 / sum_k (share_k^2 / ess_k). `join` makes one state of the runs' final
    states, in order."""
    if len(runs) == 1:
        return runs[0]
    frames = torch.cat([run.frame_log_evidence for run in runs])                        # (K, T)
    evidence = torch.logsumexp(frames, dim=0, keepdim=True) - math.log(len(runs))      # (1, T): the last, the video
    shares = torch.softmax(frames, dim=0)
    ess = 1.0 / (shares.square() / torch.cat([run.ess for run in runs])).sum(0, keepdim=True)
    log_weights = torch.cat([torch.log_softmax(run.log_weights, dim=1) + run.log_evidence[:, None] for run in runs],
                            dim=1)
    offsets = accumulate((run.log_weights.shape[1] for run in runs[:-1]), initial=0)
    origin = torch.cat([run.origin + offset for run, offset in zip(runs, offsets)], dim=1)
    resampled = torch.stack([run.resampled for run in runs]).any(dim=0)
    return SMCRun(evidence[:, -1], log_weights, join([run.state for run in runs]), ess, resampled, origin, evidence)
