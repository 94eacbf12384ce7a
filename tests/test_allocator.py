import os
import subprocess
import sys

import pytest

from xvoe import allocator

LOOP = """
import resource, sys, threading
import xvoe, torch
from xvoe import allocator

def loop(size, out):
    for _ in range(15):                              # warm up: the heap grows to a steady size
        x = torch.empty(size); x.fill_(1.0); del x
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(10):
        x = torch.empty(size); x.fill_(1.0); del x
    out.append((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) // 10)

found = []
loop(16 << 20, found)                                # 64 MiB: 16,384 pages
thread = threading.Thread(target=loop, args=(32 << 20, found))   # 128 MiB, more than a thread's own arena holds
thread.start()
thread.join()
print(allocator.tuned(), *found)
"""


def run_loop(**env: str) -> tuple[bool, int, int]:
    clean = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", allocator._ENV)
             and not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", LOOP], env=clean | env, capture_output=True, text=True,
                         check=True).stdout.split()
    return out[0] == "True", int(out[1]), int(out[2])


GLIBC = pytest.mark.skipif(not sys.platform.startswith("linux") or allocator._glibc() is None, reason="glibc only")


@GLIBC
def test_import_leaves_the_allocator_alone_and_a_tuned_parent_is_followed():
    system, system_faults, system_thread_faults = run_loop()
    tuned, faults, thread_faults = run_loop(XVOE_MALLOC="tuned")     # what tune() sets for the workers it starts
    assert tuned and not system
    assert system_faults > 10_000 and system_thread_faults > 20_000     # every buffer faulted in again
    assert faults < 500 and thread_faults < 500                         # the pages stay
    assert not run_loop(XVOE_MALLOC="system")[0]


@GLIBC
def test_the_command_line_tunes():
    code = ("import os; from xvoe.cli import main; from xvoe import allocator; "
            "main(['metrics', 'missing.csv', '--out', 'report']); print(allocator.tuned(), os.environ['XVOE_MALLOC'])")
    clean = {k: v for k, v in os.environ.items() if k != allocator._ENV}
    out = subprocess.run([sys.executable, "-c", code], env=clean, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["True", "tuned"] and "missing.csv: no such file" in out.stderr


def test_tune_is_idempotent():
    assert allocator.tune() == allocator.tune() == allocator.tuned()
