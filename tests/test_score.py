"""The MSE surprise on hand-made cases, with tiny untrained networks."""
import pytest
import torch

import xvoe
from xvoe.errors import XvoeError
from xvoe.evaluation.score_curves import SCORE_COLUMNS
from xvoe.evaluation.surprise import Surprise, _better_explanation, _latent_surprise, aggregate, mse_surprise
from xvoe.inference.score import reference_nll
from xvoe.models.dynamics import DynamicsConfig
from xvoe.models.perception import ComponentVAE, PerceptionConfig
from xvoe.models.reasoning import ReasoningConfig
from xvoe.models.slots import _BEHIND, _WALL_PIXEL, behind_walls, composite, decode_slots, scene_layers
from xvoe.models.xpl import XPL, XPLConfig

B, T, K, D = 2, 5, 4, 6


@pytest.fixture(scope="module")
def models():
    torch.manual_seed(0)
    vae = ComponentVAE(PerceptionConfig(image_size=16, latent_dim=D, cnn_channels=(8, 8), cnn_hidden=16,
                                        decoder_channels=8)).eval()
    with torch.no_grad():   # a decoder that draws something: objects in front of the background
        vae.decoder.out.weight.normal_(0, 0.5)
        vae.decoder.out.bias.copy_(torch.tensor([0.0, 0.0, 0.0, -0.5]))
    xpl = XPL(XPLConfig(reasoning=ReasoningConfig(latent_dim=D, slots=K, frames=T, width=16, layers=1, heads=2, mlp=16),
                        dynamics=DynamicsConfig(latent_dim=D, hidden=16, lstm=16, buffer_heads=2))).eval()
    return vae, xpl


def scene(moving: bool):
    torch.manual_seed(1)
    mean = torch.randn(B, 1, K, D).expand(B, T, K, D).clone()
    if moving:
        mean += 0.5 * torch.arange(T).view(1, T, 1, 1) * torch.randn(B, 1, K, D)
    visible = torch.ones(B, T, K, dtype=torch.bool)
    background = torch.randn(B, 1, D).expand(B, T, D).clone()
    occluder = torch.zeros(B, K, dtype=torch.bool)
    occluder[:, 0] = True
    return mean, visible, background, occluder


def rendered(vae, mean, visible, background):
    """The frames these latents draw: the case where the model explains the video exactly."""
    pictures = vae.decode(background.flatten(0, 1)).reshape(B, T, 4, 16, 16)
    layers = decode_slots(vae, mean, visible.any(1))
    return composite(vae, pictures, layers, visible.any(1))


def test_a_video_drawn_by_its_own_static_latents_is_no_surprise(models):
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=False)
    with torch.no_grad():
        frames = rendered(vae, mean, visible, background)
    surprise = mse_surprise(vae, xpl, frames, mean, visible, background, occluder)
    assert surprise.s_img.shape == (B, T) and surprise.s_dyn.shape == (B, T)
    torch.testing.assert_close(surprise.s_img, torch.zeros(B, T), atol=1e-6, rtol=0)
    # untrained residual dynamics predict "no change", which is right for a static scene
    torch.testing.assert_close(surprise.s_dyn, torch.zeros(B, T), atol=1e-6, rtol=0)


def test_motion_the_dynamics_did_not_predict_is_surprising(models):
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=True)
    with torch.no_grad():
        frames = rendered(vae, mean, visible, background)
    surprise = mse_surprise(vae, xpl, frames, mean, visible, background, occluder)
    assert torch.all(surprise.s_dyn[:, 0] == 0) and torch.all(surprise.s_dyn[:, 1:] > 0)
    torch.testing.assert_close(surprise.s_img, torch.zeros(B, T), atol=1e-6, rtol=0)


def test_the_occluder_is_left_out_of_the_dynamics_term(models):
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=False)
    with torch.no_grad():
        frames = rendered(vae, mean, visible, background)
    moved = mean.clone()
    moved[:, :, 0] += torch.randn(B, T, D)          # the wall jumps about: not physics
    surprise = mse_surprise(vae, xpl, frames, moved, visible, background, occluder)
    torch.testing.assert_close(surprise.s_dyn, torch.zeros(B, T), atol=1e-6, rtol=0)
    assert torch.all(surprise.s_img.sum(1) > 0)     # but the picture no longer matches


