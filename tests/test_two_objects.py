"""Explanations by identity (inference.identity): a seen object that goes out of sight and comes
back may be two identical objects; the model sums that out exactly."""
import math
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
from pyro import poutine
from pyro.util import check_model_guide_match
from test_nll import D, T, scene_of, tiny_models, video

from xvoe.errors import XvoeError
from xvoe.evaluation.surprise import draw_scene
from xvoe.inference.evidence import smc_evidence
from xvoe.inference.identity import Identity, identity_gap, two_objects
from xvoe.inference.model import HiddenObjectModel, InferenceConfig, Proposal
from xvoe.inference.model_steps import empty_branches
from xvoe.inference.score import under_prior_two
from xvoe.inference.surprise import _hidden_object_scene, _hidden_slot, nll_surprise
from xvoe.models.slots import _WALL_PIXEL


def seen(*rows: str) -> torch.Tensor:
    """Visibility (T, K) from one string per slot, '1' where the encoder saw it."""
    return torch.tensor([[c == "1" for c in row] for row in rows]).T


def test_the_longest_gap_of_a_moving_object_is_the_one_that_may_be_two():
    walls = torch.tensor([True, False, False, False, False])
    visible = seen("11111111", "11.11111", "1....111", "........", "........")
    assert identity_gap(visible, walls, hidden=3) == Identity(slot=2, second=4, last_seen=0, seen_again=5)
    assert identity_gap(visible, walls, hidden=4) == Identity(slot=2, second=3, last_seen=0, seen_again=5)


def test_no_identity_without_a_gap_a_free_slot_or_a_moving_object():
    walls = torch.tensor([True, False, False])
    assert identity_gap(seen("1..1", "1111", "...."), walls, hidden=2) is None          # only the wall has a gap
    assert identity_gap(seen("1111", "11.1", "...."), walls, hidden=2) is None          # no slot left for the second
    assert identity_gap(seen("1111", "111.", "....", "....")[:, :3], walls, hidden=2) is None   # gone, not back
    assert identity_gap(seen("1111", "1.11", "....", "...."), torch.tensor([True, False, False, False]),
                        hidden=2) == Identity(1, 3, 0, 2)


def test_the_two_objects_wait_where_the_seen_one_left_and_came_back():
    refined = torch.arange(6 * 4 * 1, dtype=torch.float32).reshape(6, 4, 1)
    visible = seen("111111", "11..11", "......", "......")
    latents, shown = two_objects(refined, visible, Identity(slot=1, second=3, last_seen=1, seen_again=4))
    first, second = latents[:, 3, 0], latents[:, 1, 0]
    assert first.tolist() == [refined[0, 1, 0], refined[1, 1, 0]] + [refined[2, 1, 0]] * 4      # stays at frame 2's
    assert second.tolist() == [refined[3, 1, 0]] * 4 + [refined[4, 1, 0], refined[5, 1, 0]]     # waits at frame 3's
    assert shown[:, 3].tolist() == [True, True, False, False, False, False]
    assert shown[:, 1].tolist() == [False, False, False, False, True, True]
    assert torch.equal(latents[:, [0, 2]], refined[:, [0, 2]]) and torch.equal(shown[:, [0, 2]], visible[:, [0, 2]])


def two_object_video():
    """The tiny video with slot 1 out of sight in frames 1-3 and slots 2 and 3 never seen."""
    frames, mean, visible, background, occluder = video()
    visible[:, 2] = False
    visible[1:4, 1] = False
    return frames, mean, visible, background, occluder


def nll_scene(vae, xpl, mean, visible, background, occluder, config, drawn=None):
    """The NLL's scene of one video, from `drawn`, its batch's drawing, or drawn alone as
    `nll_surprise` draws it."""
    if drawn is None:
        drawn = draw_scene(vae, xpl, mean[None], visible[None], background[None], occluder[None], proposed=False)
    return _hidden_object_scene(vae, xpl, visible, occluder, _hidden_slot(drawn, visible)[0], config, drawn)


