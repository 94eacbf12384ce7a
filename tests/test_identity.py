"""Self-describing score files: the identities of splits and models, the header that records
them, the refusal of another split's scores, and `xvoe verify`."""
from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

import xvoe
from xvoe.cli import main
from xvoe.errors import XvoeError
from xvoe.evaluation.score_headers import new_header, scored_nll
from xvoe.fingerprints import _sampled_videos, arrays_hash, split_identity
from xvoe.models.config import to_dict
from xvoe.models.nll import InferenceConfig
from xvoe.scenes import store
from xvoe.training.checkpoints import shipped_path

EXAMPLES = Path(__file__).resolve().parent.parent / "xvoe" / "examples"


def identity_of(path: Path) -> dict:
    with store.open_dataset(path) as file:
        return split_identity(file)


def changed_copy(source: Path, target: Path, change) -> Path:
    shutil.copy(source, target)
    with h5py.File(target, "r+") as file:
        change(file)
    return target


def _flip_pixel(file) -> None:
    file["rgbd"][0, 3, 5, 7, 0] = file["rgbd"][0, 3, 5, 7, 0] ^ 1


def _flip_label(file) -> None:
    file["event_frame"][5] = 2 if file["event_frame"][5] != 2 else 3      # still a valid split


def _nudge_state(file) -> None:
    file["states"][9, 2, 1, 0] += 1e-3


def test_a_split_has_one_identity_wherever_it_lies_and_however_it_was_written(test_file, tmp_path):
    copy = tmp_path / "elsewhere.h5"
    shutil.copy(test_file, copy)
    assert identity_of(copy) == identity_of(test_file)
    shards = [xvoe.generate(xvoe.GenerateConfig("test", pairs=8, size=64, seed=3), tmp_path / f"part{i}.h5",
                            shard=(i, 2), progress=False) for i in range(2)]
    merged = xvoe.merge(shards, tmp_path / "merged.h5", progress=False)
    assert identity_of(merged) == identity_of(test_file)
    found = identity_of(test_file)
    assert (found["seed"], found["videos"]) == (3, 176) and len(found["content_hash"]) == 16


@pytest.mark.parametrize("change", [_flip_pixel, _flip_label, _nudge_state])
def test_one_pixel_label_or_state_changed_is_another_split(test_file, tmp_path, change):
    changed = changed_copy(test_file, tmp_path / "changed.h5", change)
    assert identity_of(changed)["content_hash"] != identity_of(test_file)["content_hash"]
    assert identity_of(changed)["config_hash"] == identity_of(test_file)["config_hash"]


def test_the_sample_of_frames_holds_the_first_and_last_video():
    assert list(_sampled_videos(5)) == [0, 1, 2, 3, 4]
    rows = _sampled_videos(22_000)
    assert len(rows) == 64 and rows[0] == 0 and rows[-1] == 21_999
    assert len(_sampled_videos(0)) == 0


def test_arrays_hash_follows_names_values_types_and_settings():
    weights = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.ones(2)}
    assert arrays_hash(weights, {"x": 1}) == arrays_hash(dict(reversed(weights.items())), {"x": 1})
    others = [{"a": weights["a"] + 1e-6, "b": weights["b"]}, {"a": weights["a"].astype(np.float64), "b": weights["b"]},
              {"a": weights["a"].reshape(3, 2), "b": weights["b"]}, {"c": weights["a"], "b": weights["b"]}]
    hashes = {arrays_hash(other, {"x": 1}) for other in others} | {arrays_hash(weights, {"x": 2})}
    assert arrays_hash(weights, {"x": 1}) not in hashes and len(hashes) == 5


