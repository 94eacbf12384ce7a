"""Sequential Monte Carlo (inference.smc) against closed forms, on small models."""
import math
from dataclasses import replace

import pyro
import pytest
import torch
from pyro import poutine

from xvoe.inference.evidence import Evidence, smc_evidence, widenings_of
from xvoe.inference.hypotheses import top_hypotheses
from xvoe.inference.model import HiddenObjectModel, InferenceConfig, Proposal, _LinearGaussianScene
from xvoe.inference.model_steps import ModelSteps
from xvoe.inference.smc import effective_sample_size, pooled, run_smc, systematic_resample

pytestmark = pytest.mark.usefixtures("double_precision")


# --- resampling ------------------------------------------------------------------------------

def test_systematic_resampling_keeps_the_weights_mean():
    """Each particle is kept floor(N w) or ceil(N w) times, N w on average over the uniform;
    so the mean of any function over the copies is, in expectation, its weighted mean."""
    generator = torch.Generator().manual_seed(0)
    weights = torch.softmax(torch.randn(1, 7, generator=generator) * 2, dim=1)
    runs = 20_000
    ancestors = systematic_resample(weights.expand(runs, -1), generator)
    counts = torch.zeros(runs, 7).scatter_add_(1, ancestors, torch.ones(runs, 7))
    expected = 7 * weights[0]
    assert ((counts >= expected.floor() - 1e-9) & (counts <= expected.ceil() + 1e-9)).all()
    assert (counts.sum(1) == 7).all()
    error = (counts.mean(0) - expected).abs()
    assert (error <= 3 * counts.std(0) / math.sqrt(runs) + 1e-9).all()
    values = torch.randn(7, generator=generator)
    resampled_means = values[ancestors].mean(1)
    weighted = float((weights[0] * values).sum())
    assert abs(float(resampled_means.mean()) - weighted) < 3 * float(resampled_means.std()) / math.sqrt(runs) + 1e-12


# --- a discrete hidden Markov model: the evidence estimate is unbiased --------------------------

class DiscreteChain:
    """Three states, four frames, a proposal unlike the transitions; exact evidence by the
    forward algorithm."""

    frames = 4
    initial = torch.tensor([0.5, 0.3, 0.2])
    transition = torch.tensor([[0.7, 0.2, 0.1], [0.1, 0.6, 0.3], [0.3, 0.3, 0.4]])
    emission = torch.tensor([[0.8, 0.2], [0.3, 0.7], [0.5, 0.5]])
    observed = [0, 1, 1, 0]
    proposal = torch.tensor([0.2, 0.3, 0.5])

    def start(self, particles):
        return torch.full((particles,), -1, dtype=torch.long)

    def step(self, t, state, generator):
        drawn = torch.multinomial(self.proposal, len(state), replacement=True, generator=generator)
        prior = self.initial[drawn] if t == 0 else self.transition[state, drawn]
        weight = prior * self.emission[drawn, self.observed[t]] / self.proposal[drawn]
        return drawn, weight.log()

    def select(self, state, index):
        return state[index]

    def exact_log_evidence(self):
        alpha = self.initial * self.emission[:, self.observed[0]]
        for y in self.observed[1:]:
            alpha = (alpha @ self.transition) * self.emission[:, y]
        return float(alpha.sum().log())


@pytest.mark.parametrize("particles", [1, 3])
def test_the_evidence_estimate_is_unbiased_on_a_discrete_chain(particles):
    """E[p^(x)] = p(x): the mean of 40,000 independent runs, resampling at every frame,
    within three standard errors of the forward algorithm's evidence."""
    chain, runs = DiscreteChain(), 40_000
    found = run_smc(chain, particles, runs=runs, threshold=2.0, generator=torch.Generator().manual_seed(1))
    assert found.resampled[:, :-1].all()
    ratio = torch.exp(found.log_evidence - chain.exact_log_evidence())
    assert abs(float(ratio.mean()) - 1) < 3 * float(ratio.std()) / math.sqrt(runs)
    assert float(ratio.std()) > 0.05          # the runs do differ: the check has teeth


# --- the linear-Gaussian hidden object: evidence by the Kalman filter -------------------------

