"""Vectorised importance sampling for Pyro models whose sites carry a particle dimension.

Pyro's `Importance` draws particles one Python loop iteration at a time, and
`vectorized_importance_weights(..., normalized=True)` fails here; so the model and the guide
put their sites inside a `pyro.plate("particles", N)` and this module traces each once: one
guide run proposes all N particles, one replayed model run scores them. Log-weights are
summed in float64, so that hundreds of thousands of pixel terms do not lose the digits
that tell two videos apart.

    log p(x) ~= logsumexp(log w) - log N,      ESS = (sum w)^2 / sum w^2
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import torch
from pyro import poutine
from pyro.util import check_model_guide_match


@dataclass
class Estimate:
    log_evidence: float          # log p(x), estimated
    ess: float                   # effective sample size of the normalised weights
    log_weights: torch.Tensor    # (N,) float64
    guide_trace: poutine.Trace
    model_trace: poutine.Trace

    @property
    def nll(self) -> float:
        """The surprise: -log p(x)."""
        return -self.log_evidence

    @property
    def weights(self) -> torch.Tensor:
        """Normalised importance weights (N,)."""
        return torch.softmax(self.log_weights, dim=0)

    def posterior_mean(self, name: str) -> torch.Tensor:
        """Importance-weighted mean of a sampled site over the particle dimension (dim 0)."""
        value = self.guide_trace.nodes[name]["value"].to(torch.float64)
        weights = self.weights.reshape(-1, *([1] * (value.dim() - 1)))
        return (weights * value).sum(0)

    def standard_error(self) -> float:
        """Delta-method standard error of log p^: sd(w) / (mean(w) sqrt(N))."""
        w = torch.exp(self.log_weights - self.log_weights.max())
        return float(w.std(unbiased=True) / (w.mean() * math.sqrt(len(w))))


def site_log_probs(trace: poutine.Trace, particles: int) -> torch.Tensor:
    """Per-particle sum of every sample site's log-density (masks and scales applied)."""
    trace.compute_log_prob()
    sites = [node for node in trace.nodes.values() if node["type"] == "sample"]
    total = torch.zeros(particles, dtype=torch.float64, device=sites[0]["log_prob"].device if sites else None)
    for node in sites:
        log_prob = node["log_prob"].to(torch.float64)
        if log_prob.dim() == 0:
            log_prob = log_prob.expand(particles)
        if log_prob.shape != (particles,):
            raise ValueError(f"site {node['name']!r} has log_prob shape {tuple(log_prob.shape)}; "
                             f"put it inside the particles plate (expected ({particles},))")
        total = total + log_prob
    return total


def importance(model, guide, *args, particles: int, **kwargs) -> Estimate:
    """Estimate log p(observations) with `particles` draws from `guide`, in one vectorised pass.

    model and guide take (*args, particles=..., **kwargs) and put every sample site inside a
    plate of size `particles` at dim -1 of the batch shape.
    """
    with torch.no_grad():
        guide_trace = poutine.trace(guide).get_trace(*args, particles=particles, **kwargs)
        model_trace = poutine.trace(poutine.replay(model, trace=guide_trace)).get_trace(
            *args, particles=particles, **kwargs)
        proposal = _sampled_only(guide_trace)
        require_match(model_trace, proposal)
        log_weights = site_log_probs(model_trace, particles) - site_log_probs(proposal, particles)
    log_evidence = float(torch.logsumexp(log_weights, 0) - math.log(particles))
    normalised = torch.softmax(log_weights, dim=0)
    ess = float(1.0 / (normalised ** 2).sum())
    return Estimate(log_evidence, ess, log_weights, guide_trace, model_trace)


def require_match(model_trace: poutine.Trace, guide_trace: poutine.Trace) -> None:
    """Refuse a guide that misses a latent of the model (replay would then draw it from the
    prior and bias the estimate without a word) or samples one the model lacks."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        try:
            check_model_guide_match(model_trace, guide_trace)
        except (RuntimeWarning, UserWarning, ValueError) as problem:
            raise ValueError(f"model and guide do not match: {problem}") from None


def _sampled_only(trace: poutine.Trace) -> poutine.Trace:
    """The guide's trace without observed sites (a guide observes nothing)."""
    for name, node in list(trace.nodes.items()):
        if node["type"] == "sample" and node["is_observed"]:
            trace.remove_node(name)
    return trace
