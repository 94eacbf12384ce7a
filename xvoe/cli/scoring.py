"""The verbs of a trained model's judgement: `score` a test split, `explain` one video, the
`metrics` of score files, and `verify` a score file by scoring a sample of its rows again.

Each verb's parser sits beside what it runs; both call the public API, as a notebook does."""
from __future__ import annotations

import argparse
import sys

import xvoe

from ..domains import DISPLAY_SIZE, NON_NEGATIVE, PICTURE_SIZE, POSITIVE, SEED, TIME_LIMIT
from ..errors import XvoeError
from ..models.nll import InferenceConfig
from ..outputs import claim_file, claim_scope
from ..training.stages import RANDOM, SCORED, STAGES
from .arguments import Writes, add_device, field, flag, positive, scored_by_surprise, scored_checkpoints, shard

__all__ = ["add_explain", "add_metrics", "add_score", "add_verify"]


def add_score(verbs) -> None:
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
                       help=f"a run directory, a stage checkpoint ({scored_checkpoints()}), {RANDOM}, or a model "
                            "of your own, path/to/file.py:name or module:name")
    score.add_argument("--data", help="a test split file")
    score.add_argument("--out", required=True, help="the scores CSV to write")
    score.add_argument("--surprise", choices=("mse", "nll", "both"), default="mse",
                       help="mse: the MSE score; nll: -log p(video) under the Pyro model (adds nll, ess, "
                            "p_hidden, p_two, nll_excess); both: the MSE score with the NLL columns beside it")
    score.add_argument("--particles", type=field(InferenceConfig, "particles"),
                       help="particles per video (nll; default: the model's recipe's, 64 for the shipped one)")
    score.add_argument("--seed", type=flag(int, SEED, "seed"), default=0,
                       help="seed of the NLL's random draws (default 0)")
    score.add_argument("--nll-set", action="append", default=[], metavar="FIELD=VALUE",
                       help="change a field of the model's NLL settings (xvoe.models.nll.InferenceConfig; "
                            "repeatable), e.g. pixel_sigma=1.0")
    score.add_argument("--aggregate", choices=("sum", "max"), default="sum", help="over frames (default sum)")
    score.add_argument("--batch", type=positive, default=16, help="videos per batch")
    score.add_argument("--workers", type=positive, default=1,
                       help="processes scoring a shard each, the cores shared out, merged into --out (default 1; "
                            "2 on 2 cores is the fastest for --surprise nll)")
    score.add_argument("--no-checks", action="store_true",
                       help=f"a model of your own (file.py:name), {scored_by_surprise()}: write its scores without "
                            "the checks that the same videos score the same in another order, batch size and on a "
                            "repeat, and not all alike (NaN and inf are refused still)")
    score.add_argument("--time-limit", type=flag(float, POSITIVE, "--time-limit"), default=TIME_LIMIT,
                       metavar="SECONDS",
                       help=f"a model of your own (file.py:name), {scored_by_surprise()}: the seconds its surprise "
                            f"may take for one batch before the run ends (default {TIME_LIMIT:g})")
    score.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    score.add_argument("--quiet", action="store_true", help="no progress bar")
    score.add_argument("--shard", type=shard, default=(0, 1), metavar="I/N",
                       help="score only part I of N (counted from 0); join the parts with --merge")
    score.add_argument("--merge", nargs="+", metavar="PART", help="join the score files of --shard runs into --out")
    score.add_argument("--cache", help="the split's latent cache, read instead of encoding its frames and made if "
                                       "missing (default: beside the split, DATA.latents-PERCEPTION.h5, one per "
                                       "perception module)")
    add_device(score, "the model")
    score.set_defaults(run=_run_score, writes=Writes(("data", "model", "merge"), "out", (".csv",),
                                                     also=(("cache", (".h5",)),)))


def _run_score(args: argparse.Namespace) -> None:
    if args.merge:
        if args.model or args.data or args.shard != (0, 1) or args.cache:
            raise XvoeError("--merge joins score files as they were written; "
                            "leave out --model, --data, --shard and --cache")
        print(xvoe.merge_scores(args.merge, args.out, overwrite=args.overwrite))
        return
    if args.model is None or args.data is None:
        raise XvoeError("--model and --data are required (unless --merge joins the parts of a sharded run)")
    table = xvoe.score(args.model, args.data, args.out, surprise=args.surprise, particles=args.particles,
                       seed=args.seed, nll_settings=xvoe.nll_settings(args.nll_set), how=args.aggregate,
                       shard=args.shard, videos_per_batch=args.batch, workers=args.workers, checks=not args.no_checks,
                       overwrite=args.overwrite, progress=not args.quiet, device=args.device,
                       cache=args.cache or True, time_limit=args.time_limit)
    note = xvoe.nll_defaults_note(xvoe.score_header(table.path)) if args.surprise != "mse" else None
    if note:
        print(f"xvoe score: warning: {note}", file=sys.stderr)
    print(table)


