"""The NLL's prior of two identical objects (`prior_two`), chosen on a validation split from one
scoring: each prior's lines derived exactly from a score file made with `--surprise both`
(inference.score.under_prior_two: posterior odds are prior odds times the Bayes factor).

    xvoe score --model M --data val.h5 --surprise both --out val.csv
    python benchmarks/prior_two.py --scores val.csv --data val.h5 [--priors 0,0.001,0.01,0.1,0.3,0.5]

Per prior: the NLL-excess holistic AUC per scenario (goal >= 0.9; continuity's S2 is what the
prior serves), the identity lines (p_two > 0.5 where only two objects explain the video, < 0.5
where a lifted wall shows one; goals 90% and 95%) and the lowest NLL S1/S3 comparative accuracy
(goal 99%). Choose on a validation split, never on a report split.
"""
from __future__ import annotations

import argparse

import xvoe
from xvoe.evaluation.scorecard import identity_lines
from xvoe.inference.score import under_prior_two


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scores", required=True, help="a validation split's scores made with --surprise both")
    parser.add_argument("--data", required=True, help="the split it scored")
    parser.add_argument("--priors", default="0,0.001,0.01,0.1,0.3,0.5", help="comma-separated priors in [0, 1)")
    parser.add_argument("--rounds", type=int, default=1000, help="bootstrap resamples of the intervals")
    args = parser.parse_args()
    try:
        with xvoe.open_dataset(args.data, split="test") as file:
            xvoe.check_same_split(args.scores, xvoe.split_identity(file), args.data)
        scores = xvoe.read_scores(args.scores, args.data)
        used = xvoe.score_header(args.scores).get("nll", {}).get("prior_two")
        if "p_two" not in scores or not used:
            raise xvoe.XvoeError(f"{args.scores} holds no NLL scored with two identical objects: score it with "
                                 "--surprise both and prior_two > 0")
        priors = [float(p) for p in args.priors.split(",") if p]
        tables = {prior: under_prior_two(scores, used, prior) for prior in priors}
    except (xvoe.XvoeError, ValueError) as error:
        raise SystemExit(f"prior_two.py: error: {error}") from None
    print(f"{args.scores}, scored with prior_two {used:g}; NLL-excess holistic AUC [95% interval], identity lines "
          "(%), lowest NLL S1/S3 comparative (%)")
    for prior, table in tables.items():
        auc = xvoe.holistic(table, "nll_excess", args.rounds)
        accuracy = xvoe.comparative(table, "nll", args.rounds)
        worst = min((e.value, f"{s} {t}") for (s, t), e in accuracy.items() if t != "S2")
        identity = identity_lines(table, args.rounds) if prior > 0 else []
        print(f"prior_two {prior:<6g} AUC " + " / ".join(f"{e.value:.3f} [{e.low:.3f}, {e.high:.3f}]"
                                                         for e in auc.values())
              + "".join(f" | {line.value:.1f}" for line in identity) + f" | {100 * worst[0]:.1f} ({worst[1]})")


if __name__ == "__main__":
    main()
