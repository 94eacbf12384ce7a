import numpy as np
import pytest
import torch

from xvoe.errors import XvoeError
from xvoe.models.config import from_dict, to_dict
from xvoe.models.perception import _BLANK_DEPTH, BLANK, ComponentVAE, PerceptionConfig, normalise
from xvoe.training.data import masked_inputs, perception_batch
from xvoe.training.recipes import recipe

TINY = dict(latent_dim=4, cnn_channels=(8, 8), cnn_hidden=16, decoder_channels=8, vit_patch=4, vit_width=16,
            vit_layers=1, vit_heads=2, vit_mlp=32, vit_head_hidden=16)


@pytest.mark.parametrize("encoder", ["cnn", "vit"])
@pytest.mark.parametrize("size, grid", [(16, 4), (32, 8)])
def test_shapes_and_posterior_ranges(encoder, size, grid):
    torch.manual_seed(0)
    model = ComponentVAE(PerceptionConfig(image_size=size, broadcast_size=grid, encoder=encoder, **TINY))
    images = torch.randn(5, 4, size, size) * 3
    mean, std = model.posterior(images)
    assert mean.shape == std.shape == (5, 4)
    assert mean.abs().max() < 3 and (std > 0).all() and (std < 3).all()
    decoded = model.decode(mean)
    assert decoded.shape == (5, 4, size, size)
    # every slot starts as "nothing here": the decoder's output begins near the blank value
    assert torch.allclose(decoded.mean((0, 2, 3)), torch.tensor(BLANK), atol=0.3)


def test_a_stored_config_loads_without_a_retired_field_it_left_as_it_always_was():
    stored = to_dict(PerceptionConfig()) | {"where_latents": False, "where_scale": 0.5, "amodal": False,
                                             "cut_share": 0.0}      # what every checkpoint before their removal held
    assert from_dict(PerceptionConfig, stored) == PerceptionConfig()
    with pytest.raises(XvoeError, match="made with amodal=True, a setting xvoe no longer has"):
        from_dict(PerceptionConfig, stored | {"amodal": True})
    with pytest.raises(XvoeError, match="has no field"):
        from_dict(PerceptionConfig, stored | {"no_such_field": 1})


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
    layers[0, 2, :3], layers[0, 2, 3] = 0.75, _BLANK_DEPTH     # empty slot: blank beyond the far plane
    layers[0, 2, :3, :8], layers[0, 2, 3, :8] = 0.9, -0.3     # a nearer object on the top half
    out = model.composite(layers)[0]
    assert torch.allclose(out[:3, :8], torch.full((3, 8, 16), 0.9))
    assert torch.allclose(out[:3, 8:], torch.full((3, 8, 16), 0.25))
    layers[0, 1, 3] = _BLANK_DEPTH                             # the object leaves: background shows
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


