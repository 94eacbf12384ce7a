"""The perception's measures: PSNR and the position probe in closed form, the probe per kind on
hand-made latents; a test split is read."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from xvoe.evaluation.perception_quality import (
    POOLED,
    HeldOut,
    _probe,
    _psnr,
    position_probes,
    read_held_out,
    reconstruction,
)
from xvoe.evaluation.scorecard import format_line, perception_lines, probe_lines
from xvoe.models.perception import ComponentVAE, PerceptionConfig


def test_psnr_closed_form():
    assert _psnr(255.0 ** 2 * 10, 10) == pytest.approx(0.0)
    assert _psnr(4.0, 4) == pytest.approx(20 * np.log10(255))      # an error of 1 per value: 48.13 dB
    assert _psnr(np.array([1.0, 100.0]), np.array([1, 1])) == pytest.approx([48.13, 28.13], abs=0.01)


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
    (r2, low, high), = _probe(means, targets, chosen)
    assert r2 == pytest.approx(0.75) and np.isnan(low) and np.isnan(high)
    exact = np.array([[1.0, 3.0], [5.0, 7.0], [1.0, 3.0], [5.0, 7.0]])[:, :, None, None]
    (r2, low, high), = _probe(means, exact, chosen, rounds=50)
    assert (r2, low, high) == pytest.approx((1.0, 1.0, 1.0))


KIND_NAMES = ["none", "ball", "cube", "wall", "window_wall"]


def two_kinds(videos=8, frames=6, seed=0):
    """Slot 0 a ball whose latent is its x and y (and a constant), slot 1 a cube whose latent is
    noise drawn apart from its position, slot 2 empty; every ball and cube visible."""
    rng = np.random.default_rng(seed)
    positions = rng.uniform(0, 32, (videos, frames, 3, 2))
    means = np.zeros((videos, frames, 3, 3))
    means[:, :, 0, :2], means[:, :, 0, 2] = positions[:, :, 0], 1.0
    means[:, :, 1] = rng.normal(0, 10, (videos, frames, 3))
    visible = np.zeros((videos, frames, 3), dtype=bool)
    visible[:, :, :2] = True
    kind = np.tile([1, 2, 0], (videos, 1))
    return means, positions, visible, kind


def test_a_kind_whose_latent_codes_position_reads_it_and_one_whose_latent_does_not_reads_nothing():
    means, positions, visible, kind = two_kinds()
    probes = position_probes(means, positions, visible, kind, KIND_NAMES, rounds=50)
    ball, cube, pooled = probes["ball"], probes["cube"], probes[POOLED]
    assert ball.x[0] == pytest.approx(1.0) and ball.y[0] == pytest.approx(1.0) and ball.reason == ""
    assert ball.x[1:] == pytest.approx((1.0, 1.0)) and ball.objects == 4 * 6
    assert cube.x[0] < 0.2 and cube.y[0] < 0.2 and cube.x[1] <= cube.x[0] <= cube.x[2]
    # one probe for both kinds: the cubes' noise pulls the fit off the balls' exact line
    assert cube.x[0] + 0.1 < pooled.x[0] < 0.9 and cube.y[0] + 0.1 < pooled.y[0] < 0.9 and pooled.objects == 48
    # the pooled probe is `probe` over every visible object, the kind's over its own
    assert pooled.x == pytest.approx(_probe(means, positions, visible, 50)[0])
    chosen = visible & (kind[:, None, :] == 1)
    assert ball.y == pytest.approx(_probe(means, positions, chosen, 50)[1])


def test_a_kind_too_few_to_fit_or_not_named_is_nan_with_its_reason():
    means, positions, visible, kind = two_kinds()
    kind[:, 2] = 3                                  # slot 2 a wall, visible in two frames of the fitting half
    visible[0, :2, 2] = True
    visible[6, :, 2] = True
    probes = position_probes(means, positions, visible, kind, KIND_NAMES)
    wall = probes["wall"]
    assert np.isnan(wall.x).all() and np.isnan(wall.y).all() and wall.objects == 6
    assert wall.reason == "visible objects in the fitting half: 2, fewer than the fit's 4 weights"
    visible[:4, :, 2] = True                        # now fitted, but seen in one held-out frame only
    visible[6, 1:, 2] = False
    wall = position_probes(means, positions, visible, kind, KIND_NAMES)["wall"]
    assert np.isnan(wall.x[0]) and wall.reason == "visible objects in the held-out half: 1, fewer than 2"
    # a split that names no wall, nor any other kind: the goal kinds are there, nan
    probes = position_probes(means, positions, visible, kind, ["none", "ball", "cube"])
    assert list(probes) == [POOLED, "ball", "cube", "wall"] and probes["wall"].objects == 0
    assert np.isnan(probes["wall"].y[0]) and "fitting half" in probes["wall"].reason


def test_a_held_out_position_that_does_not_vary_has_no_r_squared_nor_interval():
    means, positions, visible, kind = two_kinds()
    positions[:, :, 0, 1] = 24.0 + np.random.default_rng(1).uniform(0, 0.0025, (8, 6))   # balls on the floor
    ball = position_probes(means, positions, visible, kind, KIND_NAMES, rounds=50)["ball"]
    assert np.isfinite(ball.x).all() and np.isnan(ball.y).all()
    assert ball.reason == "y does not vary in the held-out half"


def test_the_probe_lines_carry_the_goal_per_kind_and_report_the_pooled_probe():
    means, positions, visible, kind = two_kinds()
    lines = {line.name: line for line in probe_lines(position_probes(means, positions, visible, kind, KIND_NAMES))}
    assert list(lines) == [f"perception position probe R^2 {axis}{kind}" for kind in
                           ("", " (ball)", " (cube)", " (wall)", " (window_wall)") for axis in "xy"]
    # x and y of cubes and walls, x of balls: a ball's y never varies
    goals = ("x (ball)", "x (cube)", "y (cube)", "x (wall)", "y (wall)")
    assert [name for name, line in lines.items() if line.target is not None] == [
        f"perception position probe R^2 {name}" for name in goals]
    assert all(line.target == 0.95 for line in lines.values() if line.target is not None)
    assert lines["perception position probe R^2 x (ball)"].met
    assert not lines["perception position probe R^2 x (cube)"].met
    assert lines["perception position probe R^2 x"].met is None        # the pooled probe: reported
    wall = lines["perception position probe R^2 y (wall)"]
    assert not wall.met and "fewer than the fit's 4 weights" in format_line(wall)
    positions[:, :, 0, 1] = 24.0                    # balls on the floor: the note on y alone
    lines = {line.name: line for line in probe_lines(position_probes(means, positions, visible, kind, KIND_NAMES))}
    assert lines["perception position probe R^2 x (ball)"].note == ""
    assert lines["perception position probe R^2 y (ball)"].note == "y does not vary in the held-out half"


def test_the_perception_lines_read_a_test_split(test_file):
    torch.manual_seed(0)
    vae = ComponentVAE(PerceptionConfig(image_size=64, latent_dim=4, cnn_channels=(8, 8), cnn_hidden=16,
                                        decoder_channels=8)).eval()
    held = read_held_out(test_file, 4, 64)
    assert len(held.rgbd) == len(held.states) == 4 and held.rgbd.shape[2] == 64
    lines = {line.name: line for line in perception_lines(vae, test_file, videos=4, rounds=20)}
    assert lines["perception RGB PSNR (dB)"].target == 26.0 and np.isfinite(lines["perception RGB PSNR (dB)"].value)
    assert lines["perception position probe R^2 x"].target is None
    assert lines["perception position probe R^2 y (cube)"].target == 0.95
    assert sum(line.target is not None for line in lines.values()) == 6      # PSNR and five probe lines
