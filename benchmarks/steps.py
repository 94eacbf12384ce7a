"""Time of one training or scoring step of a preset's models, against the TensorFlow reference.

Three stages, on random inputs of the right shapes (8 slots, 15-frame videos) and freshly built
models (untrained weights cost the same as trained ones):
  perception  one training step of the Component VAE (forward, backward, Adam), per frame
  xpl         one training step of XPL (Transformers 1 and 2, the dynamics, Adam), per video
  score       one MSE scoring pass (encode every frame, Transformers 1 and 2, decode, composite), per video
  nll         one NLL scoring pass (encode every frame, then the recipe's NLL: proposal, SMC over the
              particles), per video, on frames with one slot never seen (a hidden object's); its work
              hangs on the video (a pilot run may spare the full one, a sure existence head skips
              the pilot), so on random frames it is one draw; nll-least: the smallest pilot run
              alone, nll-most: every pilot and then the full run; no reference
  phydnet     one training step of the PhyDNet baseline with the recipe's first ConvLSTM kernel, per
              video (phydnet-widened: with the kernel its widening phase gives it); no reference
Each stage runs `--warmup` steps, then `--repeats` timed ones; it prints the median wall time
per item and the median CPU time (all threads: on a loaded machine it moves less than the wall
time), the minor page faults and the kernel share (system / (user + system) CPU time) per
step, the peak resident memory, and the wall time over the reference's ("vs ref"; the goal is
below 0.5x at the paper preset). The reference (TensorFlow, 2 threads, a 32-channel decoder):
383 ms per 128x128 frame, 539 ms per video, 881 ms per video.

It also counts each step's multiply-accumulates (xvoe.evaluation.operations: torch's
FlopCounterMode with the CPU flash attention and the fused LSTM layer registered; matrix
products, convolutions and attention, forward and backward; "torch GMAC" is what FlopCounterMode
counts alone) and sets them against this machine's own rate: a large matrix product timed in the
same process ("peak"). `--count-only` prints the counts without timing anything. Rates are per
core, multiply-accumulates per CPU second, so that other jobs on the machine move them little.
"goal needs" is the rate per core at which our step would have to run on --threads cores for
half the reference's time: above the peak, the goal cannot be met by making the step faster,
only by a step with fewer operations.

    python benchmarks/steps.py --recipe paper --decoder-channels 32
    python benchmarks/steps.py --recipe cpu-short --stages score
    python benchmarks/steps.py --recipe cpu-short --stages phydnet,phydnet-widened --threads 1
    python benchmarks/steps.py --recipe paper --stages perception,xpl,score,nll --count-only

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

from inference.surprise import nll_surprise
from xvoe import allocator
from xvoe.evaluation.operations import Operations, count_operations
from xvoe.evaluation.surprise import mse_surprise
from xvoe.models.devices import mixed_precision
from xvoe.models.nll import InferenceConfig
from xvoe.models.perception import ComponentVAE, normalise
from xvoe.models.phydnet import PhyDNet, PhyDNetObjective
from xvoe.models.xpl import XPL
from xvoe.training.data import perception_batch, visible_threshold
from xvoe.training.latents import encode_frames
from xvoe.training.recipes import recipe
from xvoe.training.xpl import LatentBatch

REFERENCE_MS = {"perception": 383.0, "xpl": 539.0, "score": 881.0}   # TensorFlow, 2 threads, this machine
UNIT = {"perception": "frame", "xpl": "video", "score": "video", "nll": "video", "phydnet": "video"}
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


def training_step(model, optimiser, batch, device: str = "cpu"):
    """One optimiser step on a fixed batch, as the training loop takes it (its forward pass
    under the device's mixed precision)."""
    precision = mixed_precision(torch.device(device))

    def step() -> None:
        with precision:
            loss = model(batch)["loss"]
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
    return step


def perception_step(config, frames: int, rng: np.random.Generator, device: str = "cpu"):
    model = ComponentVAE(config).to(device).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    rgbd, ids = random_frames(rng, frames, config.image_size)
    noise = rng.standard_normal((frames, SLOTS + 1, config.latent_dim), dtype=np.float32)
    batch = perception_batch(rgbd, ids, SLOTS, noise, noise[:1, 0]).to(device)

    return training_step(model, optimiser, batch, device)


def xpl_step(config, videos: int, rng: np.random.Generator, device: str = "cpu"):
    model = XPL(config).to(device).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    dim, shape = config.dynamics.latent_dim, (videos, FRAMES, SLOTS)
    walls = torch.zeros(videos, SLOTS, dtype=torch.bool)
    walls[:, 0] = True
    batch = LatentBatch(mean=torch.from_numpy(rng.uniform(-3, 3, (*shape, dim)).astype(np.float32)),
                        visible=torch.from_numpy(rng.random(shape) < 0.8),
                        order=torch.from_numpy(np.argsort(rng.random((videos, SLOTS)), axis=1)),
                        hidden=torch.from_numpy(rng.integers(0, SLOTS, videos)),
                        refill=torch.from_numpy(rng.random(shape) < 0.2), walls=walls).to(device)

    return training_step(model, optimiser, batch, device)


def phydnet_step(config, videos: int, rng: np.random.Generator, device: str = "cpu"):
    """What the PhyDNet stage's loop does per batch of uint8 videos (B, T, H, W, 4)."""
    model = PhyDNetObjective(PhyDNet(config)).to(device).train()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-4)
    size = config.image_size
    batch = torch.from_numpy(rng.integers(0, 256, (videos, FRAMES, size, size, 4), dtype=np.uint8)).to(device)
    return training_step(model, optimiser, batch, device)


