"""The NLL's learned trajectory proposal: the module, its training stage, and its place in the SMC."""
import math
import subprocess
import sys

import pytest
import torch
from test_smc import T as LT
from test_smc import config as linear_config
from test_smc import kalman, linear_scene, rough_proposal, simulated_frames
from test_train_xpl import (  # noqa: F401 - cache is a fixture
    TINY,
    cache,
    losses,
    tiny_recipe,  # noqa: F401 - an autouse fixture: the xpl stage's tiny networks
)

from inference.smc import HiddenTrajectory, LinearSteps, run_smc
from xvoe.errors import XvoeError
from xvoe.models.trajectory import TrajectoryConfig, TrajectoryProposal
from xvoe.training.trajectory import with_trajectory
from xvoe.training.xpl import load_xpl, train_proposal, train_xpl


def randomised(config: TrajectoryConfig, seed: int = 0) -> TrajectoryProposal:
    """A proposal whose last layer is not zero: it no longer just follows the dynamics."""
    torch.manual_seed(seed)
    proposal = TrajectoryProposal(config)
    torch.nn.init.normal_(proposal.net[-1].weight, std=0.3)
    return proposal.eval()


def inputs(n=5, d=4, seed=1):
    generator = torch.Generator().manual_seed(seed)
    previous, prediction, loc = (torch.randn(n, d, generator=generator) for _ in range(3))
    return previous, prediction, loc, torch.rand(n, d, generator=generator) + 0.1


def test_untrained_it_moves_like_the_dynamics_and_starts_at_transformer2():
    proposal = TrajectoryProposal(TrajectoryConfig(latent_dim=4, frames=6, hidden=8))
    previous, prediction, loc, scale = inputs()
    mean, spread = proposal(3, previous, prediction, loc, scale)
    assert mean.shape == spread.shape == (5, 4)
    torch.testing.assert_close(mean, prediction)
    torch.testing.assert_close(spread, torch.full_like(spread, proposal.config.step_scale))
    first, first_spread = proposal(0, previous, prediction, loc, scale)
    torch.testing.assert_close(first, loc)
    torch.testing.assert_close(first_spread, scale)
    frames = torch.tensor([0, 3, 0, 1, 2])          # frames per particle too
    mixed, _ = proposal(frames, previous, prediction, loc, scale)
    torch.testing.assert_close(mixed, torch.where((frames == 0)[:, None], loc, prediction))


def test_a_trained_proposal_keeps_its_scales_in_range_and_its_dtype():
    config = TrajectoryConfig(latent_dim=4, frames=6, hidden=8)
    proposal = randomised(config)
    previous, prediction, loc, scale = (x.double() for x in inputs())
    mean, spread = proposal(2, previous, prediction, loc, scale)
    assert mean.dtype == spread.dtype == torch.float64
    ratio = spread / config.step_scale
    assert (ratio > math.exp(-config.scale_range)).all() and (ratio < math.exp(config.scale_range)).all()
    assert not torch.allclose(mean, prediction)
    density = proposal.log_density(mean, 2, previous, prediction, loc, scale)
    assert density.shape == (5,)


# --- the SMC with the learned component: still the Kalman evidence ---------------------------

@pytest.mark.usefixtures("double_precision")
@pytest.mark.parametrize("particles", [4, 64])
def test_the_smc_with_a_learned_component_matches_the_kalman_filter(particles):
    """The fused components and a learned one that is off (random weights): over 2,000 runs the
    mean of p^/p within three standard errors of 1, as without it (tests/test_smc.py)."""
    frames, runs = simulated_frames(), 2000
    learned = randomised(TrajectoryConfig(latent_dim=2, frames=LT, hidden=8, step_scale=0.3))
    proposal = rough_proposal()
    proposal.trajectory = learned
    settings = linear_config(trajectory_proposal=True)
    model = HiddenTrajectory(LinearSteps(linear_scene(), frames, settings), settings, proposal)
    found = run_smc(model, particles, runs=runs, generator=torch.Generator().manual_seed(2))
    exact = kalman(frames)
    ratio = torch.exp(found.log_evidence - exact)
    assert abs(float(ratio.mean()) - 1) < 3 * float(ratio.std()) / math.sqrt(runs)
    assert abs(float(found.log_evidence.mean()) - exact) < 3 * float(found.log_evidence.std())
    # the learned component is drawn from: it is one of three equal-weight components
    locs, _ = model.proposal_at(1, torch.zeros(3, 2), torch.ones(3, 2), torch.zeros(3, 2))
    assert locs.shape == (3, 3, 2)
    off = HiddenTrajectory(model.steps, linear_config(trajectory_proposal=False), proposal)
    assert off.proposal_at(1, torch.zeros(3, 2), torch.ones(3, 2), torch.zeros(3, 2))[0].shape == (3, 2, 2)


