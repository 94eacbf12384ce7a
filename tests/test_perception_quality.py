"""The perception's measures: PSNR and the position probe in closed form; a test split is read."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from xvoe.evaluation.perception_quality import HeldOut, probe, psnr, read_held_out, reconstruction
from xvoe.evaluation.scorecard import perception_lines
from xvoe.models.perception import ComponentVAE, PerceptionConfig


def test_psnr_closed_form():
    assert psnr(255.0 ** 2 * 10, 10) == pytest.approx(0.0)
    assert psnr(4.0, 4) == pytest.approx(20 * np.log10(255))      # an error of 1 per value: 48.13 dB
    assert psnr(np.array([1.0, 100.0]), np.array([1, 1])) == pytest.approx([48.13, 28.13], abs=0.01)


class Black:
    """A perception that draws every frame black (uint8 0) whatever it sees."""

    config = SimpleNamespace(latent_dim=2)

    def forward_batch(self, batch, sample=False):
        return {"composite": -torch.ones_like(batch.frames)}


def test_reconstruction_pools_squared_errors_over_every_frame():
    rng = np.random.default_rng(0)
    rgbd = rng.integers(0, 256, (4, 3, 8, 8, 4), dtype=np.uint8)
    ids = rng.integers(0, 3, (4, 3, 8, 8)).astype(np.uint8)
    held = HeldOut(rgbd, ids, np.zeros((4, 3, 2, 5), np.float32), np.zeros((4, 2), int), [], [])
    found = reconstruction(Black(), held, rounds=200)
    values = rgbd.astype(float) ** 2        # a black drawing's squared error is the frame's square
    assert found["rgb"][0] == pytest.approx(10 * np.log10(255 ** 2 / values[..., :3].mean()))
    assert found["depth"][0] == pytest.approx(10 * np.log10(255 ** 2 / values[..., 3].mean()))
    assert found["objects"][0] == pytest.approx(10 * np.log10(255 ** 2 / values[..., :3][ids > 0].mean()))
    assert found["rgb"][1] < found["rgb"][0] < found["rgb"][2]


def test_probe_r_squared_by_hand():
    # one latent, one target: fitted on videos 0 and 1, where y = 2 z + 1 exactly; held-out
    # videos 2 and 3 miss that line by -+1: R^2 = 1 - 4 / 16
    means = np.array([[0.0, 1.0], [2.0, 3.0], [0.0, 1.0], [2.0, 3.0]])[:, :, None, None]     # (V, T, K, D)
    targets = np.array([[1.0, 3.0], [5.0, 7.0], [2.0, 2.0], [6.0, 6.0]])[:, :, None, None]
    chosen = np.ones((4, 2, 1), dtype=bool)
    (r2, low, high), = probe(means, targets, chosen)
    assert r2 == pytest.approx(0.75) and np.isnan(low) and np.isnan(high)
    exact = np.array([[1.0, 3.0], [5.0, 7.0], [1.0, 3.0], [5.0, 7.0]])[:, :, None, None]
    (r2, low, high), = probe(means, exact, chosen, rounds=50)
    assert (r2, low, high) == pytest.approx((1.0, 1.0, 1.0))


def test_the_perception_lines_read_a_test_split(test_file):
    torch.manual_seed(0)
    vae = ComponentVAE(PerceptionConfig(image_size=64, latent_dim=4, cnn_channels=(8, 8), cnn_hidden=16,
                                        decoder_channels=8)).eval()
    held = read_held_out(test_file, 4, 64)
    assert len(held.rgbd) == len(held.states) == 4 and held.rgbd.shape[2] == 64
    lines = {line.name: line for line in perception_lines(vae, test_file, videos=4, rounds=20)}
    assert lines["perception RGB PSNR (dB)"].target == 26.0 and np.isfinite(lines["perception RGB PSNR (dB)"].value)
    assert lines["perception position probe R^2 x"].target == 0.95