def tiny_two_scene(prior_two=0.3):
    vae, xpl = tiny_models()
    frames, mean, visible, background, occluder = two_object_video()
    with torch.no_grad():
        scene = nll_scene(vae, xpl, mean, visible, background, occluder, InferenceConfig(prior_two=prior_two))
    return scene, frames


def test_the_scene_has_a_two_object_version_where_a_seen_object_comes_back():
    scene, _ = tiny_two_scene()
    assert scene.versions == 2 and scene.identity.slot == 1 and scene.identity.seen_again == 4
    assert scene.identity.second != scene.hidden
    assert not torch.equal(scene.empty(0), scene.empty(1))
    no_identity, _ = tiny_two_scene(prior_two=0.0)
    assert no_identity.versions == 1 and no_identity.identity is None


def test_the_scene_drawn_in_a_batch_is_the_scene_drawn_for_the_video_alone():
    """The NLL's scene of a video read from its batch as the MSE score drew it (`draw_scene`):
    the seen slots' pictures with the proposed one left out, and the two-object version with
    only its two slots decoded again, are the pictures `scene_layers` draws of its latents
    (within the decoder's rounding in a batch of another size)."""
    vae, xpl = tiny_models()
    videos = two_object_video()[1:], video()[1:]      # mean, visible, background, occluder of two videos
    config = InferenceConfig(prior_two=0.3)
    with torch.no_grad():
        vae.decoder.out.weight.normal_(0, 0.5)         # pictures at the walls' depth: the unseen stand behind them
        vae.decoder.out.bias.copy_(torch.tensor([0.0, 0.0, 0.0, -0.5]))
        drawn = draw_scene(vae, xpl, *(torch.stack(parts) for parts in zip(*videos)))
        scene = nll_scene(vae, xpl, *videos[0], config, drawn.video(0))
        alone = scene_of(vae, xpl, scene.refined, scene.background, scene.visible, videos[0][3], scene.hidden,
                         scene.identity)
        own = draw_scene(vae, xpl, *(part[None] for part in videos[0]), proposed=False)
    hidden = scene.hidden
    assert scene.versions == 2 and int(drawn.slot[0]) == hidden != scene.identity.second
    assert (alone.walls < _WALL_PIXEL).any()
    torch.testing.assert_close(scene.layers, alone.layers, rtol=0, atol=1e-6)
    torch.testing.assert_close(scene.walls, alone.walls, rtol=0, atol=1e-6)
    torch.testing.assert_close(scene.empty_frame(2), alone.empty_frame(2), rtol=0, atol=1e-6)
    # the proposal the guide starts from: Transformer 2's, the same in the batch as alone
    torch.testing.assert_close((drawn.proposal[0, :, hidden], drawn.scale[0, :, hidden]),
                               (own.proposal[0, :, hidden], own.scale[0, :, hidden]), rtol=0, atol=1e-6)


def test_the_model_and_guide_match_with_the_identity_site():
    scene, frames = tiny_two_scene()
    model = HiddenObjectModel(scene, InferenceConfig(prior_two=0.3))
    proposal = Proposal(torch.tensor(0.5), torch.zeros(T, D), torch.ones(T, D), torch.tensor(0.5))
    with torch.no_grad():
        guide_trace = poutine.trace(model.guide).get_trace(frames, proposal, particles=16)
        model_trace = poutine.trace(poutine.replay(model.model, trace=guide_trace)).get_trace(frames, proposal, 16)
    assert "two" in model_trace.nodes and model_trace.nodes["two"]["value"].shape == (16,)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_model_guide_match(model_trace, guide_trace)