T, D, OBS = 5, 2, 3
F64 = torch.float64
A = torch.tensor([[0.9, 0.05], [0.0, 0.8]], dtype=F64)
H = torch.tensor([[1.0, 0.0], [0.5, 1.0], [0.0, -0.7]], dtype=F64)
M_0 = torch.tensor([0.3, -0.2], dtype=F64)
S_0, Q, SIGMA, P = 0.8, 0.3, 0.4, 0.3
BACKGROUND = torch.tensor([0.1, 0.2, -0.1], dtype=F64)


def linear_scene():
    return _LinearGaussianScene(T, M_0, S_0, A, H, BACKGROUND)


def simulated_frames(seed=0):
    generator = torch.Generator().manual_seed(seed)
    z, frames = M_0 + S_0 * torch.randn(D, generator=generator), []
    for t in range(T):
        if t:
            z = A @ z + Q * torch.randn(D, generator=generator)
        frames.append(BACKGROUND + H @ z + SIGMA * torch.randn(OBS, generator=generator))
    return torch.stack(frames)


def kalman_frames(frames, background=BACKGROUND):
    """log p(frame t | frames < t, object) (T,), the predictive densities of the Kalman filter."""
    mean, cov, found = M_0, S_0 ** 2 * torch.eye(D), []
    for t in range(T):
        if t:
            mean, cov = A @ mean, A @ cov @ A.T + Q ** 2 * torch.eye(D)
        innovation = H @ cov @ H.T + SIGMA ** 2 * torch.eye(OBS)
        predicted = background + H @ mean
        found.append(torch.distributions.MultivariateNormal(predicted, innovation).log_prob(frames[t]))
        gain = cov @ H.T @ torch.linalg.inv(innovation)
        mean, cov = mean + gain @ (frames[t] - predicted), (torch.eye(D) - gain @ H) @ cov
    return torch.stack(found)


def kalman(frames):
    """log p(frames | object), by the Kalman filter."""
    return float(kalman_frames(frames).sum())


def config(**changes):
    return InferenceConfig(prior_hidden=P, pixel_sigma=SIGMA, transition_sigma=Q, **changes)


def object_branch(frames, proposal=None):
    """The model, an object held in every particle, frame by frame through Pyro: its evidence is
    log P + the Kalman filter's."""
    model = HiddenObjectModel(linear_scene(), config())
    return ModelSteps(model, frames, proposal, widenings_of(config()), {"exists": 1.0})


def rough_proposal():
    """A per-frame guess that is off: the guide's fused proposal must still be exact in expectation."""
    return Proposal(torch.tensor(0.5), torch.full((T, D), 0.5), torch.full((T, D), 0.6), torch.tensor(0.5))


@pytest.mark.parametrize("particles", [4, 16, 64])
@pytest.mark.parametrize("proposal", [None, "rough"])
def test_smc_evidence_matches_the_kalman_filter(particles, proposal):
    """Over 2,000 runs: the mean of p^/p within three standard errors of 1 (unbiased), and the
    mean log p^ within three standard errors of its own spread around log p (the downward bias
    of a log is second order). The bootstrap filter and the guide's fused proposal."""
    frames, runs = simulated_frames(), 2000
    torch.manual_seed(0)
    found = run_smc(object_branch(frames, rough_proposal() if proposal else None), particles, runs=runs,
                    generator=torch.Generator().manual_seed(2))
    exact = math.log(P) + kalman(frames)
    ratio = torch.exp(found.log_evidence - exact)
    assert abs(float(ratio.mean()) - 1) < 3 * float(ratio.std()) / math.sqrt(runs)
    logs = found.log_evidence
    assert abs(float(logs.mean()) - exact) < 3 * float(logs.std())
    assert found.resampled.any()


def test_the_evidence_after_every_frame_matches_the_kalman_filter():
    """The normaliser after frame t estimates p(x_<=t | object) without bias at every t, resampled
    there or not (over 2,000 runs, within three standard errors of the Kalman filter's), and the
    last frame's is the whole video's evidence."""
    frames, runs = simulated_frames(), 2000
    torch.manual_seed(0)
    found = run_smc(object_branch(frames, rough_proposal()), 8, runs=runs, generator=torch.Generator().manual_seed(6))
    exact = math.log(P) + kalman_frames(frames).cumsum(0)
    ratio = torch.exp(found.frame_log_evidence - exact)
    assert ((ratio.mean(0) - 1).abs() < 3 * ratio.std(0) / math.sqrt(runs)).all()
    assert float(ratio[:, -1].std()) > 0.05          # the runs do differ: the check has teeth
    assert found.resampled[:, :-1].any() and not found.resampled[:, :-1].all()
    assert torch.equal(found.frame_log_evidence[:, -1], found.log_evidence)


