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

from xvoe import store
from xvoe.models.perception import normalise
from xvoe.train_phydnet import load_phydnet


def pair_rows(path: str, scenario: str, setting: str) -> tuple[np.ndarray, np.ndarray]:
    """Row indices of the possible (member 0) and impossible (member 1) videos, pair by pair."""
    with store.open_dataset(path) as file:
        if "scenario" not in file:
            raise SystemExit(f"{path} is not a test split (no scenario labels)")
        wanted = (store.strings(file, "scenario") == scenario) & (store.strings(file, "setting") == setting)
        pair, member = file["pair"][:], file["member"][:]
    rows = np.flatnonzero(wanted)
    if not len(rows):
        raise SystemExit(f"{path} has no {scenario} {setting} videos")
    by_pair: dict[int, dict[int, int]] = {}
    for row in rows:
        by_pair.setdefault(int(pair[row]), {})[int(member[row])] = row
    complete = [rows for rows in by_pair.values() if set(rows) == {0, 1}]
    return np.array([r[0] for r in complete]), np.array([r[1] for r in complete])


def per_frame_surprise(model: str, path: str, rows: np.ndarray, batch: int = 32) -> np.ndarray:
    """(len(rows), T) one-step prediction errors of a PhyDNet on the given rows."""
    net, _ = load_phydnet(model)
    curves = []
    with store.open_dataset(path) as file, torch.no_grad():
        for start in range(0, len(rows), batch):
            frames = normalise(torch.from_numpy(file["rgbd"][np.sort(rows[start:start + batch])]))
            order = np.argsort(np.argsort(rows[start:start + batch]))
            curves.append(net.surprise(frames)[torch.from_numpy(order)])
    return torch.cat(curves).double().numpy()


def wins(difference: np.ndarray) -> np.ndarray:
    """Comparative accuracy of each column: the impossible member higher; a tie counts a half."""
    return (difference > 0).mean(0) + 0.5 * (difference == 0).mean(0)


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
        difference = surprise[len(possible):] - surprise[:len(possible)]
        print(f"{model}: {args.scenario} {args.setting}, {len(possible)} pairs")
        print("frame  mean difference  impossible higher  accuracy of the sum to here")
        for frame, (mean, higher, total) in enumerate(zip(difference.mean(0), wins(difference),
                                                          wins(difference.cumsum(1)))):
            print(f"{frame:5d}  {mean:15.1f}  {100 * higher:17.1f}  {100 * total:27.1f}")
        print(f"accuracy: sum {100 * wins(difference.sum(1, keepdims=True))[0]:.1f}, "
              f"max {100 * wins((surprise[len(possible):].max(1) - surprise[:len(possible)].max(1))[:, None])[0]:.1f}")


if __name__ == "__main__":
    main()
