import os
import subprocess
import sys

import pytest

from xvoe import allocator

LOOP = """
import resource, sys
import xvoe, torch
from xvoe import allocator
for _ in range(15):                                  # warm up: the heap grows to a steady size
    x = torch.empty(16 << 20); x.fill_(1.0); del x
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    x = torch.empty(16 << 20); x.fill_(1.0); del x   # 64 MiB: 16,384 pages
print(allocator.tuned(), (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) // 10)
"""


def run_loop(**env: str) -> tuple[bool, int]:
    clean = {k: v for k, v in os.environ.items() if k not in ("GLIBC_TUNABLES", allocator.ENV)
             and not k.startswith("MALLOC_")}
    out = subprocess.run([sys.executable, "-c", LOOP], env=clean | env, capture_output=True, text=True,
                         check=True).stdout.split()
    return out[0] == "True", int(out[1])


@pytest.mark.skipif(not sys.platform.startswith("linux") or allocator._glibc() is None, reason="glibc only")
def test_import_keeps_freed_buffers_in_the_heap():
    tuned, faults = run_loop()
    system, system_faults = run_loop(XVOE_MALLOC="system")
    assert tuned and not system
    assert system_faults > 10_000          # every 64 MiB buffer faulted in again
    assert faults < 500                    # the pages stay


def test_tune_is_idempotent():
    assert allocator.tune() == allocator.tune() == allocator.tuned()
