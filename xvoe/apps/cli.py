"""The `xvoe` command: one verb per job. Each verb calls the same functions as the notebooks.

Building the parser imports nothing of torch (nor of h5py or pymunk), so that `xvoe --help` and
`xvoe VERB --help` answer at once (benchmarks/cli_help.py); what a verb needs is imported when
it runs, or when a value is parsed."""
from __future__ import annotations

import argparse
import importlib
import re
import signal
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import xvoe

from ..allocator import tune as tune_allocator
from ..domains import (
    DEVICES,
    DISPLAY_SIZE,
    NON_NEGATIVE,
    PICTURE_SIZE,
    POSITIVE,
    SEED,
    TIME_LIMIT,
    Domain,
    check_number,
)
from ..errors import XvoeError
from ..models.config import parse_field, parse_value
from ..models.nll import InferenceConfig
from ..outputs import claim_directory, claim_file, claim_scope, refuse_overlap
from ..processes import interrupts_held
from ..resources import cores
from ..training.config import DEFAULT_RECIPE, RECIPE_NAMES, TrainConfig

# what the verbs need of the layers that import torch, loaded when a verb runs or a value is
# parsed: building the parser imports none of them, so that --help answers at once
_LATE = {"parse_device": "xvoe.models.devices", "resolve_device": "xvoe.models.devices",
         "check_focus": "xvoe.training.data", "pin_kernels": "xvoe.training.loop",
         "encoded_cache": "xvoe.training.xpl"}


def _late(name: str) -> Callable[..., Any]:
    with interrupts_held():     # a Ctrl-C inside torch's extension modules' import aborts the process
        return getattr(importlib.import_module(_LATE[name]), name)