def score_step(perception, xpl_config, videos: int, rng: np.random.Generator, device: str = "cpu"):
    vae, xpl = ComponentVAE(perception).to(device).eval(), XPL(xpl_config).to(device).eval()
    size = perception.image_size
    rgbd, ids = random_frames(rng, videos * FRAMES, size)
    occluder = torch.zeros(videos, SLOTS, dtype=torch.bool, device=device)
    occluder[:, 0] = True
    precision = mixed_precision(torch.device(device))

    def step() -> None:       # what score.score_split does per batch of videos (encode_videos, _xpl_curves)
        encoded = encode_frames(vae, rgbd, ids, SLOTS)
        shaped = {k: torch.from_numpy(v).reshape(videos, FRAMES, *v.shape[1:]).to(device) for k, v in encoded.items()}
        frames = normalise(torch.from_numpy(rgbd.reshape(videos, FRAMES, size, size, 4))).to(device)
        with precision:
            mse_surprise(vae, xpl, frames, shaped["mean"], shaped["pixels"] > visible_threshold(size),
                         shaped["background_mean"], occluder)
    return step


def nll_step(perception, xpl_config, settings, rng: np.random.Generator, device: str = "cpu"):
    """One video encoded and scored by the NLL, as xvoe score --surprise nll does per video. Its
    last slot is never drawn: a slot free for a hidden object, without which the NLL samples nothing."""
    vae, xpl = ComponentVAE(perception).to(device).eval(), XPL(xpl_config).to(device).eval()
    size = perception.image_size
    rgbd, ids = random_frames(rng, FRAMES, size)
    ids[ids == SLOTS] = 0
    occluder = torch.zeros(SLOTS, dtype=torch.bool, device=device)
    occluder[0] = True

    def step() -> None:
        encoded = {k: torch.from_numpy(v).to(device) for k, v in encode_frames(vae, rgbd, ids, SLOTS).items()}
        frames = normalise(torch.from_numpy(rgbd)).to(device)
        nll_surprise(vae, xpl, frames, encoded["mean"], encoded["pixels"] > visible_threshold(size),
                     encoded["background_mean"], occluder, settings, seed=0)
    return step


def nll_least(settings: InferenceConfig) -> InferenceConfig:
    """The NLL's cheapest path: its smallest pilot run decides, the full run is spared."""
    sizes = [size for size in np.atleast_1d(settings.smc_pilot) if 0 < size < settings.particles]
    return replace(settings, particles=int(min(sizes, default=settings.particles)), smc_pilot=0)


def nll_most(settings: InferenceConfig) -> InferenceConfig:
    """The NLL's dearest path: every pilot runs and none spares the full run."""
    return replace(settings, smc_pilot_skip_exists=1.0, smc_pilot_margin=1e12)


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


