"""How much each latent of a perception module moves the decoded picture.

    python benchmarks/latent_sensitivity.py --model RUN_DIR [--cache RUN_DIR/latents-train.h5] [--objects 256]
    python benchmarks/latent_sensitivity.py --model xpl --cache train.h5      # a split: its first videos encoded

For visible objects drawn from a latent cache (or a split, encoded here), the mean squared pixel
change per unit of each latent (`ComponentVAE.latent_sensitivity`). The later stages' losses are
squared errors in latent units, each latent weighted alike (unless XPLConfig.latent_weights says
otherwise): they stand for pixel errors only where these numbers are about equal. Last line:
`sensitivity_ratio=N` (largest over smallest).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import h5py
import torch

from xvoe.errors import XvoeError
from xvoe.training.data import visible_threshold
from xvoe.training.latents import encode_means, picture_weights
from xvoe.training.perception import load_perception


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="run directory or perception.pt")
    parser.add_argument("--cache", help="latent cache made with this model (default: RUN_DIR/latents-train.h5), "
                        "or a split file at the model's resolution")
    parser.add_argument("--objects", type=int, default=256, help="visible objects to average over")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        model, state = load_perception(args.model)
    except XvoeError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    cache = Path(args.cache or Path(state["path"]).parent / "latents-train.h5")
    if not cache.is_file():
        print(f"error: no latent cache at {cache} (give --cache)", file=sys.stderr)
        return 2
    with h5py.File(cache, "r") as file:
        if "rgbd" in file:                                      # a split: encode its first videos
            means, pixels = encode_means(model, file["rgbd"][:40], file["ids"][:40], file["states"].shape[2])
            mean, visible = torch.tensor(means), torch.tensor(pixels > visible_threshold(model.config.image_size))
        else:
            count = min(len(file["mean"]), 200)
            mean, visible = torch.tensor(file["mean"][:count]), torch.tensor(file["visible"][:count]).bool()
    sensitivity = picture_weights(model, mean, visible, args.objects, args.seed)
    where = "where latents 0, 1 = x, y; " if model.config.where_latents else ""
    print(f"model {state['path']} ({where}D={model.config.latent_dim}), {min(args.objects, int(visible.sum()))} "
          f"visible objects of {cache}")
    print("squared pixel change per unit of each latent: " + " ".join(f"{v:.0f}" for v in sensitivity.tolist()))
    weights = sensitivity / sensitivity.mean()
    print("as latent weights (mean 1): " + " ".join(f"{v:.3f}" for v in weights.tolist()))
    print(f"sensitivity_ratio={(sensitivity.max() / sensitivity.min()).item():.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
