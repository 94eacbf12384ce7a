"""The verbs of training: `train STAGE`, one subcommand per stage of the registry, each with its
own flags, and `encode`, which makes the latent cache the later stages train on.

Each verb's parser sits beside what it runs; both call the public API, as a notebook does."""
from __future__ import annotations

import argparse
from pathlib import Path

import xvoe

from ..domains import POSITIVE
from ..errors import XvoeError
from ..outputs import claim_directory
from ..processes import interrupts_held
from ..training.config import DEFAULT_RECIPE, TrainConfig
from ..training.stages import PERCEPTION, PHYDNET, STAGES, XPL, Stage
from .arguments import Parser, Writes, add_device, field, flag, latent_stages, listed, output_of, positive, recipe_names

__all__ = ["add_encode", "add_train"]


def add_train(verbs) -> None:
    train = verbs.add_parser(
        "train", help="train one stage of the XPL model, or a baseline, into a run directory",
        description="xvoe train STAGE: one stage into a run directory (STAGE.pt checkpoint and STAGE.csv "
                    "losses). Each stage runs unchanged under torchrun --nproc_per_node N.")
    stages = train.add_subparsers(dest="stage", required=True, metavar="STAGE", parser_class=Parser)
    for entry in STAGES.values():
        _add_stage(stages.add_parser(entry.name, help=entry.help, description=f"Train {entry.help}."), entry)


def _add_stage(parser: argparse.ArgumentParser, entry: Stage) -> None:
    """The flags of `xvoe train STAGE`: what the stage reads, and the run settings it may change."""
    stage = entry.name
    if entry.reads == XPL:
        parser.add_argument("--data", help=f"the latent cache (default: the one the run's {entry.reads} stage used)")
    elif entry.reads == "latents":
        parser.add_argument("--data", help="the latent cache, or a training split to encode into one first")
        parser.add_argument("--perception", help="the perception run that encodes a split (default: --out)")
    else:
        parser.add_argument("--data", help="the training split file (HDF5)")
    parser.add_argument("--out", required=True, help="the run directory")
    if entry.reads != XPL:
        parser.add_argument("--recipe", default=DEFAULT_RECIPE,
                            help=f"the recipe whose sizes and settings start the run: {recipe_names()}")
    parser.add_argument("--steps", type=field(TrainConfig, "steps"), help="training steps (default: the recipe's)")
    parser.add_argument("--minutes", type=flag(float, POSITIVE, "minutes"),
                        help="stop after this many minutes of training")
    unit = "frames" if stage == PERCEPTION else "videos"
    parser.add_argument("--batch-size", type=field(TrainConfig, "batch_size"),
                        help=f"{unit} per step over all processes" if entry.reads == "pixels" else "videos per step")
    parser.add_argument("--max-videos", type=positive, help="use only the first N videos of --data")
    parser.add_argument("--seed", type=field(TrainConfig, "seed"),
                        help="the seed of initialisation and batches (default 0)")
    parser.add_argument("--lr", type=field(TrainConfig, "lr"),
                        help="peak learning rate (default: the recipe's; it halves every decay_steps)")
    if stage != PERCEPTION:      # the others draw videos, which can come from one group
        parser.add_argument("--focus-group", help="draw --focus-share of each batch from this group's training "
                                                  "videos with a wall (e.g. permanence; several: "
                                                  "permanence,continuity)")
        parser.add_argument("--focus-share", type=field(TrainConfig, "focus_share"),
                            help="the share of each batch from --focus-group")
    parser.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                        help="change any field of a fresh run's TrainConfig or model config (repeatable; "
                             "train.FIELD or model.FIELD where both have it; model.dynamics.hidden=256 "
                             "reaches a nested one); a resumed run keeps its network")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out where it stopped")
    parser.add_argument("--overwrite", action="store_true", help="start again over an existing run")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_device(parser, "it trains")
    # a seed trains the same bytes anywhere: `main` pins the kernels before any runs
    parser.set_defaults(run=_run_train, pins_kernels=True)


def _train_overrides(args: argparse.Namespace, stage: str) -> tuple[dict, dict]:
    """The TrainConfig fields the flags and `--set` change (None: keep the recipe's), and the model's."""
    with interrupts_held():     # imported here, not for --help: a Ctrl-C inside torch's import aborts the process
        from ..training.data import check_focus
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


def _run_train(args: argparse.Namespace) -> None:
    stage = args.stage
    claim_directory(args.out, make=False)       # a bad --out is found before any data is read
    train, model = _train_overrides(args, stage)
    common = {"resume": args.resume, "overwrite": args.overwrite, "progress": not args.quiet, "device": args.device}
    reads = xvoe.STAGES[stage].reads
    if reads != XPL and args.data is None and not args.resume:
        on_latents = listed(name for name, entry in STAGES.items() if entry.reads == "latents")
        raise XvoeError(f"--data is required to start a run (the training split, or for {on_latents} its latent cache)")
    if reads == XPL:
        print(xvoe.train_proposal(args.out, args.data, model_overrides=model, **common, **train))
        return
    common |= {"recipe_name": args.recipe, "model_overrides": model}
    if stage == PERCEPTION:
        print(xvoe.train_perception(args.data, args.out, **common, **train))
    elif stage == PHYDNET:
        print(xvoe.train_phydnet(args.data, args.out, **common, **train))
    else:
        cache = None
        if args.data:
            cache = xvoe.latent_cache_for(args.data, args.out, args.perception, progress=not args.quiet,
                                          device=args.device)
        print(xvoe.train_xpl(cache, args.out, stage=stage, **common, **train))


def add_encode(verbs) -> None:
    encode = verbs.add_parser("encode", help="encode a split into a latent cache with a trained perception module",
                              description="Encode every frame of a split into a latent cache (HDF5), which the "
                                          f"{latent_stages()} stages train on.")
    encode.add_argument("--data", required=True, help="the split file to encode")
    encode.add_argument("--out", required=True,
                        help=f"the run directory (its {STAGES[PERCEPTION].checkpoint} unless --model)")
    encode.add_argument("--model", help="a perception run or checkpoint (default: --out)")
    encode.add_argument("--cache", help="the latent cache to write (default: OUT/latents-DATA.h5; of a test split, "
                                        "beside it, DATA.latents-PERCEPTION.h5, where xvoe score reads it)")
    encode.add_argument("--overwrite", action="store_true", help="replace the cache if it exists")
    encode.add_argument("--quiet", action="store_true", help="no progress bar")
    add_device(encode, "the perception module")
    encode.set_defaults(run=_run_encode, writes=Writes(("data", "model"), "cache", (".h5",), default=_default_cache))


def _default_cache(args: argparse.Namespace) -> Path:
    """The latent cache `encode` writes without --cache (beside a test split, in the run for a training one)."""
    with interrupts_held():     # imported here, not for --help: a Ctrl-C inside torch's import aborts the process
        from ..training.xpl import encoded_cache
    return encoded_cache(args.data, args.out, args.model, args.device)


def _run_encode(args: argparse.Namespace) -> None:
    print(xvoe.encode_split(args.model or args.out, args.data, output_of(args), overwrite=args.overwrite,
                            progress=not args.quiet, device=args.device))
