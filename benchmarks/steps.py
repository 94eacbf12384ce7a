"""Time of one training or scoring step of a preset's models, against the TensorFlow reference.

Three stages, on random inputs of the right shapes (8 slots, 15-frame videos) and freshly built
models (untrained weights cost the same as trained ones):
  perception  one training step of the Component VAE (forward, backward, Adam), per frame
  xpl         one training step of XPL (Transformers 1 and 2, the dynamics, Adam), per video
  score       one MSE scoring pass (encode every frame, Transformers 1 and 2, decode, composite), per video
  phydnet     one training step of the PhyDNet baseline with the recipe's first ConvLSTM kernel, per
              video (phydnet-widened: with the kernel its widening phase gives it); no reference
Each stage runs `--warmup` steps, then `--repeats` timed ones; it prints the median wall time
per item and the median CPU time (all threads: on a loaded machine it moves less than the wall
time), the minor page faults and the kernel share (system / (user + system) CPU time) per
step, the peak resident memory, and the wall time over the reference's ("vs ref"; the goal is
below 0.5x at the paper preset). The reference (TensorFlow, 2 threads, a 32-channel decoder):
383 ms per 128x128 frame, 539 ms per video, 881 ms per video.

It also counts each step's multiply-accumulates (torch's FlopCounterMode: matrix products,
convolutions and attention, forward and backward; the fused LSTM is not counted, so the XPL
figure is a floor) and sets them against this machine's own rate: a large matrix product timed
in the same process ("peak"). Rates are per core, multiply-accumulates per CPU second, so that
other jobs on the machine move them little. "goal needs" is the rate per core at which our step
would have to run on --threads cores for half the reference's time: above the peak, the goal
cannot be met by making the step faster, only by a step with fewer operations.

    python benchmarks/steps.py --recipe paper --decoder-channels 32
    python benchmarks/steps.py --recipe cpu-short --stages score
    python benchmarks/steps.py --recipe cpu-short --stages phydnet,phydnet-widened --threads 1

The allocator setting (xvoe/allocator.py) is per process: compare it by running this twice,
once with XVOE_MALLOC=system; the faults column shows the difference without timing noise.
"""
from __future__ import annotations

import argparse
import resource
import statistics
import time
from dataclasses import replace

import numpy as np
import torch
from torch.utils.flop_counter import FlopCounterMode

from xvoe import allocator
from xvoe.evaluation.surprise import mse_surprise
from xvoe.models.perception import ComponentVAE, normalise
from xvoe.models.phydnet import PhyDNet, PhyDNetObjective
from xvoe.models.xpl import XPL
from xvoe.training.data import perception_batch, visible_threshold
from xvoe.training.latents import encode_frames
from xvoe.training.recipes import recipe
from xvoe.training.xpl import LatentBatch

REFERENCE_MS = {"perception": 383.0, "xpl": 539.0, "score": 881.0}   # TensorFlow, 2 threads, this machine
UNIT = {"perception": "frame", "xpl": "video", "score": "video", "phydnet": "video"}
SLOTS, FRAMES = 8, 15


