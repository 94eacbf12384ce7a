"""The importance-sampling estimator against closed-form evidence."""
import math
import warnings

import pyro
import pyro.distributions as dist
import pytest
import torch
from pyro.util import check_model_guide_match

from inference.importance import importance
from inference.model import HiddenObjectModel, InferenceConfig, LinearGaussianScene, Proposal, fuse

pytestmark = pytest.mark.usefixtures("double_precision")     # these checks compare to 1e-4


# --- a conjugate Gaussian: theta ~ N(m0, s0^2), x_i ~ N(theta, s^2) -----------------------
M0, S0, S = 0.5, 2.0, 0.7
X = torch.tensor([1.2, 0.4, 2.1, 1.7, 0.9], dtype=torch.float64)


def conjugate_model(x, particles):
    with pyro.plate("particles", particles, dim=-1):
        theta = pyro.sample("theta", dist.Normal(torch.tensor(M0), S0))
        pyro.sample("x", dist.Normal(theta[:, None], S).to_event(1), obs=x.expand(particles, -1))


def exact_evidence(x):
    n = len(x)
    covariance = S ** 2 * torch.eye(n) + S0 ** 2 * torch.ones(n, n)
    return float(dist.MultivariateNormal(torch.full((n,), M0), covariance).log_prob(x))


def posterior_guide(x, particles):
    precision = 1 / S0 ** 2 + len(x) / S ** 2
    mean = (M0 / S0 ** 2 + x.sum() / S ** 2) / precision
    with pyro.plate("particles", particles, dim=-1):
        pyro.sample("theta", dist.Normal(mean, precision ** -0.5))


def poor_guide(x, particles):
    with pyro.plate("particles", particles, dim=-1):
        pyro.sample("theta", dist.Normal(torch.tensor(-1.0), 3.0))


def test_exact_proposal_gives_the_evidence_and_full_ess():
    pyro.set_rng_seed(0)
    estimate = importance(conjugate_model, posterior_guide, X, particles=256)
    assert estimate.log_evidence == pytest.approx(exact_evidence(X), abs=1e-4)
    assert estimate.ess == pytest.approx(256, rel=1e-6)
    assert estimate.log_weights.dtype == torch.float64


def test_poor_proposal_is_within_three_standard_errors():
    pyro.set_rng_seed(1)
    estimate = importance(conjugate_model, poor_guide, X, particles=20_000)
    error = abs(estimate.log_evidence - exact_evidence(X))
    assert error < 3 * estimate.standard_error()
    assert estimate.ess < 0.5 * 20_000          # a poor proposal does lose particles


def test_a_guide_missing_a_latent_is_refused():
    def incomplete_guide(x, particles):
        pass

    with pytest.raises(ValueError, match="do not match"):
        importance(conjugate_model, incomplete_guide, X, particles=4)


# --- a hidden object with linear-Gaussian dynamics, through the real model's code path ----
T, D, OBS = 5, 2, 3
A = torch.tensor([[0.3, 0.05], [0.0, 0.25]], dtype=torch.float64)
H = 0.25 * torch.tensor([[1.0, 0.0], [0.5, 1.0], [0.0, -0.7]], dtype=torch.float64)   # faint: existence stays uncertain
M_0 = torch.tensor([0.3, -0.2], dtype=torch.float64)
S_0, Q, SIGMA, P = 0.8, 0.3, 0.4, 0.3
BACKGROUND = torch.tensor([0.1, 0.2, -0.1], dtype=torch.float64)


def linear_model(follow_dynamics: bool = True, widening: float = 1.0):
    scene = LinearGaussianScene(T, M_0, S_0, A, H, BACKGROUND)
    return HiddenObjectModel(scene, InferenceConfig(prior_hidden=P, pixel_sigma=SIGMA, transition_sigma=Q,
                                                    guide_follows_dynamics=follow_dynamics,
                                                    proposal_widening=widening))


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


def exact_guide(frames, proposal=None, particles=1):
    """Draws from the exact posterior, as a chain of conditionals on the same sites."""
    with_object, without = kalman_log_evidence(frames), empty_log_evidence(frames)
    p_post = 1 / (1 + (1 - P) / P * math.exp(without - with_object))
    mean, chol = trajectory_posterior(frames)
    with pyro.plate("particles", particles, dim=-1):
        exists = pyro.sample("exists", dist.Bernoulli(torch.tensor(p_post)))
        noise = []
        with pyro.poutine.mask(mask=exists.bool()):
            for t in range(T):
                rows = slice(t * D, (t + 1) * D)
                loc = mean[rows] + (torch.stack(noise, 1).reshape(particles, -1) @ chol[rows, :t * D].T
                                    if noise else 0.0)
                z = pyro.sample(f"z_{t}", dist.MultivariateNormal(loc, scale_tril=chol[rows, rows]))
                noise.append(torch.linalg.solve_triangular(chol[rows, rows], (z - loc).T, upper=False).T)
    return exists


