"""The proposal moved up the model's log joint where the existence head is sure of a hidden object
(inference.guide.toward_mode, InferenceConfig.mode_steps)."""
import math

import pytest
import torch
from test_smc import BACKGROUND, M_0, S_0, SIGMA, A, H, P, Q, config, linear_scene, simulated_frames, tiny_xpl_scene

from xvoe.inference.evidence import smc_evidence
from xvoe.inference.guide import toward_mode
from xvoe.inference.model import HiddenObjectModel, InferenceConfig, Proposal

pytestmark = pytest.mark.usefixtures("double_precision")


def test_the_log_joint_is_the_closed_form_on_the_linear_scene():
    """log p(x, object, z) of each trajectory: the prior of an object, the first latent's prior, the
    transitions and the pixels, nothing else."""
    frames = simulated_frames()
    trajectories = torch.randn(3, *frames.shape[:1], len(M_0), generator=torch.Generator().manual_seed(1))
    normal = torch.distributions.Normal
    expected = (math.log(P) + normal(M_0, S_0).log_prob(trajectories[:, 0]).sum(-1)
                + normal(trajectories[:, :-1] @ A.T, Q).log_prob(trajectories[:, 1:]).sum((-2, -1))
                + normal(BACKGROUND + trajectories @ H.T, SIGMA).log_prob(frames).sum((-2, -1)))
    found = HiddenObjectModel(linear_scene(), config()).log_joint(frames, trajectories)
    assert found.dtype == torch.float64
    torch.testing.assert_close(found, expected)


def sure_and_doubtful(scene):
    """Two proposals with the same mean and scale, one whose existence probability is above
    smc_pilot_skip_exists (0.5) and one below it."""
    mean = torch.randn(scene.frames, scene.dim, generator=torch.Generator().manual_seed(0))
    scale = torch.full((scene.frames, scene.dim), 0.5)
    return Proposal(torch.tensor(0.9), mean, scale), Proposal(torch.tensor(0.3), mean, scale)


def test_the_steps_move_the_mean_toward_a_higher_log_joint_and_never_widen_it():
    torch.set_default_dtype(torch.float32)
    scene, frames = tiny_xpl_scene()
    settings = InferenceConfig(mode_steps=10)
    model = HiddenObjectModel(scene, settings)
    start, _ = sure_and_doubtful(scene)
    with torch.no_grad():
        moved = toward_mode(model, frames, start, settings)
        before, after = model.log_joint(frames, torch.stack([start.loc, moved.loc]))
    assert after > before + 1.0
    assert (moved.scale <= start.scale).all() and moved.p_exists == start.p_exists
    again = toward_mode(model, frames, start, settings)      # a function of the video: the same for every seed
    assert torch.equal(again.loc, moved.loc) and torch.equal(again.scale, moved.scale)


def test_only_a_sure_video_is_moved_and_a_doubtful_one_keeps_its_bytes():
    torch.set_default_dtype(torch.float32)
    scene, frames = tiny_xpl_scene()
    sure, doubtful = sure_and_doubtful(scene)
    off, on = (InferenceConfig(particles=16, mode_steps=steps) for steps in (0, 10))

    def estimate(settings, proposal):
        with torch.no_grad():
            return smc_evidence(scene, frames, settings, proposal, torch.Generator().manual_seed(0))

    kept, also_kept = estimate(off, doubtful), estimate(on, doubtful)
    assert (kept.log_evidence, kept.log_evidence_hidden) == (also_kept.log_evidence, also_kept.log_evidence_hidden)
    assert torch.equal(kept.trajectories, also_kept.trajectories)
    assert estimate(off, sure).log_evidence_hidden != estimate(on, sure).log_evidence_hidden