def random_frames(rng: np.random.Generator, count: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """uint8 RGBD frames (N,H,W,4) and id maps (N,H,W) with all 8 slots drawn as rectangles."""
    rgbd = rng.integers(0, 256, (count, size, size, 4), dtype=np.uint8)
    ids = np.zeros((count, size, size), np.int64)
    side = max(2, size // 5)
    for n in range(count):
        for slot in range(1, SLOTS + 1):
            y, x = rng.integers(0, size - side, 2)
            ids[n, y:y + side, x:x + side] = slot
    return rgbd, ids


def training_step(model, optimiser, batch):
    """One optimiser step on a fixed batch, as the training loop takes it."""
    def step() -> None:
        loss = model(batch)["loss"]
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
    return step


def perception_step(config, frames: int, rng: np.random.Generator):
    model = ComponentVAE(config).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    rgbd, ids = random_frames(rng, frames, config.image_size)
    noise = rng.standard_normal((frames, SLOTS + 1, config.latent_dim), dtype=np.float32)
    batch = perception_batch(rgbd, ids, SLOTS, noise, noise[:1, 0])

    return training_step(model, optimiser, batch)


def xpl_step(config, videos: int, rng: np.random.Generator):
    model = XPL(config).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    dim, shape = config.dynamics.latent_dim, (videos, FRAMES, SLOTS)
    walls = torch.zeros(videos, SLOTS, dtype=torch.bool)
    walls[:, 0] = True
    batch = LatentBatch(mean=torch.from_numpy(rng.uniform(-3, 3, (*shape, dim)).astype(np.float32)),
                        visible=torch.from_numpy(rng.random(shape) < 0.8),
                        order=torch.from_numpy(np.argsort(rng.random((videos, SLOTS)), axis=1)),
                        hidden=torch.from_numpy(rng.integers(0, SLOTS, videos)),
                        refill=torch.from_numpy(rng.random(shape) < 0.2), walls=walls)

    return training_step(model, optimiser, batch)


def phydnet_step(config, videos: int, rng: np.random.Generator):
    """What the PhyDNet stage's loop does per batch of uint8 videos (B, T, H, W, 4)."""
    model = PhyDNetObjective(PhyDNet(config)).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    size = config.image_size
    batch = torch.from_numpy(rng.integers(0, 256, (videos, FRAMES, size, size, 4), dtype=np.uint8))
    return training_step(model, optimiser, batch)


def score_step(perception, xpl_config, videos: int, rng: np.random.Generator):
    vae, xpl = ComponentVAE(perception).eval(), XPL(xpl_config).eval()
    size = perception.image_size
    rgbd, ids = random_frames(rng, videos * FRAMES, size)
    occluder = torch.zeros(videos, SLOTS, dtype=torch.bool)
    occluder[:, 0] = True

    def step() -> None:       # what score.score_split does per batch of videos (encode_videos, _xpl_curves)
        encoded = encode_frames(vae, rgbd, ids, SLOTS)
        shaped = {k: torch.from_numpy(v).reshape(videos, FRAMES, *v.shape[1:]) for k, v in encoded.items()}
        frames = normalise(torch.from_numpy(rgbd.reshape(videos, FRAMES, size, size, 4)))
        mse_surprise(vae, xpl, frames, shaped["mean"], shaped["pixels"] > visible_threshold(size),
                     shaped["background_mean"], occluder)
    return step


def counted_gmacs(step) -> float:
    """Multiply-accumulates (10^9) of one run of the step, as torch counts them (2 FLOPs each)."""
    counter = FlopCounterMode(display=False)
    fastpath = torch.backends.mha.get_fastpath_enabled()
    torch.backends.mha.set_fastpath_enabled(False)      # the Transformer's fused inference op is not counted
    try:
        with counter:
            step()
    finally:
        torch.backends.mha.set_fastpath_enabled(fastpath)
    return counter.get_total_flops() / 2e9


def matmul_peak(size: int = 2048, repeats: int = 5) -> float:
    """GMAC per CPU second of a large float32 matrix product: the fastest one core runs the
    operations the steps are made of (median CPU time over repeats, after one warm-up)."""
    generator = torch.Generator().manual_seed(0)
    a, b = (torch.randn(size, size, generator=generator) for _ in range(2))
    return size ** 3 / measure(lambda: a @ b, 1, repeats)["cpu"] / 1e9


def measure(step, warmup: int, repeats: int) -> dict[str, float]:
    """Median wall and CPU time (user + system, all threads) of a step, and its mean minor faults
    and kernel share over the repeats."""
    for _ in range(warmup):
        step()
    walls, cpus, faults, user, system = [], [], 0, 0.0, 0.0
    for _ in range(repeats):
        before, start = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
        step()
        walls.append(time.perf_counter() - start)
        after = resource.getrusage(resource.RUSAGE_SELF)
        faults += after.ru_minflt - before.ru_minflt
        user += after.ru_utime - before.ru_utime
        system += after.ru_stime - before.ru_stime
        cpus.append(after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime)
    return {"wall": statistics.median(walls), "cpu": statistics.median(cpus),
            "spread": (max(walls) - min(walls)) / 2, "faults": faults / repeats,
            "kernel": system / max(1e-9, user + system)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recipe", default="paper")
    parser.add_argument("--decoder-channels", type=int, default=0, help="override the recipe's (reference: 32)")
    parser.add_argument("--stages", default="perception,xpl,score")
    parser.add_argument("--frames", type=int, default=4, help="frames per perception step")
    parser.add_argument("--videos", type=int, default=8, help="videos per XPL step")
    parser.add_argument("--score-videos", type=int, default=2, help="videos per scoring pass")
    parser.add_argument("--phydnet-videos", type=int, default=8, help="videos per PhyDNet step (the recipes' 8)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    chosen = recipe(args.recipe)
    perception = chosen.perception
    if args.decoder_channels:
        perception = replace(perception, decoder_channels=args.decoder_channels)
    print(f"recipe {args.recipe}: {perception.image_size}px, decoder {perception.decoder_channels} channels, "
          f"{args.threads} threads, allocator tuned: {allocator.tuned()}, torch {torch.__version__}")
    peak = matmul_peak()
    print(f"peak: a 2048x2048 matrix product runs at {peak:.1f} GMAC per CPU second")
    print(f"{'stage':<15} {'ms/item':>9} {'+-':>6} {'vs ref':>7} {'cpu ms/item':>12} {'faults/step':>12} "
          f"{'kernel':>7} {'GMAC/item':>10} {'GMAC/cpu-s':>10} {'goal needs':>11}  items/step")
    builders = {"perception": lambda rng: (perception_step(perception, args.frames, rng), args.frames),
                "xpl": lambda rng: (xpl_step(chosen.xpl, args.videos, rng), args.videos),
                "score": lambda rng: (score_step(perception, chosen.xpl, args.score_videos, rng), args.score_videos),
                "phydnet": lambda rng: (phydnet_step(chosen.phydnet, args.phydnet_videos, rng), args.phydnet_videos),
                "phydnet-widened": lambda rng: (phydnet_step(chosen.final_phydnet(), args.phydnet_videos, rng),
                                                args.phydnet_videos)}
    for stage in args.stages.split(","):
        step, items = builders[stage](np.random.default_rng(args.seed))
        found = measure(step, args.warmup, args.repeats)
        gmacs = counted_gmacs(step) / items
        ms = 1000 * found["wall"] / items
        base = stage.split("-")[0]
        if base in REFERENCE_MS:
            needs = gmacs / (REFERENCE_MS[base] / 2 / 1000) / args.threads  # per core, for half the reference's time
            versus, goal = f"{ms / REFERENCE_MS[base]:6.2f}x", f"{needs:7.1f} ({needs / peak:.1f}x peak)"
        else:
            versus, goal = f"{'-':>7}", f"{'-':>7}"
        print(f"{stage:<15} {ms:9.1f} {1000 * found['spread'] / items:6.1f} {versus} "
              f"{1000 * found['cpu'] / items:12.1f} {found['faults']:12.0f} {found['kernel']:7.1%} "
              f"{gmacs:10.2f} {gmacs / (found['cpu'] / items):10.1f} {goal}  "
              f"{items} {UNIT[base]}s", flush=True)
    print(f"peak resident memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


if __name__ == "__main__":
    main()
