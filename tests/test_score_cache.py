"""A test split encoded once: the latent cache `xvoe score` makes beside the split and every
model of the same perception module reads, under every surprise definition; and each batch
drawn once, by the MSE score, for the NLL beside it."""
import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import randomise_dynamics_head

import xvoe
from xvoe.cli import main
from xvoe.evaluation import score_cache
from xvoe.evaluation import scorer as scoring
from xvoe.evaluation.score_tables import read_scores
from xvoe.inference.model import InferenceConfig
from xvoe.inference.surprise import nll_surprise
from xvoe.models.dynamics import DynamicsConfig
from xvoe.models.perception import ComponentVAE, PerceptionConfig
from xvoe.models.reasoning import ReasoningConfig
from xvoe.models.xpl import XPL, XPLConfig
from xvoe.scenes import store
from xvoe.scenes.generate import GenerateConfig, generate
from xvoe.training import latents
from xvoe.training.checkpoints import shipped_path
from xvoe.training.latents import _perception_identity, check_cache, encoder_key, split_cache
from xvoe.training.perception import load_perception

D, FRAMES = 4, 10


@pytest.fixture(scope="module")
def tiny_split(tmp_path_factory):
    return generate(GenerateConfig("test", pairs=1, size=16, frames=FRAMES, seed=21),
                    tmp_path_factory.mktemp("tiny") / "t.h5", workers=1, progress=False)


def tiny_scorer(name: str, slots: int, use_reasoning: bool = True) -> xvoe.Scorer:
    """An untrained XPL (or, without reasoning, PLATO's kind) on an untrained perception module,
    the same perception for every name."""
    torch.manual_seed(0)
    vae = ComponentVAE(PerceptionConfig(image_size=16, latent_dim=D, cnn_channels=(8, 8), cnn_hidden=16,
                                        decoder_channels=8)).eval()
    xpl = XPL(XPLConfig(reasoning=ReasoningConfig(latent_dim=D, slots=slots, frames=FRAMES, width=16, layers=1,
                                                  heads=2, mlp=16),
                        dynamics=DynamicsConfig(latent_dim=D, hidden=16, lstm=16, buffer_heads=2),
                        use_reasoning=use_reasoning))
    randomise_dynamics_head(xpl.dynamics)      # motion costs something: the curves are not all zero
    return xvoe.Scorer(name, vae, xpl.eval())


def scored(scorer: xvoe.Scorer, data: Path, out: Path, **settings) -> tuple[bytes, dict[str, np.ndarray]]:
    table = xvoe.score(scorer, data, out, progress=False, **settings)
    with np.load(table.path.with_suffix(".curves.npz")) as curves:
        return table.path.read_bytes(), dict(curves)


def test_scores_from_the_cache_are_the_scores_without_it(tiny_split, tmp_path, monkeypatch):
    """Bitwise: the cache holds what the scorer's own encoder gives, batch for batch."""
    with store.open_dataset(tiny_split) as file:
        slots = file["states"].shape[2]
    xpl, plato = tiny_scorer("xpl", slots), tiny_scorer("plato", slots, use_reasoning=False)
    nll = {"surprise": "both", "particles": 4}
    expected = {name: scored(scorer, tiny_split, tmp_path / f"{name}-alone.csv", cache=False, **settings)
                for name, scorer, settings in (("xpl", xpl, nll), ("plato", plato, {}))}
    cache = split_cache(tiny_split, _perception_identity(xpl.vae))
    assert not cache.exists()
    made = scored(xpl, tiny_split, tmp_path / "xpl-first.csv", **nll)       # makes the cache on first use
    assert cache.is_file()

    def no_encoding(*args, **kwargs):
        raise AssertionError("a split with a cache was encoded again")

    monkeypatch.setattr(scoring, "encode_frames", no_encoding)
    monkeypatch.setattr(score_cache, "encode_with", no_encoding)
    found = {"xpl": scored(xpl, tiny_split, tmp_path / "xpl.csv", **nll),      # the MSE and the NLL read it
             "plato": scored(plato, tiny_split, tmp_path / "plato.csv")}        # another model of that perception
    for name in ("xpl", "plato"):
        csv, curves = expected[name]
        assert found[name][0] == csv, name
        assert curves.keys() == found[name][1].keys() and "s_img" in curves
        for key in curves:
            np.testing.assert_array_equal(found[name][1][key], curves[key], err_msg=f"{name} {key}")
    assert made[0] == expected["xpl"][0]


def test_the_nll_beside_the_mse_score_is_the_nll_of_each_video_drawn_on_its_own(tiny_split, tmp_path):
    """`--surprise both` hands each batch as the MSE score drew it (refined, proposed, decoded)
    to the NLL, which draws nothing again: its columns and curve are those of each video drawn on
    its own, as `xvoe explain` draws it. Within float rounding, not bitwise: the decoder's
    convolutions may round a picture's last bit differently in a batch of another size."""
    with store.open_dataset(tiny_split) as file:
        scorer = tiny_scorer("xpl", file["states"].shape[2])
        batches = [scoring.encode_videos(scorer, file, start, min(start + 16, len(file["rgbd"])))
                   for start in range(0, len(file["rgbd"]), 16)]     # as `xvoe score` encodes them
    table = xvoe.score(scorer, tiny_split, tmp_path / "both.csv", surprise="both", particles=4, cache=False,
                       progress=False)
    video = ("frames", "mean", "visible", "background", "occluder")
    alone = [nll_surprise(scorer.vae, scorer.xpl, *(batch[name][i] for name in video), InferenceConfig(particles=4))
             for batch in batches for i in range(len(batch["mean"]))]
    # what is reused is tried: a proposed hidden object, and a second version of two identical objects
    assert any(found.hidden_slot >= 0 for found in alone) and any(found.identity is not None for found in alone)
    scores = read_scores(table)
    for column in ("nll", "ess", "p_hidden", "p_two"):
        np.testing.assert_allclose(scores[column], [getattr(found, column) for found in alone], rtol=1e-6,
                                   atol=1e-9, err_msg=column)
    with np.load(table.path.with_suffix(".curves.npz")) as curves:
        np.testing.assert_allclose(curves["nll"], np.stack([found.frame_nll.numpy() for found in alone]),
                                   rtol=1e-6, atol=1e-6)


