"""Keep freed tensor memory in the process instead of handing it back to the system.

glibc serves blocks above its mmap threshold (128 KiB at first, raised as blocks are freed,
at most 32 MiB) with fresh mmap and gives them back on free; it also trims the top of its
heap beyond 128 KiB. A training or scoring step allocates and frees the same large buffers
every time, so every step faults all their pages in again: a quarter of the CPU time went to
the kernel. `tune()` raises both thresholds so the heap keeps those pages; the process's
memory stays at its peak, which it reaches anyway on the next step. It also keeps every thread
on the one main arena: another thread's arena is made of 64 MiB heaps, so a larger block
allocated there (by a torch worker thread, or a thread of the user's) is mapped and unmapped
each time whatever the thresholds say.

The settings are the whole process's, so only the command line calls `tune()` (first thing
after reading its arguments); `import xvoe` leaves the allocator as it is, since a notebook's
other code runs under it too. A notebook or script that wants them calls
`xvoe.allocator.tune()` before its first large tensor (a thread that allocated before the call
keeps its arena). `tune()` sets XVOE_MALLOC=tuned in the environment, and `import xvoe` in a
process started with it (the spawned workers of scoring, training and the pipeline; torchrun
workers of a tuned launcher) tunes too; forked workers inherit the settings. XVOE_MALLOC=system,
or a GLIBC_TUNABLES or MALLOC_*_ setting of the user's own, keeps glibc's settings throughout.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["tune", "follow", "tuned"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_M_ARENA_MAX = -8
_MMAP_THRESHOLD = 1 << 30            # blocks up to 1 GiB come from the heap, whose pages stay
_TRIM_THRESHOLD = (1 << 31) - 1      # the largest int: free memory at the top of the heap stays
_ARENA_MAX = 1                       # one arena (a lock shared by a few threads costs nothing measurable)
_ENV = "XVOE_MALLOC"                 # "system": leave glibc's defaults; "tuned": tune at import (set by tune())

_state: dict[str, bool] = {}


def _user_set() -> bool:
    """Whether the user chose malloc settings of their own (or asked for the system's)."""
    return (os.environ.get(_ENV, "").strip().lower() == "system"
            or "glibc.malloc." in os.environ.get("GLIBC_TUNABLES", "")
            or any(name in os.environ for name in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_",
                                                    "MALLOC_TOP_PAD_", "MALLOC_MMAP_MAX_", "MALLOC_ARENA_MAX")))


def _glibc() -> ctypes.CDLL | None:
    """This process's C library if it is glibc (not on macOS, Windows or musl)."""
    try:
        libc = ctypes.CDLL(None)
        found = hasattr(libc, "gnu_get_libc_version") and hasattr(libc, "mallopt")    # only glibc has both
    except (OSError, TypeError):
        return None
    return libc if found else None


def tune() -> bool:
    """Raise glibc's mmap and trim thresholds and keep one arena, once per process; True if done.

    False where the C library is not glibc or the user set malloc options (XVOE_MALLOC=system,
    GLIBC_TUNABLES, MALLOC_*_). Calling it again changes nothing."""
    if "tuned" not in _state:
        tuned = False
        if not _user_set():
            libc = _glibc()
            if libc is not None:
                libc.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
                libc.mallopt.restype = ctypes.c_int
                # trim first: setting either one turns glibc's dynamic threshold off
                tuned = all([libc.mallopt(_M_TRIM_THRESHOLD, _TRIM_THRESHOLD),
                             libc.mallopt(_M_MMAP_THRESHOLD, _MMAP_THRESHOLD),
                             libc.mallopt(_M_ARENA_MAX, _ARENA_MAX)])
        if tuned:
            os.environ[_ENV] = "tuned"       # the workers this process starts tune as they import xvoe
        _state["tuned"] = tuned
    return _state["tuned"]


def follow() -> bool:
    """Tune if the process that started this one did (XVOE_MALLOC=tuned); what `import xvoe` calls."""
    return os.environ.get(_ENV, "").strip().lower() == "tuned" and tune()


def tuned() -> bool:
    """Whether `tune()` raised the thresholds in this process."""
    return _state.get("tuned", False)
