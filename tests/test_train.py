"""The shared training loop, driven by the perception stage with a tiny model on 16 px videos."""
import csv
import subprocess
import sys
import textwrap

import pytest
import torch
from conftest import interrupt_during
from torch import nn

from xvoe.cli import main
from xvoe.errors import XvoeError
from xvoe.models.config import from_dict, override
from xvoe.models.perception import ComponentVAE, PerceptionConfig
from xvoe.scenes.generate import GenerateConfig, generate
from xvoe.training.checkpoints import load_checkpoint
from xvoe.training.config import TrainConfig
from xvoe.training.data import ShardedFrames
from xvoe.training.distributed import seed_everything
from xvoe.training.loop import Job, fit, learning_rate
from xvoe.training.perception import load_perception, train_perception
from xvoe.training.recipes import DEFAULT_RECIPE, recipe

TINY = dict(image_size=16, broadcast_size=4, latent_dim=4, cnn_channels=(8, 8), cnn_hidden=16, decoder_channels=8)
TRAIN = dict(batch_size=4, log_every=2, warmup_steps=2, threads=1)
TINY_CONFIG = override(recipe(DEFAULT_RECIPE).perception, **TINY)     # what train_perception builds from the overrides


@pytest.fixture(scope="module")
def tiny_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("tiny") / "train16.h5"
    return generate(GenerateConfig("train", videos=8, size=16, seed=11), path, workers=1, progress=False)


def run(data, out, steps, **extra):
    return train_perception(data, out, steps=steps, model_overrides=TINY, progress=False, **TRAIN, **extra)