def test_the_evidence_sums_both_explanations_exactly():
    """Without a free slot for a hidden object the SMC's estimate is exact: the prior-weighted
    sum of the two explanations' branches, and p(two) their posterior share."""
    scene, frames = tiny_two_scene()
    config = InferenceConfig(prior_two=0.3)
    model = HiddenObjectModel(scene, config)
    with torch.no_grad():
        one, two = empty_branches(model, frames).sum(1).tolist()
        found = smc_evidence(scene, frames, config, None, torch.Generator().manual_seed(0), free=False)
    assert found.log_evidence == pytest.approx(float(torch.logaddexp(*torch.tensor([one, two], dtype=torch.float64))),
                                               abs=1e-9)
    assert found.p_two == pytest.approx(1 / (1 + math.exp(one - two)), abs=1e-9)
    assert float(found.frame_nll.sum()) == pytest.approx(found.nll, rel=1e-12)
    # the prior is one of the terms: halving the odds of two objects moves the branch by log 2 less
    odds = 0.5 * 0.3 / 0.7
    lowered = HiddenObjectModel(scene, InferenceConfig(prior_two=odds / (1 + odds)))
    with torch.no_grad():
        shift = float(empty_branches(lowered, frames).sum(1).diff())
    assert shift == pytest.approx(two - one - math.log(2), abs=1e-6)


def test_the_nll_reports_p_two_and_the_identity_and_a_zero_prior_leaves_one_explanation():
    vae, xpl = tiny_models()
    frames, mean, visible, background, occluder = two_object_video()
    # a wide motion likelihood: the untrained dynamics' misses would settle p_two at 1 to the float
    settings = InferenceConfig(particles=8, smc_pilot=0, prior_two=0.3, motion_sigma=1.0)
    with torch.no_grad():
        found = nll_surprise(vae, xpl, frames, mean, visible, background, occluder, settings, seed=0)
        single = nll_surprise(vae, xpl, frames, mean, visible, background, occluder,
                              replace(settings, prior_two=0.0), seed=0)
    assert found.identity is not None and 0.0 < found.p_two < 1.0
    assert found.estimate.version.tolist().count(1) == 8 and len(found.estimate.trajectories) == 16
    assert single.identity is None and single.p_two == 0.0 and single.nll != found.nll
    assert math.isfinite(found.nll) and float(found.frame_nll.sum()) == pytest.approx(found.nll, rel=1e-12)


def test_another_prior_of_two_objects_follows_from_one_scoring_by_hand():
    one, two = -100.0, -97.0        # log p(x | one object), log p(x | two identical ones)

    def scored(prior):
        log_x = np.logaddexp(np.log1p(-prior) + one, np.log(prior) + two)
        return -log_x, np.exp(np.log(prior) + two - log_x)

    nll, p_two = scored(0.1)
    table = {"nll": np.array([nll, 50.0]), "p_two": np.array([p_two, 0.0]),     # the second video has no gap
             "nll_excess": np.array([nll - 10.0, 7.0])}
    for prior in (0.3, 0.001):
        derived = under_prior_two(table, 0.1, prior)
        assert derived["nll"][0] == pytest.approx(scored(prior)[0], abs=1e-9)
        assert derived["p_two"][0] == pytest.approx(scored(prior)[1], abs=1e-12)
        assert derived["nll_excess"][0] == pytest.approx(derived["nll"][0] - 10.0, abs=1e-9)
        assert (derived["nll"][1], derived["p_two"][1], derived["nll_excess"][1]) == (50.0, 0.0, 7.0)
    off = under_prior_two(table, 0.1, 0.0)
    assert off["nll"][0] == pytest.approx(-one, abs=1e-9) and off["p_two"][0] == 0.0
    certain = {"nll": np.array([97.0]), "p_two": np.array([1.0]), "nll_excess": np.array([5.0])}
    with warnings.catch_warnings():
        warnings.simplefilter("error")      # p(x | one) underflowed: no NaN, no warning
        lone = under_prior_two(certain, 0.1, 0.0)
    assert lone["nll"][0] == np.inf and lone["p_two"][0] == 0.0 and lone["nll_excess"][0] == np.inf
    with pytest.raises(XvoeError, match="priors of two objects"):
        under_prior_two(table, 0.0, 0.1)