def add_explain(verbs) -> None:
    explain = verbs.add_parser("explain", help="draw the model's explanation of what is behind the wall",
                               description="Rows of observed frames, the decoded scene with the occluder left "
                                           "out (what the model believes is behind the wall), and the decoded "
                                           "explanation object alone, under the scene at --display-size with the "
                                           "explanation drawn onto it. With --surprise nll the explanation is the "
                                           "posterior mean of the particles that hold a hidden object, and "
                                           "its heaviest distinct hypotheses, each with its weight.")
    explain.add_argument("--model", required=True,
                         help=f"a run directory or a stage checkpoint ({STAGES[SCORED[0]].checkpoint}, ...)")
    explain.add_argument("--data", required=True, help="a split file")
    explain.add_argument("--index", type=flag(int, NON_NEGATIVE, "index"), default=0, help="the video")
    explain.add_argument("--out", required=True, help="the PNG to write")
    explain.add_argument("--surprise", choices=("mse", "nll"), default="mse",
                         help="mse: Transformer 2's proposal (default, see --explanation); nll: the Pyro "
                              "model's posterior, the weighted hidden object, its top hypotheses, p(hidden "
                              "object) and the ESS")
    explain.add_argument("--particles", type=field(InferenceConfig, "particles"),
                         help="particles (nll; default: the model's recipe's, 64 for the shipped one)")
    explain.add_argument("--explanation", choices=("better", "proposal"), default="better",
                         help="mse: draw Transformer 2's proposal only where it explains the video better than "
                              "nothing hidden (better, the default verdict), or always (proposal, the paper's)")
    explain.add_argument("--seed", type=flag(int, SEED, "seed"), default=0, help="seed of the particles (nll)")
    explain.add_argument("--display-size", type=flag(int, PICTURE_SIZE, "display-size"), default=DISPLAY_SIZE,
                         help=f"pixels a side of the scene the explanation is drawn onto (default {DISPLAY_SIZE}); "
                              "the model reads its own frames")
    explain.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    explain.add_argument("--quiet", action="store_true",
                         help="accepted as by every verb; explain draws no progress bar")
    add_device(explain, "the model")
    explain.set_defaults(run=_run_explain, writes=Writes(("data", "model"), "out", (".png",)))


@claim_scope()
def _run_explain(args: argparse.Namespace) -> None:
    claim_file(args.out, args.overwrite)
    explanation = xvoe.explain(args.model, args.data, args.index, surprise=args.surprise, particles=args.particles,
                               seed=args.seed, explanation=args.explanation, display_size=args.display_size,
                               device=args.device)
    print(xvoe.save_figure(xvoe.plot_explanation(explanation), args.out))


def add_metrics(verbs) -> None:
    metrics = verbs.add_parser("metrics", help="comparative, holistic and relative metrics with figures",
                               description="The paper's metrics with bootstrap 95% intervals, for the total "
                                           "score and each component, of one or more models' scores files: "
                                           "metrics.csv, metrics.json and the figures in --out. Scores holding "
                                           "both the MSE score and the NLL also get them side by side "
                                           "(surprise-MODEL.csv) and the pairs they judge differently "
                                           "(disagreements-MODEL.csv, and with --data a figure).")
    metrics.add_argument("scores", nargs="+", help="scores CSV files (one per model)")
    metrics.add_argument("--out", required=True, help="the report directory")
    metrics.add_argument("--rounds", type=positive, default=1000, help="bootstrap resamples (default 1000)")
    metrics.add_argument("--seed", type=flag(int, SEED, "seed"), default=0, help="seed of the bootstrap")
    metrics.add_argument("--data", help="the test split that was scored: with scores of both surprise definitions "
                                        "(xvoe score --surprise both), draws pairs they judge differently")
    metrics.add_argument("--overwrite", action="store_true", help="replace a report already in --out")
    metrics.add_argument("--quiet", action="store_true",
                         help="accepted as by every verb; metrics draws no progress bar")
    metrics.add_argument("--table", choices=("md", "latex"),
                         help="also write table.md or table.tex: the paper's layout (scenarios across; holistic, "
                              "comparative and relative by setting with the reference's sub-rows S2-ext1, S2-ext2, "
                              "S3-ext, S3-sur), in percent, every model, ready to paste")
    metrics.set_defaults(run=_run_metrics)


def _run_metrics(args: argparse.Namespace) -> None:
    for path in xvoe.report(args.scores, args.out, rounds=args.rounds, seed=args.seed, data=args.data,
                            overwrite=args.overwrite, table=args.table):
        print(path)


def add_verify(verbs) -> None:
    verify = verbs.add_parser("verify", help="score a sample of a scores file's rows again and compare",
                              description="Score again a seeded sample of the rows of a scores file (or of every "
                                          "scores file a report of xvoe metrics names), with the model and on the "
                                          "split its header records, and say whether they match the file within "
                                          "float tolerance: exit 0 when every one does, 1 when not.")
    verify.add_argument("scores", help="a scores CSV of xvoe score, or a report directory of xvoe metrics")
    verify.add_argument("--rows", type=positive, default=5, help="rows to score again (default 5)")
    verify.add_argument("--data", help="the scored split, where it is not at the path the header records")
    verify.add_argument("--seed", type=flag(int, SEED, "seed"), default=0, help="seed of the rows drawn")
    verify.add_argument("--model", help="the model to score with, as xvoe score takes it (by default the weights the "
                                        "header names; a model of your own must be named here: a header never "
                                        "decides what code runs)")
    verify.add_argument("--quiet", action="store_true",
                        help="print the verdict alone when every row matches (a mismatch is always named)")
    verify.set_defaults(run=_run_verify)


def _run_verify(args: argparse.Namespace) -> int:
    found = xvoe.verify(args.scores, rows=args.rows, data=args.data, seed=args.seed, model=args.model)
    if not (args.quiet and found.matches):     # quiet: the verdict alone, unless a row is named in it
        print("\n".join(found.lines))
    print("every row matches its curves and labels, and every row scored again matches the file" if found.matches
          else "some rows do not match the file")
    return 0 if found.matches else 1