def gaps(counted: Operations) -> str:
    """A warning after a row whose count misses a product kernel (a new torch, another path)."""
    return f"  NOT COUNTED: {', '.join(sorted(counted.uncounted))}" if counted.uncounted else ""


def timed_row(stage: str, found: dict[str, float], counted: Operations, items: int, threads: int,
              peak: float) -> str:
    """One stage's line: times per item, the true and torch-counted GMAC, the rate and the goal."""
    gmacs, ms = counted.gmacs / items, 1000 * found["wall"] / items
    base = stage.split("-")[0]
    if base in REFERENCE_MS:
        needs = gmacs / (REFERENCE_MS[base] / 2 / 1000) / threads    # per core, for half the reference's time
        versus, goal = f"{ms / REFERENCE_MS[base]:6.2f}x", f"{needs:7.1f} ({needs / peak:.1f}x peak)"
    else:
        versus, goal = f"{'-':>7}", f"{'-':>7}"
    return (f"{stage:<15} {ms:9.1f} {1000 * found['spread'] / items:6.1f} {versus} "
            f"{1000 * found['cpu'] / items:12.1f} {found['faults']:12.0f} {found['kernel']:7.1%} "
            f"{gmacs:10.2f} {counted.torch_gmacs / items:10.2f} {gmacs / (found['cpu'] / items):10.1f} {goal}  "
            f"{items} {UNIT[base]}s")


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
    parser.add_argument("--count-only", action="store_true", help="count the operations, time nothing")
    args = parser.parse_args()

    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    chosen = recipe(args.recipe)
    perception = chosen.perception
    if args.decoder_channels:
        perception = replace(perception, decoder_channels=args.decoder_channels)
    print(f"recipe {args.recipe}: {perception.image_size}px, decoder {perception.decoder_channels} channels, "
          f"{args.threads} threads, allocator tuned: {allocator.tuned()}, torch {torch.__version__}")
    builders = {"perception": lambda rng: (perception_step(perception, args.frames, rng), args.frames),
                "xpl": lambda rng: (xpl_step(chosen.xpl, args.videos, rng), args.videos),
                "score": lambda rng: (score_step(perception, chosen.xpl, args.score_videos, rng), args.score_videos),
                "nll": lambda rng: (nll_step(perception, chosen.xpl, chosen.nll, rng), 1),
                "nll-least": lambda rng: (nll_step(perception, chosen.xpl, nll_least(chosen.nll), rng), 1),
                "nll-most": lambda rng: (nll_step(perception, chosen.xpl, nll_most(chosen.nll), rng), 1),
                "phydnet": lambda rng: (phydnet_step(chosen.phydnet, args.phydnet_videos, rng), args.phydnet_videos),
                "phydnet-widened": lambda rng: (phydnet_step(chosen.final_phydnet(), args.phydnet_videos, rng),
                                                args.phydnet_videos)}
    if args.count_only:
        print(f"{'stage':<15} {'GMAC/item':>10} {'torch GMAC':>10}  items/step")
        for stage in args.stages.split(","):
            torch.manual_seed(args.seed)    # the same weights, so the NLL's path, whichever stages ran before
            step, items = builders[stage](np.random.default_rng(args.seed))
            counted = count_operations(step)
            print(f"{stage:<15} {counted.gmacs / items:10.3f} {counted.torch_gmacs / items:10.3f}  "
                  f"{items} {UNIT[stage.split('-')[0]]}s{gaps(counted)}", flush=True)
        return
    peak = matmul_peak()
    print(f"peak: a 2048x2048 matrix product runs at {peak:.1f} GMAC per CPU second")
    print(f"{'stage':<15} {'ms/item':>9} {'+-':>6} {'vs ref':>7} {'cpu ms/item':>12} {'faults/step':>12} "
          f"{'kernel':>7} {'GMAC/item':>10} {'torch GMAC':>10} {'GMAC/cpu-s':>10} {'goal needs':>11}  items/step")
    for stage in args.stages.split(","):
        torch.manual_seed(args.seed)        # the same weights whichever stages ran before
        step, items = builders[stage](np.random.default_rng(args.seed))
        found = measure(step, args.warmup, args.repeats)
        counted = count_operations(step)
        print(timed_row(stage, found, counted, items, args.threads, peak) + gaps(counted), flush=True)
    print(f"peak resident memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


if __name__ == "__main__":
    main()
