"""Every goal (docs/design.md, "Goals") that one model's run can measure, one line each, met or not.

    python benchmarks/scorecard.py --model xpl --data val.h5 [--frames heldout-train.h5]
                                   [--baselines plato,phydnet] [--role xpl|baseline|random|reported]
                                   [--particles N] [--seeds 0,1] [--pairs 100] [--json card.json]
                                   [--against shipped.json] [--nll-set FIELD=VALUE ...]
                                   [--scores both.csv [--repeat seed1.csv | seed1-part*.csv]]

Scores the split (`xvoe score`; with `--surprise both` for an XPL model with reasoning, once per
--seeds), then prints the card of xvoe.evaluation.scorecard: comparative accuracy per setting
under the default verdict (`score`, the goals), the paper's score (`paper_score`), the excess,
the NLL and the NLL excess, each with its 95% interval over pairs and the permutation p-value against 50%; the
S3 - S2 gap under the default verdict and the NLL; holistic AUC; hidden_iou and mae_iou on --pairs
videos; the NLL's p_hidden, ESS, p_two (two identical objects) and what both make of each S2
member, and its repeatability; the perception's PSNR and position probes (per kind, and one for
all kinds) on --frames (a train-type split the model was not trained on); XPL's S3 lead over each
of --baselines; videos per second.
`--scores FILE` reads the model's scores of the split made already with `--surprise both` (the
parts of `xvoe score --shard` merged: a 200-pair split takes hours of NLL) instead of scoring it,
and `--repeat FILE ...` the same with the NLL's second seed, whole or some of its shards;
both are checked to be this model's and this split's, and the card then has no speed lines.
`--against CARD` (the shipped model's --json on the same split) applies the shipping rule
(docs/design.md, "Recipes, choosing and shipping") and prints its verdict. Choose on validation
seeds, report on fresh ones.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import xvoe
from xvoe.evaluation import scorecard


def timed_scores(model, data: str, out: Path, **options) -> tuple[dict, float]:
    """A model's scores of the split and the seconds they took."""
    start = time.perf_counter()
    path = xvoe.score(model, data, out, progress=False, **options)
    return xvoe.read_scores(path), time.perf_counter() - start


def reasons(model) -> bool:
    """Whether the model has Transformer 2 (an explanation, and the NLL)."""
    return model.xpl is not None and model.xpl.config.use_reasoning


def given_scores(path: str, model, data: str, identity: dict, nll: bool = True) -> dict:
    """A score file of this model on this split (whose `split_identity` is `identity`), made with
    `--surprise both` where the card carries the NLL's lines (`nll`)."""
    xvoe.check_scored_by(path, model)
    xvoe.check_same_split(path, identity, data)
    scores = xvoe.read_scores(path)
    if nll and "nll" not in scores:
        raise xvoe.XvoeError(f"{path} holds no NLL: score it with --surprise both, or give --no-nll")
    return scores


def scored_runs(args: argparse.Namespace, model, work: Path) -> tuple[list[dict], list[scorecard.Line]]:
    """The model's score tables, the first the card's (the NLL's seeds after it, where it has
    one), and the speed lines of scoring them: read from --scores and --repeat where given."""
    if args.scores:
        with xvoe.open_dataset(args.data, split="test") as file:
            identity = xvoe.split_identity(file)        # hashes frames: once for every file given
        runs = [given_scores(args.scores, model, args.data, identity, not args.no_nll)]
        if args.repeat:
            parts = [given_scores(path, model, args.data, identity) for path in args.repeat]
            runs.append({name: np.concatenate([part[name] for part in parts]) for name in ("index", "nll")})
        return runs, []
    if not reasons(model) or args.no_nll:
        scores, seconds = timed_scores(model, args.data, work / "mse.csv")
        return [scores], [scorecard.speed_line("MSE scoring", len(scores["index"]), seconds, scorecard.MSE_SPEED)]
    mse, mse_seconds = timed_scores(model, args.data, work / "mse.csv")
    nll_settings = xvoe.nll_settings(args.nll_set)
    timed = [timed_scores(model, args.data, work / f"both-{seed}.csv", surprise="both", particles=args.particles,
                          seed=seed, nll_settings=nll_settings) for seed in args.seeds]
    videos = len(mse["index"])
    return [found for found, _ in timed], [
        scorecard.speed_line("MSE scoring", videos, mse_seconds, scorecard.MSE_SPEED),
        scorecard.speed_line("NLL scoring (with MSE)", videos, timed[0][1], scorecard.NLL_SPEED)]