def test_pooled_runs_are_one_unbiased_estimate_with_every_particle_weighted_by_its_run():
    """Runs pooled: their evidence the mean of theirs after every frame (so unbiased, over 2,000
    pairs within three standard errors of the Kalman filter's), each run's particles weighted by
    its share of that mean, the ESS that of the pooled weights."""
    frames, runs = simulated_frames(), 2000
    torch.manual_seed(0)
    branch = object_branch(frames, rough_proposal())
    first, second = (run_smc(branch, 8, runs=runs, generator=torch.Generator().manual_seed(seed)) for seed in (6, 7))
    pairs = [pooled([first.one(r, branch), second.one(r, branch)], lambda states: states) for r in range(runs)]
    evidence = torch.cat([pair.log_evidence for pair in pairs])
    mean = torch.logaddexp(first.log_evidence, second.log_evidence) - math.log(2)
    torch.testing.assert_close(evidence, mean, rtol=0, atol=1e-12)
    exact = math.log(P) + kalman(frames)
    ratio = torch.exp(evidence - exact)
    assert abs(float(ratio.mean()) - 1) < 3 * float(ratio.std()) / math.sqrt(runs)
    assert float(ratio.std()) < float(torch.exp(first.log_evidence - exact).std())     # and steadier than one
    pair = pairs[0]
    assert torch.equal(pair.frame_log_evidence[:, -1], pair.log_evidence) and pair.log_weights.shape == (1, 16)
    shares = torch.softmax(pair.log_weights[0], 0).view(2, 8).sum(1)
    torch.testing.assert_close(shares, torch.softmax(torch.stack([first.log_evidence[0], second.log_evidence[0]]), 0))
    torch.testing.assert_close(pair.final_ess, effective_sample_size(pair.log_weights))
    assert int(pair.lineages[0]) == len(first.origin[0].unique()) + len(second.origin[0].unique())


def test_more_particles_narrow_the_estimate():
    frames, runs = simulated_frames(), 500
    torch.manual_seed(0)
    model = object_branch(frames)
    spreads = [float(run_smc(model, n, runs=runs, generator=torch.Generator().manual_seed(3)).log_evidence.std())
               for n in (4, 64)]
    assert spreads[1] < 0.5 * spreads[0]


def test_the_mixture_over_existence_matches_the_closed_form():
    frames = simulated_frames(1)
    found = smc_evidence(linear_scene(), frames, config(particles=4096, smc_pilot=0), None,
                         torch.Generator().manual_seed(4))
    with_object = kalman(frames)
    without = float(torch.distributions.Normal(BACKGROUND, SIGMA).log_prob(frames).sum())
    exact = float(torch.logsumexp(torch.tensor([math.log(P) + with_object, math.log(1 - P) + without]), 0))
    assert found.log_evidence_empty == pytest.approx(math.log(1 - P) + without, abs=1e-9)
    assert found.log_evidence == pytest.approx(exact, abs=0.4)     # 3 sd of log p^ at 4,096 particles here
    assert found.p_hidden == pytest.approx(math.exp(math.log(P) + with_object - exact), abs=0.1)
    assert found.trajectories.shape == (4096, T, D) and found.log_weights.dtype == torch.float64
    # frame by frame: -log p(x_t | x_<t) adds up to the NLL, and is the closed form's within 3 sd
    assert float(found.frame_nll.sum()) == pytest.approx(found.nll, rel=1e-13, abs=1e-12)
    empty = torch.distributions.Normal(BACKGROUND, SIGMA).log_prob(frames).sum(1).cumsum(0)
    hidden = kalman_frames(frames).cumsum(0)
    so_far = torch.logaddexp(math.log(P) + hidden, math.log(1 - P) + empty)
    exact_frames = -torch.diff(so_far, prepend=so_far.new_zeros(1))
    torch.testing.assert_close(found.frame_nll, exact_frames, rtol=0, atol=0.4)
    assert 1 <= found.ess <= 4096 and 1 <= found.lineages <= 4096


