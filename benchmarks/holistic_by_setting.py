"""Which possible videos pull a holistic AUC down: the AUC of a scenario's impossible videos
against each setting's possible members in turn.

    python benchmarks/holistic_by_setting.py --scores scores.csv [--column nll_excess]

The holistic AUC (DESIGN section 6) ranks every impossible video of a scenario above every
possible one, S2's included, although S2 is no goal (both its members are possible, and one of
them may look impossible to a model that cannot reason its way out: two identical balls in
continuity). Prints, per scenario, the AUC against all possible videos, against each (setting,
member) group of them, and without S2, each with its 95% interval over pairs.
Last line: worst_group=SCENARIO/SETTING/mMEMBER auc=N.NNN
"""
from __future__ import annotations

import argparse

import numpy as np

import xvoe


def subset(scores: dict[str, np.ndarray], keep: np.ndarray) -> dict[str, np.ndarray]:
    return {name: values[keep] for name, values in scores.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scores", required=True, help="a score file of `xvoe score`")
    parser.add_argument("--column", default="score", help="the score column (default score; nll_excess, excess, nll)")
    args = parser.parse_args()
    scores = xvoe.read_scores(args.scores)
    if args.column not in scores:
        raise SystemExit(f"{args.scores} has no column {args.column!r}; it has {', '.join(scores)}")
    impossible = ~scores["possible"].astype(bool)
    worst = ("", 2.0)
    for scenario, whole in xvoe.holistic(scores, args.column).items():
        print(f"{scenario}: all possible videos {whole.value:.3f} [{whole.low:.3f}, {whole.high:.3f}]")
        here = scores["scenario"] == scenario
        without_s2 = here & (impossible | (scores["setting"] != "S2"))
        found = xvoe.holistic(subset(scores, without_s2), args.column)[scenario]
        print(f"  without S2: {found.value:.3f} [{found.low:.3f}, {found.high:.3f}]")
        for setting in sorted(set(scores["setting"][here])):
            for member in (0, 1):
                group = here & ~impossible & (scores["setting"] == setting) & (scores["member"] == member)
                if not group.any():
                    continue
                found = xvoe.holistic(subset(scores, (here & impossible) | group), args.column)[scenario]
                print(f"  against {setting} member {member} ({int(group.sum())} possible videos): "
                      f"{found.value:.3f} [{found.low:.3f}, {found.high:.3f}]")
                if found.value < worst[1]:
                    worst = (f"{scenario}/{setting}/m{member}", found.value)
    print(f"worst_group={worst[0]} auc={worst[1]:.3f}")


if __name__ == "__main__":
    main()
