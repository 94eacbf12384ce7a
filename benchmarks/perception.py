"""Benchmark of a trained perception module on held-out frames.

Prints the composite reconstruction PSNR (RGB, depth, and RGB on object pixels only, each with
its interval over videos), the R^2 of a linear probe from the latent means to each visible
object's x and y, fitted on half of the videos and scored on the other half, one for each kind
(the goal for x and y of cubes and walls and x of balls) and one for all objects, each with its
interval over videos: xvoe.evaluation.perception_quality, the scorecard's perception lines.
Then the training throughput in object images per second (training steps on the frames read,
whatever the split: nothing is learned from them), the decoder throughput, and the training
time recorded in the checkpoint. Last line: `psnr=NN.N probe_r2=0.NNN` (RGB PSNR; the smallest R^2 of the probe
goals, nan where one could not be measured).

    python benchmarks/perception.py --model runs/perception-cpu --data data/val32.h5
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

import xvoe
from xvoe.apps.frames import save_reconstructions
from xvoe.evaluation import perception_quality as quality
from xvoe.evaluation.scorecard import PROBE_R2
from xvoe.models.config import from_dict
from xvoe.models.perception import ComponentVAE
from xvoe.training.config import TrainConfig
from xvoe.training.data import perception_batch
from xvoe.training.perception import load_perception
from xvoe.training.recipes import recipe_of


def train_throughput(model: ComponentVAE, held: quality.HeldOut, config: TrainConfig, steps: int) -> float:
    """Median object images per second of full training steps (forward, backward, Adam) on
    batches of the held-out frames, drawn with a fixed seed."""
    frames = held.rgbd.reshape(-1, *held.rgbd.shape[2:])
    ids = held.ids.reshape(-1, *held.ids.shape[2:])
    slots, rng = held.states.shape[2], np.random.default_rng(1)
    trainee = ComponentVAE(model.config)
    trainee.load_state_dict(model.state_dict())
    optimiser = torch.optim.Adam(trainee.parameters(), lr=config.lr)
    rates = []
    for step in range(steps + 3):
        start = time.perf_counter()
        chosen = rng.integers(0, len(frames), config.batch_size)
        noise = rng.standard_normal((len(chosen), slots + 1, model.config.latent_dim), dtype=np.float32)
        batch = perception_batch(frames[chosen], ids[chosen], slots, noise, noise[:1, 0])
        loss = trainee.loss(batch)["loss"]
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        if step >= 3:
            rates.append(batch.images / (time.perf_counter() - start))
    return statistics.median(rates)


def decode_throughput(model: ComponentVAE, batch: int = 32, repeats: int = 30) -> float:
    """Median object decodes per second at a small batch, as scoring uses them."""
    z = torch.randn(batch, model.config.latent_dim)
    times = []
    with torch.no_grad():
        for _ in range(repeats + 3):
            start = time.perf_counter()
            model.decode(z)
            times.append(time.perf_counter() - start)
    return batch / statistics.median(times[3:])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, help="run directory, perception.pt, or run name under runs/")
    parser.add_argument("--data", required=True, help="held-out split file at the model's resolution (any split)")
    parser.add_argument("--videos", type=int, default=300, help="videos of --data to use (default 300)")
    parser.add_argument("--steps", type=int, default=20, help="training steps timed for throughput")
    parser.add_argument("--rounds", type=int, default=1000, help="bootstrap resamples of the intervals")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--figure", help="also draw originals against reconstructions to this PNG")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        model, state = load_perception(args.model)
        held = quality.read_held_out(args.data, args.videos, model.config.image_size)
    except xvoe.XvoeError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    count, frames, size = held.rgbd.shape[:3]
    if Path(args.data).resolve() == Path(state["meta"].get("data", "")):
        print(f"warning: {args.data} is the file this model was trained on; its frames are not held out")
    train_config = from_dict(TrainConfig, state["train"])
    took = f" in {state['elapsed'] / 60:.1f} min" if "elapsed" in state else ""    # shipped weights keep no timing
    print(f"model {state['path']}: {recipe_of(state['config'])} recipe, {model.config.encoder} encoder, "
          f"{size}x{size}, D={model.config.latent_dim}, {state['step']} steps{took} "
          f"(batch {train_config.batch_size} frames, {state.get('world', 1)} process(es))")
    print(f"data {args.data}: {count} videos x {frames} frames")
    psnr = quality.reconstruction(model, held, args.rounds)
    print("composite PSNR (95% interval over videos): " + ", ".join(
        f"{label} {psnr[name][0]:.2f} dB [{psnr[name][1]:.2f}, {psnr[name][2]:.2f}]"
        for name, label in (("rgb", "RGB"), ("depth", "depth"), ("objects", "RGB on object pixels"))))
    means, targets, visible = quality.latent_positions(model, held)
    probes = quality.position_probes(means, targets, visible, held.kind, held.kind_names, args.rounds)
    print("linear probe (latent mean -> x, y) fitted on the first half of the videos, R^2 on the visible objects "
          "of the second half (95% interval over videos):")
    for name, found in probes.items():
        which = "all kinds, one probe" if name == quality.POOLED else name
        axes = quality.PROBE_GOALS.get(name, ())
        goal = f" (goal: {' and '.join(axes)} >= {PROBE_R2})" if axes else ""
        figures = ", ".join(f"{axis} {value:.4f} [{low:.4f}, {high:.4f}]"
                            for axis, (value, low, high) in (("x", found.x), ("y", found.y)))
        print(f"  {which}, {found.objects} objects: {figures}{goal}" + (f" ({found.reason})" if found.reason else ""))
    fraction = held.states[..., held.columns.index("visible")]
    x, radius = targets[..., 0], held.states[..., held.columns.index("size")]
    edge = (x - radius < 0) | (x + radius > size)
    for name, (count_in, rms) in quality.hidden_part_error(means, targets, visible, fraction, edge).items():
        print(f"  position read from the latents, {name} objects ({count_in}): RMS error x {rms[0]:.2f} px, "
              f"y {rms[1]:.2f} px")
    rate = train_throughput(model, held, train_config, args.steps)
    print(f"training throughput: {rate:.0f} object images/s ({args.threads} threads, batch "
          f"{train_config.batch_size} frames)")
    print(f"decoder throughput: {decode_throughput(model):.0f} object decodes/s (batch 32)")
    if args.figure:
        print(f"figure: {save_reconstructions(model, held.rgbd, held.ids, args.figure)}")
    goals = [getattr(probes[name], axis)[0] for name, axes in quality.PROBE_GOALS.items() for axis in axes]
    print(f"psnr={psnr['rgb'][0]:.1f} probe_r2={float('nan') if np.isnan(goals).any() else min(goals):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
