"""Importance sampling of the hidden-object model (`inference.evidence.importance_evidence`: the
frame-by-frame model and guide, never resampled) against closed-form evidence."""
import math
import warnings

import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro import poutine
from pyro.util import check_model_guide_match

from xvoe.inference.evidence import importance_evidence
from xvoe.inference.model import HiddenObjectModel, InferenceConfig, Proposal, _fuse, _LinearGaussianScene

pytestmark = pytest.mark.usefixtures("double_precision")     # these checks compare to 1e-4


# --- a hidden object with linear-Gaussian dynamics, through the real model's code path ----
T, D, OBS = 5, 2, 3
A = torch.tensor([[0.3, 0.05], [0.0, 0.25]], dtype=torch.float64)
H = 0.25 * torch.tensor([[1.0, 0.0], [0.5, 1.0], [0.0, -0.7]], dtype=torch.float64)   # faint: existence stays uncertain
M_0 = torch.tensor([0.3, -0.2], dtype=torch.float64)
S_0, Q, SIGMA, P = 0.8, 0.3, 0.4, 0.3
BACKGROUND = torch.tensor([0.1, 0.2, -0.1], dtype=torch.float64)


def settings(widening: float = 1.0, particles: int = 64) -> InferenceConfig:
    return InferenceConfig(prior_hidden=P, pixel_sigma=SIGMA, transition_sigma=Q, proposal_widening=widening,
                           particles=particles)


def linear_scene():
    return _LinearGaussianScene(T, M_0, S_0, A, H, BACKGROUND)


def linear_model(widening: float = 1.0):
    return HiddenObjectModel(linear_scene(), settings(widening))


def kalman_log_evidence(frames):
    """log p(frames | a hidden object exists), by the Kalman filter."""
    mean, cov, total = M_0, S_0 ** 2 * torch.eye(D), 0.0
    for t in range(T):
        if t > 0:
            mean, cov = A @ mean, A @ cov @ A.T + Q ** 2 * torch.eye(D)
        innovation_cov = H @ cov @ H.T + SIGMA ** 2 * torch.eye(OBS)
        predicted = BACKGROUND + H @ mean
        total += float(dist.MultivariateNormal(predicted, innovation_cov).log_prob(frames[t]))
        gain = cov @ H.T @ torch.linalg.inv(innovation_cov)
        mean, cov = mean + gain @ (frames[t] - predicted), (torch.eye(D) - gain @ H) @ cov
    return total


def empty_log_evidence(frames):
    return float(dist.Normal(BACKGROUND, SIGMA).log_prob(frames).sum())


def exact_mixture_evidence(frames):
    with_object, without = kalman_log_evidence(frames), empty_log_evidence(frames)
    return float(torch.logsumexp(torch.tensor([math.log(P) + with_object, math.log(1 - P) + without]), 0))


def trajectory_posterior(frames):
    """The joint Gaussian posterior of z_0..z_{T-1} given an object exists (dense algebra)."""
    transition_powers = [torch.linalg.matrix_power(A, t) for t in range(T)]
    prior_mean = torch.cat([p @ M_0 for p in transition_powers])
    prior_cov = torch.zeros(T * D, T * D)
    step_cov = [S_0 ** 2 * torch.eye(D)]
    for _ in range(1, T):
        step_cov.append(A @ step_cov[-1] @ A.T + Q ** 2 * torch.eye(D))
    for t in range(T):
        for s in range(t + 1):
            block = transition_powers[t - s] @ step_cov[s]          # Cov(z_t, z_s), s <= t
            prior_cov[t * D:(t + 1) * D, s * D:(s + 1) * D] = block
            prior_cov[s * D:(s + 1) * D, t * D:(t + 1) * D] = block.T
    camera = torch.block_diag(*[H] * T)
    precision = torch.linalg.inv(prior_cov) + camera.T @ camera / SIGMA ** 2
    cov = torch.linalg.inv(precision)
    mean = cov @ (torch.linalg.solve(prior_cov, prior_mean) + camera.T @ (frames - BACKGROUND).reshape(-1) / SIGMA ** 2)
    return mean, torch.linalg.cholesky(cov)


