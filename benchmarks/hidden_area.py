"""How much does an object draw? The areas behind the NLL's presence penalty.

    python benchmarks/hidden_area.py --model RUN_DIR --data val.h5 [--videos 200]

The area of a picture is what it draws in front of the background, before any wall hides it
(`inference.xpl_scene.XPLScene.area`). Printed, as percentiles over frames: the seen objects'
areas in the frames the encoder saw them; Transformer 2's mean for the hidden slot (the
proposal's centre, before the NLL moves it out of sight against this very penalty) on videos
with a never-seen object and on the others; and the presence threshold of the default
`InferenceConfig` in pixels. A threshold that falls between the real objects and the blank
slots charges only the blanks.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from nll import ground_truth

import xvoe
from inference.model import InferenceConfig
from inference.surprise import hidden_object_scene
from xvoe.benchmark import store
from xvoe.evaluation.score import encode_videos

PERCENTILES = (1, 5, 25, 50, 75, 95, 99)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a shipped model's name or a run directory")
    parser.add_argument("--data", required=True, help="a validation split at the model's resolution")
    parser.add_argument("--videos", type=int, default=200, help="the first N videos, and every never-seen one")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scorer = xvoe.load_model(args.model)
    config = InferenceConfig()
    seen, hidden, blank = [], [], []
    with store.open_dataset(args.data) as file, torch.no_grad():
        names, columns = list(file.attrs["kind_names"]), list(file["states"].attrs["state_columns"])
        kinds = [ground_truth(file, i, names, columns) for i in range(len(file["kind"]))]
        chosen = sorted(set(range(min(args.videos, len(kinds)))) | {i for i, k in enumerate(kinds) if k == "hidden"})
        for index in chosen:
            video = {k: v[0] for k, v in encode_videos(scorer, file, index, index + 1).items()}
            scene, loc, _, free = hidden_object_scene(scorer.vae, scorer.xpl, video["mean"], video["visible"],
                                                      video["background"], video["occluder"])
            for slot in torch.nonzero(scene.moving).flatten():
                area = scene.area(scorer.vae.decode(scene.refined[:, slot]))
                seen += area[video["visible"][:, slot]].tolist()
            if free:
                (hidden if kinds[index] == "hidden" else blank).extend(scene.area(scorer.vae.decode(loc)).tolist())
    pixels = scorer.vae.config.image_size ** 2
    print(f"areas in pixels, percentiles {'/'.join(map(str, PERCENTILES))}")
    for label, values in (("seen objects, frames seen", seen), ("hidden slot's mean, never-seen-object videos", hidden),
                          ("hidden slot's mean, other videos", blank)):
        if values:
            print(f"  {label} ({len(values)} frames): {np.percentile(values, PERCENTILES).round(1).tolist()}")
    print(f"presence threshold: {config.object_area * pixels:.1f} pixels ({config.object_area:g} of {pixels})")


if __name__ == "__main__":
    main()
