"""The NLL's rendering of a hidden object: compositing by the full softmax over every slot
against finishing the fixed slots' partial softmax (inference.xpl_scene), in one process.

    python benchmarks/composite.py [--model xpl] [--data test.h5] [--particles 56] [--threads 2]

Last line: full_ms=N.N incremental_ms=N.N ratio=N.N max_diff=...
"""
from __future__ import annotations

import argparse
import time

import torch

from inference.xpl_scene import XPLScene
from xvoe.benchmark import store
from xvoe.evaluation.score import encode_videos, load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="xpl")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--index", type=int, default=0, help="the video whose scene is rendered")
    parser.add_argument("--particles", type=int, default=56, help="particles holding an object (56 of 64 at most)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    scorer = load_model(args.model)
    with store.open_dataset(args.data) as file:
        video = encode_videos(scorer, file, args.index, args.index + 1)
    with torch.no_grad():
        refined = scorer.xpl.refine(video["mean"], video["visible"], video["occluder"])[0]
        occupied = video["visible"][0].any(0)
        hidden = int((~occupied).float().argmax())
        scene = XPLScene(scorer.vae, scorer.xpl, refined, scorer.vae.decode(video["background"][0]),
                         video["visible"][0], video["occluder"][0], hidden)
        frames, dim = refined.shape[0], refined.shape[-1]
        pictures = scorer.vae.decode(torch.randn(args.particles * frames, dim)).reshape(
            args.particles, frames, *scene.layers.shape[-3:])
        began = time.perf_counter()
        for _ in range(args.repeats):
            layers = scene.layers.expand(args.particles, *scene.layers.shape).clone()
            layers[:, :, hidden] = pictures
            full = scene._composite(layers)
        middle = time.perf_counter()
        for _ in range(args.repeats):
            fast = scene._composite_hidden(pictures)[0]
        done = time.perf_counter()
    full_ms, fast_ms = 1000 * (middle - began) / args.repeats, 1000 * (done - middle) / args.repeats
    print(f"{args.particles} particles x {frames} frames, {scene.layers.shape[1]} slots, {args.threads} thread(s)")
    print(f"full_ms={full_ms:.1f} incremental_ms={fast_ms:.1f} ratio={full_ms / fast_ms:.1f} "
          f"max_diff={float((full - fast).abs().max()):.1e}")


if __name__ == "__main__":
    main()