def simulate_frames(seed):
    torch.manual_seed(seed)
    z, frames = M_0 + S_0 * torch.randn(D), []
    for t in range(T):
        if t > 0:
            z = A @ z + Q * torch.randn(D)
        frames.append(BACKGROUND + H @ z + SIGMA * torch.randn(OBS))
    return torch.stack(frames)


@pytest.mark.parametrize("widening", [1.0, 3.0])
def test_importance_sampling_matches_the_kalman_evidence_and_the_posterior_of_existence(widening):
    """The real guide (Gaussians per frame fused with the dynamics' step, widened or not, and its
    own existence probability) stays within three standard errors of the exact evidence; the
    weighted share of particles with an object is the exact posterior probability that a
    hidden object exists."""
    frames = simulate_frames(2)
    mean, chol = trajectory_posterior(frames)
    marginal_sd = torch.sqrt((chol ** 2).sum(1)).reshape(T, D)
    proposal = Proposal(torch.tensor(0.5), mean.reshape(T, D), 1.2 * marginal_sd, torch.tensor(0.5))
    found = importance_evidence(linear_scene(), frames, settings(widening, particles=20_000), proposal,
                                torch.Generator().manual_seed(3))
    weights = torch.exp(found.log_weights - found.log_weights.max())
    standard_error = float(weights.std() / (weights.mean() * math.sqrt(len(weights))))
    assert abs(found.log_evidence - exact_mixture_evidence(frames)) < 3 * standard_error
    with_object, without = kalman_log_evidence(frames), empty_log_evidence(frames)
    p_post = 1 / (1 + (1 - P) / P * math.exp(without - with_object))
    assert 0.15 < p_post < 0.85                    # a case where the answer is not trivially 0 or 1
    assert found.p_hidden == pytest.approx(p_post, abs=0.02)
    assert found.log_weights.dtype == torch.float64 and found.exists.dtype == torch.bool


def test_the_models_guide_matches_the_model():
    frames, model = simulate_frames(2), linear_model()
    proposal = Proposal(torch.tensor(0.5), torch.zeros(T, D), torch.ones(T, D), torch.tensor(0.5))
    pyro.set_rng_seed(0)
    guide_trace = poutine.trace(model.guide).get_trace(frames, proposal, particles=8)
    model_trace = poutine.trace(poutine.replay(model.model, trace=guide_trace)).get_trace(frames, proposal, 8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_model_guide_match(model_trace, guide_trace)


def test_a_widened_proposal_becomes_the_models_own_prior():
    """Widened without bound, the fused proposal is the model's own first-frame prior and
    transitions (a bootstrap proposal), so the trajectory sites add nothing to the log-weights;
    unwidened, they do."""
    frames = simulate_frames(2)
    mean, chol = trajectory_posterior(frames)
    proposal = Proposal(torch.tensor(0.9), mean.reshape(T, D), 0.5 * torch.sqrt((chol ** 2).sum(1)).reshape(T, D),
                        torch.tensor(0.9))
    gaps = {}
    for widening in (1.0, 1e6):
        model = linear_model(widening=widening)
        pyro.set_rng_seed(4)
        guide_trace = poutine.trace(model.guide).get_trace(frames, proposal, particles=64)
        model_trace = poutine.trace(poutine.replay(model.model, trace=guide_trace)).get_trace(frames, proposal, 64)
        model_trace.compute_log_prob()
        guide_trace.compute_log_prob()
        alive = guide_trace.nodes["exists"]["value"].bool()
        assert alive.sum() > 10
        gap = sum(model_trace.nodes[f"z_{t}"]["log_prob"] - guide_trace.nodes[f"z_{t}"]["log_prob"] for t in range(T))
        gaps[widening] = gap[alive]
    torch.testing.assert_close(gaps[1e6], torch.zeros_like(gaps[1e6]), atol=1e-4, rtol=0)
    assert gaps[1.0].abs().min() > 0.01


def test_fuse_is_the_product_of_two_gaussians():
    loc, scale = _fuse(torch.tensor([0.0, 1.0]), torch.tensor([1.0, 0.1]), torch.tensor([2.0, 1.0]),
                      torch.tensor([1.0, 0.3]))
    torch.testing.assert_close(loc, torch.tensor([1.0, 1.0]))
    torch.testing.assert_close(scale, torch.tensor([0.5 ** 0.5, (1 / (100 + 1 / 0.09)) ** 0.5]))
