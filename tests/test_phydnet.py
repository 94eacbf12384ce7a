"""PhyDNet: moment constraint, shapes, causality, learning, the training stage and scoring."""
import csv
import shutil
from dataclasses import replace

import numpy as np
import pytest
import torch
from conftest import interrupt_during

from xvoe.apps.comparisons import plot_predictions, predicted_frames
from xvoe.apps.pipeline import PipelineConfig, run_pipeline
from xvoe.cli import main
from xvoe.errors import XvoeError
from xvoe.evaluation.score_curves import SCORE_COLUMNS
from xvoe.evaluation.scorer import load_model
from xvoe.models.perception import normalise, to_uint8
from xvoe.models.phydnet import (
    PhyDNet,
    PhyDNetConfig,
    _change_mask,
    _derivative_targets,
    _kernel_moments,
    _kernels_with_moments,
)
from xvoe.scenes.generate import GenerateConfig, generate
from xvoe.training.config import TrainConfig
from xvoe.training.distributed import Dist
from xvoe.training.phydnet import _VideoBatches, _widen_checkpoint, load_phydnet, train_phydnet
from xvoe.training.recipes import DEFAULT_RECIPE, RECIPES

TINY = PhyDNetConfig(image_size=16, encoder_channels=(8, 8, 8), phycell_kernel=5, lstm_channels=(8,))
TRAIN = {"steps": 4, "batch_size": 2, "warmup_steps": 1, "log_every": 1, "threads": 1}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny networks run fastest on one thread (and a busy machine makes two threads wait on each other)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def videos(batch: int = 2, frames: int = 5, size: int = 16, seed: int = 0) -> torch.Tensor:
    return torch.rand(batch, frames, 4, size, size, generator=torch.Generator().manual_seed(seed)) * 2 - 1


def test_moments_are_a_w_a_transpose_and_the_inverse_is_exact():
    rng = torch.Generator().manual_seed(0)
    targets = torch.randn(3, 7, 7, dtype=torch.float64, generator=rng)
    torch.testing.assert_close(_kernel_moments(_kernels_with_moments(targets)), targets)
    # by hand for k = 3 (offsets -1, 0, 1): M[1, 0] = sum_ij (i - 1) w[i, j]
    w = torch.arange(9, dtype=torch.float64).reshape(3, 3)
    assert _kernel_moments(w)[1, 0] == -w[0].sum() + w[2].sum()
    assert _kernel_moments(w)[0, 2] == (w[:, 0].sum() + w[:, 2].sum()) / 2


def test_a_filter_with_one_hot_moments_takes_that_derivative():
    """Cross-correlating x^a y^b with the (p, q) stencil gives d^p/di^p d^q/dj^q exactly."""
    k = 5
    stencils = _kernels_with_moments(_derivative_targets(k).double())
    i, j = torch.meshgrid(torch.arange(k, dtype=torch.float64) - 2.3, torch.arange(k, dtype=torch.float64) + 0.7,
                          indexing="ij")
    field = i ** 3 * j ** 2                                   # a patch centred on (i, j) = (-0.3, 2.7)
    at = (-0.3, 2.7)
    expected = {(0, 0): at[0] ** 3 * at[1] ** 2, (1, 0): 3 * at[0] ** 2 * at[1] ** 2, (0, 1): 2 * at[0] ** 3 * at[1],
                (2, 1): 12 * at[0] * at[1], (3, 2): 12.0, (4, 0): 0.0}
    for (p, q), value in expected.items():
        assert float((stencils[p * k + q] * field).sum()) == pytest.approx(value, abs=1e-9)


def test_projection_sets_the_moments_and_the_loss_includes_them():
    net = PhyDNet(TINY)
    targets = net.moment_targets[:, None]
    with torch.no_grad():
        net.filters()[0].add_(torch.randn_like(net.filters()[0]))
    frames = videos()
    terms = net.loss(frames)
    assert terms["moment"] > 0.1
    torch.testing.assert_close(terms["loss"], terms["prediction"] + TINY.moment_weight * terms["moment"])
    terms["loss"].backward()
    assert net.filters()[0].grad.abs().sum() > 0
    net.project_moments()
    torch.testing.assert_close(net.moments()[0], targets.expand_as(net.moments()[0]), atol=1e-4, rtol=0)
    assert float(net.moment_loss().detach()) < 1e-9


