import numpy as np
import pytest
import torch

from xvoe.errors import XvoeError
from xvoe.models.config import from_dict, to_dict
from xvoe.models.perception import BLANK, BLANK_DEPTH, ComponentVAE, PerceptionConfig, normalise, visible_centroid
from xvoe.training.data import cut_objects, cut_plan, masked_inputs, perception_batch
from xvoe.training.recipes import recipe

TINY = dict(latent_dim=4, cnn_channels=(8, 8), cnn_hidden=16, decoder_channels=8, vit_patch=4, vit_width=16,
            vit_layers=1, vit_heads=2, vit_mlp=32, vit_head_hidden=16)


@pytest.mark.parametrize("where", [False, True])
@pytest.mark.parametrize("encoder", ["cnn", "vit"])
@pytest.mark.parametrize("size, grid", [(16, 4), (32, 8)])
def test_shapes_and_posterior_ranges(encoder, size, grid, where):
    torch.manual_seed(0)
    model = ComponentVAE(PerceptionConfig(image_size=size, broadcast_size=grid, encoder=encoder, where_latents=where,
                                          **TINY))
    images = torch.randn(5, 4, size, size) * 3
    mean, std = model.posterior(images)
    assert mean.shape == std.shape == (5, 4)
    assert mean.abs().max() < 3 and (std > 0).all() and (std < 3).all()
    decoded = model.decode(mean)
    assert decoded.shape == (5, 4, size, size)
    # every slot starts as "nothing here": the decoder's output begins near the blank value
    assert torch.allclose(decoded.mean((0, 2, 3)), torch.tensor(BLANK), atol=0.3)


def test_paper_preset_has_the_paper_sizes():
    config = recipe("paper").perception
    assert (config.image_size, config.latent_dim, config.encoder) == (128, 32, "vit")
    assert (config.vit_patch, config.vit_width, config.vit_layers, config.vit_heads, config.vit_mlp) == (8, 256, 6, 8,
                                                                                                         1024)
    assert (config.sigma, config.beta, config.broadcast_size) == (0.05, 0.5, 8)
    assert from_dict(PerceptionConfig, to_dict(config)) == config


def test_compositing_picks_the_nearest_slot():
    model = ComponentVAE(PerceptionConfig(image_size=16, broadcast_size=4, **TINY))
    layers = torch.zeros(1, 3, 4, 16, 16)
    layers[0, 0, :3], layers[0, 0, 3] = -0.5, 1.0            # background, far
    layers[0, 1, :3], layers[0, 1, 3] = 0.25, 0.2            # an object
    layers[0, 2, :3], layers[0, 2, 3] = 0.75, BLANK_DEPTH     # empty slot: blank beyond the far plane
    layers[0, 2, :3, :8], layers[0, 2, 3, :8] = 0.9, -0.3     # a nearer object on the top half
    out = model.composite(layers)[0]
    assert torch.allclose(out[:3, :8], torch.full((3, 8, 16), 0.9))
    assert torch.allclose(out[:3, 8:], torch.full((3, 8, 16), 0.25))
    layers[0, 1, 3] = BLANK_DEPTH                             # the object leaves: background shows
    assert torch.allclose(model.composite(layers)[0, :3, 8:], torch.full((3, 8, 16), -0.5))


def test_masked_inputs_blank_outside_each_mask_and_skip_empty_slots():
    rgbd = torch.randint(0, 255, (2, 8, 8, 4), dtype=torch.uint8)
    ids = torch.zeros(2, 8, 8, dtype=torch.uint8)
    ids[0, :2, :2] = 3                                         # slot 2 in frame 0
    ids[1, 4:, 4:] = 1                                         # slot 0 in frame 1
    parts = masked_inputs(normalise(rgbd), ids, slots=8)
    assert parts["object_frame"].tolist() == [0, 1] and parts["object_slot"].tolist() == [2, 0]
    frames = normalise(rgbd)
    assert torch.equal(parts["objects"][0][:, :2, :2], frames[0][:, :2, :2])
    assert torch.equal(parts["objects"][0][:, 2:, :], torch.tensor(BLANK).view(4, 1, 1).expand(4, 6, 8))
    assert parts["pixels"][0].tolist() == [0, 0, 4, 0, 0, 0, 0, 0]
    assert parts["background_mask"][1, 0, 4:, 4:].sum() == 0 and parts["background_mask"][1].sum() == 48