def test_an_explanation_from_an_encoded_chunk_is_the_explanation_encoding_its_video(tiny_split, monkeypatch):
    """`xvoe.explain(..., chunk=...)` reads the video from a chunk encoded once for all its videos,
    and draws what explaining it alone draws, to the bit, under either surprise."""
    with store.open_dataset(tiny_split) as file:
        scorer = tiny_scorer("xpl", file["states"].shape[2])
        chunk = scoring.encode_chunk(scorer, file, 3)
    assert chunk.first == 0 and chunk.holds(3) and not chunk.holds(len(chunk.videos["mean"]))
    settings = {"display_size": None, "particles": 4}
    alone = {surprise: xvoe.explain(scorer, tiny_split, 3, surprise=surprise, **settings)
             for surprise in ("mse", "nll")}

    def no_encoding(*args, **kwargs):
        raise AssertionError("a video of an encoded chunk was encoded again")

    monkeypatch.setattr(scoring, "encode_frames", no_encoding)
    for surprise, expected in alone.items():
        found = xvoe.explain(scorer, tiny_split, 3, surprise=surprise, chunk=chunk, **settings)
        np.testing.assert_array_equal(found.behind_wall, expected.behind_wall, err_msg=surprise)
        assert found.title == expected.title
    assert found.nll == alone["nll"].nll and found.p_hidden == alone["nll"].p_hidden


def shipped_or_skip() -> Path:
    if shipped_path("plato") is None or shipped_path("xpl", "perception") is None:
        pytest.skip("no shipped plato model in xvoe/weights")
    return shipped_path("xpl", "perception")


def snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "folder"
            for p in sorted(root.rglob("*"))}


def refused(args: list[str], root: Path, capsys) -> str:
    """The one line `xvoe ARGS` fails with (exit 2), having written nothing under root."""
    before = snapshot(root)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert snapshot(root) == before
    return err


def test_a_cache_of_another_split_or_another_perception_is_refused(tmp_path, capsys):
    perception = shipped_or_skip()
    ours, theirs = (generate(GenerateConfig("test", pairs=1, seed=seed), tmp_path / f"{name}.h5", workers=1,
                             progress=False) for name, seed in (("ours", 31), ("theirs", 32)))
    # xvoe encode on a test split writes the cache where xvoe score reads it
    assert main(["encode", "--model", "plato", "--data", str(theirs), "--out", str(tmp_path), "--quiet"]) == 0
    shipped_key = _perception_identity(load_perception("plato")[0])
    made = split_cache(theirs, shipped_key)
    assert made.is_file()
    score = ["score", "--out", str(tmp_path / "s.csv"), "--quiet"]
    err = refused(score + ["--model", "plato", "--data", str(ours), "--cache", str(made)], tmp_path, capsys)
    assert f"was encoded from {theirs}" in err and f"not from {ours}" in err
    # the split's own cache from an earlier file of its name (a split generated again) is made again
    own = split_cache(ours, shipped_key)
    shutil.copy(made, own)
    assert main(score + ["--model", "plato", "--data", str(ours)]) == 0
    check_cache(own, ours, shipped_key)
    (tmp_path / "s.csv").unlink()
    (tmp_path / "s.curves.npz").unlink()
    # a perception module with one weight changed, beside a copy of plato: another perception
    other = tmp_path / "other"
    other.mkdir()
    state = torch.load(perception, weights_only=True)
    first = next(iter(state["model"]))
    state["model"][first] = state["model"][first] + 1e-3
    torch.save(state, other / "perception.pt")
    shutil.copy(shipped_path("plato"), other / "plato.pt")
    err = refused(score + ["--model", str(other / "plato.pt"), "--data", str(theirs), "--cache", str(made)],
                  tmp_path, capsys)
    assert "was encoded by another perception module" in err and shipped_key in err
    # its own cache has a name of its own beside the split: both perceptions score the split
    assert main(score + ["--model", str(other / "plato.pt"), "--data", str(theirs)]) == 0
    assert split_cache(theirs, _perception_identity(load_perception(other)[0])).is_file()


def test_a_cache_encoded_in_another_precision_is_another_cache(tiny_split, tmp_path, monkeypatch):
    """bfloat16 on CUDA moves the latents beyond float rounding: its cache is not read on the CPU."""
    vae = tiny_scorer("xpl", slots=8).vae
    cpu_key = encoder_key(vae)
    assert cpu_key == _perception_identity(vae)          # float32: every CPU cache keeps its name
    monkeypatch.setattr(latents, "autocast_dtype", lambda device: torch.bfloat16)      # as on a CUDA device
    gpu_key = encoder_key(vae)
    assert gpu_key == f"{cpu_key}-bfloat16" and split_cache(tiny_split, gpu_key) != split_cache(tiny_split, cpu_key)
    made = latents.encode_with(vae, tiny_split, tmp_path / "gpu.h5", progress=False)    # records the bfloat16 key
    monkeypatch.undo()
    with pytest.raises(xvoe.XvoeError, match="another perception module"):
        check_cache(made, tiny_split, encoder_key(vae))