@pytest.mark.parametrize("size, widths", [(16, (8, 8, 8)), (32, (8, 8, 16, 16))])
def test_shapes(size, widths):
    net = PhyDNet(replace(TINY, image_size=size, encoder_channels=widths, lstm_channels=(8, 4)))
    frames = videos(3, 6, size)
    assert net(frames).shape == (3, 5, 4, size, size)
    surprise = net.surprise(frames)
    assert surprise.shape == (3, 6) and torch.all(surprise[:, 0] == 0) and torch.all(surprise[:, 1:] > 0)
    with pytest.raises(XvoeError, match="expects frames"):
        net(videos(1, 4, size // 2))


def test_config_errors():
    with pytest.raises(XvoeError, match="multiple of 4"):
        PhyDNetConfig(image_size=18, encoder_channels=(8, 8, 8))
    with pytest.raises(XvoeError, match="odd"):
        PhyDNetConfig(phycell_kernel=4)


def test_the_prediction_of_a_frame_never_sees_that_frame():
    torch.manual_seed(0)
    net = PhyDNet(TINY).eval()
    frames = videos(2, 6)
    before = net(frames)
    for t in range(5):                  # prediction index t is frame t + 1
        changed = frames.clone()
        changed[:, t + 1:] = videos(2, 5 - t, seed=t + 1)
        after = net(changed)
        torch.testing.assert_close(after[:, :t + 1], before[:, :t + 1], atol=1e-6, rtol=0)
        if t + 1 < 5:
            assert not torch.allclose(after[:, t + 1:], before[:, t + 1:])


def test_the_change_weight_counts_changed_pixels_more_in_training_only():
    frames = torch.zeros(1, 3, 4, 16, 16)
    frames[0, 1, 3, 2, 5] = 0.5           # frame 1: one pixel's depth changes (and changes back at 2)
    frames[0, 2, 0, 7, 7] = 1 / 255       # frame 2: a change below one uint8 level is not a change
    mask = _change_mask(frames)
    assert mask.shape == (1, 2, 1, 16, 16) and mask.sum() == 2
    assert mask[0, 0, 0, 2, 5] == 1 and mask[0, 1, 0, 2, 5] == 1 and mask[0, 1, 0, 7, 7] == 0

    torch.manual_seed(0)
    plain = PhyDNet(TINY)
    weighted = PhyDNet(replace(TINY, change_weight=9.0))
    weighted.load_state_dict(plain.state_dict())
    frames = videos(1, 3)
    frames[:, 2] = frames[:, 1]
    frames[:, 2, :, :4, :4] = -frames[:, 1, :, :4, :4]          # frame 2 differs from 1 in a 4x4 corner
    error = (plain(frames) - frames[:, 1:]).pow(2).detach()
    changed = torch.zeros(1, 2, 1, 16, 16, dtype=torch.bool)
    changed[:, 0] = True                                          # frame 1 is new noise everywhere
    changed[:, 1, :, :4, :4] = True
    # by hand: changed pixels count 10 times, unchanged ones once, averaged over channels too
    by_hand = (error * changed).sum() * 10 + (error * ~changed).sum()
    by_hand /= (changed.sum() * 10 + (~changed).sum()) * 4
    terms = weighted.loss(frames)
    torch.testing.assert_close(terms["loss"] - terms["moment"], by_hand)
    torch.testing.assert_close(terms["prediction"], error.mean())     # logged as the plain MSE
    torch.testing.assert_close(plain.surprise(frames), weighted.surprise(frames))


def test_a_few_steps_lower_the_loss_on_a_tiny_batch():
    torch.manual_seed(0)
    net = PhyDNet(TINY)
    frames = videos(4, 1)[:, :, :, :1, :1].expand(4, 5, 4, 16, 16)    # one colour per video: learnable
    optimiser = torch.optim.Adam(net.parameters(), lr=3e-3)
    first = float(net.loss(frames)["loss"].detach())
    for _ in range(5):
        optimiser.zero_grad()
        net.loss(frames)["loss"].backward()
        optimiser.step()
    assert float(net.loss(frames)["loss"].detach()) < 0.9 * first


# --- the training stage and scoring, on tiny generated 16x16 splits -----------------------

@pytest.fixture(scope="module")
def splits(tmp_path_factory):
    folder = tmp_path_factory.mktemp("phydnet-data")
    train = generate(GenerateConfig("train", videos=6, size=16, frames=10, seed=2), folder / "train.h5", workers=1,
                     progress=False)
    test = generate(GenerateConfig("test", pairs=1, size=16, frames=10, seed=3), folder / "test.h5", workers=1,
                    progress=False)
    return train, test


@pytest.fixture
def tiny_recipe(monkeypatch):
    base = RECIPES[DEFAULT_RECIPE]
    tiny = replace(base, phydnet=TINY, phydnet_train=TrainConfig(**TRAIN), phases=())
    monkeypatch.setitem(RECIPES, DEFAULT_RECIPE, tiny)


def test_stage_trains_resumes_exactly_and_loads(splits, tmp_path, tiny_recipe):
    straight = train_phydnet(splits[0], tmp_path / "a", progress=False)
    train_phydnet(splits[0], tmp_path / "b", progress=False, steps=2)
    resumed = train_phydnet(None, tmp_path / "b", progress=False, resume=True, steps=4)
    a, b = torch.load(straight, weights_only=True), torch.load(resumed, weights_only=True)
    assert a["step"] == b["step"] == 4
    for name, value in a["model"].items():
        torch.testing.assert_close(value, b["model"][name], msg=name)
    rows = [list(csv.DictReader(open(run / "phydnet.csv"))) for run in (tmp_path / "a", tmp_path / "b")]
    assert [r["loss"] for r in rows[0]] == [r["loss"] for r in rows[1]] and "moment" in rows[0][0]
    net, state = load_phydnet(tmp_path / "a")
    assert net.config == TINY and not net.training and state["config"]["recipe"] == DEFAULT_RECIPE
    one, two = _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=2, seed=1), [
        _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=2, rank=r, world=2, seed=1) for r in (0, 1)]
    assert torch.equal(one.batch(3), torch.cat([part.batch(3) for part in two]))
    with pytest.raises(XvoeError, match="nothing to resume"):
        train_phydnet(None, tmp_path / "c", progress=False)
    with pytest.raises(XvoeError, match="16x16"):
        train_phydnet(splits[0], tmp_path / "d", progress=False, model_overrides={"image_size": 32})