def test_the_amodal_object_loss_ignores_what_stands_behind_other_objects():
    """Where another object covers the frame, an object may stand hidden: with `amodal` its
    picture there costs nothing in its own loss (the composite still sees it), else it does."""
    rgbd = np.full((1, 16, 16, 4), 200, np.uint8)
    ids = np.zeros((1, 16, 16), np.uint8)
    ids[0, 4:10, 2:8] = 1                                      # an object, its right part ...
    ids[0, 2:12, 6:12] = 2                                     # ... behind a wall in front of it
    rgbd[0][ids[0] == 2] = (90, 90, 90, 10)
    rgbd[0][ids[0] == 1] = (30, 180, 60, 100)
    batch = perception_batch(rgbd, ids, 2, np.zeros((1, 3, 4), np.float32), np.zeros((1, 4), np.float32))
    known = batch.object_known[batch.object_slot == 0][0, 0]
    assert known[ids[0] == 2].sum() == 0 and known[ids[0] != 2].min() == 1
    drawn = batch.objects.clone()
    drawn[batch.object_slot == 0, :, 2:12, 6:12] = 0.3          # the whole object drawn, under the wall too
    for amodal in (False, True):
        model = ComponentVAE(PerceptionConfig(image_size=16, broadcast_size=4, amodal=amodal, **TINY))
        assert model.object_nll(batch.objects, batch).sum() == 0
        cost = model.object_nll(drawn, batch)
        assert cost[batch.object_slot == 1] == 0                 # the wall's picture did not change
        assert (cost[batch.object_slot == 0] == 0) == amodal


def test_loss_is_finite_with_empty_frames_and_decreases_on_a_tiny_batch():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    rgbd = np.full((4, 16, 16, 4), 200, np.uint8)
    ids = np.zeros((4, 16, 16), np.uint8)
    rgbd[:3, 4:9, 3:8] = (30, 180, 60, 100)
    for f in range(3):
        ids[f, 4:9, 3 + f:8 + f] = f + 1                      # frame 3 has no object at all
    batch = perception_batch(rgbd, ids, 8, rng.standard_normal((4, 9, 4)).astype(np.float32),
                             rng.standard_normal((1, 4)).astype(np.float32))
    model = ComponentVAE(PerceptionConfig(image_size=16, broadcast_size=4, **TINY))
    optimiser = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        loss = model.loss(batch)["loss"]
        assert torch.isfinite(loss)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])


def test_the_paper_preset_builds_at_128_pixels():
    config = recipe("paper").perception
    model = ComponentVAE(config)
    with torch.no_grad():
        mean, std = model.posterior(torch.zeros(1, 4, 128, 128))
        assert mean.shape == std.shape == (1, 32)
        assert model.decode(mean).shape == (1, 4, 128, 128)
    assert len(model.decoder.convs) == 2 * 4 + 2          # 8 -> 128: four stride-2 layers, one stride-1


def test_where_latents_move_the_picture_by_whole_grid_cells():
    """Shifting latents 0 and 1 by one broadcast cell shifts the decoded picture by 32/8 = 4 pixels
    (exactly, away from the borders, where the cells that enter and leave the grid differ)."""
    torch.manual_seed(0)
    model = ComponentVAE(PerceptionConfig(where_latents=True))
    with torch.no_grad():
        for weight in model.decoder.parameters():
            weight.normal_(0, 0.5)                  # pictures that vary a lot with position
        z = torch.randn(3, model.config.latent_dim) * 0.3
        cell = 2 * 4 / 31 / model.config.where_scale    # 4 pixels ([-1, 1] pixel-centre coordinates), latent units
        right, down = z.clone(), z.clone()
        right[:, 0] += cell
        down[:, 1] += cell
        picture = model.decode(z)
        assert (model.decode(right) - picture).abs().max() > 1.0
        assert torch.allclose(model.decode(right)[..., 8:24], picture[..., 4:20], atol=1e-3)
        assert torch.allclose(model.decode(down)[..., 8:24, :], picture[..., 4:20, :], atol=1e-3)