def test_the_sum_over_two_explanations_of_what_was_seen_matches_the_closed_form():
    """Two versions of the scene (two backgrounds, the second with prior P2): the SMC sums them
    and existence out exactly; log p(x), p(two) and the per-frame curve are the closed form's."""
    other, p_two = BACKGROUND + torch.tensor([0.5, -0.4, 0.3], dtype=F64), 0.4
    scene = _LinearGaussianScene(T, M_0, S_0, A, H, torch.stack([BACKGROUND, other]))
    frames = simulated_frames(1)
    found = smc_evidence(scene, frames, config(particles=4096, smc_pilot=0, prior_two=p_two), None,
                         torch.Generator().manual_seed(4))
    branches = []
    for prior, background in ((1 - p_two, BACKGROUND), (p_two, other)):
        empty = torch.distributions.Normal(background, SIGMA).log_prob(frames).sum(1).cumsum(0)
        hidden = kalman_frames(frames, background).cumsum(0)
        branches += [math.log(prior * (1 - P)) + empty, math.log(prior * P) + hidden]
    so_far = torch.logsumexp(torch.stack(branches), 0)
    exact_two = float(torch.logsumexp(torch.stack([branches[2][-1], branches[3][-1]]), 0) - so_far[-1])
    assert 0.05 < math.exp(exact_two) < 0.95                # neither explanation is a foregone one
    assert found.log_evidence == pytest.approx(float(so_far[-1]), abs=0.4)
    assert found.p_two == pytest.approx(math.exp(exact_two), abs=0.05)
    torch.testing.assert_close(found.frame_nll, -torch.diff(so_far, prepend=so_far.new_zeros(1)), rtol=0, atol=0.4)
    assert found.version.tolist() == [0] * 4096 + [1] * 4096 and found.trajectories.shape == (8192, T, D)


def test_without_a_free_slot_the_estimate_is_the_empty_branch_and_exact():
    frames = simulated_frames()
    found = smc_evidence(linear_scene(), frames, config(), None, torch.Generator().manual_seed(0), free=False)
    without = float(torch.distributions.Normal(BACKGROUND, SIGMA).log_prob(frames).sum())
    assert found.log_evidence == pytest.approx(math.log(1 - P) + without)
    per_frame = torch.distributions.Normal(BACKGROUND, SIGMA).log_prob(frames).sum(1)
    torch.testing.assert_close(found.frame_nll, -per_frame - math.log(1 - P) * (torch.arange(T) == 0))
    assert found.p_hidden == 0.0 and found.trajectories is None and top_hypotheses(found) is None


def test_without_a_free_slot_two_explanations_are_summed_exactly():
    other, p_two = BACKGROUND + torch.tensor([0.5, -0.4, 0.3], dtype=F64), 0.4
    scene = _LinearGaussianScene(T, M_0, S_0, A, H, torch.stack([BACKGROUND, other]))
    frames = simulated_frames()
    found = smc_evidence(scene, frames, config(prior_two=p_two), None, torch.Generator().manual_seed(0), free=False)
    each = [math.log(prior * (1 - P)) + float(torch.distributions.Normal(background, SIGMA).log_prob(frames).sum())
            for prior, background in ((1 - p_two, BACKGROUND), (p_two, other))]
    assert found.log_evidence == pytest.approx(float(torch.logsumexp(torch.tensor(each, dtype=F64), 0)), abs=1e-9)
    assert found.p_two == pytest.approx(1 / (1 + math.exp(each[0] - each[1])), abs=1e-12)


def test_the_pilot_skips_the_full_run_only_where_the_object_cannot_matter():
    frames = simulated_frames()
    with_object = smc_evidence(linear_scene(), frames, config(particles=64), None, torch.Generator().manual_seed(0))
    assert with_object.particles == 64         # the object branch matters here: the full run was taken
    blank = BACKGROUND.expand(T, -1) + 0.01   # no object in sight: it can only cost
    far = _LinearGaussianScene(T, M_0 + 20.0, 0.1, A, H, BACKGROUND)
    skipped = smc_evidence(far, blank, config(particles=64, smc_pilot=8), None, torch.Generator().manual_seed(0))
    assert skipped.particles == 8 and skipped.p_hidden < 1e-10
    staged = config(particles=64, smc_pilot=(4, 16))         # the smallest pilot that settles it is kept
    assert smc_evidence(far, blank, staged, None, torch.Generator().manual_seed(0)).particles == 4
    assert smc_evidence(linear_scene(), frames, staged, None, torch.Generator().manual_seed(0)).particles == 64