def simulate_frames(seed):
    torch.manual_seed(seed)
    z, frames = M_0 + S_0 * torch.randn(D), []
    for t in range(T):
        if t > 0:
            z = A @ z + Q * torch.randn(D)
        frames.append(BACKGROUND + H @ z + SIGMA * torch.randn(OBS))
    return torch.stack(frames)


def test_linear_gaussian_exact_proposal_matches_the_kalman_evidence():
    frames, model = simulate_frames(0), linear_model()
    pyro.set_rng_seed(2)
    estimate = importance(model.model, exact_guide, frames, particles=512)
    assert estimate.log_evidence == pytest.approx(exact_mixture_evidence(frames), abs=1e-4)
    assert estimate.ess == pytest.approx(512, rel=1e-6)


@pytest.mark.parametrize("follow_dynamics, widening", [(True, 1.0), (True, 3.0), (False, 1.0)])
def test_linear_gaussian_amortised_style_proposal_and_posterior_of_existence(follow_dynamics, widening):
    """The real guide (Gaussians per frame, fused with the dynamics' step or not, widened or
    not, and its own existence probability) stays within three standard errors; the weighted
    share of particles with an object is the exact posterior probability that a hidden object
    exists."""
    frames, model = simulate_frames(2), linear_model(follow_dynamics, widening)
    mean, chol = trajectory_posterior(frames)
    marginal_sd = torch.sqrt((chol ** 2).sum(1)).reshape(T, D)
    proposal = Proposal(torch.tensor(0.5), mean.reshape(T, D), 1.2 * marginal_sd)
    pyro.set_rng_seed(3)
    estimate = importance(model.model, model.guide, frames, proposal=proposal, particles=20_000)
    assert abs(estimate.log_evidence - exact_mixture_evidence(frames)) < 3 * estimate.standard_error()
    with_object, without = kalman_log_evidence(frames), empty_log_evidence(frames)
    p_post = 1 / (1 + (1 - P) / P * math.exp(without - with_object))
    assert 0.15 < p_post < 0.85                    # a case where the answer is not trivially 0 or 1
    assert float(estimate.posterior_mean("exists")) == pytest.approx(p_post, abs=0.02)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_model_guide_match(estimate.model_trace, estimate.guide_trace)


def test_a_widened_proposal_becomes_the_models_own_prior():
    """Widened without bound, the fused proposal is the model's own first-frame prior and
    transitions (a bootstrap proposal), so the trajectory sites add nothing to the log-weights;
    unwidened, they do."""
    frames = simulate_frames(2)
    mean, chol = trajectory_posterior(frames)
    proposal = Proposal(torch.tensor(0.9), mean.reshape(T, D), 0.5 * torch.sqrt((chol ** 2).sum(1)).reshape(T, D))
    gaps = {}
    for widening in (1.0, 1e6):
        model = linear_model(widening=widening)
        pyro.set_rng_seed(4)
        estimate = importance(model.model, model.guide, frames, proposal=proposal, particles=64)
        model_trace, guide_trace = estimate.model_trace, estimate.guide_trace
        alive = guide_trace.nodes["exists"]["value"].bool()
        assert alive.sum() > 10
        gap = sum(model_trace.nodes[f"z_{t}"]["log_prob"] - guide_trace.nodes[f"z_{t}"]["log_prob"] for t in range(T))
        gaps[widening] = gap[alive]
    torch.testing.assert_close(gaps[1e6], torch.zeros_like(gaps[1e6]), atol=1e-4, rtol=0)
    assert gaps[1.0].abs().min() > 0.01


def test_fuse_is_the_product_of_two_gaussians():
    loc, scale = fuse(torch.tensor([0.0, 1.0]), torch.tensor([1.0, 0.1]), torch.tensor([2.0, 1.0]),
                      torch.tensor([1.0, 0.3]))
    torch.testing.assert_close(loc, torch.tensor([1.0, 1.0]))
    torch.testing.assert_close(scale, torch.tensor([0.5 ** 0.5, (1 / (100 + 1 / 0.09)) ** 0.5]))