@pytest.mark.usefixtures("double_precision")
def test_the_switch_takes_the_learned_component_out_of_the_draws():
    frames = simulated_frames(1)
    proposal = rough_proposal()
    proposal.trajectory = randomised(TrajectoryConfig(latent_dim=2, frames=LT, hidden=8))
    results = []
    for on in (True, False):
        settings = linear_config(trajectory_proposal=on)
        model = HiddenTrajectory(LinearSteps(linear_scene(), frames, settings), settings, proposal)
        results.append(run_smc(model, 16, runs=10, generator=torch.Generator().manual_seed(3)))
    plain = HiddenTrajectory(LinearSteps(linear_scene(), frames, linear_config()), linear_config(), rough_proposal())
    alone = run_smc(plain, 16, runs=10, generator=torch.Generator().manual_seed(3))
    assert not torch.equal(results[0].state.trajectory, results[1].state.trajectory)
    assert torch.equal(results[1].state.trajectory, alone.state.trajectory)


# --- the stage -------------------------------------------------------------------------------

@pytest.fixture(autouse=True)
def trajectory_recipe(monkeypatch, tiny_recipe):     # noqa: F811 - the xpl stage's tiny recipe, here too
    import xvoe.training.trajectory as stage
    import xvoe.training.xpl as xpl_stage

    monkeypatch.setattr(stage, "recipe", xpl_stage.recipe)


def test_the_stage_lowers_the_csis_loss_trains_the_proposal_alone_and_loads_beside_xpl(cache, tmp_path):  # noqa: F811
    from xvoe.training.trajectory import train_trajectory

    with pytest.raises(XvoeError, match="no xpl.pt"):
        train_trajectory(tmp_path, cache, progress=False)
    train_xpl(cache, tmp_path, progress=False, **{**TINY, "steps": 10})
    before = {name: value.clone() for name, value in load_xpl(tmp_path)[0].state_dict().items()}
    path = train_trajectory(tmp_path, progress=False, **{**TINY, "steps": 60})    # the cache from xpl.pt's meta
    rows = losses(tmp_path, "trajectory")
    assert float(rows[-1]["nll"]) < float(rows[0]["nll"]) - 1.0
    assert float(rows[-1]["nll"]) < float(rows[-1]["untrained_nll"])
    state = torch.load(path, weights_only=False)
    assert state["model"] and all(name.startswith("proposal.") for name in state["model"])
    assert state["step"] == 60 and state["optimizer"] and state["meta"]["xpl_fingerprint"]
    xpl, loaded = load_xpl(tmp_path)
    assert xpl.trajectory is None                      # load_xpl leaves it to with_trajectory
    assert with_trajectory(xpl, loaded)["trajectory"] == str(path) and isinstance(xpl.trajectory, TrajectoryProposal)
    assert not xpl.trajectory.training
    assert all(torch.equal(value, xpl.state_dict()[name]) for name, value in before.items())   # XPL untouched
    # a proposal.pt trained afterwards changes Transformer 2's marginals: the old trajectory.pt is refused
    train_proposal(tmp_path, progress=False, **{**TINY, "steps": 3})
    with pytest.raises(XvoeError, match="another xpl.pt or proposal.pt"):
        with_trajectory(*load_xpl(tmp_path))
    without = load_xpl(tmp_path, proposal=False)
    assert with_trajectory(*without)["stage"] == "xpl" and without[0].trajectory is None


