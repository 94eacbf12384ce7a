"""Does PhyDNet remember where a cube fell behind the wall? Its prediction of the frame the wall
has gone, at the cubes' pixels.

    python benchmarks/phydnet_memory.py --data train.h5 --model phydnet [--model RUN ...] [--videos 160]

Takes the first training videos of the permanence group that have a wall, and splits their cubes
into those at rest on the floor from the start and those that fell (behind the wall). For each
model, its one-step prediction of `--frame` (12: the wall is down) is compared with the frame at
each cube's pixels: mean squared error per pixel, summed over the four channels. For the fallen
cubes it also prints the distance from the prediction to frame 0 at the same pixels (the place
before the cube came), so a model that forgot the cube is near 0 there and far from the cube.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from xvoe.benchmark import store
from xvoe.models.perception import normalise
from xvoe.training.data import focus_videos
from xvoe.training.phydnet import load_phydnet


def permanence_videos(path: str, count: int) -> dict[str, np.ndarray]:
    """The first `count` permanence videos with a wall: frames, slot ids per pixel, which slots are
    cubes, and every slot's height (y, pixels down)."""
    with store.open_dataset(path) as file:
        rows = focus_videos(file, "permanence", 0, len(file["group"]))[:count]
        if not len(rows):
            raise SystemExit(f"{path} has no permanence videos with a wall")
        columns = [str(name) for name in file["states"].attrs["state_columns"]]
        kinds = [str(name) for name in file.attrs["kind_names"]]
        return {"rgbd": file["rgbd"][rows], "ids": file["ids"][rows], "cube": file["kind"][rows] == kinds.index("cube"),
                "y": file["states"][rows][..., columns.index("y")]}


def squared(guess: torch.Tensor, target: torch.Tensor) -> float:
    """Mean over pixels of the squared error summed over channels; (C, pixels) each."""
    return (guess - target).pow(2).sum(0).mean().item()


def cube_errors(predicted: torch.Tensor, frames: torch.Tensor, videos: dict, frame: int) -> dict[str, list[float]]:
    """Per cube: the prediction's error at its pixels in `frame`, split by whether it fell;
    `frames` are the videos' normalised frames."""
    errors: dict[str, list[float]] = {"resting": [], "fallen": [], "fallen, to frame 0": []}
    for video, slot in zip(*np.nonzero(videos["cube"])):
        mask = torch.from_numpy(videos["ids"][video, frame] == slot + 1)
        if mask.sum() < 4:       # hardly visible there: no pixels to measure
            continue
        guess = predicted[video, frame - 1][:, mask]
        if videos["y"][video, -1, slot] < videos["y"][video, 0, slot] + 1:     # y down: it did not fall
            errors["resting"].append(squared(guess, frames[video, frame][:, mask]))
        else:
            errors["fallen"].append(squared(guess, frames[video, frame][:, mask]))
            errors["fallen, to frame 0"].append(squared(guess, frames[video, 0][:, mask]))
    return errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="a training split (it has group labels)")
    parser.add_argument("--model", action="append", required=True, help="phydnet, a run or a checkpoint")
    parser.add_argument("--videos", type=int, default=160)
    parser.add_argument("--frame", type=int, default=12)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    videos = permanence_videos(args.data, args.videos)
    frames = normalise(torch.from_numpy(videos["rgbd"]))
    for model in args.model:
        net, _ = load_phydnet(model)
        with torch.no_grad():
            predicted = torch.cat([net(frames[i:i + 32]) for i in range(0, len(frames), 32)])
        errors = cube_errors(predicted, frames, videos, args.frame)
        print(model, f"frame {args.frame}:",
              " | ".join(f"{name} {np.mean(values):.3f} (n={len(values)})" for name, values in errors.items()))


if __name__ == "__main__":
    main()