def rows(path):
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def assert_same_tensors(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_same_tensors(a[key], b[key])
    elif isinstance(a, torch.Tensor):
        assert torch.equal(a, b)
    else:
        assert a == b


def test_checkpoint_round_trip_and_exact_resume(tiny_file, tmp_path):
    straight = load_checkpoint(run(tiny_file, tmp_path / "straight", 6))
    first = run(tiny_file, tmp_path / "stopped", 3)
    state = load_checkpoint(first)
    assert state["step"] == 3 and state["stage"] == "perception"
    assert from_dict(PerceptionConfig, state["config"]["perception"]) == TINY_CONFIG
    assert from_dict(TrainConfig, state["train"]).batch_size == 4
    resumed = load_checkpoint(train_perception(tiny_file, tmp_path / "stopped", steps=6, resume=True, progress=False))
    assert resumed["step"] == 6
    assert_same_tensors(straight["model"], resumed["model"])
    assert_same_tensors(straight["optimizer"]["state"], resumed["optimizer"]["state"])
    # the loss log continues where it stopped, with the same numbers as the uninterrupted run
    logged = [(r["step"], r["loss"]) for r in rows(tmp_path / "stopped" / "perception.csv")]
    assert logged == [(r["step"], r["loss"]) for r in rows(tmp_path / "straight" / "perception.csv")]
    assert [step for step, _ in logged] == ["2", "4", "6"]
    model, _ = load_perception(tmp_path / "straight")
    assert_same_tensors(model.state_dict(), straight["model"])
    # the same model overrides again are no change; another network is refused, not ignored
    assert load_checkpoint(run(tiny_file, tmp_path / "stopped", 7, resume=True))["step"] == 7
    with pytest.raises(XvoeError, match="resumed perception run keeps its network.*not latent_dim"):
        train_perception(tiny_file, tmp_path / "stopped", steps=8, resume=True, progress=False,
                         model_overrides={**TINY, "latent_dim": 6})


def test_an_existing_run_is_kept_unless_asked(tiny_file, tmp_path):
    run(tiny_file, tmp_path, 1)
    with pytest.raises(XvoeError, match="--resume"):
        run(tiny_file, tmp_path, 1)
    assert load_checkpoint(run(tiny_file, tmp_path, 2, overwrite=True))["step"] == 2


def test_learning_rate_warms_up_then_halves():
    config = TrainConfig(lr=1.0, warmup_steps=10, decay_steps=100)
    assert learning_rate(config, 0) == pytest.approx(0.1)
    assert learning_rate(config, 9) == pytest.approx(1.0)
    assert learning_rate(config, 110) == pytest.approx(0.5)


class Regression(nn.Module):
    """A toy stage: a line fitted to seeded random points; batches() records the weights it sees."""

    def __init__(self):
        super().__init__()
        seed_everything(0)
        self.line = nn.Linear(3, 1)
        self.seen = []

    def batches(self, step):
        self.seen.append(self.line.weight.detach().clone())      # the weights after `step` steps
        return torch.randn(4, 3, generator=torch.Generator().manual_seed(step))

    def forward(self, points):
        return {"loss": ((self.line(points) - points.sum(1, keepdim=True)) ** 2).mean()}


def fit_regression(out, steps, resume=False, decay=0.6):
    model = Regression()
    config = TrainConfig(steps=steps, lr=0.1, warmup_steps=1, log_every=1, threads=1, average_decay=decay)
    state = load_checkpoint(fit(Job("toy", model, model.batches, {}), config, out, resume=resume, progress=False))
    return model, state


def test_the_checkpoint_holds_the_moving_average_of_the_weights(tmp_path):
    model, state = fit_regression(tmp_path / "straight", 5)
    trained = [*model.seen[1:], state["trained"]["line.weight"]]          # after steps 1..5
    weights = torch.tensor([0.6 ** (5 - s) for s in range(1, 6)])
    expected = sum(w * x for w, x in zip(weights / weights.sum(), trained))
    torch.testing.assert_close(state["model"]["line.weight"], expected)
    assert not torch.allclose(state["model"]["line.weight"], state["trained"]["line.weight"])
    # a run stopped and resumed averages as the straight one: training goes on from the trained weights
    fit_regression(tmp_path / "stopped", 2)
    _, resumed = fit_regression(tmp_path / "stopped", 5, resume=True)
    assert_same_tensors(state["model"], resumed["model"])
    assert_same_tensors(state["trained"], resumed["trained"])
    with pytest.raises(XvoeError, match="average_decay must be"):
        fit_regression(tmp_path / "bad", 1, decay=1.0)


def test_data_at_another_resolution_is_refused(tiny_file, tmp_path, capsys):
    with pytest.raises(XvoeError, match="16x16 frames but the model works at 32x32"):
        train_perception(tiny_file, tmp_path, steps=1, progress=False)
    code = main(["train", "perception", "--data", str(tiny_file), "--out", str(tmp_path / "cli"),
                 "--steps", "1", "--quiet"])
    assert code == 2
    error = capsys.readouterr().err.strip()
    assert "--size 32" in error and len(error.splitlines()) == 1


# the tiny split's shards hold too few frames in the air for the default recipe's airborne share,
# which has tests of its own; these are about the processes
SCRIPT = """
import sys
from xvoe.training.perception import train_perception
train_perception(sys.argv[1], sys.argv[2], steps=4, model_overrides={tiny!r}, progress=False, batch_size=8,
                 data_shards=2, log_every=2, warmup_steps=2, threads=1, airborne_share=0.0)
"""


def test_two_processes_under_torchrun_match_one_process(tiny_file, tmp_path):
    script = tmp_path / "train_tiny.py"
    script.write_text(textwrap.dedent(SCRIPT.format(tiny=TINY)))
    one, two = tmp_path / "one", tmp_path / "two"
    subprocess.run([sys.executable, str(script), str(tiny_file), str(one)], check=True, timeout=120)
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           str(script), str(tiny_file), str(two)], timeout=180, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]      # what torchrun said, should it fail
    single, double = load_checkpoint(one / "perception.pt"), load_checkpoint(two / "perception.pt")
    assert double["world"] == 2 and single["world"] == 1 and double["step"] == 4
    for name, weight in single["model"].items():
        if name == "theta":
            # the z-buffer temperature gets a near-zero gradient (a saturated softmax), whose sign
            # can flip with the order of float sums; Adam then moves it by up to lr per step
            torch.testing.assert_close(double["model"][name], weight, rtol=0, atol=4 * 1e-3)
        else:
            torch.testing.assert_close(double["model"][name], weight, rtol=1e-4, atol=1e-5)
    # and training moved the weights away from their (seeded) initial values
    seed_everything(0)
    initial = ComponentVAE(TINY_CONFIG).state_dict()
    assert not torch.equal(initial["decoder.out.weight"], single["model"]["decoder.out.weight"])