def test_a_phase_that_widens_the_lstm_kernel_predicts_the_same_and_trains_on(splits, tmp_path, tiny_recipe):
    """A phase's lstm_kernel pads the trained 3x3 gates with zeros to 7x7: the same predictions,
    the run's step kept and Adam afresh; the resumed phase's outer taps learn, and a rerun of the
    phase (an interrupted one resumed) does not widen again."""
    source = train_phydnet(splits[0], tmp_path / "a", progress=False, model_overrides={"lstm_channels": (8, 8)})
    (net, _), frames = load_phydnet(source), videos(2, 6)
    copy = tmp_path / "b" / "phydnet.pt"
    copy.parent.mkdir()
    shutil.copy(source, copy)
    _widen_checkpoint(copy, 7, Dist())
    wide, state = load_phydnet(copy)
    assert wide.config == replace(net.config, lstm_kernel=7) and state["step"] == 4
    assert state["optimizer"]["state"] == {} and "rng" in state
    with torch.no_grad():
        torch.testing.assert_close(wide(frames), net(frames), rtol=0, atol=1e-6)
    trained = torch.load(train_phydnet(None, tmp_path / "a", progress=False, resume=True, steps=6, lstm_kernel=7,
                                       model_overrides={"change_weight": 3.0}), weights_only=True)
    gates = trained["model"]["net.lstm.1.gates.weight"]
    assert trained["step"] == 6 and gates.shape[-2:] == (7, 7) and gates[..., 0, :].abs().sum() > 0
    assert trained["config"]["phydnet"]["change_weight"] == 3.0      # a loss field changed in the same phase
    again = torch.load(train_phydnet(None, tmp_path / "a", progress=False, resume=True, steps=7, lstm_kernel=7),
                       weights_only=True)
    assert again["step"] == 7 and again["model"]["net.lstm.1.gates.weight"].shape[-2:] == (7, 7)
    with pytest.raises(XvoeError, match="larger odd size, not 7 -> 5"):
        train_phydnet(None, tmp_path / "a", progress=False, resume=True, steps=8, lstm_kernel=5)
    with pytest.raises(XvoeError, match="a fresh run takes its kernel"):
        train_phydnet(splits[0], tmp_path / "c", progress=False, lstm_kernel=5)