def test_each_explanation_keeps_its_pilot_or_takes_the_full_run_on_its_own():
    """The explanations' runs go as one batch, each deciding alone: one whose object branch
    cannot matter keeps its pilot while the other takes its full run."""
    frames = simulated_frames()
    far_off = BACKGROUND + 6.0          # the second explanation draws nothing like these frames
    scene = _LinearGaussianScene(T, M_0, S_0, A, H, torch.stack([BACKGROUND, far_off]))
    found = smc_evidence(scene, frames, config(particles=64, smc_pilot=8, prior_two=0.4), None,
                         torch.Generator().manual_seed(0))
    assert found.version.tolist() == [0] * 64 + [1] * 8 and found.particles == 64
    assert found.p_two < 1e-10


def test_no_pilot_where_the_existence_head_is_sure_of_an_object():
    """Where the head doubts an object, a pilot; where it is sure, no pilot: sure_runs full runs
    pooled, but under sure_runs_exists a first run that trails by the pilot's margin ends the
    video. The head's own probability decides, not the guide's, which _defensive keeps at most
    1 - 8/64."""
    blank = BACKGROUND.expand(T, -1) + 0.01   # a pilot would dismiss the object branch here
    far = _LinearGaussianScene(T, M_0 + 20.0, 0.1, A, H, BACKGROUND)
    guide = torch.tensor(0.875)
    doubtful, sure, surest = (Proposal(min(guide, torch.tensor(p)), (M_0 + 20.0).expand(T, -1),
                                       torch.full((T, D), 0.6), torch.tensor(p)) for p in (0.3, 0.9, 0.99))
    gated = config(particles=64, smc_pilot=8, smc_pilot_skip_exists=0.5, sure_runs=2, sure_runs_exists=0.95)
    for proposal, particles in ((doubtful, 8), (sure, 64), (surest, 2 * 64)):     # `sure`'s first run trails
        assert smc_evidence(far, blank, gated, proposal, torch.Generator().manual_seed(0)).particles == particles
    near = replace(sure, loc=M_0.expand(T, -1))       # an object explains these frames: the runs are pooled
    assert smc_evidence(linear_scene(), simulated_frames(), gated, near,
                        torch.Generator().manual_seed(0)).particles == 2 * 64
    always = replace(gated, smc_pilot_skip_exists=1.0)
    assert smc_evidence(far, blank, always, surest, torch.Generator().manual_seed(0)).particles == 8


def test_no_run_where_the_existence_head_all_but_rules_an_object_out():
    """Under smc_object_floor no particle is drawn: the evidence is the exact branch without an
    object, which is what a pilot that trails far behind leaves of it, to the bit."""
    blank = BACKGROUND.expand(T, -1) + 0.01
    far = _LinearGaussianScene(T, M_0 + 20.0, 0.1, A, H, BACKGROUND)
    ruled_out = Proposal(torch.tensor(8 / 64), (M_0 + 20.0).expand(T, -1), torch.full((T, D), 0.6), torch.tensor(0.01))
    floored = config(particles=64, smc_pilot=8, smc_object_floor=0.05)
    none = smc_evidence(far, blank, floored, ruled_out, torch.Generator().manual_seed(0))
    piloted = smc_evidence(far, blank, replace(floored, smc_object_floor=0.0), ruled_out,
                           torch.Generator().manual_seed(0))
    assert none.particles == 0 and none.p_hidden == 0.0 and none.trajectories is None
    assert none.log_evidence == none.log_evidence_empty
    assert piloted.particles == 8 and piloted.log_evidence_hidden < piloted.log_evidence_empty - 40
    assert none.log_evidence == piloted.log_evidence


