"""The hidden-object model taken frame by frame through Pyro's trace and replay, for `run_smc`.

Frame t's draws come from the guide's step, their log-weights from the model's step replayed on
them; the branch without a hidden object is traced once, exactly (`empty_branches`).
"""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pyro
import torch
from pyro import poutine
from torch import Tensor

from .model import HiddenObjectModel, Proposal, State

__all__ = ["ModelSteps", "empty_branches", "seeded", "site_log_probs"]


class ModelSteps:
    """`HiddenObjectModel` and its guide taken frame by frame, for `run_smc`: frame t's draws are
    a trace of the guide's step, and their log-weights the model's step replayed on them (log p
    less log q of every site, summed per particle in float64); the first frame runs `init` too.
    `fixed` holds the first frame's discrete sites (`exists`, `two`) the SMC sums out by running
    each value: one value for every particle, or one per run (R,), the runs stepped as one batch;
    a site it leaves out the guide proposes (importance sampling)."""

    def __init__(self, model: HiddenObjectModel, frames: Tensor, proposal: Proposal | None,
                 widenings: tuple[float, ...], fixed: dict[str, float | Tensor] | None = None):
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
            fixed = {name: _per_particle(value, n, self.observed.device) for name, value in self.fixed.items()}
            guide, model = poutine.condition(guide, data=fixed), poutine.condition(model, data=fixed)
        guide_trace = poutine.trace(guide).get_trace()
        model_trace = poutine.trace(poutine.replay(model, trace=guide_trace)).get_trace()
        return state, site_log_probs(model_trace, n) - site_log_probs(guide_trace, n, sampled_only=True)

    def select(self, state: State, index: Tensor) -> State:
        chosen = {name: value[index] if isinstance(value, Tensor) else value for name, value in state.items()}
        chosen["memory"] = self.model.scene.select(state["memory"], index)
        chosen["particles"] = len(index)
        return chosen


def _per_particle(value: float | Tensor, particles: int, device: torch.device) -> Tensor:
    """A fixed site's value for each of the particles (n,): one for all, or one per run (R,)
    repeated for that run's n / R particles (`run_smc` lays runs out one after another); float64,
    as the priors' logits are, so that their log-densities keep their digits."""
    if isinstance(value, Tensor):
        return value.to(device, torch.float64).repeat_interleave(particles // len(value))
    return torch.full((particles,), float(value), dtype=torch.float64, device=device)


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


def empty_branches(model: HiddenObjectModel, frames: Tensor) -> Tensor:
    """log p(x, no hidden object, v) frame by frame (V, T) float64 for each explanation v of what
    was seen, exact: the whole-video model traced once with one particle per explanation,
    `exists` fixed to 0 and `two` to v, every latent masked. Frame t holds the terms its step
    adds (x_t and motion_{t+1}; `exists` and `two` at frame 0), as the SMC's weights do."""
    versions = model.scene.versions
    absent = {"exists": torch.zeros(versions, dtype=torch.float64, device=frames.device),
              "two": torch.arange(versions, dtype=torch.float64, device=frames.device)}
    per_frame = torch.zeros(versions, model.frames, dtype=torch.float64, device=frames.device)
    for name, log_prob in model.site_terms(frames, absent, versions):
        per_frame[:, _site_frame(name)] += log_prob.to(torch.float64)
    return per_frame


def _site_frame(name: str) -> int:
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
