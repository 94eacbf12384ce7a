import os

import numpy as np
import pytest
from hypothesis import settings

from xvoe.training.distributed import KERNELS

# The training's kernels in this process too, before its first: stages trained here then match
# those trained in the processes the pipeline starts (xvoe.training.distributed.pin_kernels).
os.environ.update({name: os.environ.get(name, value) for name, value in KERNELS.items()})

from xvoe.scenes import store
from xvoe.scenes.generate import GenerateConfig, generate

# Property tests draw the same examples on every run: a red CI run can be replayed.
settings.register_profile("xvoe", derandomize=True, deadline=None, database=None)
settings.load_profile("xvoe")


def randomise_dynamics_head(dynamics) -> None:
    """Give the dynamics' output head random weights: it starts at zero (no change), which
    would hide any difference between two ways of running the dynamics."""
    import torch

    for layer in dynamics.out:
        if isinstance(layer, torch.nn.Linear):
            torch.nn.init.normal_(layer.weight, std=0.3)


def interrupt_during(monkeypatch, batches: type, step: int):
    """Ctrl-C in the middle of a training step: SIGINT to this process while `batches` draws
    step `step`. Returns the batch method it wraps, to put back for a resumed run."""
    import os
    import signal

    draw = batches.batch

    def interrupted(self, at):
        if at == step:
            os.kill(os.getpid(), signal.SIGINT)
        return draw(self, at)

    monkeypatch.setattr(batches, "batch", interrupted)
    return draw


@pytest.fixture
def double_precision():
    """Run a test in float64 and leave the default dtype as it was."""
    import torch

    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


@pytest.fixture(scope="session")
def test_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "test.h5"
    return generate(GenerateConfig("test", pairs=8, size=64, seed=3), path, workers=2, progress=False)


@pytest.fixture(scope="session")
def train_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "train.h5"
    return generate(GenerateConfig("train", videos=96, size=64, seed=5), path, workers=1, progress=False)


@pytest.fixture(scope="session")
def test_data(test_file):
    """Everything of the small test split, in memory."""
    with store.open_dataset(test_file) as f:
        data = {name: f[name][:] for name in ("rgbd", "ids", "states", "kind", "color", "pair",
                                               "member", "possible", "event_frame")}
        data["scenario"] = store.strings(f, "scenario")
        data["setting"] = store.strings(f, "setting")
        data["columns"] = list(f["states"].attrs["state_columns"])
        data["kind_names"] = list(f.attrs["kind_names"])
    return data


def column(data, name):
    return data["states"][..., data["columns"].index(name)]


def videos_of(data, scenario, setting, member):
    mask = (data["scenario"] == scenario) & (data["setting"] == setting) & (data["member"] == member)
    return np.flatnonzero(mask)