def test_the_proposal_is_refined_only_for_a_full_run():
    """A pilot draws from the proposal as it is; `refine` (the XPL scene's out-of-sight steps) is
    paid once, by a video that goes on to its full run, which then draws from what it returns."""
    blank = BACKGROUND.expand(T, -1) + 0.01
    far = _LinearGaussianScene(T, M_0 + 20.0, 0.1, A, H, BACKGROUND)
    doubtful = Proposal(torch.tensor(0.3), (M_0 + 20.0).expand(T, -1), torch.full((T, D), 0.6), torch.tensor(0.3))
    calls = []

    def refine(proposal: Proposal) -> Proposal:
        calls.append(proposal)
        return replace(proposal, loc=M_0.expand(T, -1))

    gated = config(particles=64, smc_pilot=8)
    assert smc_evidence(far, blank, gated, doubtful, torch.Generator().manual_seed(0), refine=refine).particles == 8
    assert calls == []                              # ended at its pilot: nothing refined
    found = smc_evidence(far, blank, config(particles=64, smc_pilot=0), doubtful, torch.Generator().manual_seed(0),
                         refine=refine)
    assert len(calls) == 1 and calls[0] is doubtful
    unrefined = smc_evidence(far, blank, config(particles=64, smc_pilot=0), doubtful,
                             torch.Generator().manual_seed(0))
    assert found.log_evidence_hidden != unrefined.log_evidence_hidden    # the full run drew from the refined one


def test_a_sure_video_pools_its_full_runs_and_a_doubtful_one_keeps_its_bytes():
    """Where the existence head is sure of an object there is no pilot: sure_runs full runs around
    the mean moved out of sight, pooled, the first of them the one run alone (the same draws, first
    from the generator). A doubtful video's estimate does not depend on sure_runs."""
    sure = Proposal(torch.tensor(0.875), torch.full((T, D), 0.5), torch.full((T, D), 0.6), torch.tensor(0.99))
    doubtful = Proposal(torch.tensor(0.3), sure.loc, sure.scale, torch.tensor(0.3))
    moved = replace(sure, loc=M_0.expand(T, -1))
    frames = simulated_frames()

    def estimate(proposal, runs):
        return smc_evidence(linear_scene(), frames, config(particles=64, smc_pilot=8, sure_runs=runs), proposal,
                            torch.Generator().manual_seed(0), refine=lambda given: moved)

    pooled_three, alone = estimate(sure, 3), estimate(sure, 1)
    assert pooled_three.particles == 3 * 64 and pooled_three.trajectories.shape == (3 * 64, T, D)
    assert alone.particles == 64
    torch.testing.assert_close(pooled_three.trajectories[:64], alone.trajectories, rtol=0, atol=0)
    assert pooled_three.log_evidence_hidden != alone.log_evidence_hidden
    once, thrice = estimate(doubtful, 1), estimate(doubtful, 3)
    assert once.log_evidence == thrice.log_evidence and torch.equal(once.trajectories, thrice.trajectories)


def test_pilots_must_come_smallest_first():
    with pytest.raises(ValueError, match="smallest first"):
        smc_evidence(linear_scene(), simulated_frames(), config(particles=64, smc_pilot=(16, 4)), None,
                     torch.Generator().manual_seed(0))


def test_the_same_seed_gives_the_same_estimate_and_leaves_the_global_state_alone():
    frames = simulated_frames()
    state = torch.get_rng_state()
    first, second, other = (smc_evidence(linear_scene(), frames, config(particles=16, smc_pilot=0), rough_proposal(),
                                         torch.Generator().manual_seed(seed)) for seed in (5, 5, 6))
    assert torch.equal(torch.get_rng_state(), state)
    assert first.log_evidence == second.log_evidence and torch.equal(first.trajectories, second.trajectories)
    assert first.log_evidence != other.log_evidence


# --- the hypotheses -------------------------------------------------------------------------

def test_top_hypotheses_merge_copies_and_say_where_they_differ():
    trajectories = torch.zeros(5, 3, 2)
    trajectories[1:3, 2] = 1.0                   # particles 1 and 2 are copies; they differ from 0 at frame 2
    trajectories[3:, 1:] = -1.0                  # 3 and 4 are copies; they differ from 0 at frames 1 and 2
    log_weights = torch.tensor([0.1, 0.2, 0.2, 0.25, 0.25]).log()
    estimate = Evidence(0.0, 0.0, 0.0, 1.0, 4.0, 4.0, 3, 0, 5, trajectories, log_weights)
    found = top_hypotheses(estimate, top=2)
    assert found.trajectories.shape == (2, 3, 2)
    torch.testing.assert_close(found.weights, torch.tensor([0.5, 0.4]))
    assert found.copies.tolist() == [2, 2]
    assert found.spread[0] == 0 and found.disagree == [2, 1]
    assert len(top_hypotheses(estimate, top=10).weights) == 3


