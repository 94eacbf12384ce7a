"""Worker processes that end with the process that started them.

A process killed with -9 runs no cleanup, so its pool cannot stop its workers: they would
score or generate on for nobody, and hold what the run held (the resource tracker's pipe,
which keeps multiprocessing's tracker alive; a forked worker's copy of an output's claim).
Each worker therefore asks the kernel to kill it when its parent dies (Linux), or watches
for that itself (elsewhere).
"""
from __future__ import annotations

import _thread
import ctypes
import os
import signal
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

__all__ = ["end_with_parent", "interrupts_held", "interrupts_kept"]

PR_SET_PDEATHSIG = 1        # from <linux/prctl.h>


def end_with_parent(parent: int) -> None:
    """Called first in a worker whose parent is the process `parent`: the worker ends when it does."""
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    else:
        threading.Thread(target=_watch, args=(parent,), daemon=True).start()
    if os.getppid() != parent:      # it died before the request was made: nothing would come
        os._exit(1)


def _watch(parent: int) -> None:
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


@contextmanager
def interrupts_held(workers: bool = False) -> Iterator[None]:
    """Ctrl-C held back while worker processes start in the block: they start with it blocked
    (the mask outlives exec), so a Ctrl-C to the terminal's process group never interrupts a
    worker mid-import with a traceback of its own, and their parent, which ends them, gets one
    that came meanwhile as the block ends. `workers`: processes start in the block, so
    multiprocessing's resource tracker starts first, outside it (starting, it unblocks Ctrl-C
    in this process, and the workers started after it would get it)."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    if workers:
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def interrupts_kept() -> None:
    """A Ctrl-C whose handler runs inside a finaliser (a weakref callback, a `__del__`) raises
    there, where Python can only print "Exception ignored ... KeyboardInterrupt" and go on as
    if none had come: it is sent again, to be raised in the code that runs next, and nothing is
    printed. Once the handler ignores Ctrl-C (the outputs are written), it is dropped."""
    shown = sys.unraisablehook

    def hook(unraisable: Any) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            _thread.start_new_thread(_interrupt_soon, ())
            return
        shown(unraisable)

    sys.unraisablehook = hook


def _interrupt_soon() -> None:
    """Ctrl-C again in a moment, from another thread: raised from the hook that saw it ignored,
    it would be ignored again."""
    time.sleep(0.01)
    _thread.interrupt_main(signal.SIGINT)       # the handler in force runs (none where Ctrl-C is ignored)
