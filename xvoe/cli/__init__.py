"""The `xvoe` command: one verb per job. Each verb calls the same functions as the notebooks.

The command is a client of the public API, as a notebook is: it sits above `xvoe/__init__.py`,
and nothing in the package imports it. Each verb's parser and what it runs sit together in a
module of this package (one per group of verbs); here they are put in their order and run, each
error, warning and interruption one line. Building the parser imports nothing of torch (nor of
h5py or pymunk), so that `xvoe --help` and `xvoe VERB --help` answer at once
(benchmarks/cli_help.py); what a verb needs is imported when it runs, or when a value is parsed."""
from __future__ import annotations

import argparse
import signal
import sys
import warnings

import xvoe

from ..allocator import tune as tune_allocator
from ..errors import XvoeError
from ..processes import interrupts_held
from .arguments import Parser, check_paths
from .runs import add_pipeline, add_ship
from .scoring import add_explain, add_metrics, add_score, add_verify
from .splits import add_generate, add_import, add_list, add_show
from .train import add_encode, add_train

__all__ = ["build_parser", "main"]

# the verbs, in the order --help lists them: each adds its parser, which names what it runs
_VERBS = (add_generate, add_import, add_show, add_list, add_train, add_encode, add_score, add_explain,
          add_metrics, add_verify, add_pipeline, add_ship)


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="xvoe", description="The X-VoE benchmark and the XPL model.")
    parser.add_argument("--version", action="version", version=f"xvoe {xvoe.__version__}")
    # what a verb sets beside its parser, where it does not: no file written, no kernels pinned
    parser.set_defaults(writes=None, pins_kernels=False)
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB", parser_class=Parser)
    for add in _VERBS:
        add(verbs)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    tune_allocator()        # before any large tensor: freed buffers stay in the heap (xvoe/allocator.py)
    if args.pins_kernels:      # before any kernel runs, so that a seed trains the same bytes anywhere
        with interrupts_held():     # imported here, not for --help: a Ctrl-C inside torch's import aborts the process
            from ..training.distributed import pin_kernels
        pin_kernels()
    previous = signal.signal(signal.SIGTERM, _interrupt)   # so that a kill cleans up as Ctrl-C does
    try:
        if hasattr(args, "device"):     # a device this machine lacks, before any work
            with interrupts_held():
                from ..models.devices import resolve_device
            resolve_device(args.device)
        check_paths(args)
        with warnings.catch_warnings():     # a warning is one line, as an error is
            warnings.showwarning = lambda message, *_: print(f"xvoe {args.verb}: warning: {message}", file=sys.stderr)
            code = args.run(args)
    except XvoeError as error:
        print(f"xvoe {args.verb}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as stop:
        print(f"xvoe {args.verb}: interrupted; {str(stop) or 'nothing half-written was left behind'}",
              file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
    return code or 0


def _interrupt(number: int, frame) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":
    sys.exit(main())
