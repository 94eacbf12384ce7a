"""`python -m xvoe` (and the `xvoe` script): the command line, xvoe.cli.main. A Ctrl-C
while it starts (torch takes seconds to import), before any file is read or written, is one
line and exit code 130, as one during the work is; one once the work is done changes nothing."""
import os
import signal
import sys


def _interrupted_at_start(number: int, frame) -> None:
    sys.stderr.write("xvoe: interrupted as it started; nothing was written\n")
    os._exit(130)


signal.signal(signal.SIGINT, _interrupted_at_start)
from .cli import main  # noqa: E402 - after the handler, which covers the import
from .processes import interrupts_kept  # noqa: E402

interrupts_kept()

signal.signal(signal.SIGINT, signal.default_int_handler)


def run() -> int:
    try:
        code = main()
    except KeyboardInterrupt:       # while the arguments were read, before any work
        sys.stderr.write("xvoe: interrupted; nothing was written\n")
        code = 130
    signal.signal(signal.SIGINT, signal.SIG_IGN)      # the outputs are written: a Ctrl-C now changes nothing
    return code


if __name__ == "__main__":
    sys.exit(run())