class _Parser(argparse.ArgumentParser):
    """argparse, but a bad argument gives one line (and exit code 2), not the whole usage."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # a value such as -1/2 (for --shard) is a value to check, not an unknown option
        self._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-\d+/\d+$")

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _shard(text: str) -> tuple[int, int]:
    try:
        index, count = (int(v) for v in text.split("/"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N (part I of N, counted from 0), not {text!r}") from None
    if not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"expected I/N with 0 <= I < N, not {text!r}")
    return index, count


def _recipe_names() -> str:
    """The recipes for a --help line, the default (the shipped models') named first."""
    others = [name for name in RECIPE_NAMES if name != DEFAULT_RECIPE]
    return f"{DEFAULT_RECIPE} (default, the shipped models'), " + ", ".join(others)


def _positive(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, not {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a number >= 1, not {value}")
    return value


def _argument(parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """An argparse type that refuses, in one line, what `parse` refuses: before any work."""
    def checked(text: str) -> Any:
        try:
            return parse(text)
        except XvoeError as error:
            raise argparse.ArgumentTypeError(str(error)) from None
    return checked


def _flag(kind: type, domain: Domain, name: str) -> Callable[[str], Any]:
    """The argparse type of a flag of no config field: a `kind` in `domain`, refused naming `name`."""
    return _argument(lambda text: check_number(domain, name, parse_value(kind, text)))


def _field(cls: type, name: str) -> Callable[[str], Any]:
    """The argparse type of a flag that sets field `name` of config `cls`: its type and declared domain."""
    return _argument(lambda text: parse_field(cls, name, text))


def _generate_field(name: str) -> Callable[[str], Any]:
    """`_field` of GenerateConfig, whose module (h5py, pymunk) loads when a value is parsed, not for --help."""
    return _argument(lambda text: parse_field(xvoe.GenerateConfig, name, text))


def _device(text: str) -> str:
    return str(_late("parse_device")(text))


def _add_device(parser: argparse.ArgumentParser, what: str) -> None:
    # a device name is checked here; whether this machine has it, first thing in `main`
    parser.add_argument("--device", type=_argument(_device), default="cpu",
                        help=f"where {what} runs: {DEVICES} (default cpu)")


def _default_workers() -> int:
    return min(8, cores())


def cmd_generate(args: argparse.Namespace) -> None:
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


def cmd_import(args: argparse.Namespace) -> None:
    print(xvoe.import_released(args.source, args.split, args.out, size=args.size, overwrite=args.overwrite,
                               progress=not args.quiet))


def cmd_show(args: argparse.Namespace) -> None:
    print(xvoe.show(args.file, args.index, output_of(args), overwrite=args.overwrite, scores=args.scores,
                    display_size=args.display_size))


def cmd_list(args: argparse.Namespace) -> None:
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


def cmd_score(args: argparse.Namespace) -> None:
    with interrupts_held():     # imported here, not for --help: a Ctrl-C inside torch's import aborts the process
        from xvoe.inference.score import nll_defaults_note, nll_settings

        from ..evaluation.score_headers import score_header
        from ..evaluation.shards import merge_scores
        from .verbs import score
    if args.merge:
        if args.model or args.data or args.shard != (0, 1) or args.cache:
            raise XvoeError("--merge joins score files as they were written; "
                            "leave out --model, --data, --shard and --cache")
        print(merge_scores(args.merge, args.out, overwrite=args.overwrite))
        return
    if args.model is None or args.data is None:
        raise XvoeError("--model and --data are required (unless --merge joins the parts of a sharded run)")
    table = score(args.model, args.data, args.out, surprise=args.surprise, particles=args.particles, seed=args.seed,
                  nll_settings=nll_settings(args.nll_set), how=args.aggregate, shard=args.shard,
                  videos_per_batch=args.batch, workers=args.workers, checks=not args.no_checks,
                  overwrite=args.overwrite, progress=not args.quiet, device=args.device, cache=args.cache or True,
                  time_limit=args.time_limit)
    note = nll_defaults_note(score_header(table.path)) if args.surprise != "mse" else None
    if note:
        print(f"xvoe score: warning: {note}", file=sys.stderr)
    print(table)


@claim_scope()
def cmd_explain(args: argparse.Namespace) -> None:
    claim_file(args.out, args.overwrite)
    explanation = xvoe.explain(args.model, args.data, args.index, surprise=args.surprise, particles=args.particles,
                               seed=args.seed, explanation=args.explanation, display_size=args.display_size,
                               device=args.device)
    print(xvoe.save_figure(xvoe.plot_explanation(explanation), args.out))


def cmd_pipeline(args: argparse.Namespace) -> None:
    models = tuple(m.strip() for m in args.models.split(",") if m.strip())
    print(xvoe.run_pipeline(xvoe.PipelineConfig(args.out, args.recipe, args.train_videos, args.pairs, models, args.seed,
                                      args.workers, not args.quiet, args.jobs, args.train_processes,
                                      args.device)))


def cmd_metrics(args: argparse.Namespace) -> None:
    for path in xvoe.report(args.scores, args.out, rounds=args.rounds, seed=args.seed, data=args.data,
                            overwrite=args.overwrite, table=args.table):
        print(path)


def cmd_verify(args: argparse.Namespace) -> int:
    with interrupts_held():     # imported here, not for --help: a Ctrl-C inside torch's import aborts the process
        from .verify import verify
    found = verify(args.scores, rows=args.rows, data=args.data, seed=args.seed, model=args.model)
    if not (args.quiet and found.matches):     # quiet: the verdict alone, unless a row is named in it
        print("\n".join(found.lines))
    print("every row matches its curves and labels, and every row scored again matches the file" if found.matches
          else "some rows do not match the file")
    return 0 if found.matches else 1


def cmd_ship(args: argparse.Namespace) -> None:
    for path in xvoe.ship(args.run_dir, args.out):
        print(path if args.quiet else f"{path}  {path.stat().st_size / 2**20:.1f} MB")


# --- training: one subcommand per stage, each with its own flags --------------------------

def _train_overrides(args: argparse.Namespace, stage: str) -> tuple[dict, dict]:
    """The TrainConfig fields the flags and `--set` change (None: keep the recipe's), and the model's."""
    check_focus = _late("check_focus")
    train, model = xvoe.stage_settings(stage, args.set)
    flags = {"steps": args.steps, "max_minutes": args.minutes, "batch_size": args.batch_size, "seed": args.seed,
             "max_videos": args.max_videos, "lr": args.lr, "focus_group": getattr(args, "focus_group", None),
             "focus_share": getattr(args, "focus_share", None)}
    train = {**train, **{k: v for k, v in flags.items() if v is not None}}
    # a fresh run starts from its recipe's focus; where the run's config is not known yet (a resumed
    # run, the proposal stage's recipe from its xpl.pt), the names alone are checked here
    if args.resume or not hasattr(args, "recipe"):
        check_focus(train.get("focus_group", ""))
    else:
        base = xvoe.recipe(args.recipe).training(stage)
        check_focus(train.get("focus_group", base.focus_group), train.get("focus_share", base.focus_share))
    return train, model


def cmd_train(args: argparse.Namespace) -> None:
    stage = args.stage
    claim_directory(args.out, make=False)       # a bad --out is found before any data is read
    train, model = _train_overrides(args, stage)
    common = {"resume": args.resume, "overwrite": args.overwrite, "progress": not args.quiet, "device": args.device}
    reads = xvoe.STAGES[stage].reads
    if reads != "xpl" and args.data is None and not args.resume:
        raise XvoeError("--data is required to start a run (the training split, or for xpl and plato its latent "
                        "cache)")
    if reads == "xpl":
        print(xvoe.train_proposal(args.out, args.data, model_overrides=model, **common, **train))
        return
    common |= {"recipe_name": args.recipe, "model_overrides": model}
    if stage == "perception":
        print(xvoe.train_perception(args.data, args.out, **common, **train))
    elif stage == "phydnet":
        print(xvoe.train_phydnet(args.data, args.out, **common, **train))
    else:
        cache = None
        if args.data:
            cache = xvoe.latent_cache_for(args.data, args.out, args.perception, progress=not args.quiet,
                                          device=args.device)
        print(xvoe.train_xpl(cache, args.out, stage=stage, stop_gradient=not args.no_stop_gradient, **common,
                             **train))


def cmd_encode(args: argparse.Namespace) -> None:
    print(xvoe.encode_split(args.model or args.out, args.data, output_of(args), overwrite=args.overwrite,
                            progress=not args.quiet, device=args.device))


def add_train_parser(verbs) -> None:
    train = verbs.add_parser(
        "train", help="train one stage of the XPL model, or a baseline, into a run directory",
        description="xvoe train STAGE: one stage into a run directory (STAGE.pt checkpoint and STAGE.csv "
                    "losses). Each stage runs unchanged under torchrun --nproc_per_node N.")
    stages = train.add_subparsers(dest="stage", required=True, metavar="STAGE", parser_class=_Parser)
    for stage, entry in xvoe.STAGES.items():
        parser = stages.add_parser(stage, help=entry.help, description=f"Train {entry.help}.")
        if entry.reads == "xpl":
            parser.add_argument("--data", help="the latent cache (default: the one the run's xpl stage used)")
        elif entry.reads == "latents":
            parser.add_argument("--data", help="the latent cache, or a training split to encode into one first")
            parser.add_argument("--perception", help="the perception run that encodes a split (default: --out)")
        else:
            parser.add_argument("--data", help="the training split file (HDF5)")
        parser.add_argument("--out", required=True, help="the run directory")
        if entry.reads != "xpl":
            parser.add_argument("--recipe", default=DEFAULT_RECIPE,
                                help=f"the recipe whose sizes and settings start the run: {_recipe_names()}")
        parser.add_argument("--steps", type=_field(TrainConfig, "steps"), help="training steps (default: the recipe's)")
        parser.add_argument("--minutes", type=_flag(float, POSITIVE, "minutes"),
                            help="stop after this many minutes of training")
        parser.add_argument("--batch-size", type=_field(TrainConfig, "batch_size"),
                            help="videos per step over all processes" if stage == "phydnet"
                            else "frames per step over all processes" if stage == "perception"
                            else "videos per step")
        parser.add_argument("--max-videos", type=_positive, help="use only the first N videos of --data")
        parser.add_argument("--seed", type=_field(TrainConfig, "seed"),
                            help="the seed of initialisation and batches (default 0)")
        parser.add_argument("--lr", type=_field(TrainConfig, "lr"),
                            help="peak learning rate (default: the recipe's; it halves every decay_steps)")
        if stage != "perception":      # the others draw videos, which can come from one group
            parser.add_argument("--focus-group", help="draw --focus-share of each batch from this group's training "
                                                      "videos with a wall (e.g. permanence; several: "
                                                      "permanence,continuity)")
            parser.add_argument("--focus-share", type=_field(TrainConfig, "focus_share"),
                                help="the share of each batch from --focus-group")
        if entry.reads == "latents":
            parser.add_argument("--no-stop-gradient", action="store_true",
                                help="let the dynamics loss reach Transformer 1 through the target too")
        parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                            help="change any field of a fresh run's TrainConfig or model config (repeatable; "
                                 "train.FIELD or model.FIELD where both have it; model.dynamics.hidden=256 "
                                 "reaches a nested one); a resumed run keeps its network")
        parser.add_argument("--resume", action="store_true", help="continue the run in --out where it stopped")
        parser.add_argument("--overwrite", action="store_true", help="start again over an existing run")
        parser.add_argument("--quiet", action="store_true", help="no progress bar")
        _add_device(parser, "it trains")
        parser.set_defaults(run=cmd_train)

    encode = verbs.add_parser("encode", help="encode a split into a latent cache with a trained perception module",
                              description="Encode every frame of a split into a latent cache (HDF5), which the "
                                          "xpl, plato and proposal stages train on.")
    encode.add_argument("--data", required=True, help="the split file to encode")
    encode.add_argument("--out", required=True, help="the run directory (its perception.pt unless --model)")
    encode.add_argument("--model", help="a perception run or checkpoint (default: --out)")
    encode.add_argument("--cache", help="the latent cache to write (default: OUT/latents-DATA.h5; of a test split, "
                                        "beside it, DATA.latents-PERCEPTION.h5, where xvoe score reads it)")
    encode.add_argument("--overwrite", action="store_true", help="replace the cache if it exists")
    encode.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_device(encode, "the perception module")
    encode.set_defaults(run=cmd_encode)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="xvoe", description="The X-VoE benchmark and the XPL model.")
    parser.add_argument("--version", action="version", version=f"xvoe {xvoe.__version__}")
    verbs = parser.add_subparsers(dest="verb", required=True, metavar="VERB", parser_class=_Parser)

    gen = verbs.add_parser("generate", help="generate a split of the benchmark into an HDF5 file",
                           description="Simulate, render and store a split. Same seed, same bytes, "
                                       "whatever the number of workers.")
    gen.add_argument("--split", choices=("train", "test"), help="training videos or test pairs")
    gen.add_argument("--out", required=True, help="the HDF5 file to write")
    gen.add_argument("--videos", type=_generate_field("videos"), default=10_000,
                     help="training videos (default 10000)")
    gen.add_argument("--pairs", type=_generate_field("pairs"), default=1_000,
                     help="test pairs per setting (default 1000)")
    gen.add_argument("--size", type=_generate_field("size"), default=32,
                     help="frame size in pixels (default 32, what the default recipe's models read)")
    gen.add_argument("--frames", type=_generate_field("frames"), default=15,
                     help="frames per video (default 15)")
    gen.add_argument("--seed", type=_generate_field("seed"), default=0,
                     help="the seed every random choice flows from")
    gen.add_argument("--workers", type=_positive, default=_default_workers(), help="worker processes")
    gen.add_argument("--shard", type=_shard, default=(0, 1), metavar="I/N",
                     help="write only part I of N (counted from 0); join the parts with --merge")
    gen.add_argument("--merge", nargs="+", metavar="PART", help="join shard files into --out")
    gen.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    gen.add_argument("--quiet", action="store_true", help="no progress bar")
    gen.set_defaults(run=cmd_generate)

    imp = verbs.add_parser("import", help="import the paper's released X-VoE TFRecords into an HDF5 file",
                           description="Read the released X-VoE split (gzip TFRecords, no TensorFlow needed) and "
                                       "write it in xvoe's HDF5 schema: RGBD frames, slot ids from the masks and, "
                                       "for the test split, the labels as the reference's metrics lay them out "
                                       "(docs/benchmark.md, \"The released X-VoE and this one\").")
    imp.add_argument("source", help="the downloaded X-VoE directory (holding test/ and train/)")
    imp.add_argument("--split", choices=("train", "test"), required=True,
                     help="test: test/SCENARIO/eval-part-NNN.tfrecord; train: train/train-part-NNN.tfrecord")
    imp.add_argument("--out", required=True, help="the HDF5 file to write")
    imp.add_argument("--size", type=_positive,
                     help="resample to this many pixels a side, a divisor of the release's 128 (32 for the shipped "
                          "models): RGB by area, ids and depth by the label covering most of a block, no seen "
                          "object lost (default: as released)")
    imp.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    imp.add_argument("--quiet", action="store_true", help="no progress bar")
    imp.set_defaults(run=cmd_import)

    show = verbs.add_parser("show", help="contact sheet (PNG), animation (GIF) or video (MP4) of a video or pair",
                            description="Frames in a row: the scene at --display-size above what the model "
                                        "sees, its RGB, depth and slot ids; a test pair's members one above the "
                                        "other with the event frame outlined.")
    show.add_argument("file", help="an xvoe HDF5 file")
    show.add_argument("--index", type=_flag(int, NON_NEGATIVE, "index"), default=0,
                      help="video index (a test video shows its pair)")
    show.add_argument("--out", help="fig.png, anim.gif or pair.mp4 (default: FILE.INDEX.png here)")
    show.add_argument("--scores", help="mp4: a scores CSV of xvoe score, whose surprise curves play under the pair")
    show.add_argument("--display-size", type=_flag(int, PICTURE_SIZE, "display-size"), default=DISPLAY_SIZE,
                      help=f"pixels a side of the scene drawn above the model's frames (default {DISPLAY_SIZE})")
    show.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    show.add_argument("--quiet", action="store_true", help="accepted as by every verb; show draws no progress bar")
    show.set_defaults(run=cmd_show)

    listing = verbs.add_parser("list", help="list a test split's videos by scenario, setting, member and pair",
                               description="One line per video of a test split: its index (what show, explain "
                                           "and the notebooks take), scenario, setting, pair, member and whether "
                                           "it is possible; the filters given narrow the list.")
    listing.add_argument("file", help="a test split (HDF5)")
    listing.add_argument("--scenario", help="collision, blocking, permanence or continuity")
    listing.add_argument("--setting", help="S1, S2 or S3")
    listing.add_argument("--member", type=_flag(int, NON_NEGATIVE, "member"), help="0 (expected) or 1")
    listing.add_argument("--pair", type=_flag(int, NON_NEGATIVE, "pair"), help="the pair's number")
    listing.add_argument("--quiet", action="store_true", help="the indices alone, one a line (for a shell loop)")
    listing.set_defaults(run=cmd_list)

    add_train_parser(verbs)

    score = verbs.add_parser("score", help="score test videos with a trained model (surprise per video)",
                             description="One CSV row per test video (index, scenario, setting, pair, member, "
                                         "possible, score, s_img, s_dyn; a model of your own: score alone) and "
                                         "the per-frame surprise curves in "
                                         "OUT.curves.npz, with the header: the package version, the model's and "
                                         "the split's identities, the surprise settings. The MSE surprise is "
                                         "the paper's (Eq. 2-4): its score column takes the better of "
                                         "Transformer 2's proposal and nothing hidden, paper_score always the "
                                         "proposal, as the paper does.")
    score.add_argument("--model",
                       help="a run directory, a stage checkpoint (xpl.pt, plato.pt, xpl-noresidual.pt, "
                            "phydnet.pt), random, or a model of your own, path/to/file.py:name or module:name")
    score.add_argument("--data", help="a test split file")
    score.add_argument("--out", required=True, help="the scores CSV to write")
    score.add_argument("--surprise", choices=("mse", "nll", "both"), default="mse",
                       help="mse: the MSE score; nll: -log p(video) under the Pyro model (adds nll, ess, "
                            "p_hidden, p_two, nll_excess); both: the MSE score with the NLL columns beside it")
    score.add_argument("--particles", type=_field(InferenceConfig, "particles"),
                       help="particles per video (nll; default: the model's recipe's, 64 for the shipped one)")
    score.add_argument("--seed", type=_flag(int, SEED, "seed"), default=0,
                       help="seed of the NLL's random draws (default 0)")
    score.add_argument("--nll-set", action="append", default=[], metavar="FIELD=VALUE",
                       help="change a field of the model's NLL settings (xvoe.models.nll.InferenceConfig; "
                            "repeatable), e.g. pixel_sigma=1.0")
    score.add_argument("--aggregate", choices=("sum", "max"), default="sum", help="over frames (default sum)")
    score.add_argument("--batch", type=_positive, default=16, help="videos per batch")
    score.add_argument("--workers", type=_positive, default=1,
                       help="processes scoring a shard each, the cores shared out, merged into --out (default 1; "
                            "2 on 2 cores is the fastest for --surprise nll)")
    score.add_argument("--no-checks", action="store_true",
                       help="a model of your own (file.py:name), phydnet or random: write its scores without the "
                            "checks that the same videos score the same in another order, batch size and on a "
                            "repeat, and not all alike (NaN and inf are refused still)")
    score.add_argument("--time-limit", type=_flag(float, POSITIVE, "--time-limit"), default=TIME_LIMIT,
                       metavar="SECONDS",
                       help=f"a model of your own (file.py:name), phydnet or random: the seconds its surprise may take "
                            f"for one batch before the run ends (default {TIME_LIMIT:g})")
    score.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    score.add_argument("--quiet", action="store_true", help="no progress bar")
    score.add_argument("--shard", type=_shard, default=(0, 1), metavar="I/N",
                       help="score only part I of N (counted from 0); join the parts with --merge")
    score.add_argument("--merge", nargs="+", metavar="PART", help="join the score files of --shard runs into --out")
    score.add_argument("--cache", help="the split's latent cache, read instead of encoding its frames and made if "
                                       "missing (default: beside the split, DATA.latents-PERCEPTION.h5, one per "
                                       "perception module)")
    _add_device(score, "the model")
    score.set_defaults(run=cmd_score)

    explain = verbs.add_parser("explain", help="draw the model's explanation of what is behind the wall",
                               description="Rows of observed frames, the decoded scene with the occluder left "
                                           "out (what the model believes is behind the wall), and the decoded "
                                           "explanation object alone, under the scene at --display-size with the "
                                           "explanation drawn onto it. With --surprise nll the explanation is the "
                                           "posterior mean of the particles that hold a hidden object, and "
                                           "its heaviest distinct hypotheses, each with its weight.")
    explain.add_argument("--model", required=True, help="a run directory or a stage checkpoint (xpl.pt, ...)")
    explain.add_argument("--data", required=True, help="a split file")
    explain.add_argument("--index", type=_flag(int, NON_NEGATIVE, "index"), default=0, help="the video")
    explain.add_argument("--out", required=True, help="the PNG to write")
    explain.add_argument("--surprise", choices=("mse", "nll"), default="mse",
                         help="mse: Transformer 2's proposal (default, see --explanation); nll: the Pyro "
                              "model's posterior, the weighted hidden object, its top hypotheses, p(hidden "
                              "object) and the ESS")
    explain.add_argument("--particles", type=_field(InferenceConfig, "particles"),
                         help="particles (nll; default: the model's recipe's, 64 for the shipped one)")
    explain.add_argument("--explanation", choices=("better", "proposal"), default="better",
                         help="mse: draw Transformer 2's proposal only where it explains the video better than "
                              "nothing hidden (better, the default verdict), or always (proposal, the paper's)")
    explain.add_argument("--seed", type=_flag(int, SEED, "seed"), default=0, help="seed of the particles (nll)")
    explain.add_argument("--display-size", type=_flag(int, PICTURE_SIZE, "display-size"), default=DISPLAY_SIZE,
                         help=f"pixels a side of the scene the explanation is drawn onto (default {DISPLAY_SIZE}); "
                              "the model reads its own frames")
    explain.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    explain.add_argument("--quiet", action="store_true",
                         help="accepted as by every verb; explain draws no progress bar")
    _add_device(explain, "the model")
    explain.set_defaults(run=cmd_explain)

    metrics = verbs.add_parser("metrics", help="comparative, holistic and relative metrics with figures",
                               description="The paper's metrics with bootstrap 95% intervals, for the total "
                                           "score and each component, of one or more models' scores files: "
                                           "metrics.csv, metrics.json and the figures in --out. Scores holding "
                                           "both the MSE score and the NLL also get them side by side "
                                           "(surprise-MODEL.csv) and the pairs they judge differently "
                                           "(disagreements-MODEL.csv, and with --data a figure).")
    metrics.add_argument("scores", nargs="+", help="scores CSV files (one per model)")
    metrics.add_argument("--out", required=True, help="the report directory")
    metrics.add_argument("--rounds", type=_positive, default=1000, help="bootstrap resamples (default 1000)")
    metrics.add_argument("--seed", type=_flag(int, SEED, "seed"), default=0, help="seed of the bootstrap")
    metrics.add_argument("--data", help="the test split that was scored: with scores of both surprise definitions "
                                        "(xvoe score --surprise both), draws pairs they judge differently")
    metrics.add_argument("--overwrite", action="store_true", help="replace a report already in --out")
    metrics.add_argument("--quiet", action="store_true",
                         help="accepted as by every verb; metrics draws no progress bar")
    metrics.add_argument("--table", choices=("md", "latex"),
                         help="also write table.md or table.tex: the paper's layout (scenarios across; holistic, "
                              "comparative and relative by setting with the reference's sub-rows S2-ext1, S2-ext2, "
                              "S3-ext, S3-sur), in percent, every model, ready to paste")
    metrics.set_defaults(run=cmd_metrics)

    verify = verbs.add_parser("verify", help="score a sample of a scores file's rows again and compare",
                              description="Score again a seeded sample of the rows of a scores file (or of every "
                                          "scores file a report of xvoe metrics names), with the model and on the "
                                          "split its header records, and say whether they match the file within "
                                          "float tolerance: exit 0 when every one does, 1 when not.")
    verify.add_argument("scores", help="a scores CSV of xvoe score, or a report directory of xvoe metrics")
    verify.add_argument("--rows", type=_positive, default=5, help="rows to score again (default 5)")
    verify.add_argument("--data", help="the scored split, where it is not at the path the header records")
    verify.add_argument("--seed", type=_flag(int, SEED, "seed"), default=0, help="seed of the rows drawn")
    verify.add_argument("--model", help="the model to score with, as xvoe score takes it (by default the weights the "
                                        "header names; a model of your own must be named here: a header never "
                                        "decides what code runs)")
    verify.add_argument("--quiet", action="store_true",
                        help="print the verdict alone when every row matches (a mismatch is always named)")
    verify.set_defaults(run=cmd_verify)

    pipeline = verbs.add_parser("pipeline", help="generate, train, score and report, end to end",
                                description="Generate the benchmark, train every stage, score the test split, "
                                            "compute the metrics and write RUN_DIR/report.md. A rerun skips "
                                            "the stages already done and resumes an interrupted one.")
    pipeline.add_argument("--out", required=True, help="the run directory")
    pipeline.add_argument("--recipe", default=DEFAULT_RECIPE,
                          help=f"every stage and setting of the models: {_recipe_names()}")
    pipeline.add_argument("--train-videos", type=_positive, help="training videos (default: the recipe's, 10000)")
    pipeline.add_argument("--pairs", type=_positive, default=200, help="test pairs per setting (default 200)")
    pipeline.add_argument("--models", default="xpl,random",
                          help="comma-separated: xpl, plato, xpl-noresidual, phydnet, random (default xpl,random)")
    pipeline.add_argument("--seed", type=_flag(int, Domain(0, SEED.high - 1), "seed"), default=0,
                          help="training seed; the test split uses seed + 1")
    pipeline.add_argument("--workers", type=_positive, default=_default_workers(), help="generation workers")
    pipeline.add_argument("--jobs", type=_flag(int, NON_NEGATIVE, "jobs"), default=1,
                          help="models trained side by side, the cores shared out (0: one per core; default 1: "
                               "one at a time); more lanes hold more memory")
    pipeline.add_argument("--train-processes", type=int, default=0,
                          help="one-thread processes that train the XPL, proposal and PLATO stages together "
                               "(default 0: one per core), at most as many as a stage has data shards and a "
                               "divisor of them, so that the batches are the same on any machine")
    pipeline.add_argument("--quiet", action="store_true", help="no progress bars")
    _add_device(pipeline, "every stage (training, encoding, scoring)")
    pipeline.set_defaults(run=cmd_pipeline)

    ship = verbs.add_parser("ship", help="make a run's models the shipped ones (xpl, plato, ...)",
                            description="Copy RUN_DIR's checkpoints, stripped to weights and configs, into "
                                        "the package's weights directory, where --model xpl finds them.")
    ship.add_argument("run_dir", help="the run directory (of xvoe pipeline)")
    ship.add_argument("--out", help="another directory to write to (default: the package's)")
    ship.add_argument("--quiet", action="store_true", help="the paths written, without their sizes")
    ship.set_defaults(run=cmd_ship)
    return parser


# each verb that writes a file: the arguments naming what it reads, the one naming what it
# writes, and the suffixes of what it writes
WRITES = {
    "generate": (("merge",), "out", (".h5",)),
    "import": (("source",), "out", (".h5",)),
    "show": (("file", "scores"), "out", (".png", ".gif", ".mp4")),
    "score": (("data", "model", "merge"), "out", (".csv",)),
    "explain": (("data", "model"), "out", (".png",)),
    "encode": (("data", "model"), "cache", (".h5",)),
}

# what a verb writes when its output argument is left out
DEFAULT_OUTPUTS: dict[str, Callable[[argparse.Namespace], Path]] = {
    "show": lambda args: Path(Path(args.file).with_suffix(f".{args.index}.png").name),
    "encode": lambda args: _late("encoded_cache")(args.data, args.out, args.model, args.device),
}

# what a verb writes besides its main output, where the argument is given: (argument, suffixes)
ALSO_WRITES = {"score": (("cache", (".h5",)),)}


def output_of(args: argparse.Namespace) -> str | Path | None:
    """The file a verb writes: its output argument, or where the verb writes without one."""
    output = getattr(args, WRITES[args.verb][1])
    return output if output is not None or args.verb not in DEFAULT_OUTPUTS else DEFAULT_OUTPUTS[args.verb](args)


def check_paths(args: argparse.Namespace) -> None:
    """The one check of a command's paths before any work: no output, given or by default, may
    be one of its inputs."""
    if args.verb not in WRITES:
        return
    reads, writes, suffixes = WRITES[args.verb]
    inputs = []
    for name in reads:
        value = getattr(args, name)
        inputs += value if isinstance(value, list) else [value] if value else []
    for name, written in ALSO_WRITES.get(args.verb, ()):
        if getattr(args, name) is not None:
            refuse_overlap(inputs, getattr(args, name), written, what=f"--{name}")
    output = output_of(args)
    if output is None:
        return
    given = getattr(args, writes) is not None
    refuse_overlap(inputs, output, suffixes, what=f"--{writes}" if given else f"the default --{writes}")


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    tune_allocator()        # before any large tensor: freed buffers stay in the heap (xvoe/allocator.py)
    if args.verb in ("train", "pipeline"):      # before any kernel runs, so that a seed trains the same bytes anywhere
        _late("pin_kernels")()
    previous = signal.signal(signal.SIGTERM, _interrupt)   # so that a kill cleans up as Ctrl-C does
    try:
        if hasattr(args, "device"):     # a device this machine lacks, before any work
            _late("resolve_device")(args.device)
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