def card_lines(args: argparse.Namespace, model, work: Path) -> list[scorecard.Line]:
    """Score (or read the scores given), then measure every line this model's card carries."""
    runs, lines = scored_runs(args, model, work)
    scores = runs[0]
    lines += scorecard.score_lines(scores, args.role, args.rounds)
    baselines = {Path(name).stem: timed_scores(name, args.data, work / f"{Path(name).stem}.csv")[0]
                 for name in args.baselines}
    lines += scorecard.lead_lines(scores, baselines, args.rounds)
    with xvoe.open_dataset(args.data) as file:
        if "nll" in scores and not args.no_nll:
            lines += scorecard.nll_lines(scores, file, runs[1] if len(runs) > 1 else None, args.rounds)
        if reasons(model) and args.pairs:
            lines += scorecard.explanation_lines(model, file, args.pairs, args.rounds)
    if model.vae is not None and args.frames:
        lines += scorecard.perception_lines(model.vae, args.frames, args.frame_videos, args.rounds)
    return lines


def parse() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a shipped model's name or a run directory")
    parser.add_argument("--data", required=True, help="a validation or report split at the model's resolution")
    parser.add_argument("--frames", help="a train-type split the model was not trained on: the perception's lines")
    parser.add_argument("--frame-videos", type=int, default=300, help="videos of --frames to measure (default 300)")
    parser.add_argument("--baselines", default="", help="comma-separated models scored beside for XPL's S3 lead")
    parser.add_argument("--role", choices=scorecard.ROLES,
                        help="which goals the lines carry (default: from the model's name; a run is an XPL)")
    parser.add_argument("--particles", type=int, help="the NLL's particles (default: the model's own NLL settings)")
    parser.add_argument("--seeds", default="0,1",
                        help="the NLL's seeds; the first scores, the second measures repeatability")
    parser.add_argument("--no-nll", action="store_true", help="leave out the NLL's lines (and its scoring time)")
    parser.add_argument("--pairs", type=int, default=100, help="videos for hidden_iou and mae_iou (0: none)")
    parser.add_argument("--rounds", type=int, default=1000, help="bootstrap and permutation resamples")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--nll-set", action="append", default=[], metavar="FIELD=VALUE",
                        help="change a field of the NLL's settings (inference.InferenceConfig), as xvoe score's")
    parser.add_argument("--scores", help="the model's scores of --data with --surprise both, made already")
    parser.add_argument("--repeat", nargs="+", metavar="FILE",
                        help="with --scores: the same with the NLL's second seed, whole or some of its shards")
    parser.add_argument("--json", help="write the card here too")
    parser.add_argument("--against", help="the shipped model's card (--json) on the same split: the shipping rule")
    args = parser.parse_args()
    args.seeds = [int(s) for s in args.seeds.split(",") if s]
    args.baselines = [b for b in args.baselines.split(",") if b]
    args.role = args.role or scorecard.role_of(args.model)
    if args.repeat and not args.scores:
        parser.error("--repeat goes with --scores")
    return args


def main() -> None:
    args = parse()
    torch.set_num_threads(args.threads)
    try:
        model = xvoe.load_model(args.model)
        lines = card_lines(args, model, Path(tempfile.mkdtemp(prefix="scorecard-")))
    except xvoe.XvoeError as error:
        raise SystemExit(f"scorecard.py: error: {error}") from None
    shipped = {line.name: line for line in scorecard.read_card(args.against)} if args.against else {}
    for line in lines:
        print(scorecard.format_line(line, shipped.get(line.name)))
    goals = [line for line in lines if line.target is not None]
    print(f"{sum(bool(line.met) for line in goals)} of {len(goals)} goals met; model {args.model}, data {args.data}")
    if args.against:
        decision = scorecard.compare(lines, list(shipped.values()))
        print(f"against {args.against}: {'SHIPS' if decision.ships else 'does not ship'}"
              + "".join(f"\n  unmet (the shipped model meets it): {name}" for name in decision.unmet)
              + "".join(f"\n  worse beyond its interval: {name}" for name in decision.worse))
    if args.json:
        scorecard.write_card(args.json, lines, model=args.model, data=str(args.data), role=args.role)


if __name__ == "__main__":
    main()