def test_an_explanation_that_draws_the_hidden_object_is_kept_and_one_where_nothing_is_hidden_is_not(models,
                                                                                                   monkeypatch):
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=False)
    visible[:, :, 3] = False                       # slot 3 is seen in no frame of either video
    occluder[:] = False                            # and no wall hides it: whatever it draws shows
    drawn = visible.any(1)
    drawn[0, 3] = True                             # but video 0's frames draw it: something is hidden there
    with torch.no_grad():
        pictures = vae.decode(background.flatten(0, 1)).reshape(B, T, 4, 16, 16)
        frames = composite(vae, pictures, scene_layers(vae, mean, drawn, visible, occluder)[0], drawn)
    # Transformer 2 stands in as an oracle: it proposes the true latents in slot 3 of both videos
    monkeypatch.setattr(xpl, "explain", lambda refined, seen: (torch.where(
        torch.arange(K).view(1, 1, K, 1) == 3, mean, refined), None, torch.tensor([3, 3])))
    surprise = mse_surprise(vae, xpl, frames, mean, visible, background, occluder, explanation="better")
    assert surprise.explained_slot.tolist() == [3, -1]
    torch.testing.assert_close(surprise.s_img, torch.zeros(B, T), atol=1e-5, rtol=0)   # each explained exactly
    # the paper's score keeps the proposal in both: video 1 pays for an object that is not there
    paper = mse_surprise(vae, xpl, frames, mean, visible, background, occluder)
    assert paper.explained_slot.tolist() == [3, 3] and paper.s_img[1].sum() > 1.0
    with pytest.raises(ValueError, match="proposal, better"):
        mse_surprise(vae, xpl, frames, mean, visible, background, occluder, explanation="best")
    empty = _latent_surprise(vae, xpl, frames, xpl.refine(mean, visible, occluder), visible.any(1), visible,
                            background, occluder)
    proposed = _latent_surprise(vae, xpl, frames, mean, visible.any(1) | (torch.arange(K) == 3), visible,
                               background, occluder)
    # the explanation not chosen would have cost pixels: video 0's hidden object, video 1's object in front of nothing
    assert empty[0][0].sum() > 1.0 and proposed[0][1].sum() > 1.0


def test_transformer2_explains_a_never_seen_slot(models):
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=False)
    visible[0, :, 3] = False
    surprise = mse_surprise(vae, xpl, rendered(vae, mean, visible, background), mean, visible, background, occluder)
    assert surprise.explained_slot.tolist() == [3, -1]


def test_the_better_explanation_is_chosen_per_video_and_the_first_on_a_tie():
    ones = torch.ones(3, 2)
    first = Surprise(ones * torch.tensor([[1.0], [2.0], [3.0]]), ones, ones * 7, torch.tensor([-1, -1, -1]))
    second = Surprise(ones * 2, ones * torch.tensor([[0.0], [1.0], [0.0]]), ones * 9, torch.tensor([4, 5, 6]))
    chosen = _better_explanation(first, second)
    # sums: first 4, 6, 8; second 4, 6, 4: a tie in videos 0 and 1 keeps the first
    assert chosen.explained_slot.tolist() == [-1, -1, 6]
    assert chosen.s_rec[:, 0].tolist() == [7.0, 7.0, 9.0] and chosen.s_img[:, 0].tolist() == [1.0, 2.0, 2.0]


def test_aggregate():
    per_frame = torch.tensor([[1.0, 3.0, 2.0], [0.0, 0.0, 5.0]])
    assert aggregate(per_frame, "sum").tolist() == [6.0, 5.0]
    assert aggregate(per_frame, "max").tolist() == [3.0, 5.0]
    with pytest.raises(ValueError, match="sum"):
        aggregate(per_frame, "mean")