LEAVES = """
import atexit, torch, torch.distributed as dist
from xvoe.training.distributed import setup_distributed
atexit.register(lambda: print("joined at exit:", dist.is_initialized()))     # runs after the handlers set up later
place = setup_distributed()
flags = torch.ones(2)
dist.all_reduce(flags)
print("summed:", flags.tolist())
"""


def test_a_process_that_joined_a_group_leaves_it_before_the_interpreter_ends(tmp_path):
    """A gloo group still held as Python shuts down aborts its process in about a third of launches
    (torchrun then fails a run that finished): the group is left while the interpreter still runs."""
    script = tmp_path / "leaves.py"
    script.write_text(LEAVES)
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           "--tee", "1", str(script)], timeout=120, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("summed: [2.0, 2.0]") == 2
    assert done.stdout.count("joined at exit: False") == 2


INTERRUPTED = """
import os, signal, sys
from xvoe.training.data import ShardedFrames
from xvoe.training.perception import train_perception
draw = ShardedFrames.batch

def interrupted(self, step):
    if step == 2 and os.environ["RANK"] == "1":
        os.kill(os.getpid(), signal.SIGINT)
    return draw(self, step)

ShardedFrames.batch = interrupted
train_perception(sys.argv[1], sys.argv[2], steps=8, model_overrides={tiny!r}, progress=False, batch_size=8,
                 data_shards=2, log_every=2, warmup_steps=2, threads=1, airborne_share=0.0)
"""


def test_an_interrupt_in_one_process_under_torchrun_stops_both_after_the_same_step(tiny_file, tmp_path):
    """Only rank 1 gets Ctrl-C, during step 2: both processes finish that step and stop, and rank 0
    checkpoints step 3 (were they to disagree, one would wait for the other's gradients until the
    timeout)."""
    script = tmp_path / "interrupted.py"
    script.write_text(textwrap.dedent(INTERRUPTED.format(tiny=TINY)))
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
                           str(script), str(tiny_file), str(tmp_path / "run")], timeout=180, capture_output=True,
                          text=True)
    assert done.returncode != 0 and "stopped at step 3" in done.stderr
    state = load_checkpoint(tmp_path / "run" / "perception.pt")
    assert state["step"] == 3 and state["world"] == 2


def test_a_request_that_lands_during_the_exchange_stops_the_next_step(monkeypatch):
    """Ctrl-C often arrives while a process waits in the stop exchange for the others; the request
    must survive the exchange's answer (no process had asked yet) and stop every process one step
    later, or the run trains on after the user asked it to stop."""
    import signal

    from xvoe.training import distributed

    stops = distributed.StopRequests(enabled=False)
    place = distributed.Dist(rank=0, world=2)

    def exchange(flags, op):            # the other process had no request; ours lands meanwhile
        stops.ask(signal.SIGINT, None)

    monkeypatch.setattr(distributed.dist, "all_reduce", exchange)
    assert not stops.agreed(place, out_of_time=False) and not stops.asked
    monkeypatch.setattr(distributed.dist, "all_reduce", lambda flags, op: None)
    assert stops.agreed(place, out_of_time=False) and stops.asked
    with pytest.raises(KeyboardInterrupt):          # a second request stops at once
        stops.ask(signal.SIGINT, None)


def test_a_request_during_the_last_step_still_stops_the_caller(tiny_file, tmp_path, monkeypatch):
    """Ctrl-C in a stage's last step: the stage is whole, but what called it (the pipeline's next
    stage) must not start as if nothing had been asked."""
    interrupt_during(monkeypatch, ShardedFrames, 2)
    with pytest.raises(KeyboardInterrupt, match="stopped at step 3"):
        run(tiny_file, tmp_path, 3)
    assert load_checkpoint(tmp_path / "perception.pt")["step"] == 3


