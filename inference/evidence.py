"""The evidence of one video under the hidden-object model, by SMC or by importance sampling.

The SMC sums the existence of a hidden object and the explanation of the seen objects (one, or
two identical ones) out exactly: without a hidden object, every latent is masked and one
particle gives the exact branch; with one, N particles carry the trajectory (`run_smc`), in
runs pooled where the existence head is sure of an object (`pooled`).
Importance sampling is the same run never resampled, the guide proposing existence and the
explanation too.

    log p^(x, object, v) = the SMC's evidence of the branch with an object under explanation v
    log p^(x) = logsumexp over v of (log p^(x, object, v), log p(x, no object, v))

Both branches are kept frame by frame too: the SMC's normaliser after each frame estimates
p(x_<=t | object) (as unbiased as the whole video's), the branch without one is exact per
frame, and the differences of their mixture are each frame's surprise, -log p^(x_t | x_<t).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .model import HiddenObjectModel, InferenceConfig, Proposal, Scene
from .model_steps import ModelSteps, empty_branches, seeded
from .smc import SMCRun, pooled, run_smc

__all__ = ["Evidence", "hidden_runs", "importance_evidence", "smc_evidence", "widenings_of"]

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


def _frame_surprise(branches: list[Tensor]) -> Tensor:
    """-log p(x_t | x_<t) (T,) float64 from each branch's log p(x_<=t, branch) after every frame
    (T,): the differences of their sum over frames."""
    so_far = torch.logsumexp(torch.stack(branches), dim=0)
    return -torch.diff(so_far, prepend=so_far.new_zeros(1))


def _log_sum(values: list[float]) -> float:
    """log sum exp of a list of float64 log-values (-inf where it is empty)."""
    return float(torch.logsumexp(torch.tensor(values, dtype=torch.float64), dim=0)) if values else -math.inf


@torch.no_grad()
def smc_evidence(scene: Scene, frames: Tensor, config: InferenceConfig, proposal: Proposal | None,
                 generator: torch.Generator | None = None, free: bool = True,
                 refine: Callable[[Proposal], Proposal] | None = None) -> Evidence:
    """One video's evidence, summed over the scene's explanations of what was seen (its
    versions): each run once without a hidden object (one particle: every latent is masked, so
    it is exact) and by SMC over `config.particles` particles with one. `free` False: no slot is
    left for a hidden object, and the evidence is that of the branches without one, as where the
    existence head all but rules one out (`hidden_runs`; then 0 particles). `refine`: what the
    full run's proposal is made from the pilot's."""
    model = HiddenObjectModel(scene, config)
    device, versions = frames.device, range(scene.versions)
    with seeded(generator, device):
        empty = list(empty_branches(model, frames).cumsum(1))
        empty_end = [float(branch[-1]) for branch in empty]
        known = _log_sum(empty_end)
        runs = hidden_runs(model, frames, config, proposal, known, generator, refine) if free else []
    hidden_end = [float(run.log_evidence[0]) for run in runs]
    total = _log_sum(empty_end + hidden_end)
    p_two = math.exp(_log_sum(empty_end[1:] + hidden_end[1:]) - total) if scene.versions > 1 else 0.0
    frame_nll = _frame_surprise(empty + [run.frame_log_evidence[0] for run in runs])
    if not runs:        # no slot free for a hidden object, or no run made for one (`hidden_runs`)
        particles = config.particles if not free else 0
        return Evidence(total, -math.inf, total, 0.0, float(particles), float(particles), 0, 0, particles,
                        None, None, frame_nll=frame_nll, p_two=p_two)
    hidden = _log_sum(hidden_end)
    likelier = runs[max(versions, key=lambda version: hidden_end[version])]
    # every run's particles, each run's weights scaled to its share of p(x, object): one posterior
    log_weights = torch.cat([torch.log_softmax(run.log_weights[0], 0) + float(run.log_evidence[0]) for run in runs])
    version = torch.cat([torch.full((run.log_weights.shape[1],), v, dtype=torch.long, device=device)
                         for v, run in zip(versions, runs)])
    return Evidence(total, hidden, known, math.exp(hidden - total), float(likelier.final_ess[0]),
                    float(likelier.ess[0].min()), int(likelier.lineages[0]), int(likelier.resampled[0].sum()),
                    likelier.log_weights.shape[1], torch.cat([run.state["trajectory"] for run in runs]),
                    log_weights, frame_nll=frame_nll, p_two=p_two, version=version)


def hidden_runs(model: HiddenObjectModel, frames: Tensor, config: InferenceConfig, proposal: Proposal | None,
                known: float, generator: torch.Generator | None,
                refine: Callable[[Proposal], Proposal] | None = None) -> list[SMCRun]:
    """The SMC of the branch with a hidden object under each explanation of what was seen (one
    run each, in order, the explanations stepped as one batch). Where the existence head doubts
    an object, pilots first (`_piloted_runs`); where it is sure, full runs pooled
    (`_pooled_runs`); where it all but rules one out (under config.smc_object_floor), none: the
    branch with an object counts as nothing, as after a pilot that trails by more than float64
    keeps of log p(x). `known`: the exact branches' log p(x, no object), summed; `refine` moves
    the proposal's mean out of sight before a full run (`inference.guide.out_of_sight`)."""
    if proposal is not None and float(proposal.head) < config.smc_object_floor:
        return []
    if proposal is not None and float(proposal.head) > config.smc_pilot_skip_exists:
        return _pooled_runs(model, frames, config, proposal, known, generator, refine)
    return _piloted_runs(model, frames, config, proposal, known, generator, refine)


