"""The device plumbing, run on the CPU: a device named explicitly changes nothing, and one the
machine lacks is refused before any work."""
import pytest
import torch
from test_train import TINY, TRAIN, assert_same_tensors

import xvoe
from xvoe.errors import XvoeError
from xvoe.models.devices import resolve_device
from xvoe.training.checkpoints import load_checkpoint
from xvoe.training.perception import train_perception


@pytest.fixture(scope="module")
def split32(tmp_path_factory):
    """A test split at the shipped models' 32 px: one pair per setting."""
    path = tmp_path_factory.mktemp("device") / "test32.h5"
    return xvoe.generate(xvoe.GenerateConfig(split="test", pairs=1, size=32, seed=21), path, workers=1,
                         progress=False)


def test_a_device_is_named_or_refused_in_one_line():
    assert resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(XvoeError, match="'tpu' is not a device"):
        resolve_device("tpu")
    with pytest.raises(XvoeError, match="'cuda:99'"):       # no machine has a hundredth GPU
        resolve_device("cuda:99")
    if not torch.cuda.is_available():
        with pytest.raises(XvoeError, match="no CUDA device"):
            resolve_device("cuda")


def test_scores_on_an_explicit_cpu_are_the_bytes_of_the_default(split32, tmp_path):
    settings = dict(surprise="both", particles=8, videos_per_batch=2, shard=(0, 11), progress=False)   # 2 videos
    default = xvoe.score("xpl", split32, tmp_path / "default.csv", **settings)
    chosen = xvoe.score("xpl", split32, tmp_path / "cpu.csv", **settings, device="cpu")
    assert chosen.path.read_bytes() == default.path.read_bytes()
    assert chosen.path.with_suffix(".curves.npz").read_bytes() == default.path.with_suffix(".curves.npz").read_bytes()


def test_an_absent_device_is_refused_before_anything_is_read_or_written(split32, tmp_path):
    with pytest.raises(XvoeError, match="'cuda:99'"):
        xvoe.score("xpl", tmp_path / "no-such-split.h5", tmp_path / "s.csv", device="cuda:99")
    with pytest.raises(XvoeError, match="'cuda:99'"):
        xvoe.load_model("xpl", device="cuda:99")
    with pytest.raises(XvoeError, match="'cuda:99'"):
        xvoe.PipelineConfig(str(tmp_path / "run"), device="cuda:99")
    assert list(tmp_path.iterdir()) == []


def test_an_explanation_on_an_explicit_cpu_is_the_default_one(split32):
    default = xvoe.explain("xpl", split32, 2)
    chosen = xvoe.explain("xpl", split32, 2, device="cpu")
    for name in ("observed", "behind_wall", "hidden_object"):
        assert (getattr(chosen, name) == getattr(default, name)).all()
    assert chosen.slot == default.slot


def test_training_on_an_explicit_cpu_is_the_default_training(tmp_path):
    data = xvoe.generate(xvoe.GenerateConfig(split="train", videos=4, size=16, seed=11), tmp_path / "train16.h5",
                         workers=1, progress=False)
    runs = [load_checkpoint(train_perception(data, tmp_path / name, steps=3, model_overrides=TINY, progress=False,
                                             **TRAIN, **extra))
            for name, extra in (("default", {}), ("cpu", {"device": "cpu"}))]
    assert_same_tensors(runs[0]["model"], runs[1]["model"])
    assert_same_tensors(runs[0]["optimizer"]["state"], runs[1]["optimizer"]["state"])