def test_random_agent_scores_a_split(test_file, tmp_path):
    import csv

    import numpy as np


    out = xvoe.score("random", str(test_file), str(tmp_path / "random.csv"), progress=False)
    rows = list(csv.DictReader(open(out)))
    assert tuple(rows[0]) == SCORE_COLUMNS[:8] and len(rows) == 176      # its own score alone
    assert rows[1]["member"] == "1" and rows[0]["model"] == "random"
    curves = np.load(out.path.with_suffix(".curves.npz"))
    assert curves["surprise"].shape == (176, 15)       # its own curve: random surprise, not a pixel error
    np.testing.assert_allclose([float(r["score"]) for r in rows], curves["surprise"].sum(1))
    again = xvoe.score("random", str(test_file), str(tmp_path / "again.csv"), progress=False)
    assert open(out).read() == open(again).read()
    with pytest.raises(XvoeError, match="exists"):
        xvoe.score("random", str(test_file), str(out), progress=False)
    with pytest.raises(XvoeError, match="not a model"):
        xvoe.score(str(tmp_path / "random.csv"), str(test_file), str(tmp_path / "x.csv"), progress=False)


def test_scores_need_a_test_split(train_file, tmp_path):
    with pytest.raises(XvoeError, match="test split"):
        xvoe.score("random", str(train_file), str(tmp_path / "x.csv"), progress=False)


def test_objects_unseen_in_a_frame_stay_behind_the_walls_there():
    layers = torch.ones(1, 2, 3, 4, 2, 2)                   # far everywhere: depth 1
    layers[0, :, 0, 3, 0, :] = -0.5                         # slot 0, a wall, covers the top row
    layers[0, :, 1, 3] = -0.8                               # slot 1 decodes in front of it, everywhere
    layers[0, :, 2, 3] = -0.8                               # slot 2 too
    visible = torch.tensor([[[True, False, True], [True, True, False]]])     # slot 1 unseen in frame 0, slot 2 in 1
    occluder = torch.tensor([[True, False, False]])
    out = behind_walls(layers, visible, occluder)
    assert torch.equal(out[0, 0, 1, 3, 0], torch.full((2,), -0.5 + _BEHIND))      # pushed behind the wall
    assert torch.equal(out[0, 0, 1, 3, 1], torch.full((2,), -0.8))               # no wall below: still shows
    assert torch.equal(out[0, 1, 1], layers[0, 1, 1]) and torch.equal(out[0, 0, 2], layers[0, 0, 2])   # seen
    assert torch.equal(out[0, 1, 2, 3, 0], torch.full((2,), -0.5 + _BEHIND))
    assert torch.equal(out[:, :, 0], layers[:, :, 0]) and torch.equal(out[..., :3, :, :], layers[..., :3, :, :])
    assert torch.equal(behind_walls(layers, visible, torch.tensor([[False, False, False]])), layers)   # no wall


def test_a_wall_is_drawn_only_in_the_frames_it_was_seen(models):
    """Nothing hides a wall (the nearest lane): unseen, it is out of the picture, whatever
    Transformer 1 fills it with; so its fill costs no pixels and hides nothing."""
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=False)
    visible[:, 3:, 0] = False                              # the wall (slot 0) is lifted away at frame 3
    with torch.no_grad():   # the frames as the encoder saw them: no wall from frame 3
        frames = rendered(vae, mean, visible, background)
        frames[:, 3:] = rendered(vae, mean, visible & ~occluder[:, None, :], background)[:, 3:]
        layers, walls = scene_layers(vae, mean, visible.any(1), visible, occluder)
    assert torch.equal(layers[:, 3:, 0], vae.blank()[0].expand_as(layers[:, 3:, 0]))
    assert torch.equal(layers[:, :3, 0], decode_slots(vae, mean, visible.any(1))[:, :3, 0])
    assert torch.all(walls[:, 3:] >= _WALL_PIXEL)          # it covers no pixel there
    surprise = mse_surprise(vae, xpl, frames, mean, visible, background, occluder)
    torch.testing.assert_close(surprise.s_img, torch.zeros(B, T), atol=1e-6, rtol=0)


