"""Bring your own model: anything with a name and a per-frame `surprise(videos)` scores and is
measured like the shipped models, from a module or a file."""
import csv
from pathlib import Path

import numpy as np
import pytest

import xvoe
from xvoe.cli import main

EXAMPLES = Path(__file__).resolve().parent.parent / "xvoe" / "examples"


@pytest.mark.parametrize("reference, curve", [("frame_change.py:FrameChange", "frame_change"),
                                              ("object_tracker.py:ObjectTracker", "events")])
def test_an_example_model_goes_from_score_to_the_paper_metrics(reference, curve, test_file, tmp_path):
    scores = tmp_path / "scores.csv"
    assert main(["score", "--model", str(EXAMPLES / reference), "--data", str(test_file), "--out", str(scores),
                 "--quiet"]) == 0
    rows = list(csv.DictReader(open(scores)))
    assert len(rows) == 176 and list(rows[0])[-1] == "score" and "s_dyn" not in rows[0]    # 8 pairs of 11 settings
    curves = np.load(scores.with_suffix(".curves.npz"))      # its own curve, under its own name
    assert sorted(curves.files) == sorted(["header", curve])
    np.testing.assert_allclose([float(r["score"]) for r in rows], curves[curve].sum(1), rtol=1e-9)
    assert main(["metrics", str(scores), "--out", str(tmp_path / "report"), "--rounds", "10"]) == 0
    metrics = list(csv.DictReader(open(tmp_path / "report" / "metrics.csv")))
    assert {r["column"] for r in metrics} == {"score"}       # its own score, once: no MSE terms it has not
    assert (tmp_path / "report" / "comparative.png").exists()


def test_the_object_tracker_misses_a_cube_that_is_gone_when_the_wall_lifts(test_file, tmp_path):
    scores = tmp_path / "t.csv"
    main(["score", "--model", str(EXAMPLES / "object_tracker.py:ObjectTracker"), "--data", str(test_file),
          "--out", str(scores), "--quiet"])
    rows = [r for r in csv.DictReader(open(scores)) if (r["scenario"], r["setting"]) == ("permanence", "S1")]
    by_pair = {}
    for r in rows:
        by_pair.setdefault(r["pair"], {})[r["member"]] = float(r["score"])
    assert all(pair["1"] > pair["0"] for pair in by_pair.values())


def write_module(folder: Path, text: str, name: str = "my_models") -> None:
    """A module of the user's; each test names its own, as Python keeps one imported by name."""
    (folder / f"{name}.py").write_text(text)