def test_an_interrupt_stops_after_its_step_and_the_run_resumes_exactly(splits, tmp_path, tiny_recipe, monkeypatch):
    """Ctrl-C (SIGINT) during step 2 lets that step finish: the checkpoint holds step 3, the handler
    in place before is back, and the resumed run ends where an uninterrupted one does."""
    import signal

    straight = torch.load(train_phydnet(splits[0], tmp_path / "a", progress=False), weights_only=True)
    before = signal.getsignal(signal.SIGINT)
    draw = interrupt_during(monkeypatch, _VideoBatches, 2)
    with pytest.raises(KeyboardInterrupt, match="stopped at step 3"):
        train_phydnet(splits[0], tmp_path / "b", progress=False)
    assert signal.getsignal(signal.SIGINT) is before
    assert torch.load(tmp_path / "b" / "phydnet.pt", weights_only=True)["step"] == 3
    monkeypatch.setattr(_VideoBatches, "batch", draw)
    resumed = torch.load(train_phydnet(None, tmp_path / "b", progress=False, resume=True), weights_only=True)
    assert resumed["step"] == straight["step"] == 4
    for name, value in straight["model"].items():
        torch.testing.assert_close(value, resumed["model"][name], msg=name)
    again = torch.load(train_phydnet(None, tmp_path / "b", progress=False, resume=True, steps=5,
                                     model_overrides={"change_weight": 3.0}), weights_only=True)
    assert again["step"] == 5 and again["config"]["phydnet"]["change_weight"] == 3.0
    with pytest.raises(XvoeError, match="only change_weight, moment_weight may change, not lstm_channels"):
        train_phydnet(None, tmp_path / "b", progress=False, resume=True, model_overrides={"lstm_channels": (4,)})


def test_a_focus_group_fills_its_share_of_each_batch_with_that_groups_wall_videos(splits):
    import h5py


    with h5py.File(splits[0]) as file:
        groups, walls = file["group"].asstr()[:], file["has_wall"][:].astype(bool)
    focus = np.flatnonzero((groups == "continuity") & walls)
    assert 0 < len(focus) < len(groups)
    batches = _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=1, seed=1, focus_group="continuity",
                           focus_share=0.5)
    for step in range(20):
        tail = batches.batch(step)[2:]
        assert all(any(torch.equal(video, batches.rgbd[row]) for row in focus) for video in tail)
    plain = _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=1, seed=1)
    mixed = torch.cat([plain.batch(step) for step in range(20)])
    assert not all(any(torch.equal(video, plain.rgbd[row]) for row in focus) for video in mixed)
    with pytest.raises(XvoeError, match=r"\[0, 1\]"):
        _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=1, focus_group="continuity", focus_share=1.5)
    with pytest.raises(XvoeError, match="needs a focus_group"):
        _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=1, focus_share=0.5)
    with pytest.raises(XvoeError, match="focus_group names no group 'permanance'"):
        _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=1, focus_group="permanance", focus_share=0.5)
    with pytest.raises(XvoeError, match="rounds to none"):
        _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=1, focus_group="continuity", focus_share=0.1)
    with pytest.raises(XvoeError, match="no continuity videos with a wall in rows 3 to 5"):
        _VideoBatches(str(splits[0]), image_size=16, batch_size=4, shards=2, focus_group="continuity", focus_share=0.5)
    with pytest.raises(XvoeError, match="needs a train split"):
        _VideoBatches(str(splits[1]), image_size=16, batch_size=4, shards=1, focus_group="continuity", focus_share=0.5)


def test_a_focus_on_several_groups_draws_from_the_wall_videos_of_each(tmp_path):
    import h5py


    path = generate(GenerateConfig("train", videos=10, size=16, frames=10, seed=0), tmp_path / "train.h5", workers=1,
                    progress=False)
    with h5py.File(path) as file:
        groups, walls = file["group"].asstr()[:], file["has_wall"][:].astype(bool)
    kinds = {name: set(np.flatnonzero((groups == name) & walls)) for name in ("continuity", "permanence")}
    assert all(kinds.values()) and (walls & ~np.isin(groups, list(kinds))).any()
    batches = _VideoBatches(str(path), image_size=16, batch_size=4, shards=1, seed=1,
                           focus_group="continuity, permanence", focus_share=0.5)
    drawn = {int(row) for step in range(40) for row in batches.focus.draw(np.random.default_rng(step), 0, 0, 10, 4)[2:]}
    assert drawn == kinds["continuity"] | kinds["permanence"]
    with pytest.raises(XvoeError, match="focus_group names no group 'permanance'"):
        _VideoBatches(str(path), image_size=16, batch_size=4, shards=1, focus_group="continuity,permanance",
                     focus_share=0.5)


