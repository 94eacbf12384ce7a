"""Interruptions leave nothing broken: tests/interruptions.py, a Ctrl-C once per command
(generate, encode, score in two workers, metrics) at a seeded moment, finds no process left
behind, no broken file under a final name, no traceback, and a rerun equal to the uninterrupted
run. The harder case of the two signals and the training run are left to the full run that
docs/results.md ("Interruptions") gives, 20 per command, to keep the suite within its time.
Two moments a random draw seldom meets are placed on purpose: a Ctrl-C as training processes
start (`on_cores`), and one whose handler runs inside a finaliser."""
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")
def test_random_interruptions_leave_nothing_broken_and_a_rerun_makes_the_same_bytes(tmp_path):
    script = Path(__file__).with_name("interruptions.py")
    done = subprocess.run([sys.executable, str(script), str(tmp_path), "--times", "1", "--seed", "1",
                           "--commands", "generate,encode,score,metrics", "--signals", "SIGINT"],
                          capture_output=True, text=True, timeout=900, env=os.environ | {"OMP_NUM_THREADS": "1"})
    reports = [json.loads(line) for line in done.stdout.splitlines()]
    assert [r["command"] for r in reports] == ["generate", "encode", "score", "metrics"], done.stderr[-2000:]
    for report in reports:
        assert "SIGKILL" not in report and report["SIGINT"]["trials"] == 1, report
        assert report["SIGINT"]["problems"] == [], report
    assert done.returncode == 0


LAUNCHER = """
import sys
from pathlib import Path
from xvoe.training.launch import on_cores
from xvoe.training.perception import train_perception
if __name__ == "__main__":
    Path(sys.argv[3]).touch()       # imported: the processes start next
    try:
        on_cores(train_perception, 2, data=sys.argv[1], run_dir=sys.argv[2], steps=100_000, progress=False,
                 model_overrides=dict(image_size=16, broadcast_size=4, latent_dim=4, cnn_channels=(8, 8),
                                      cnn_hidden=16, decoder_channels=8),
                 batch_size=8, log_every=2, warmup_steps=2, data_shards=2, airborne_share=0.0)
    except KeyboardInterrupt as stop:
        sys.exit(f"interrupted {stop}")
"""


def marked(mark: str) -> list[int]:
    """The processes whose environment holds `mark`: a launcher's processes, in groups of their own."""
    found = []
    for entry in Path("/proc").iterdir():
        with contextlib.suppress(OSError):
            if entry.name.isdigit() and mark.encode() in (entry / "environ").read_bytes():
                found.append(int(entry.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")
def test_a_ctrl_c_as_training_processes_start_stops_them_all_in_one_line(tmp_path):
    """A terminal's Ctrl-C reaches the launcher and its processes as they import torch again:
    the processes hold it until their stage runs and stop there, the launcher raises it (the
    command line's one line), and nothing is left running or half-written."""
    from xvoe.scenes.generate import GenerateConfig, generate

    data = generate(GenerateConfig("train", videos=8, size=16, seed=11), tmp_path / "t.h5", workers=1, progress=False)
    script, started, run = tmp_path / "launch.py", tmp_path / "started", tmp_path / "run"
    script.write_text(LAUNCHER)
    mark = f"XVOE_LAUNCH_TEST={uuid.uuid4().hex}"
    name, value = mark.split("=")
    launcher = subprocess.Popen([sys.executable, str(script), str(data), str(run), str(started)], text=True,
                                stderr=subprocess.PIPE, start_new_session=True,
                                env=os.environ | {"OMP_NUM_THREADS": "1", name: value})
    try:
        deadline = time.monotonic() + 120
        while not started.exists() and launcher.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)                 # the processes are importing
        os.killpg(launcher.pid, signal.SIGINT)
        _, err = launcher.communicate(timeout=300)
    finally:
        stray = marked(mark)
        for pid in stray:
            os.kill(pid, signal.SIGKILL)
    assert stray == [] and launcher.returncode == 1, (stray, err)
    assert err.strip().startswith("interrupted") and len(err.strip().splitlines()) == 1, err
    written = sorted(p.name for p in run.rglob("*")) if run.exists() else []
    assert set(written) <= {"perception.pt", "perception.csv"}, written


SLOW_FINALISER = """
import time
import weakref
from pathlib import Path

import numpy as np


class Held:
    pass


def finalise():
    if Path({mark!r}).exists():        # slow once
        return
    Path({mark!r}).touch()
    ends = time.monotonic() + 10
    while time.monotonic() < ends:      # Python code, so that a Ctrl-C's handler runs in here
        pass


class SlowFinaliser:
    name = "slow-finaliser"

    def surprise(self, videos):
        held = Held()
        weakref.finalize(held, finalise)
        del held                        # the finaliser runs now, in the main thread
        time.sleep(1)                   # the scores are not written before the Ctrl-C raised again
        return np.zeros((len(videos.index), videos.frames))
"""


def test_a_ctrl_c_met_in_a_finaliser_interrupts_the_run_in_one_line(tmp_path):
    """Python cannot raise a KeyboardInterrupt out of a finaliser: it prints "Exception
    ignored" and goes on. The command line raises it again after the finaliser instead."""
    from xvoe.scenes.generate import GenerateConfig, generate

    data = generate(GenerateConfig("test", pairs=1, size=32, seed=3), tmp_path / "t.h5", workers=1, progress=False)
    mark, model = tmp_path / "finalising", tmp_path / "slow.py"
    model.write_text(SLOW_FINALISER.format(mark=str(mark)))
    score = subprocess.Popen([sys.executable, "-m", "xvoe", "score", "--model", f"{model}:SlowFinaliser", "--data",
                              str(data), "--out", str(tmp_path / "s.csv"), "--no-checks", "--quiet"],
                             stderr=subprocess.PIPE, text=True, start_new_session=True,
                             env=os.environ | {"OMP_NUM_THREADS": "1"})
    deadline = time.monotonic() + 120
    while not mark.exists() and score.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)
    os.killpg(score.pid, signal.SIGINT)
    _, err = score.communicate(timeout=120)
    assert score.returncode == 130 and err.count("\n") == 1, err
    assert "interrupted" in err and not (tmp_path / "s.csv").exists()