def test_the_stage_resumes_exactly(cache, tmp_path):  # noqa: F811
    from xvoe.training.trajectory import train_trajectory

    for run in ("a", "b"):
        train_xpl(cache, tmp_path / run, progress=False, **{**TINY, "steps": 5})
    straight = train_trajectory(tmp_path / "a", progress=False, **{**TINY, "steps": 20})
    copy = tmp_path / "copy.h5"                  # a cache of its own: a resumed run goes on with it
    copy.write_bytes(cache.read_bytes())
    train_trajectory(tmp_path / "b", copy, progress=False, **{**TINY, "steps": 8})
    with pytest.raises(XvoeError, match="--resume"):
        train_trajectory(tmp_path / "b", copy, progress=False, **{**TINY, "steps": 20})
    resumed = train_trajectory(tmp_path / "b", progress=False, resume=True, **{**TINY, "steps": 20})
    a, b = torch.load(straight, weights_only=False), torch.load(resumed, weights_only=False)
    assert a["step"] == b["step"] == 20 and b["meta"]["latents"] == str(copy.resolve())
    for name, value in a["model"].items():
        torch.testing.assert_close(value, b["model"][name], msg=name)


def test_nll_surprise_uses_the_learned_component_only_when_switched_on():
    from test_nll import T, tiny_models, video

    from inference.model import InferenceConfig
    from inference.surprise import nll_surprise

    vae, xpl = tiny_models()
    args = video()
    # no exposure penalty: the tiny decoder's objects hold half of every pixel, and the branch with
    # one, where the learned component acts, would not count
    settings = InferenceConfig(particles=16, smc_pilot=0, trajectory_proposal=True, exposure_penalty=0.0)
    without = nll_surprise(vae, xpl, *args, settings, seed=3)
    xpl.trajectory = randomised(TrajectoryConfig(latent_dim=args[1].shape[-1], frames=T, hidden=8))
    on = nll_surprise(vae, xpl, *args, settings, seed=3)
    off = nll_surprise(vae, xpl, *args, InferenceConfig(particles=16, smc_pilot=0, exposure_penalty=0.0),
                       seed=3)     # off by default
    assert off.nll == without.nll and on.nll != without.nll and math.isfinite(on.nll)
    assert on.nll == nll_surprise(vae, xpl, *args, settings, seed=3).nll


def test_the_cli_refuses_a_run_without_xpl(tmp_path):
    done = subprocess.run([sys.executable, "-m", "xvoe", "train", "trajectory", "--out", str(tmp_path), "--quiet"],
                          capture_output=True, text=True)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1 and "no xpl.pt" in done.stderr
    assert not (tmp_path / "trajectory.pt").exists()


@pytest.mark.usefixtures("double_precision")
def test_the_learned_scale_is_floored_at_the_transitions_after_the_first_frame():
    proposal = rough_proposal()
    proposal.trajectory = TrajectoryProposal(TrajectoryConfig(latent_dim=2, frames=LT, hidden=8, step_scale=0.01))
    frames = simulated_frames()
    for floor, expected in ((1.0, 0.3), (0.0, 0.01)):
        settings = linear_config(trajectory_proposal=True, trajectory_scale_floor=floor)
        model = HiddenTrajectory(LinearSteps(linear_scene(), frames, settings), settings, proposal)
        prior_scale = torch.full((3, 2), 0.3)
        _, scales = model.proposal_at(2, torch.zeros(3, 2), prior_scale, torch.zeros(3, 2))
        torch.testing.assert_close(scales[:, -1], torch.full((3, 2), expected))
        _, first = model.proposal_at(0, torch.zeros(3, 2), torch.ones(3, 2), torch.zeros(3, 2))
        torch.testing.assert_close(first[:, -1], torch.full((3, 2), 0.6))       # the marginal's at t = 0