def _piloted_runs(model: HiddenObjectModel, frames: Tensor, config: InferenceConfig, proposal: Proposal | None,
                  known: float, generator: torch.Generator | None,
                  refine: Callable[[Proposal], Proposal] | None) -> list[SMCRun]:
    """Pilots of fewer particles around Transformer 2's mean as it is; an explanation whose pilot
    trails `known` by more than smc_pilot_margin nats ends there (the branch changes log p(x) by
    less than exp(-margin)), the others take the full run around the mean moved by `refine`:
    work that most videos, which show every object, never need."""
    found: dict[int, SMCRun] = {}
    for size in (*_pilot_sizes(config), config.particles):
        if size == config.particles and proposal is not None and refine is not None:
            proposal = refine(proposal)
        versions = [version for version in range(model.scene.versions) if version not in found]
        for version, one in zip(versions, _runs(model, frames, config, proposal, versions, size, generator)):
            if size == config.particles or _trails(one, known, config):
                found[version] = one
        if len(found) == model.scene.versions:
            break
    return [found[version] for version in range(model.scene.versions)]


def _pooled_runs(model: HiddenObjectModel, frames: Tensor, config: InferenceConfig, proposal: Proposal,
                 known: float, generator: torch.Generator | None,
                 refine: Callable[[Proposal], Proposal] | None) -> list[SMCRun]:
    """config.sure_runs full runs around the mean moved out of sight, each explanation's pooled
    into one estimate (`pooled`: the mean of their evidence). A never-seen cube is narrow and a
    run misses it now and then; the mean then loses log K nats where one run alone lost tens or
    hundreds (docs/decisions.md, "The NLL's settings", row `sure_runs`). Where the existence head
    is sure but not above config.sure_runs_exists, mostly videos whose every object is seen, an
    explanation whose first run trails `known` by more than smc_pilot_margin nats ends there, as
    after a pilot (row `sure_runs_exists`)."""
    versions = list(range(model.scene.versions))
    proposal = refine(proposal) if refine is not None else proposal
    first = _runs(model, frames, config, proposal, versions, config.particles, generator)
    made = {version: [run] for version, run in zip(versions, first)}
    more = versions if float(proposal.head) > config.sure_runs_exists else [
        version for version, run in zip(versions, first) if not _trails(run, known, config)]
    for _ in range(config.sure_runs - 1 if more else 0):
        for version, run in zip(more, _runs(model, frames, config, proposal, more, config.particles, generator)):
            made[version].append(run)
    return [pooled(made[version], _trajectories) for version in versions]


def _trails(run: SMCRun, known: float, config: InferenceConfig) -> bool:
    """Whether a run's branch with an object trails `known` (the branches without one) by more
    than config.smc_pilot_margin nats: it then changes log p(x) by less than exp(-margin)."""
    return known - float(run.log_evidence[0]) > config.smc_pilot_margin


def _runs(model: HiddenObjectModel, frames: Tensor, config: InferenceConfig, proposal: Proposal | None,
          versions: list[int], particles: int, generator: torch.Generator | None) -> list[SMCRun]:
    """One SMC run of `particles` for each explanation in `versions`, stepped as one batch."""
    steps = ModelSteps(model, frames, proposal, widenings_of(config),
                       {"exists": 1.0, "two": torch.tensor(versions, dtype=torch.float64)})
    run = run_smc(steps, particles, runs=len(versions), threshold=config.resample_threshold, generator=generator,
                  device=frames.device)
    return [run.one(row, steps) for row in range(len(versions))]


def _trajectories(states: list[dict]) -> dict[str, Tensor]:
    """The final states of pooled runs as one: their particles' trajectories, all `smc_evidence` reads."""
    return {"trajectory": torch.cat([state["trajectory"] for state in states])}


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


def _pilot_sizes(config: InferenceConfig) -> tuple[int, ...]:
    """The pilot runs' particle counts, smallest first: those of config.smc_pilot between 0 and
    config.particles."""
    sizes = (config.smc_pilot,) if isinstance(config.smc_pilot, int) else tuple(config.smc_pilot)
    if list(sizes) != sorted(sizes):
        raise ValueError(f"smc_pilot's runs go smallest first, not {sizes}")
    return tuple(size for size in sizes if 0 < size < config.particles)