def test_the_excess_leaves_out_what_the_perception_misses_of_what_it_saw(models):
    """When every object is seen in every frame, nothing is filled: s_img is the perception's
    own reconstruction error, whatever the frames hold, and the excess is the dynamics term."""
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=True)
    with torch.no_grad():
        frames = rendered(vae, mean, visible, background) + 0.3 * torch.randn(B, T, 4, 16, 16)   # clutter
    surprise = mse_surprise(vae, xpl, frames, mean, visible, background, occluder)
    assert torch.all(surprise.s_img > 1)
    torch.testing.assert_close(surprise.s_rec, surprise.s_img)
    torch.testing.assert_close(surprise.excess, surprise.s_dyn)


def test_the_excess_keeps_a_fill_drawn_where_nothing_was_seen(models):
    """An object seen, then hidden with no wall in front of it: Transformer 1's fill draws it
    in the open. s_rec (the seen entries alone) matches frames without it; s_img pays the
    fill, and so does the excess, by the same amount, however noisy the picture elsewhere."""
    vae, xpl = models
    mean, visible, background, occluder = scene(moving=False)
    occluder[:] = False                                   # no wall to hide behind
    visible[:, 3:, 1] = False                             # slot 1 unseen from frame 3
    with torch.no_grad():
        pictures = vae.decode(background.flatten(0, 1)).reshape(B, T, 4, 16, 16)
        seen = torch.where(visible[..., None, None, None], decode_slots(vae, mean, visible.any(1)), vae.blank()[0])
        frames = composite(vae, pictures, seen, visible.any(1))   # what the encoder saw: slot 1 gone
        filled = mean.clone()                               # a fill: the object stays where it was
        s_img, s_dyn, s_rec = _latent_surprise(vae, xpl, frames, filled, visible.any(1), visible, background, occluder)
    torch.testing.assert_close(s_rec, torch.zeros(B, T), atol=1e-6, rtol=0)
    assert torch.all(s_img[:, 3:] > 1e-3) and torch.all(s_img[:, :3].abs() < 1e-6)
    with torch.no_grad():     # noise where the fill draws nothing moves s_img and s_rec alike
        drawn = (rendered(vae, filled, torch.ones_like(visible), background) - frames).abs().amax(2, keepdim=True)
        noisy = frames + torch.where(drawn > 1e-4, 0.0, 0.3 * torch.randn_like(frames))
        noisy_img, _, noisy_rec = _latent_surprise(vae, xpl, noisy, filled, visible.any(1), visible, background,
                                                  occluder)
    assert torch.all(noisy_rec > 1)
    torch.testing.assert_close(noisy_img - noisy_rec, s_img - s_rec, atol=1e-3, rtol=1e-4)


def test_the_reference_nll_is_the_gaussian_density_of_the_seen_drawing(models):
    """nll_excess = nll - reference_nll: the reference is -log N(frames | the composite of the
    seen entries, sigma^2) summed over every pixel of every frame, from the s_rec curve alone."""
    import numpy as np


    vae, xpl = models
    mean, visible, background, occluder = scene(moving=False)
    visible[:, 2:, 1] = False
    with torch.no_grad():
        frames = rendered(vae, mean, visible, background) + 0.2 * torch.randn(B, T, 4, 16, 16)
        _, _, s_rec = _latent_surprise(vae, xpl, frames, mean, visible.any(1), visible, background, occluder)
        pictures = vae.decode(background.flatten(0, 1)).reshape(B, T, 4, 16, 16)
        seen = torch.where(visible[..., None, None, None], decode_slots(vae, mean, visible.any(1)), vae.blank()[0])
        drawing = composite(vae, pictures, seen, visible.any(1))
    sigma = 0.5
    expected = -torch.distributions.Normal(drawing.double(), sigma).log_prob(frames.double()).flatten(1).sum(1)
    np.testing.assert_allclose(reference_nll(s_rec.double().numpy(), 4 * 16 * 16, sigma), expected.numpy(),
                               rtol=1e-6)
