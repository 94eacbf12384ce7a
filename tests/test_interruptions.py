"""Interruptions leave nothing broken: tests/interruptions.py, once per signal and command
(generate, encode, score in two workers, a tiny training run, metrics) at seeded moments, finds
no process left behind, no broken file under a final name, no traceback on Ctrl-C, and a rerun
equal to the uninterrupted run. docs/results.md ("Interruptions") gives a run of 20 per command."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads processes from /proc")
def test_random_interruptions_leave_nothing_broken_and_a_rerun_makes_the_same_bytes(tmp_path):
    script = Path(__file__).with_name("interruptions.py")
    done = subprocess.run([sys.executable, str(script), str(tmp_path), "--times", "1", "--seed", "1"],
                          capture_output=True, text=True, timeout=900, env=os.environ | {"OMP_NUM_THREADS": "1"})
    reports = [json.loads(line) for line in done.stdout.splitlines()]
    assert [r["command"] for r in reports] == ["generate", "encode", "score", "train", "metrics"], done.stderr[-2000:]
    for report in reports:
        for how in ("SIGKILL", "SIGINT"):
            assert report[how]["trials"] == 1 and report[how]["problems"] == [], report
    assert done.returncode == 0