# --- the XPL scene: the SMC's factors are the Pyro model's ----------------------------------

def tiny_xpl_scene():
    from test_nll import tiny_scene

    torch.set_default_dtype(torch.float32)
    return tiny_scene()


@pytest.mark.parametrize("versions", [1, 2])
@pytest.mark.parametrize("exists", [True, False, None])
def test_the_frame_by_frame_weights_are_the_whole_videos_model_over_guide(exists, versions):
    """Taken frame by frame through trace and replay (never resampled), a particle's log-weight is
    log p(x, z) - log q(z) of the whole-video model and guide at its draws: with an object, without
    one (exact: every latent masked) and with existence proposed by the guide; with one
    explanation of the seen objects, or two (`two` proposed by the guide)."""
    from conftest import randomise_dynamics_head
    from test_two_objects import tiny_two_scene

    torch.set_default_dtype(torch.float32)
    scene, frames = tiny_xpl_scene() if versions == 1 else tiny_two_scene()
    randomise_dynamics_head(scene.xpl.dynamics)
    settings = InferenceConfig(pixel_sigma=0.3, motion_sigma=0.2, transition_sigma=0.1, exposure_penalty=1.5,
                               presence_penalty=1.5, object_area=0.9)
    model = HiddenObjectModel(scene, settings)
    proposal = Proposal(torch.tensor(0.5), torch.randn(scene.frames, scene.dim), torch.ones(scene.frames, scene.dim),
                        torch.tensor(0.5))
    steps = ModelSteps(model, frames, proposal, (settings.proposal_widening,),
                       None if exists is None else {"exists": float(exists)})
    torch.manual_seed(0)
    with torch.no_grad():
        run = run_smc(steps, 4, threshold=0.0)
        values = {"exists": run.state["exists"].double(), "two": run.state["version"].double()} | {
            f"z_{t}": run.state["trajectory"][:, t] for t in range(scene.frames)}
        joint = poutine.trace(poutine.condition(model.model, data=values)).get_trace(frames, proposal, 4)
        proposed = poutine.trace(poutine.condition(model.guide, data=values)).get_trace(frames, proposal, 4)
    from xvoe.inference.model_steps import site_log_probs
    proposed.compute_log_prob()         # conditioned, every guide site is observed: pick the proposed ones
    drawn = [name for name in proposed.nodes
             if name.startswith("z_") or name == "two" or (name == "exists" and exists is None)]
    expected = site_log_probs(joint, 4) - sum(proposed.nodes[name]["log_prob"].double() for name in drawn)
    torch.testing.assert_close(run.log_weights[0], expected, rtol=1e-5, atol=1e-3)
    assert exists is not False or torch.allclose(run.log_weights[0], run.log_weights[0, :1].expand(4))


def test_smc_runs_on_the_xpl_scene_and_resamples_the_dynamics_memory():
    scene, frames = tiny_xpl_scene()
    proposal = Proposal(torch.tensor(0.5), torch.zeros(scene.frames, scene.dim), torch.ones(scene.frames, scene.dim),
                        torch.tensor(0.5))
    settings = InferenceConfig(particles=16, smc_pilot=0)
    with torch.no_grad():
        found = smc_evidence(scene, frames, settings, proposal, torch.Generator().manual_seed(0))
    assert math.isfinite(found.log_evidence) and 0.0 <= found.p_hidden <= 1.0
    assert found.resamplings > 0 and found.trajectories.shape == (16, scene.frames, scene.dim)
    pyro.clear_param_store()


# --- the NLL entry points on the tiny XPL model ---------------------------------------------

def tiny_video():
    from test_nll import tiny_models, video
    torch.set_default_dtype(torch.float32)
    return tiny_models(), video()


def test_each_video_draws_from_a_stream_of_its_own():
    """One score seed, two videos: two streams (one seed for all correlated the videos' errors);
    the same video and seed: the same stream, from a copy of the frames too."""
    from xvoe.inference.surprise import video_seed
    frames = torch.rand(3, 4, 8, 8)
    other = frames.clone()
    other[1, 2, 3, 4] += 0.5
    assert video_seed(7, frames) == video_seed(7, frames.clone()) == video_seed(7, frames.double())
    assert len({video_seed(7, frames), video_seed(7, other), video_seed(8, frames), video_seed(None, frames)}) == 4
    assert video_seed(None, frames) == video_seed(0, frames)
    assert 0 <= video_seed(7, frames) < 2 ** 63


