"""The `xvoe` command: one verb per job. Each verb calls the same functions as the notebooks."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from .errors import XvoeError


class _Parser(argparse.ArgumentParser):
    """argparse, but a bad argument gives one line (and exit code 2), not the whole usage."""

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _shard(text: str) -> tuple[int, int]:
    try:
        index, count = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N (part I of N, counted from 0), not {text!r}") from None
    return index, count


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, not {value}")
    return value


def _default_workers() -> int:
    return max(1, min(8, len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1))


def cmd_generate(args: argparse.Namespace) -> None:
    from .generate import GenerateConfig, generate, merge

    if args.merge:
        out = merge(args.merge, args.out, overwrite=args.overwrite, progress=not args.quiet)
    else:
        if args.split is None:
            raise XvoeError("--split is required (train or test) unless --merge is given")
        config = GenerateConfig(split=args.split, videos=args.videos, pairs=args.pairs, size=args.size,
                                frames=args.frames, seed=args.seed)
        out = generate(config, args.out, workers=args.workers, shard=args.shard,
                       overwrite=args.overwrite, progress=not args.quiet)
    print(out)


def cmd_show(args: argparse.Namespace) -> None:
    from .viz import show

    out = args.out or Path(args.file).with_suffix(f".{args.index}.png").name
    print(show(args.file, args.index, out))


def _not_built(verb: str):
    def run(args: argparse.Namespace) -> None:
        raise XvoeError(f"'xvoe {verb}' is not built yet in this version of xvoe")
    return run


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="xvoe", description="The X-VoE benchmark and the XPL model.")
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB", parser_class=_Parser)

    gen = verbs.add_parser("generate", help="generate a split of the benchmark into an HDF5 file",
                           description="Simulate, render and store a split. Same seed, same bytes, "
                                       "whatever the number of workers.")
    gen.add_argument("--split", choices=("train", "test"), help="training videos or test pairs")
    gen.add_argument("--out", required=True, help="the HDF5 file to write")
    gen.add_argument("--videos", type=_positive, default=10_000, help="training videos (default 10000)")
    gen.add_argument("--pairs", type=_positive, default=1_000, help="test pairs per setting (default 1000)")
    gen.add_argument("--size", type=_positive, default=64, help="frame size in pixels (default 64)")
    gen.add_argument("--frames", type=_positive, default=15, help="frames per video (default 15)")
    gen.add_argument("--seed", type=int, default=0, help="the seed every random choice flows from")
    gen.add_argument("--workers", type=_positive, default=_default_workers(), help="worker processes")
    gen.add_argument("--shard", type=_shard, default=(0, 1), metavar="I/N",
                     help="write only part I of N (counted from 0); join the parts with --merge")
    gen.add_argument("--merge", nargs="+", metavar="PART", help="join shard files into --out")
    gen.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    gen.set_defaults(run=cmd_generate)

    show = verbs.add_parser("show", help="contact sheet (PNG) or animation (GIF) of a video or test pair",
                            description="Frames in a row: RGB, depth and slot ids; a test pair's members "
                                        "one above the other with the event frame outlined.")
    show.add_argument("file", help="an xvoe HDF5 file")
    show.add_argument("--index", type=int, default=0, help="video index (a test video shows its pair)")
    show.add_argument("--out", help="fig.png or anim.gif (default: FILE.INDEX.png here)")
    show.set_defaults(run=cmd_show)

    later = {
        "train": "train a stage of the XPL model (perception, encode, xpl, plato)",
        "score": "score test videos with a trained model (surprise per video)",
        "metrics": "comparative, holistic and relative metrics with figures",
        "pipeline": "generate, train, score and report, end to end",
        "explain": "draw the model's explanation of what is behind the wall",
    }
    for verb, text in later.items():
        sub = verbs.add_parser(verb, help=f"{text} (not built yet)", description=f"{text}. Not built yet.")
        sub.set_defaults(run=_not_built(verb))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and args.verb in ("generate", "show"):
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    try:
        args.run(args)
    except XvoeError as error:
        print(f"xvoe {args.verb}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"xvoe {args.verb}: interrupted; nothing half-written was left behind", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
