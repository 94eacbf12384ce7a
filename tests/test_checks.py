"""The harness that catches a broken model of your own before its scores are written: each
check catches a model planted to fail it, a well-behaved one passes, --no-checks lets one through."""
import csv
from pathlib import Path

import matplotlib
import numpy as np
import pytest

import xvoe
from xvoe.cli import main

matplotlib.use("Agg")
EXAMPLES = Path(__file__).resolve().parent.parent / "xvoe" / "examples"

PLANTED = '''
import numpy as np


def change(videos):
    """A well-behaved surprise: each frame's mean squared change from the one before."""
    frames = videos.rgbd.astype(np.float64) / 255.0
    out = np.zeros(frames.shape[:2])
    out[:, 1:] = ((frames[:, 1:] - frames[:, :-1]) ** 2).mean(axis=(2, 3, 4))
    return out


class Good:
    name = "good"
    curve, curve_label = "change", "mean squared change"

    def surprise(self, videos):
        # a batch rounds a little differently from a single video: within the float tolerance
        return change(videos) * (1 + 1e-7 * len(videos.rgbd))


class OrderDependent:
    name = "order-dependent"

    def surprise(self, videos):
        return change(videos) + np.arange(len(videos.rgbd))[:, None]      # the place in the batch leaks in


class BatchDependent:
    name = "batch-dependent"

    def surprise(self, videos):
        found = change(videos)
        return found / found.mean()         # normalised over the batch, not the video


class Constant:
    name = "constant"

    def surprise(self, videos):
        return np.ones((len(videos.rgbd), videos.frames))


class NaNForSome:
    name = "nan-for-some"

    def surprise(self, videos):
        found = change(videos)
        found[videos.index % 5 == 3] = np.nan
        return found


class NonDeterministic:
    name = "non-deterministic"

    def surprise(self, videos):
        return change(videos) + np.random.default_rng().random((len(videos.rgbd), videos.frames))


class BadCurve(Good):
    curve = "my/curve"
'''


@pytest.fixture
def planted(tmp_path) -> Path:
    path = tmp_path / "planted.py"
    path.write_text(PLANTED)
    return path


def score(planted: Path, name: str, test_file, out: Path, *extra: str) -> int:
    return main(["score", "--model", f"{planted}:{name}", "--data", str(test_file), "--out", str(out), "--quiet",
                 *extra])


@pytest.mark.parametrize("name, check", [("OrderDependent", "order"), ("BatchDependent", "batch size"),
                                         ("Constant", "spread"), ("NaNForSome", "finite"),
                                         ("NonDeterministic", "repeat")])
def test_each_check_catches_its_planted_model_and_writes_nothing(planted, name, check, test_file, tmp_path, capsys):
    code = score(planted, name, test_file, tmp_path / "s.csv")
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"failed the check {check!r}" in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["planted.py"]


@pytest.mark.parametrize("name", ["OrderDependent", "BatchDependent", "Constant", "NonDeterministic"])
def test_no_checks_lets_the_planted_model_through(planted, name, test_file, tmp_path):
    assert score(planted, name, test_file, tmp_path / "s.csv", "--no-checks") == 0
    assert len(list(csv.DictReader(open(tmp_path / "s.csv")))) == 176


def test_a_score_that_is_not_a_number_is_refused_even_without_the_checks(planted, test_file, tmp_path, capsys):
    assert score(planted, "NaNForSome", test_file, tmp_path / "s.csv", "--no-checks") == 2
    assert "failed the check 'finite'" in capsys.readouterr().err
    assert not (tmp_path / "s.csv").exists()


def test_a_well_behaved_model_passes(planted, test_file, tmp_path):
    assert score(planted, "Good", test_file, tmp_path / "good.csv") == 0
    assert xvoe.score("random", test_file, tmp_path / "random.csv", progress=False).path.exists()   # the baselines too


def test_a_model_s_own_curve_is_stored_and_drawn_under_its_own_name(test_file, tmp_path):
    out = xvoe.score(xvoe.load_model(f"{EXAMPLES / 'frame_change.py'}:FrameChange"), test_file,
                     tmp_path / "change.csv", progress=False)
    with np.load(out.path.with_suffix(".curves.npz")) as saved:
        assert sorted(saved.files) == ["frame_change", "header"]
        per_frame = saved["frame_change"]
    assert xvoe.score_header(out)["curve_label"] == "summed squared change of the frame"
    np.testing.assert_allclose(xvoe.read_scores(out)["score"], per_frame.sum(1), rtol=1e-9)
    fig = xvoe.plot_surprise_curves(out, test_file, "collision", "S1", 0)
    assert [ax.get_title().splitlines()[0] for ax in fig.axes] == ["frame_change"]
    assert fig.axes[0].get_ylabel() == "surprise\n(summed squared change of the frame)"
    assert main(["show", str(test_file), "--index", "0", "--scores", str(out), "--out",
                 str(tmp_path / "pair.mp4")]) == 0
    assert main(["metrics", str(out), "--data", str(test_file), "--out", str(tmp_path / "report"),
                 "--rounds", "10"]) == 0
    assert (tmp_path / "report" / "onset.png").exists()      # the onset reads the model's own curve


def test_a_curve_name_that_cannot_be_stored_gets_one_line(planted, test_file, tmp_path, capsys):
    assert score(planted, "BadCurve", test_file, tmp_path / "s.csv") == 2
    assert "curve must be a name" in capsys.readouterr().err
