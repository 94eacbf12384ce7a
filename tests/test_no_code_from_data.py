"""Files from elsewhere are data: a payload planted in any kind of file xvoe reads never runs.

Each payload, when unpickled or imported, creates a marker file; every case checks that the
command refuses in one line (or reads the data it needs and ignores the rest) and that the
marker never appears.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

import xvoe
from xvoe.cli import main
from xvoe.training.checkpoints import WEIGHTS, load_checkpoint, shipped_path


class Payload:
    """Unpickled, it opens (creates) the marker file: the smallest code a pickle can run."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


@pytest.fixture(scope="module")
def split(tmp_path_factory):
    path = tmp_path_factory.mktemp("split") / "t.h5"
    return xvoe.generate(xvoe.GenerateConfig("test", pairs=1, size=32, seed=11), path, progress=False)


@pytest.fixture
def marker(tmp_path):
    found = tmp_path / "payload-ran"
    yield found
    assert not found.exists(), "a payload planted in a file ran"


def shipped_run(folder: Path) -> Path:
    """The shipped xpl as a run directory: perception.pt, xpl.pt, proposal.pt, phydnet.pt."""
    folder.mkdir()
    for stage in ("perception", "xpl", "proposal"):
        shutil.copy(shipped_path("xpl", stage), folder / f"{stage}.pt")
    shutil.copy(shipped_path("phydnet"), folder / "phydnet.pt")
    return folder


def plant(checkpoint: Path, payload: Payload, where: str) -> None:
    """Rewrite a checkpoint with the payload in it: beside its data, inside its config, or as the whole file."""
    state = torch.load(checkpoint, weights_only=True)
    if where == "whole":
        state = payload
    elif where == "config":
        state["config"] = {**state["config"], "extra": payload}
    else:
        state["meta"] = payload
    torch.save(state, checkpoint)


@pytest.mark.parametrize("stage", ["perception", "xpl", "proposal", "phydnet"])
@pytest.mark.parametrize("where", ["whole", "config", "meta"])
def test_a_checkpoint_with_a_pickled_payload_is_refused_and_never_run(stage, where, split, tmp_path, marker, capsys):
    run = shipped_run(tmp_path / "run")
    plant(run / f"{stage}.pt", Payload(marker), where)
    model = str(run / "phydnet.pt") if stage == "phydnet" else str(run)
    commands = [["score", "--model", model, "--data", str(split), "--out", str(tmp_path / "s.csv")],
                ["ship", str(run), "--out", str(tmp_path / "weights")]]
    for command in commands:
        assert main(command) == 2
        error = capsys.readouterr().err.strip()
        assert "holds objects other than tensors and plain data" in error and "\n" not in error
    assert not (tmp_path / "s.csv").exists() and not (tmp_path / "weights").exists()


def test_resuming_a_run_whose_checkpoint_holds_a_payload_is_refused(tmp_path, marker, capsys):
    data = xvoe.generate(xvoe.GenerateConfig("train", videos=4, size=16, seed=1), tmp_path / "train.h5",
                         progress=False)
    run = tmp_path / "run"
    tiny = ["--set", "model.image_size=16", "--set", "model.broadcast_size=4", "--set", "model.latent_dim=4",
            "--set", "model.cnn_channels=8,8", "--set", "model.cnn_hidden=16", "--set", "model.decoder_channels=8",
            "--set", "airborne_share=0"]
    train = ["train", "perception", "--data", str(data), "--out", str(run), "--batch-size", "8", "--quiet"]
    assert main([*train, "--steps", "2", *tiny]) == 0
    plant(run / "perception.pt", Payload(marker), "meta")
    assert main([*train, "--steps", "4", "--resume"]) == 2
    assert "holds objects other than tensors" in capsys.readouterr().err


def test_every_shipped_checkpoint_loads_as_plain_data():
    shipped = sorted(WEIGHTS.glob("*.pt"))
    assert [path.stem for path in shipped] == ["perception", "phydnet", "plato", "proposal", "xpl-noresidual", "xpl"]
    for path in shipped:
        assert load_checkpoint(path, path.stem)["stage"] == path.stem


def test_a_score_header_naming_code_never_runs_it(split, tmp_path, marker, capsys):
    """A header is edited to name a model of one's own whose file would create the marker on import:
    verify refuses without running it; metrics reads the scores and never imports it."""
    scores = xvoe.score("random", split, tmp_path / "r.csv", progress=False)
    planted = tmp_path / "planted.py"
    planted.write_text(f"open({str(marker)!r}, 'w')\nclass Model:\n    name = 'planted'\n"
                       "    def surprise(self, videos):\n        return videos.rgbd[..., 0, 0, 0] * 0\n")
    curves = scores.path.with_suffix(".curves.npz")
    with np.load(curves) as found:
        arrays = {name: found[name] for name in found.files}
    header = json.loads(str(arrays["header"]))
    header["model_identity"] = {"source": f"{planted}:Model", "module": "planted:Model", "file_hash": "0"}
    arrays["header"] = np.array(json.dumps(header))
    np.savez(curves, **arrays)
    assert main(["verify", str(scores)]) == 2
    error = capsys.readouterr().err.strip()
    assert "verify runs no code a file names: pass --model" in error and "\n" not in error
    assert main(["metrics", str(scores), "--data", str(split), "--out", str(tmp_path / "report"), "--rounds", "5"]) == 0


def test_a_curves_file_holding_a_pickled_object_is_refused_and_never_run(split, tmp_path, marker, capsys):
    scores = xvoe.score("xpl", split, tmp_path / "x.csv", progress=False)
    curves = scores.path.with_suffix(".curves.npz")
    with np.load(curves) as found:
        arrays = {name: found[name] for name in found.files}
    for name in set(arrays) - {"header"}:
        arrays[name] = np.array([Payload(marker)] * len(arrays[name]), dtype=object)
    np.savez(curves, **arrays)
    for command in (["verify", str(scores)],
                    ["metrics", str(scores), "--data", str(split), "--out", str(tmp_path / "report")],
                    ["show", str(split), "--index", "0", "--scores", str(scores), "--out", str(tmp_path / "p.mp4")]):
        assert main(command) == 2, command
        assert "\n" not in capsys.readouterr().err.strip()


def test_a_split_holding_pickled_bytes_is_read_as_data(split, tmp_path, marker):
    """HDF5 holds no code; bytes that would run if unpickled stay bytes."""
    import pickle

    copy = tmp_path / "t.h5"
    shutil.copy(split, copy)
    with h5py.File(copy, "r+") as file:
        file.attrs["extra"] = np.void(pickle.dumps(Payload(marker)))
        file.create_dataset("extra", data=np.frombuffer(pickle.dumps(Payload(marker)), dtype=np.uint8))
    assert main(["score", "--model", "random", "--data", str(copy), "--out", str(tmp_path / "s.csv")]) == 0
    assert main(["show", str(copy), "--index", "0", "--out", str(tmp_path / "p.png")]) == 0