@pytest.mark.parametrize("method", ["smc", "importance"])
def test_nll_surprise_is_reproducible_from_a_seed_and_leaves_the_global_state_alone(method):
    from xvoe.inference.surprise import nll_surprise, video_seed

    (vae, xpl), args = tiny_video()
    # no exposure penalty: the tiny decoder draws every picture at about the background's depth, so a
    # hidden object holds half of every pixel and its branch would not count
    settings = InferenceConfig(particles=16, smc_pilot=0, exposure_penalty=0.0)
    first = nll_surprise(vae, xpl, *args, settings, method=method, seed=7)
    torch.manual_seed(123)                      # what was drawn before must not matter
    second = nll_surprise(vae, xpl, *args, settings, method=method, seed=7)
    third = nll_surprise(vae, xpl, *args, settings, method=method,
                         seed=torch.Generator().manual_seed(video_seed(7, args[0])))
    before = torch.get_rng_state()
    other = nll_surprise(vae, xpl, *args, settings, method=method, seed=8)
    assert torch.equal(torch.get_rng_state(), before)
    assert first.nll == second.nll and first.method == method
    assert first.nll != other.nll
    assert method == "importance" or third.nll == first.nll      # an int seed: a fresh generator of the video's
    assert 1.0 <= first.holding_ess <= 16 + 1e-9 and 0.0 <= first.p_hidden <= 1.0


def test_explain_surprise_returns_the_heaviest_hypotheses_and_the_posterior_mean():
    from xvoe.inference.surprise import explain_surprise, hidden_posterior

    (vae, xpl), args = tiny_video()
    found = explain_surprise(vae, xpl, *args, InferenceConfig(particles=32, smc_pilot=0, sure_runs_exists=0.5), top=3)
    hypotheses = found.hypotheses
    assert found.method == "smc" and found.hidden_slot == 3
    assert hypotheses.trajectories.shape[1:] == (args[1].shape[0], args[1].shape[2])
    assert 1 <= len(hypotheses.weights) <= 3 and float(hypotheses.weights.sum()) <= 1 + 1e-9
    assert (hypotheses.weights[:-1] >= hypotheses.weights[1:]).all()
    posterior = hidden_posterior(found.result)
    estimate = found.result.estimate
    expected = (estimate.weights[:, None, None] * estimate.trajectories.double()).sum(0)
    torch.testing.assert_close(posterior.mean.double(), expected, rtol=1e-5, atol=1e-5)
    assert posterior.holding == estimate.particles == 2 * 32     # the head is above 0.5 here: two runs, pooled
    importance = explain_surprise(vae, xpl, *args, InferenceConfig(particles=32), method="importance", top=3)
    assert importance.method == "importance" and importance.hypotheses is not None


@pytest.mark.parametrize("hidden_free", [True, False])
def test_the_nll_of_each_frame_adds_up_to_the_videos(hidden_free):
    """-log p(x_t | x_<t) of the XPL scene, existence summed out, sums to the video's NLL to
    float64 precision, with a free slot (both branches) and without one (the exact branch)."""
    from test_nll import tiny_models, video

    from xvoe.inference.surprise import nll_surprise

    torch.set_default_dtype(torch.float32)
    vae, xpl = tiny_models()
    settings = InferenceConfig(particles=16, exposure_penalty=0.0, smc_pilot=0)
    found = nll_surprise(vae, xpl, *video(hidden_free), settings, seed=3)
    if hidden_free:         # the prior that leaves the hidden object as likely as not, on the same draws
        gap = found.estimate.log_evidence_hidden - found.estimate.log_evidence_empty
        settings = replace(settings, prior_hidden=1 / (1 + math.exp(gap)))
        found = nll_surprise(vae, xpl, *video(hidden_free), settings, seed=3)
    frames = video()[0].shape[0]
    assert found.frame_nll.shape == (frames,) and found.frame_nll.dtype == torch.float64
    assert float(found.frame_nll.sum()) == pytest.approx(found.nll, rel=1e-13)
    assert not hidden_free or 0.01 < found.p_hidden < 0.99       # both branches count in the sum
    assert nll_surprise(vae, xpl, *video(hidden_free), settings, method="importance").frame_nll is None
