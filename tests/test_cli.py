"""The command line: generate and show, and one-line errors with exit code 2."""
import subprocess
import sys

import numpy as np
import pytest

import xvoe
from xvoe.cli import main


def run_cli(*args):
    """Run `python -m xvoe` as a user would; returns (code, stdout, stderr)."""
    done = subprocess.run([sys.executable, "-m", "xvoe", *args], capture_output=True, text=True)
    return done.returncode, done.stdout, done.stderr


def test_generate_then_show(tmp_path):
    out = tmp_path / "t.h5"
    code, stdout, _ = run_cli("generate", "--split", "test", "--pairs", "1", "--out", str(out), "--quiet")
    assert code == 0 and stdout.strip() == str(out)
    png, gif = tmp_path / "sheet.png", tmp_path / "anim.gif"
    assert main(["show", str(out), "--index", "3", "--out", str(png)]) == 0
    assert main(["show", str(out), "--index", "3", "--out", str(gif)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert gif.read_bytes()[:6] == b"GIF89a"


@pytest.mark.parametrize("args,needle", [
    (["generate", "--split", "test", "--size", "abc", "--out", "x.h5"], "--size"),
    (["generate", "--split", "val", "--out", "x.h5"], "invalid choice"),
    (["generate", "--split", "test", "--shard", "1of2", "--out", "x.h5"], "I/N"),
    (["generate", "--out", "x.h5"], "--split is required"),
    (["generate", "--split", "test", "--pairs", "0", "--out", "x.h5"], ">= 1"),
    (["generate", "--split", "test", "--frames", "3", "--out", "x.h5"], "frames"),
    (["show", "missing.h5"], "no such file"),
])
def test_bad_input_gives_one_line_and_exit_2(tmp_path, args, needle):
    args = [str(tmp_path / a) if a.endswith(".h5") else a for a in args]
    code, stdout, stderr = run_cli(*args)
    assert code == 2
    assert len(stderr.strip().splitlines()) == 1 and needle in stderr
    assert not (tmp_path / "x.h5").exists()


def test_show_errors(tmp_path, capsys):
    out = tmp_path / "t.h5"
    assert main(["generate", "--split", "train", "--videos", "2", "--out", str(out), "--quiet"]) == 0
    assert main(["show", str(out), "--index", "5"]) == 2
    assert "out of range" in capsys.readouterr().err
    assert main(["show", str(out), "--out", str(tmp_path / "fig.jpg")]) == 2
    assert ".png, .gif or .mp4" in capsys.readouterr().err
    assert not (tmp_path / "fig.jpg").exists()


def test_existing_output_needs_overwrite(tmp_path, capsys):
    out = tmp_path / "t.h5"
    args = ["generate", "--split", "train", "--videos", "2", "--out", str(out), "--quiet"]
    assert main(args) == 0
    before = out.read_bytes()
    assert main(args + ["--seed", "9"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert out.read_bytes() == before
    assert main(args + ["--seed", "9", "--overwrite"]) == 0
    assert out.read_bytes() != before


@pytest.mark.parametrize("verb", ["generate", "list", "show", "train", "score", "metrics", "pipeline", "explain"])
def test_every_verb_has_help(verb, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([verb, "--help"])
    assert exit_.value.code == 0
    assert "usage: xvoe " + verb in capsys.readouterr().out


def test_list_names_the_videos_a_filter_picks_as_find_pair_does(test_file, test_data, capsys):
    assert main(["list", str(test_file), "--scenario", "blocking", "--setting", "S2", "--pair", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["index", "scenario", "setting", "pair", "member"]
    with xvoe.open_dataset(test_file) as file:
        assert [int(line.split()[0]) for line in lines[1:]] == list(xvoe.find_pair(file, "blocking", "S2", 3))
        impossible = xvoe.list_videos(file, setting="S3", member=1)
    assert len(impossible) == 3 * 8     # a pair of every S3 scenario (permanence has none)
    assert all(not row["possible"] and test_data["setting"][row["index"]] == "S3" for row in impossible)
    assert main(["list", str(test_file), "--setting", "S3", "--member", "1", "--quiet"]) == 0
    assert capsys.readouterr().out.split() == [str(row["index"]) for row in impossible]


def test_show_writes_an_mp4_with_the_surprise_curves(test_file, tmp_path, capsys):
    scores = tmp_path / "random.csv"
    assert main(["score", "--model", "random", "--data", str(test_file), "--out", str(scores), "--quiet"]) == 0
    for name, extra in (("plain.mp4", []), ("curves.mp4", ["--scores", str(scores)])):
        out = tmp_path / name
        assert main(["show", str(test_file), "--index", "5", "--out", str(out), *extra]) == 0
        assert out.read_bytes()[4:8] == b"ftyp"         # an MP4 container
    assert main(["show", str(test_file), "--out", str(tmp_path / "a.png"), "--scores", str(scores)]) == 2
    assert "give --out NAME.mp4" in capsys.readouterr().err
    own = np.load(scores.with_suffix(".curves.npz"))["surprise"]     # as a score file with the NLL's curve
    np.savez(scores.with_suffix(".curves.npz"), s_img=0 * own, s_dyn=own, nll=own + 1.0)
    assert main(["show", str(test_file), "--index", "5", "--out", str(tmp_path / "both.mp4"),
                 "--scores", str(scores)]) == 0
    assert (tmp_path / "both.mp4").read_bytes()[4:8] == b"ftyp"
