"""Surprise curves of a chosen pair (xvoe.plot_surprise_curves) and their helpers."""
import matplotlib
import numpy as np
import pytest

import xvoe
from xvoe.errors import XvoeError
from xvoe.scenes import custom, store, videos

matplotlib.use("Agg")


@pytest.fixture(scope="module")
def scored(test_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("scores") / "random.csv"
    return xvoe.score("random", str(test_file), str(out), progress=False).path


def test_the_curves_of_a_pair_are_drawn_and_written(scored, test_file, tmp_path):
    fig = xvoe.plot_surprise_curves(scored, test_file, "collision", "S3", 2, frame=5)
    out = tmp_path / "curves.png"
    fig.savefig(out)
    assert out.stat().st_size > 10_000
    axes = fig.axes      # the random agent's own curve, alone, on its own axis
    assert [ax.get_title().splitlines()[0] for ax in axes] == ["surprise"]
    assert axes[0].get_ylabel() == "surprise\n(surprise)"
    with np.load(scored.with_suffix(".curves.npz")) as curves, store.open_dataset(test_file) as file:
        first, second = xvoe.find_pair(file, "collision", "S3", 2)
        drawn = [line.get_ydata() for line in axes[0].get_lines() if len(line.get_ydata()) > 2]
        np.testing.assert_allclose(drawn[0], curves["surprise"][first])
        np.testing.assert_allclose(drawn[1], curves["surprise"][second])
        event = int(file["event_frame"][first])
    assert any(list(line.get_xdata()) == [event, event] and line.get_color() == "red" for line in axes[0].get_lines())
    xvoe.plot_surprise_curves(scored, None, "permanence", "S2", 0)       # the curves alone


def test_the_pair_plays_without_a_kernel_frame_by_frame(scored, test_file):
    """animate_pair: a frame of the player per video frame, with the cursor and the pictures
    moving with it; its HTML player holds every frame (no kernel needed)."""
    animation = xvoe.animate_pair(scored, test_file, "blocking", "S3", 1, display_size=64)
    with store.open_dataset(test_file) as file:
        frames = file["rgbd"].shape[1]
        first, _ = xvoe.find_pair(file, "blocking", "S3", 1)
        scene = xvoe.display_video(file, first, 64).rgbd[..., :3]
    drawn = animation._func(7)
    np.testing.assert_array_equal(drawn[0].get_array(), scene[7])
    assert list(drawn[2].get_xdata()) == [7, 7] and "frame 7" in drawn[-1].get_text()
    player = animation.to_jshtml()
    assert player.count("data:image/png;base64") == frames


def test_curves_with_the_perception_error_add_the_excess_panel(scored, test_file, tmp_path):
    with np.load(scored.with_suffix(".curves.npz")) as saved:
        s_img, s_dyn = saved["surprise"], 2 * saved["surprise"]
    s_rec = 0.5 * s_img
    np.savez(tmp_path / "rec.npz", s_img=s_img, s_dyn=s_dyn, s_rec=s_rec)
    fig = xvoe.plot_surprise_curves(scored, None, "collision", "S3", 2, curves=tmp_path / "rec.npz")
    assert [ax.get_title().splitlines()[0] for ax in fig.axes] == [
        "s_img, image error", "s_dyn, motion error", "s_img + s_dyn, the score", "excess: s_img - s_rec + s_dyn"]
    assert fig.axes[0].get_ylabel() == "surprise\n(squared pixel error)"
    with store.open_dataset(test_file) as file:
        first, _ = xvoe.find_pair(file, "collision", "S3", 2)
    drawn = [line.get_ydata() for line in fig.axes[3].get_lines() if len(line.get_ydata()) > 2]
    np.testing.assert_allclose(drawn[0], s_img[first] - s_rec[first] + s_dyn[first])


def test_the_two_definitions_are_drawn_side_by_side_each_on_its_own_axis(scored, test_file, tmp_path):
    """The MSE's per-frame surprise and the NLL's, each with its unit and the event frame."""
    with np.load(scored.with_suffix(".curves.npz")) as saved:     # the MSE's terms made of the agent's curve
        s_img, s_dyn = 0.5 * saved["surprise"], saved["surprise"] ** 2
    nll = 100 + 10 * s_dyn[:, ::-1]
    np.savez(tmp_path / "nll.npz", s_img=s_img, s_dyn=s_dyn, nll=nll)
    fig = xvoe.plot_surprise_definitions(scored, test_file, "collision", "S3", 2, curves=tmp_path / "nll.npz")
    assert [(ax.get_title().splitlines()[0], ax.get_ylabel()) for ax in fig.axes] == [
        ("MSE: s_img + s_dyn", "squared pixel error"), ("NLL: -log p(x_t | x_<t)", "nats")]
    with store.open_dataset(test_file) as file:
        first, second = xvoe.find_pair(file, "collision", "S3", 2)
        event = int(file["event_frame"][second])
    for ax, expected in zip(fig.axes, (s_img + s_dyn, nll)):
        drawn = [line.get_ydata() for line in ax.get_lines() if len(line.get_ydata()) > 2]
        np.testing.assert_allclose(drawn, expected[[first, second]])
        assert any(list(line.get_xdata()) == [event, event] and line.get_color() == "red" for line in ax.get_lines())
    with pytest.raises(XvoeError, match="holds no NLL curve"):
        xvoe.plot_surprise_definitions(scored, test_file, "collision", "S3", 2)


def test_wall_timetables_read_back_from_the_states(test_file):
    with store.open_dataset(test_file) as file:
        s1 = videos.wall_lowered(file, xvoe.find_pair(file, "blocking", "S1", 0)[0])
        s2 = videos.wall_lowered(file, xvoe.find_pair(file, "blocking", "S2", 0)[1])
        s3 = videos.wall_lowered(file, xvoe.find_pair(file, "continuity", "S3", 0)[0])
    standing = np.arange(3, 12)
    assert list(np.flatnonzero(s1 == 1)) == list(standing) and s1[0] == 0 and s1[-1] == 0 and 0 < s1[2] < 1
    assert (s2 == 1).all()
    assert list(np.flatnonzero(s3 == 1)) == list(range(12)) and s3[-1] == 0


@pytest.mark.parametrize("scenario, setting, pair, message", [
    ("collision", "S3", 99, "no pair 99 of collision S3; its pairs are 0..7"),
    ("permanence", "S3", 0, "no setting 'S3' of permanence; it holds S1, S2"),
    ("falling", "S1", 0, "no scenario 'falling'"),
])
def test_a_bad_pair_gets_a_clear_error(scored, test_file, scenario, setting, pair, message):
    with pytest.raises(XvoeError, match=message):
        xvoe.plot_surprise_curves(scored, test_file, scenario, setting, pair)


def test_scores_without_curves_or_from_other_data_are_refused(scored, test_file, tmp_path):
    lonely = tmp_path / "lonely.csv"
    lonely.write_text(scored.read_text())
    with pytest.raises(XvoeError, match="writes the curves beside"):
        xvoe.plot_surprise_curves(lonely, test_file, "collision", "S1", 0)
    with pytest.raises(XvoeError, match="frame 15 is out of range"):
        xvoe.plot_surprise_curves(scored, test_file, "collision", "S1", 0, frame=15)
    other = custom.make_pair([custom.ball(4, vx=50), custom.ball(34)], custom.pass_through(0, 1))
    mine = other.save(tmp_path / "mine.h5", size=32)
    with pytest.raises(XvoeError, match="scored on another split"):
        xvoe.plot_surprise_curves(scored, mine, "collision", "S1", 0)
