"""How long a notebook waits for its first NLL score: one video scored twice in a fresh process.

    python benchmarks/nll_latency.py [--model xpl] [--data val.h5] [--video 0] [--threads 1]

The first call pays whatever a process imports or builds once (the second does not); their
difference is that one-time cost. Last line: first_s=N.NN second_s=N.NN once_s=N.NN
"""
from __future__ import annotations

import argparse
import time

import torch

from inference.model import InferenceConfig
from inference.surprise import nll_surprise
from xvoe.benchmark import store
from xvoe.evaluation.score import encode_videos, load_model


def one_video(description: str) -> tuple[argparse.Namespace, object, list]:
    """The arguments of a one-video benchmark (--model, --data, --video, --threads), the model,
    and that video encoded: frames, latents, visibility, background, walls."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--model", default="xpl")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--video", type=int, default=0)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scorer = load_model(args.model)
    with store.open_dataset(args.data) as file:
        batch = encode_videos(scorer, file, args.video, args.video + 1)
    return args, scorer, [batch[k][0] for k in ("frames", "mean", "visible", "background", "occluder")]


def main() -> None:
    args, scorer, video = one_video(__doc__.splitlines()[0])
    seconds = []
    for _ in range(2):
        start = time.perf_counter()
        nll_surprise(scorer.vae, scorer.xpl, *video, InferenceConfig())
        seconds.append(time.perf_counter() - start)
    print(f"video {args.video} of {args.data}, {args.threads} thread(s)")
    print(f"first_s={seconds[0]:.2f} second_s={seconds[1]:.2f} once_s={seconds[0] - seconds[1]:.2f}")


if __name__ == "__main__":
    main()
