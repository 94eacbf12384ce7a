"""Interruptions leave nothing broken: tests/interruptions.py, a Ctrl-C once per command
(generate, encode, score in two workers, metrics) at a seeded moment, finds no process left
behind, no broken file under a final name, no traceback, and a rerun equal to the uninterrupted
run. The harder case of the two signals and the training run are left to the full run that
docs/results.md ("Interruptions") gives, 20 per command, to keep the suite within its time."""
import json
import os
import subprocess
import sys
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
