"""The verbs of a split file: `generate` and `import` write one, `show` and `list` read one.

Each verb's parser sits beside what it runs; both call the public API, as a notebook does."""
from __future__ import annotations

import argparse
from pathlib import Path

import xvoe

from ..domains import DISPLAY_SIZE, NON_NEGATIVE, PICTURE_SIZE
from ..errors import XvoeError
from .arguments import Writes, default_workers, flag, generate_field, output_of, positive, shard

__all__ = ["add_generate", "add_import", "add_list", "add_show", "format_videos"]


def add_generate(verbs) -> None:
    gen = verbs.add_parser("generate", help="generate a split of the benchmark into an HDF5 file",
                           description="Simulate, render and store a split. Same seed, same bytes, "
                                       "whatever the number of workers.")
    gen.add_argument("--split", choices=("train", "test"), help="training videos or test pairs")
    gen.add_argument("--out", required=True, help="the HDF5 file to write")
    gen.add_argument("--videos", type=generate_field("videos"), default=10_000,
                     help="training videos (default 10000)")
    gen.add_argument("--pairs", type=generate_field("pairs"), default=1_000,
                     help="test pairs per setting (default 1000)")
    gen.add_argument("--size", type=generate_field("size"), default=32,
                     help="frame size in pixels (default 32, what the default recipe's models read)")
    gen.add_argument("--frames", type=generate_field("frames"), default=15,
                     help="frames per video (default 15)")
    gen.add_argument("--seed", type=generate_field("seed"), default=0,
                     help="the seed every random choice flows from")
    gen.add_argument("--workers", type=positive, default=default_workers(), help="worker processes")
    gen.add_argument("--shard", type=shard, default=(0, 1), metavar="I/N",
                     help="write only part I of N (counted from 0); join the parts with --merge")
    gen.add_argument("--merge", nargs="+", metavar="PART", help="join shard files into --out")
    gen.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    gen.set_defaults(run=_run_generate, writes=Writes(("merge",), "out", (".h5",)))


def _run_generate(args: argparse.Namespace) -> None:
    if args.merge:
        if args.split is not None:
            raise XvoeError("--merge joins shards as they were generated; leave out --split")
        out = xvoe.merge(args.merge, args.out, overwrite=args.overwrite, progress=not args.quiet)
    else:
        if args.split is None:
            raise XvoeError("--split is required (train or test) unless --merge is given")
        config = xvoe.GenerateConfig(split=args.split, videos=args.videos, pairs=args.pairs, size=args.size,
                                     frames=args.frames, seed=args.seed)
        out = xvoe.generate(config, args.out, workers=args.workers, shard=args.shard,
                            overwrite=args.overwrite, progress=not args.quiet)
    print(out)


def add_import(verbs) -> None:
    imp = verbs.add_parser("import", help="import the paper's released X-VoE TFRecords into an HDF5 file",
                           description="Read the released X-VoE split (gzip TFRecords, no TensorFlow needed) and "
                                       "write it in xvoe's HDF5 schema: RGBD frames, slot ids from the masks and, "
                                       "for the test split, the labels as the reference's metrics lay them out "
                                       "(docs/benchmark.md, \"The released X-VoE and this one\").")
    imp.add_argument("source", help="the downloaded X-VoE directory (holding test/ and train/)")
    imp.add_argument("--split", choices=("train", "test"), required=True,
                     help="test: test/SCENARIO/eval-part-NNN.tfrecord; train: train/train-part-NNN.tfrecord")
    imp.add_argument("--out", required=True, help="the HDF5 file to write")
    imp.add_argument("--size", type=positive,
                     help="resample to this many pixels a side, a divisor of the release's 128 (32 for the shipped "
                          "models): RGB by area, ids and depth by the label covering most of a block, no seen "
                          "object lost (default: as released)")
    imp.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    imp.add_argument("--quiet", action="store_true", help="no progress bar")
    imp.set_defaults(run=_run_import, writes=Writes(("source",), "out", (".h5",)))


def _run_import(args: argparse.Namespace) -> None:
    print(xvoe.import_released(args.source, args.split, args.out, size=args.size, overwrite=args.overwrite,
                               progress=not args.quiet))


def add_show(verbs) -> None:
    show = verbs.add_parser("show", help="contact sheet (PNG), animation (GIF) or video (MP4) of a video or pair",
                            description="Frames in a row: the scene at --display-size above what the model "
                                        "sees, its RGB, depth and slot ids; a test pair's members one above the "
                                        "other with the event frame outlined.")
    show.add_argument("file", help="an xvoe HDF5 file")
    show.add_argument("--index", type=flag(int, NON_NEGATIVE, "index"), default=0,
                      help="video index (a test video shows its pair)")
    show.add_argument("--out", help="fig.png, anim.gif or pair.mp4 (default: FILE.INDEX.png here)")
    show.add_argument("--scores", help="mp4: a scores CSV of xvoe score, whose surprise curves play under the pair")
    show.add_argument("--display-size", type=flag(int, PICTURE_SIZE, "display-size"), default=DISPLAY_SIZE,
                      help=f"pixels a side of the scene drawn above the model's frames (default {DISPLAY_SIZE})")
    show.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    show.add_argument("--quiet", action="store_true", help="accepted as by every verb; show draws no progress bar")
    show.set_defaults(run=_run_show, writes=Writes(("file", "scores"), "out", (".png", ".gif", ".mp4"),
                                                   default=_default_sheet))


def _default_sheet(args: argparse.Namespace) -> Path:
    """FILE.INDEX.png, in the current directory."""
    return Path(Path(args.file).with_suffix(f".{args.index}.png").name)


def _run_show(args: argparse.Namespace) -> None:
    print(xvoe.show(args.file, args.index, output_of(args), overwrite=args.overwrite, scores=args.scores,
                    display_size=args.display_size))


def add_list(verbs) -> None:
    listing = verbs.add_parser("list", help="list a test split's videos by scenario, setting, member and pair",
                               description="One line per video of a test split: its index (what show, explain "
                                           "and the notebooks take), scenario, setting, pair, member and whether "
                                           "it is possible; the filters given narrow the list.")
    listing.add_argument("file", help="a test split (HDF5)")
    # the scenario registry's names, written out: the registry loads pymunk, which --help leaves out
    # (tests/test_conventions.py keeps them in step)
    listing.add_argument("--scenario", help="collision, blocking, permanence or continuity")
    listing.add_argument("--setting", help="S1, S2 or S3")
    listing.add_argument("--member", type=flag(int, NON_NEGATIVE, "member"), help="0 (expected) or 1")
    listing.add_argument("--pair", type=flag(int, NON_NEGATIVE, "pair"), help="the pair's number")
    listing.add_argument("--quiet", action="store_true", help="the indices alone, one a line (for a shell loop)")
    listing.set_defaults(run=_run_list)


def _run_list(args: argparse.Namespace) -> None:
    with xvoe.open_dataset(args.file) as file:
        rows = xvoe.list_videos(file, args.scenario, args.setting, args.member, args.pair)
    print("\n".join(str(row["index"]) for row in rows) if args.quiet else format_videos(rows))


def format_videos(rows: list[dict]) -> str:
    """`list_videos` rows as an aligned table, a header first."""
    lines = [("index", "scenario", "setting", "pair", "member", "")]
    lines += [(str(r["index"]), r["scenario"], r["setting"], str(r["pair"]), str(r["member"]),
               "possible" if r["possible"] else "impossible") for r in rows]
    widths = [max(len(line[i]) for line in lines) for i in range(len(lines[0]))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(line, widths)).rstrip() for line in lines)