def test_where_latents_start_at_the_visible_pixels_centroid():
    images = torch.tensor(BLANK).view(1, 4, 1, 1).repeat(3, 1, 32, 32)
    images[0, :, 10:13, 20:23] = 0.0                 # a 3x3 square centred on pixel (x 21, y 11)
    images[1, :, 0, 0] = images[1, :, 31, 31] = 0.5  # two opposite corners: the centre
    centroid = visible_centroid(images)
    assert torch.allclose(centroid[0], torch.tensor([-1 + 2 * 21 / 31, -1 + 2 * 11 / 31]))
    assert torch.allclose(centroid[1], torch.zeros(2), atol=1e-6)
    assert torch.equal(centroid[2], torch.zeros(2))  # an empty slot: no pixels, no NaN
    model = ComponentVAE(PerceptionConfig(where_latents=True))
    with torch.no_grad():                            # an encoder that outputs a = 0: the means are the start
        last = model.encoder.head[-1]
        last.weight.zero_()
        last.bias[:model.config.latent_dim] = 0.0
        mean, _ = model.posterior(images)
    assert torch.allclose(mean[:, :2] * model.config.where_scale, centroid, atol=1e-5)
    assert torch.equal(mean[:, 2:], torch.zeros(3, model.config.latent_dim - 2))


def test_where_latents_are_off_in_older_configs():
    older = to_dict(PerceptionConfig(where_latents=True, amodal=True, cut_share=0.25))
    for field in ("where_latents", "where_scale", "amodal", "cut_share"):
        del older[field]                              # a checkpoint written before the fields existed
    model = ComponentVAE(from_dict(PerceptionConfig, older))
    assert not model.decoder.where and hasattr(model.decoder, "position") and not model.config.amodal
    with pytest.raises(XvoeError, match="where_latents needs latent_dim >= 3"):
        PerceptionConfig(where_latents=True, latent_dim=2)


@pytest.mark.parametrize("where", [False, True])
def test_latent_sensitivity_is_the_decoders_squared_jacobian(where):
    torch.manual_seed(0)
    model = ComponentVAE(PerceptionConfig(image_size=16, broadcast_size=4, where_latents=where, **TINY)).double()
    with torch.no_grad():
        for weight in model.decoder.parameters():
            weight.normal_(0, 0.5)
    z = torch.randn(3, 4, dtype=torch.float64) * 0.5
    jacobian = torch.stack([torch.autograd.functional.jacobian(lambda v: model.decode(v[None])[0], row) for row in z])
    expected = jacobian.pow(2).flatten(1, 3).sum(1).mean(0)          # (D,): per latent, mean over z
    torch.testing.assert_close(model.latent_sensitivity(z, step=1e-6), expected, rtol=1e-3, atol=1e-6)


def test_cut_objects_blank_one_side_of_the_chosen_objects_only():
    objects = torch.tensor(BLANK).view(1, 4, 1, 1).repeat(3, 1, 12, 12)
    objects[:, :, 2:8, 3:9] = -0.5                             # a 6x6 object in each image
    plan = np.array([[1, 0, 0.5], [1, 3, 0.5], [0, 0, 0.5]])   # right half goes; top half goes; untouched
    cut = cut_objects(objects, plan)
    shown = cut[:, 3] < 1.0
    assert shown[0].sum() == 18 and shown[0, 2:8, 3:6].all()   # columns 3-5 stay
    assert shown[1].sum() == 18 and shown[1, 5:8, 3:9].all()   # rows 5-7 stay
    assert torch.equal(cut[2], objects[2])
    rng = np.random.default_rng(0)
    drawn = cut_plan(rng, 4000, 0.25)
    assert abs(drawn[:, 0].mean() - 0.25) < 0.03 and set(drawn[:, 1]) == {0, 1, 2, 3}
    assert 0.3 <= drawn[:, 2].min() and drawn[:, 2].max() <= 0.9
    assert np.array_equal(cut_plan(np.random.default_rng(0), 4000, 0.25), drawn)