def test_a_checkpoint_hashes_alike_in_any_directory_and_the_next_model_does_not(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for stage in ("xpl", "perception", "proposal"):        # the proposal stage's Transformer 2 is part of xpl
        shutil.copy(shipped_path("xpl", stage), run / f"{stage}.pt")
    shipped, moved = xvoe.model_identity(xvoe.load_model("xpl")), xvoe.model_identity(xvoe.load_model(str(run)))
    assert shipped["checkpoint_hash"] == moved["checkpoint_hash"] and moved["source"] == str(run.resolve())
    assert xvoe.model_identity(xvoe.load_model("plato"))["checkpoint_hash"] != shipped["checkpoint_hash"]


def test_a_score_header_says_which_model_settings_the_command_line_changed_from_the_recipe(tmp_path):
    """Each checkpoint's settings are its recipe's but where `--set` changed them when it was
    trained: the header names the recipe and those (`model_settings`), beside the NLL's sources."""
    run = tmp_path / "run"
    run.mkdir()
    for stage in ("xpl", "perception", "proposal"):
        shutil.copy(shipped_path("xpl", stage), run / f"{stage}.pt")
    state = torch.load(run / "xpl.pt", map_location="cpu", weights_only=True)
    state["train"]["lr"] *= 2       # as `xvoe train xpl --set lr=...` would have stored it
    torch.save(state, run / "xpl.pt")
    scorer = xvoe.load_model(str(run))
    header = new_header(scorer, {}, tmp_path / "t.h5", "score", "sum")
    recipe = state["config"]["recipe"]
    assert header["model_settings"]["perception"] == {"recipe": recipe, "changed from the recipe": []}
    changed = header["model_settings"]["xpl"]["changed from the recipe"]
    assert len(changed) == 1 and changed[0].startswith(f"train.lr: {state['train']['lr']!r} != ")
    assert "model_settings" not in new_header(xvoe.load_model("random"), {}, tmp_path / "t.h5", "score", "sum")


def test_a_model_of_your_own_is_named_by_module_and_file_hash(tmp_path):
    source = tmp_path / "mine.py"
    source.write_text((EXAMPLES / "frame_change.py").read_text())
    first = xvoe.model_identity(xvoe.load_model(f"{source}:FrameChange"))
    assert first["module"] == "mine:FrameChange" and first["source"] == f"{source.resolve()}:FrameChange"
    source.write_text(source.read_text() + "\n# edited\n")
    assert xvoe.model_identity(xvoe.load_model(f"{source}:FrameChange"))["file_hash"] != first["file_hash"]


def test_a_score_file_records_the_model_the_split_and_the_surprise(test_file, tmp_path):
    out = xvoe.score("random", test_file, tmp_path / "r.csv", progress=False)
    header = xvoe.score_header(out)
    assert header["split"] == identity_of(test_file) and header["data"] == str(Path(test_file).resolve())
    assert header["model_identity"] == {"source": "random", "seed": 0}
    assert header["xvoe"] and header["surprise"] == {"own": "the model's per-frame surprise, sum over frames"}


@pytest.fixture(scope="module")
def other_split(tmp_path_factory):
    """A split of the test split's size and labels from another seed (smaller frames, for speed)."""
    path = tmp_path_factory.mktemp("other") / "other.h5"
    return xvoe.generate(xvoe.GenerateConfig("test", pairs=8, size=16, seed=4), path, progress=False)


def test_a_report_repeats_each_score_files_header(test_file, tmp_path):
    scores = xvoe.score("random", test_file, tmp_path / "r.csv", progress=False)
    xvoe.report([scores], tmp_path / "report", rounds=5, data=test_file)
    (entry,) = json.loads((tmp_path / "report" / "headers.json").read_text())
    assert entry["scores"] == str(scores.path.resolve()) and entry["header"] == xvoe.score_header(scores)


def test_scores_of_another_split_of_the_same_layout_are_refused(test_file, other_split, tmp_path):
    ours = xvoe.score("random", test_file, tmp_path / "ours.csv", progress=False)
    theirs = xvoe.score(str(EXAMPLES / "frame_change.py:FrameChange"), other_split, tmp_path / "theirs.csv",
                        progress=False)
    with pytest.raises(XvoeError, match="scored on different splits"):
        xvoe.report([ours, theirs], tmp_path / "report", rounds=5)
    with pytest.raises(XvoeError, match="scored on another split"):
        xvoe.report([theirs], tmp_path / "report", rounds=5, data=test_file)
    assert not (tmp_path / "report").exists()


def test_a_score_file_without_a_split_is_read_with_a_warning(test_file, tmp_path, capsys):
    scores = xvoe.score("random", test_file, tmp_path / "r.csv", progress=False)
    scores.path.with_suffix(".curves.npz").unlink()          # as a CSV made elsewhere
    assert main(["metrics", str(scores), "--data", str(test_file), "--out", str(tmp_path / "report"),
                 "--rounds", "5"]) == 0
    assert "warning: " in capsys.readouterr().err and (tmp_path / "report" / "metrics.csv").is_file()


def tamper(path: Path, column: str, row: int, factor: float) -> None:
    rows = list(csv.DictReader(open(path, newline="")))
    rows[row][column] = repr(float(rows[row][column]) * factor)
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


@pytest.mark.parametrize("model", ["random", str(EXAMPLES / "frame_change.py:FrameChange")])
def test_verify_passes_a_score_file_as_written_and_fails_a_tampered_one(model, test_file, tmp_path, capsys):
    scores = xvoe.score(model, test_file, tmp_path / "s.csv", progress=False)
    every_row = ["verify", str(scores), "--rows", "176"]
    if model != "random":       # a header never names code to run: a model of one's own is named by its user
        assert main(every_row) == 2
        assert "verify runs no code a file names: pass --model" in capsys.readouterr().err
        every_row += ["--model", model]
    assert main(every_row) == 0
    assert "every row scored again matches" in capsys.readouterr().out
    tamper(scores, "score", 17, 1.001)
    assert main(every_row) == 1
    assert "video 17: differs in score" in capsys.readouterr().out


def test_verify_of_a_report_rescores_its_files_and_names_a_moved_split(test_file, tmp_path, capsys):
    data = tmp_path / "test.h5"
    shutil.copy(test_file, data)
    scores = xvoe.score("random", data, tmp_path / "s.csv", progress=False)
    xvoe.report([scores], tmp_path / "report", rounds=5)
    data.rename(tmp_path / "moved.h5")
    assert main(["verify", str(tmp_path / "report")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["verify", str(tmp_path / "report"), "--data", str(tmp_path / "moved.h5")]) == 0


def test_verify_rescores_the_shipped_model_within_tolerance(tmp_path, capsys):
    data = xvoe.generate(xvoe.GenerateConfig("test", pairs=1, size=32, seed=11), tmp_path / "t.h5", progress=False)
    scores = xvoe.score("xpl", data, tmp_path / "xpl.csv", progress=False)
    assert main(["verify", str(scores), "--rows", "3"]) == 0
    tamper(scores, "excess", 4, 0.99)
    assert main(["verify", str(scores), "--rows", "22"]) == 1
    assert "differs in excess" in capsys.readouterr().out


def test_verify_rescores_the_nll_columns_with_the_settings_and_seed_the_file_records(tmp_path, capsys):
    data = xvoe.generate(xvoe.GenerateConfig("test", pairs=1, size=32, seed=11), tmp_path / "t.h5", progress=False)
    scores = xvoe.score("xpl", data, tmp_path / "nll.csv", surprise="both", particles=8, seed=3, progress=False)
    tamper(scores, "nll", 12, 1.001)
    assert main(["verify", str(scores), "--rows", "22"]) == 1
    found = capsys.readouterr().out
    assert "video 12: differs in nll" in found and found.count(": matches") == 21     # every other video
    assert "1 of 22 rows differ from what was written: row 13 (video 12): nll" in found    # its curve's sum


def test_nll_settings_this_xvoe_no_longer_has_are_refused_in_one_line():
    """A score file made with a setting measurement retired (the mode's steps) cannot have its NLL
    run again as it was: verify and the explanation rows say so and ask for a rescore."""
    recorded = to_dict(InferenceConfig(particles=8))
    assert scored_nll("x.csv", {"nll": recorded}) == InferenceConfig(particles=8)
    with pytest.raises(XvoeError, match=r"^x\.csv was scored with NLL settings this xvoe cannot run \(its NLL "
                                        r"settings has no field\(s\) mode_steps .*\); rescore it$"):
        scored_nll("x.csv", {"nll": recorded | {"mode_steps": 10}})


def test_verify_names_an_edit_of_any_row_outside_the_rescored_sample(tmp_path):
    """Every row is checked against the curves it was summed from, not only the rescored sample:
    each row's score edited in turn is named, as is an edited label or model name."""
    data = xvoe.generate(xvoe.GenerateConfig("test", pairs=1, size=32, seed=11), tmp_path / "t.h5", progress=False)
    scores = xvoe.score("random", data, tmp_path / "r.csv", progress=False).path
    written = scores.read_bytes()
    assert xvoe.verify(scores, rows=1).matches
    for row in range(22):
        tamper(scores, "score", row, 1.5)
        found = xvoe.verify(scores, rows=1)
        assert not found.matches and f"1 of 22 rows differ from what was written: row {row + 1} (video {row})" \
            in found.lines[0], (row, found.lines)
        scores.write_bytes(written)
    for column, values in (("setting", ("S1", "S2")), ("possible", ("True", "False")), ("model", ("someone-else",))):
        rows = list(csv.DictReader(open(scores, newline="")))
        rows[5][column] = next(value for value in values if value != rows[5][column])
        with open(scores, "w", newline="") as handle:
            writer = csv.DictWriter(handle, list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        if column == "model":       # two models in one file: refused, naming the row
            with pytest.raises(XvoeError, match="two models, 'random' and 'someone-else' \\(row 6\\)"):
                xvoe.verify(scores, rows=1)
        else:
            found = xvoe.verify(scores, rows=1)
            assert not found.matches and f"row 6 (video 5): {column}" in found.lines[0], found.lines
        scores.write_bytes(written)
