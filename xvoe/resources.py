"""What this machine has, checked before the work: a size or count past it is one line
("needs N GB, has M"), not a traceback at the first allocation, an out-of-memory kill an hour
in, a full disk an hour in, or a million forked processes.

Memory is what the kernel says a new allocation can take now (MemAvailable, under the
cgroup's limit where one is set); cores are those this process may run on. An estimate counts
the large arrays a command holds at once, not every temporary: it refuses what cannot fit,
it does not promise that the rest will.
"""
from __future__ import annotations

import os
import shutil
from pathlib import Path

from .errors import XvoeError

__all__ = ["cores", "available_memory", "gigabytes", "memory_problem", "check_memory", "check_workers",
           "check_disk"]

_CGROUP = Path("/sys/fs/cgroup")


def cores() -> int:
    """The cores this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def available_memory() -> int:
    """Bytes a new allocation can take now: the kernel's MemAvailable (all of the physical
    memory where the kernel does not say), no more than the cgroup leaves."""
    available = _meminfo("MemAvailable") or os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return min(available, _cgroup_room() or available)


def _meminfo(field: str) -> int | None:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            name, _, value = line.partition(":")
            if name == field:
                return int(value.split()[0]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_room() -> int | None:
    """What the cgroup (v2) still lets this process take, where it sets a limit."""
    try:
        limit = (_CGROUP / "memory.max").read_text().strip()
        if limit == "max":
            return None
        return max(0, int(limit) - int((_CGROUP / "memory.current").read_text()))
    except (OSError, ValueError):
        return None


def gigabytes(count: float) -> str:
    """A byte count for a message: in GB, to a precision that shows a small one too."""
    value = count / 1e9
    return f"{value:.3g} GB" if value < 100 else f"{value:,.0f} GB"


def memory_problem(needed: float) -> str | None:
    """"need N GB of memory, ..." where `needed` bytes are more than this machine has free, else None."""
    available = available_memory()
    if needed <= available:
        return None
    return f"need {gigabytes(needed)} of memory, this machine has {gigabytes(available)} free"


def check_memory(needed: float, what: str) -> None:
    """Refuse, in one line before the work, `what` (a phrase: "--particles 10^9") where its
    `needed` bytes are more than this machine has free."""
    if problem := memory_problem(needed):
        raise XvoeError(f"{what} {problem.replace('need ', 'needs ', 1)}")


def check_workers(workers: int, what: str = "--workers") -> None:
    """Refuse, before any process is started, more worker processes than this process has cores."""
    if workers > (count := cores()):
        raise XvoeError(f"{what} {workers} is more than this machine's {count} cores; give at most {count}")


def check_disk(needed: float, out: str | os.PathLike, what: str) -> None:
    """Refuse, in one line before the work, `what` (a phrase: "a split of 10,000 videos") where
    the file system that `out` goes to has less free than the `needed` bytes it surely takes."""
    folder = Path(os.path.abspath(out)).parent
    while not folder.is_dir() and folder != folder.parent:
        folder = folder.parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return      # a folder that cannot be looked at is named by the claim of the output
    if needed > free:
        raise XvoeError(f"{what} needs at least {_disk_amount(needed)} of disk space, {folder} has "
                        f"{_disk_amount(free)} free")


def _disk_amount(count: float) -> str:
    """A byte count in MB below a GB: a small file system (a quota, a memory disk) is common."""
    return f"{count / 1e6:.3g} MB" if count < 1e9 else gigabytes(count)