def test_the_command_line_sets_the_focus_and_the_learning_rate(splits, tmp_path, tiny_recipe, capsys):
    run = tmp_path / "run"
    assert main(["train", "phydnet", "--data", str(splits[0]), "--out", str(run), "--quiet", "--steps", "2",
                 "--lr", "0.004", "--focus-group", "continuity", "--focus-share", "0.5"]) == 0
    train = torch.load(run / "phydnet.pt", weights_only=True)["train"]
    assert (train["lr"], train["focus_group"], train["focus_share"], train["steps"]) == (0.004, "continuity", 0.5, 2)
    with pytest.raises(SystemExit) as stop:     # perception takes no focus: the flag is not its own
        main(["train", "perception", "--data", str(splits[0]), "--out", str(tmp_path / "p"),
              "--focus-group", "continuity"])
    assert stop.value.code == 2
    assert "unrecognized arguments: --focus-group continuity" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()


def test_the_name_resolves_and_scores_a_tiny_test_set(splits, tmp_path, tiny_recipe):
    run = tmp_path / "run"
    assert main(["train", "phydnet", "--data", str(splits[0]), "--out", str(run), "--quiet"]) == 0
    assert load_model(str(run / "phydnet")).name == "phydnet"
    out = tmp_path / "phydnet.csv"
    assert main(["score", "--model", str(run / "phydnet.pt"), "--data", str(splits[1]), "--out", str(out),
                 "--quiet"]) == 0
    rows = list(csv.DictReader(open(out)))
    assert tuple(rows[0]) == SCORE_COLUMNS and len(rows) == 22 and rows[0]["model"] == "phydnet"
    curves = np.load(out.with_suffix(".curves.npz"))
    assert curves["s_dyn"].shape == (22, 10) and "s_img" not in curves.files and np.all(curves["s_dyn"][:, 0] == 0)
    np.testing.assert_allclose([float(r["score"]) for r in rows], curves["s_dyn"].sum(1), rtol=1e-6)
    assert all(float(r["s_img"]) == 0 for r in rows)
    figure = tmp_path / "x.png"
    explain = ["explain", "--model", str(run / "phydnet.pt"), "--data", str(splits[1]), "--out", str(figure)]
    assert main(explain) == 2 and not figure.exists()      # no hidden object to draw


def test_pipeline_trains_and_scores_phydnet_without_perception(tmp_path, monkeypatch):
    base = RECIPES[DEFAULT_RECIPE]
    tiny = replace(base, phydnet=replace(TINY, image_size=base.perception.image_size),
                   phydnet_train=TrainConfig(**TRAIN), phases=())
    monkeypatch.setitem(RECIPES, DEFAULT_RECIPE, tiny)
    config = PipelineConfig(str(tmp_path / "run"), train_videos=4, pairs=1, models=("phydnet", "random"), workers=1,
                            progress=False)
    report = run_pipeline(config).read_text()
    assert "phydnet" in report and "| collision |" in report
    assert (tmp_path / "run" / "phydnet.pt").exists() and (tmp_path / "run" / "scores" / "phydnet.csv").exists()
    assert not (tmp_path / "run" / "perception.pt").exists()


def test_plot_predictions_draws_each_frame_as_predicted_from_the_ones_before(splits):
    import h5py
    import matplotlib.pyplot as plt


    torch.manual_seed(0)
    net = PhyDNet(TINY).eval()
    with h5py.File(splits[1]) as file:
        rgbd = file["rgbd"][3]
    predicted = predicted_frames(net, rgbd)
    assert predicted.shape == rgbd.shape and predicted.dtype == np.uint8 and np.all(predicted[0] == 255)
    np.testing.assert_array_equal(predicted[1:], to_uint8(net(normalise(torch.from_numpy(rgbd))[None])[0]).numpy())
    changed = rgbd.copy()
    changed[5:] = 0                                           # frames 0-4 alone make frames 1-5
    np.testing.assert_array_equal(predicted_frames(net, changed)[:6], predicted[:6])
    assert not np.array_equal(predicted_frames(net, changed)[6:], predicted[6:])
    figure = plot_predictions(net, splits[1], 3)
    surprise = net.surprise(normalise(torch.from_numpy(rgbd))[None])[0, 1:]
    assert figure.axes[0].get_title().endswith(": " + " ".join(f"{value:.0f}" for value in surprise.tolist()))
    plt.close(figure)
    with pytest.raises(XvoeError, match="index 99 is out of range"):
        plot_predictions(net, splits[1], 99)