def test_a_perception_batch_does_not_depend_on_the_process_count(tiny_file):
    """Frames and noise are drawn shard by shard: two processes' halves are the one process's batch."""
    common = dict(image_size=16, latent_dim=4, batch_size=8, shards=2, seed=3)
    whole = ShardedFrames(str(tiny_file), **common).batch(5)
    halves = [ShardedFrames(str(tiny_file), rank=r, world=2, **common).batch(5) for r in (0, 1)]
    assert torch.equal(torch.cat([h.objects for h in halves]), whole.objects)
    assert torch.equal(torch.cat([h.noise for h in halves]), whole.noise)


@pytest.fixture(scope="module")
def falling_file(tmp_path_factory):
    """A training split with permanence videos (cubes drop from above the picture) in both halves."""
    path = tmp_path_factory.mktemp("falling") / "train16.h5"
    return generate(GenerateConfig("train", videos=24, size=16, seed=3), path, workers=1, progress=False)


def test_airborne_frames_are_those_whose_pictures_show_an_object_above_the_floor(falling_file):
    """Read from the saved states, checked against the rendered masks of the balls and cubes: only
    falling cubes leave the floor, so no other scenario has such a frame."""
    import h5py
    import numpy as np

    from xvoe.training.data import _airborne

    with h5py.File(falling_file) as file:
        lifted = _airborne(file, 0, len(file["rgbd"]))
        groups, ids, kind = file["group"].asstr()[:], file["ids"][:], file["kind"][:]
        kinds = list(file.attrs["kind_names"])
    floor_row = 16 * (1 - 12 / 64)                      # the floor's top, in pixels from the top
    assert lifted[groups == "permanence"].any()
    assert not lifted[groups != "permanence"].any()
    for video, frame in np.argwhere(lifted):
        movable = np.flatnonzero(np.isin(kind[video], [kinds.index("ball"), kinds.index("cube")])) + 1
        rows = [np.nonzero(ids[video, frame] == slot)[0] for slot in movable]
        assert any(len(r) and r.max() < floor_row - 1 for r in rows)


def test_the_airborne_share_of_a_perception_batch(falling_file, tmp_path):
    """That share of each shard's frames shows an object off the floor, drawn shard by shard so that
    two processes' halves are the one process's batch; a share outside [0, 1] or a stage without
    frames is refused, as a batch focus on a group is in the perception stage."""
    import h5py

    from xvoe.training.data import _airborne

    common = dict(image_size=16, latent_dim=4, batch_size=8, shards=2, seed=3, airborne_share=0.5)
    frames = ShardedFrames(str(falling_file), **common)
    with h5py.File(falling_file) as file:
        lifted = _airborne(file, 0, len(file["rgbd"]))
    video, frame = frames.picks(5)
    shards = [list(zip(video[:4], frame[:4])), list(zip(video[4:], frame[4:]))]
    assert [[bool(lifted[v, f]) for v, f in shard[2:]] for shard in shards] == [[True, True]] * 2
    assert all(v < 12 for v, _ in shards[0]) and all(v >= 12 for v, _ in shards[1])
    whole = frames.batch(5)
    halves = [ShardedFrames(str(falling_file), rank=r, world=2, **common).batch(5) for r in (0, 1)]
    assert torch.equal(torch.cat([h.frames for h in halves]), whole.frames)
    with pytest.raises(XvoeError, match="airborne_share must lie in"):
        ShardedFrames(str(falling_file), **(common | {"airborne_share": 1.5}))
    job = Job("xpl", nn.Linear(1, 1), lambda step: None, {})
    with pytest.raises(XvoeError, match="the xpl stage has none"):
        fit(job, TrainConfig(steps=1, airborne_share=0.5), tmp_path, progress=False)
    job = Job("perception", nn.Linear(1, 1), lambda step: None, {})
    with pytest.raises(XvoeError, match="the perception stage draws single frames"):
        fit(job, TrainConfig(steps=1, focus_group="permanence", focus_share=0.5), tmp_path, progress=False)