def test_a_module_factory_loads_and_bad_models_get_one_line(test_file, tmp_path, monkeypatch, capsys):
    write_module(tmp_path, (
        "import numpy as np\n"
        "class Still:\n"
        "    name = 'still'\n"
        "    image_size = 64\n"
        "    def surprise(self, videos):\n"
        "        return videos.rgbd.mean(axis=(2, 3, 4))\n"
        "def make():\n"
        "    return Still()\n"
        "class Wrong:\n"
        "    name = 'wrong'\n"
        "    def surprise(self, videos):\n"
        "        return np.zeros(3)\n"
        "class Small(Still):\n"
        "    image_size = 32\n"
        "nothing = 3\n"))
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "s.csv"
    assert main(["score", "--model", "my_models:make", "--data", str(test_file), "--out", str(out), "--quiet"]) == 0
    assert {r["model"] for r in csv.DictReader(open(out))} == {"still"}
    for reference, needle in [("my_models:Wrong", "shape (3,)"), ("my_models:nothing", "not a surprise model"),
                              ("my_models:absent", "has no 'absent'"), ("no_such_module:x", "cannot import"),
                              ("my_models:Small", "works at 32x32"), ("missing.py:x", "no such file")]:
        code = main(["score", "--model", reference, "--data", str(test_file), "--out", str(tmp_path / "x.csv"),
                     "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and len(err.strip().splitlines()) == 1 and needle in err, (reference, err)
        assert not (tmp_path / "x.csv").exists()


def test_scoring_in_shards_merges_to_the_bytes_of_one_run(test_file, tmp_path, capsys):
    model = str(EXAMPLES / "frame_change.py:FrameChange")
    parts = []
    for index in (2, 0, 1):      # merged in any order
        part = tmp_path / f"part{index}.csv"
        assert main(["score", "--model", model, "--data", str(test_file), "--shard", f"{index}/3", "--batch", "8",
                     "--out", str(part), "--quiet"]) == 0
        parts.append(str(part))
    assert main(["score", "--merge", *parts, "--out", str(tmp_path / "merged.csv")]) == 0
    assert main(["score", "--model", model, "--data", str(test_file), "--batch", "8", "--out",
                 str(tmp_path / "whole.csv"), "--quiet"]) == 0
    for suffix in (".csv", ".curves.npz"):
        assert (tmp_path / f"merged{suffix}").read_bytes() == (tmp_path / f"whole{suffix}").read_bytes()
    capsys.readouterr()
    assert main(["score", "--merge", parts[0], parts[2], "--out", str(tmp_path / "gap.csv")]) == 2
    assert "do not follow each other" in capsys.readouterr().err


def test_scoring_in_worker_processes_writes_the_bytes_of_one_run(test_file, tmp_path, capsys):
    model = str(EXAMPLES / "frame_change.py:FrameChange")
    for name, extra in (("whole", []), ("workers", ["--workers", "2"])):
        assert main(["score", "--model", model, "--data", str(test_file), "--batch", "8", "--out",
                     str(tmp_path / f"{name}.csv"), "--quiet", *extra]) == 0
    for suffix in (".csv", ".curves.npz"):
        assert (tmp_path / f"workers{suffix}").read_bytes() == (tmp_path / f"whole{suffix}").read_bytes()
    assert sorted(path.name for path in tmp_path.iterdir()) == [
        "whole.csv", "whole.curves.npz", "workers.csv", "workers.curves.npz"]     # no parts left behind
    capsys.readouterr()
    assert main(["score", "--model", model, "--data", str(test_file), "--out", str(tmp_path / "workers.csv"),
                 "--workers", "2", "--quiet"]) == 2
    assert "exists" in capsys.readouterr().err


def test_the_split_as_a_pytorch_dataset_reads_the_same_in_loader_workers(test_file):
    import torch
    from torch.utils.data import DataLoader

    import xvoe
    from xvoe.scenes import store

    dataset = xvoe.SplitDataset(test_file)
    assert len(dataset) == 176 and dataset[-1]["index"] == 175
    with pytest.raises(IndexError):
        dataset[176]
    seen = {}
    for batch in DataLoader(dataset, batch_size=16, num_workers=2):
        for row, index in enumerate(batch["index"].tolist()):
            seen[index] = (batch["rgbd"][row], batch["scenario"][row], bool(batch["possible"][row]))
    assert sorted(seen) == list(range(176))
    with store.open_dataset(test_file) as file:
        for index in (0, 57, 175):
            rgbd, scenario, possible = seen[index]
            assert torch.equal(rgbd, torch.from_numpy(file["rgbd"][index]))
            assert scenario == file["scenario"].asstr()[index] and possible == bool(file["possible"][index])


def test_a_model_of_your_own_may_draw_its_explanation(test_file, tmp_path, monkeypatch, capsys):
    write_module(tmp_path, (
        "import numpy as np\n"
        "class Painter:\n"
        "    name = 'painter'\n"
        "    def surprise(self, videos):\n"
        "        return np.zeros((len(videos.rgbd), videos.frames))\n"
        "    def explain(self, videos):\n"
        "        return 255 - videos.rgbd\n"
        "class Mute:\n"
        "    name = 'mute'\n"
        "    def surprise(self, videos):\n"
        "        return np.zeros((len(videos.rgbd), videos.frames))\n"), name="my_painters")
    monkeypatch.syspath_prepend(str(tmp_path))
    import xvoe

    drawn = xvoe.explain("my_painters:Painter", test_file, 3)
    assert [label for label, _ in drawn.rows()] == ["observed", "the model's\nexplanation"]
    assert (drawn.behind_wall == 255 - drawn.observed).all()
    assert main(["explain", "--model", "my_painters:Painter", "--data", str(test_file), "--index", "3",
                 "--out", str(tmp_path / "p.png")]) == 0
    assert main(["explain", "--model", "my_painters:Mute", "--data", str(test_file), "--out",
                 str(tmp_path / "m.png")]) == 2
    assert "no explanation to draw" in capsys.readouterr().err


class _Mine:
    """A model made in a script: a name and a surprise, none of the optional attributes."""

    name = "mine"

    def surprise(self, videos):
        return np.stack([np.random.default_rng(int(i)).random(videos.frames) for i in videos.index])


def test_a_model_object_from_python_scores_into_a_table_that_keeps_its_path(test_file, tmp_path):
    table = xvoe.score(_Mine(), data=test_file, out=tmp_path / "mine.csv", progress=False)
    assert table.path == tmp_path / "mine.csv" and Path(table) == table.path and table.path.is_file()
    rows = table.rows
    assert len(rows) == 176 and rows[3]["index"] == 3 and rows[0]["model"] == "mine"
    assert set(rows[0]) == {"index", "model", "scenario", "setting", "pair", "member", "possible", "score"}
    np.testing.assert_allclose(table.columns["score"], xvoe.read_scores(table)["score"])
    nameless = _Mine()
    nameless.name = "two\nlines"
    with pytest.raises(xvoe.XvoeError, match="control character"):
        xvoe.score(nameless, data=test_file, out=tmp_path / "n.csv", progress=False)
    assert not (tmp_path / "n.csv").exists()
