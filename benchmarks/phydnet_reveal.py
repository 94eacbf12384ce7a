"""Frame by frame, where does PhyDNet's sum-over-frames surprise win or lose a pair?

    python benchmarks/phydnet_reveal.py --data val.h5 --model phydnet [--model RUN ...]
                                        [--scenario permanence] [--setting S1]

For each pair of the setting, the one-step prediction error of each frame (`PhyDNet.surprise`,
what `xvoe score` sums) of the impossible member less that of the possible one. Prints, per
frame: the mean of that difference, the share of pairs in which it is positive at that frame,
and the accuracy of the surprise summed over frames 0..t, whose last value is the comparative
accuracy `xvoe metrics` reports. In permanence S1 the members are the same frames until the wall
is lifted, so the rows before that are 0 and 0.5.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from xvoe.benchmark import store
from xvoe.evaluation.metrics import pairs_table, pairwise_win
from xvoe.models.perception import normalise
from xvoe.training.phydnet import load_phydnet


def pair_rows(path: str, scenario: str, setting: str) -> tuple[np.ndarray, np.ndarray]:
    """Row indices of the possible (member 0) and impossible (member 1) videos, pair by pair."""
    with store.open_dataset(path) as file:
        if "scenario" not in file:
            raise SystemExit(f"{path} is not a test split (no scenario labels)")
        labels = {"scenario": store.strings(file, "scenario"), "setting": store.strings(file, "setting"),
                  "pair": file["pair"][:], "member": file["member"][:]}
    labels["row"] = np.arange(len(labels["pair"]))
    _, possible, impossible = pairs_table(labels, scenario, setting, "row")
    if not len(possible):
        raise SystemExit(f"{path} has no {scenario} {setting} pairs")
    return possible, impossible


def per_frame_surprise(model: str, path: str, rows: np.ndarray, batch: int = 32) -> np.ndarray:
    """(len(rows), T) one-step prediction errors of a PhyDNet on the given rows (read in
    increasing order, as HDF5 wants them)."""
    net, _ = load_phydnet(model)
    ordered = np.unique(rows)
    with store.open_dataset(path) as file, torch.no_grad():
        curves = torch.cat([net.surprise(normalise(torch.from_numpy(file["rgbd"][ordered[start:start + batch]])))
                            for start in range(0, len(ordered), batch)])
    return curves.double().numpy()[np.searchsorted(ordered, rows)]


def wins(impossible: np.ndarray, possible: np.ndarray) -> np.ndarray:
    """Comparative accuracy of each column (`xvoe metrics`' rule: a tie counts a half)."""
    return pairwise_win(impossible, possible).mean(0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a test or validation split")
    parser.add_argument("--model", action="append", required=True, help="phydnet, a run or a checkpoint")
    parser.add_argument("--scenario", default="permanence")
    parser.add_argument("--setting", default="S1")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    possible, impossible = pair_rows(args.data, args.scenario, args.setting)
    for model in args.model:
        surprise = per_frame_surprise(model, args.data, np.concatenate([possible, impossible]))
        first, second = surprise[:len(possible)], surprise[len(possible):]
        difference = second - first
        print(f"{model}: {args.scenario} {args.setting}, {len(possible)} pairs")
        print("frame  mean difference  impossible higher  accuracy of the sum to here")
        for frame, (mean, higher, total) in enumerate(zip(difference.mean(0), wins(second, first),
                                                          wins(second.cumsum(1), first.cumsum(1)))):
            print(f"{frame:5d}  {mean:15.1f}  {100 * higher:17.1f}  {100 * total:27.1f}")
        print(f"accuracy: sum {100 * wins(second.sum(1), first.sum(1)):.1f}, "
              f"max {100 * wins(second.max(1), first.max(1)):.1f}")


if __name__ == "__main__":
    main()