def test_a_training_config_out_of_its_domains_is_refused_where_it_is_built():
    """In Python as from the command line, before a stage reads data."""
    with pytest.raises(XvoeError, match="lr must be a finite number > 0, not -1"):
        TrainConfig(lr=-1)


def test_bad_input_in_training_processes_reads_as_it_does_in_one(tmp_path):
    """A stage started by `on_cores` in two processes stops with the stage's own message."""
    from xvoe.training.launch import on_cores
    from xvoe.training.xpl import train_xpl

    for processes in (1, 2):
        with pytest.raises(XvoeError, match="give the latent cache to start a run"):
            on_cores(train_xpl, processes, latents=None, run_dir=str(tmp_path / "run"))
    with pytest.raises(ValueError, match="at least 1"):
        on_cores(train_xpl, 0)


def test_training_processes_meet_on_a_port_held_from_before_they_start():
    """A port found free and let go could be taken by another run before the processes bind
    it (two pipelines, or a test beside a training job): the launcher's store holds it."""
    import socket

    from xvoe.training.launch import rendezvous_store

    store = rendezvous_store()
    with socket.socket() as other, pytest.raises(OSError):
        other.bind(("127.0.0.1", store.port))


ON_CORES = """
import sys
from xvoe.training.launch import on_cores
from xvoe.training.perception import train_perception
if __name__ == "__main__":
    on_cores(train_perception, 2, data=sys.argv[1], run_dir=sys.argv[2], steps=100_000, model_overrides={tiny!r},
             progress=False, batch_size=8, log_every=2, warmup_steps=2, data_shards=2, airborne_share=0.0,
             checkpoint_minutes=0.01)
"""


def test_an_interrupt_of_the_launching_process_stops_its_training_processes_after_one_step(tiny_file, tmp_path):
    """A Jupyter interrupt reaches the launching process alone: both training processes stop
    after the same step, rank 0 checkpoints it, and the launcher says so in one line."""
    import signal
    import time

    script = tmp_path / "on_cores.py"
    script.write_text(textwrap.dedent(ON_CORES.format(tiny=TINY)))
    run = tmp_path / "run"
    launcher = subprocess.Popen([sys.executable, str(script), str(tiny_file), str(run)], stderr=subprocess.PIPE,
                                text=True)
    deadline = time.monotonic() + 120
    while not (run / "perception.csv").exists() and launcher.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    launcher.send_signal(signal.SIGINT)
    try:
        _, err = launcher.communicate(timeout=120)
    finally:
        launcher.kill()         # on a time-out, its processes get the kernel's SIGINT and stop too
    assert launcher.returncode != 0
    said = err.strip().splitlines()[-1]
    assert "KeyboardInterrupt: stopped at step" in said, err
    state = load_checkpoint(run / "perception.pt")
    assert said.split("stopped at step ")[1].startswith(f"{state['step']},") and state["world"] == 2
    assert 0 < state["step"] < 100_000


def test_a_checkpoint_of_an_older_xvoe_whose_rng_state_holds_an_array_resumes_the_same(tiny_file, tmp_path):
    """Older run checkpoints kept numpy's generator key as an array: read as data, it resumes exactly."""
    import numpy as np

    straight = load_checkpoint(run(tiny_file, tmp_path / "straight", 4))
    path = run(tiny_file, tmp_path / "older", 2)
    state = torch.load(path, weights_only=True)
    kind, key, *rest = state["rng"]["numpy"]
    state["rng"]["numpy"] = (kind, key.numpy().astype(np.uint32), *rest)
    torch.save(state, path)
    resumed = load_checkpoint(train_perception(tiny_file, tmp_path / "older", steps=4, resume=True, progress=False))
    assert_same_tensors(straight["model"], resumed["model"])
    assert isinstance(resumed["rng"]["numpy"][1], torch.Tensor)
