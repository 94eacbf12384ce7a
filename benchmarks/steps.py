"""Time of one training or scoring step of a preset's models, against what this machine can do.

Three stages, on random inputs of the right shapes (8 slots, 15-frame videos) and freshly built
models (untrained weights cost the same as trained ones):
  perception  one training step of the Component VAE (forward, backward, Adam), per frame
  xpl         one training step of XPL (Transformers 1 and 2, the dynamics, Adam), per video
  score       one MSE scoring pass (encode every frame, Transformers 1 and 2, decode, composite), per video
  nll         one NLL scoring pass (encode every frame, then the recipe's NLL: proposal, SMC over the
              particles), per video, on frames with one slot never seen (a hidden object's); its work
              hangs on the video (a pilot run may spare the full one, a sure existence head skips
              the pilot), so on random frames it is one draw; nll-least: the smallest pilot run
              alone, nll-most: every pilot and then the full run
  phydnet     one training step of the PhyDNet baseline with the recipe's first ConvLSTM kernel, per
              video (phydnet-widened: with the kernel its widening phase gives it)
Each stage is built once and timed at every thread count of `--threads` (default 1 and 2) in
turn: `--warmup` steps, then `--repeats` timed ones. Per stage and thread count it prints the
median wall time per item, the median CPU time (all threads), the minor page faults and the
kernel share (system / (user + system) CPU time) per step, and, from the step's true counts
(xvoe.evaluation.operations: torch's FlopCounterMode with the CPU flash attention and the fused
LSTM layer registered; "torch GMAC" is what FlopCounterMode counts alone), its multiply-
accumulates per wall-clock second and their fraction of a 2048x2048 float32 matrix product's
rate, measured in this process at the same thread count ("of product"), and its items per second
at N threads over those at 1 ("x 1 thread").

The goals (docs/design.md, "Goals") are printed beside them: at 1 thread >= 80% of the product's
rate for a step bound by arithmetic, and at N threads >= 0.9 N times the 1-thread throughput
(1.8x at 2). A step is bound by memory when its bytes moved take longer at the machine's
bandwidth than its multiply-accumulates at the product's rate; it is then held to the bandwidth
instead. The bandwidth is a large tensor copy's (bytes read and written per wall second) at the
same thread count; the bytes are those its operations read and write, counted with the
multiply-accumulates (xvoe.evaluation.operations says what that leaves out: a lower bound on
traffic). A step below 30% of the product's rate gets a note: how much of its time its bytes at
the bandwidth explain. The figures are wall clock: other jobs on the machine move them, so only
an idle machine's are results. `--count-only` prints the counts without timing anything.

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
from dataclasses import dataclass, replace

import numpy as np
import torch

from xvoe import allocator
from xvoe.evaluation.operations import Operations, count_operations
from xvoe.evaluation.surprise import mse_surprise
from xvoe.inference.surprise import nll_surprise
from xvoe.models.devices import mixed_precision
from xvoe.models.nll import InferenceConfig
from xvoe.models.perception import ComponentVAE, normalise
from xvoe.models.phydnet import PhyDNet, PhyDNetObjective
from xvoe.models.xpl import XPL
from xvoe.training import stages as registry  # the stage names (XPL here is the network)
from xvoe.training.data import perception_batch, visible_threshold
from xvoe.training.latent_batches import LatentBatch
from xvoe.training.latents import encode_frames
from xvoe.training.recipes import recipe

UNIT = {registry.PERCEPTION: "frame", registry.XPL: "video", "score": "video", "nll": "video",
        registry.PHYDNET: "video"}
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

    def step() -> None:       # what xvoe score does per batch of videos (encode_videos, mse_curves)
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


# the goals (docs/design.md, "Goals"): a share of the product's rate (or of the bandwidth, for a
# step bound by memory) at 1 thread, and of perfect scaling at N threads
GOAL_SHARE, GOAL_SCALING, FAR_BELOW = 0.8, 0.9, 0.3


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


@dataclass(frozen=True)
class Machine:
    """What this process gets from the machine at one thread count: the two ceilings of a step."""

    threads: int
    product_rate: float     # GMAC per wall second of a 2048x2048 float32 matrix product
    bandwidth: float        # GB per wall second read and written by a large tensor copy


def matmul_rate(size: int = 2048, repeats: int = 5) -> float:
    """GMAC per wall second of a large float32 matrix product: the fastest the operations the
    steps are made of run here (median over repeats, after one warm-up)."""
    generator = torch.Generator().manual_seed(0)
    a, b = (torch.randn(size, size, generator=generator) for _ in range(2))
    return size ** 3 / measure(lambda: a @ b, 1, repeats)["wall"] / 1e9


def copy_bandwidth(megabytes: int = 256, repeats: int = 5) -> float:
    """GB per wall second a copy of a tensor far larger than the caches reads and writes."""
    source = torch.ones(megabytes * 2**20 // 4)
    target = torch.empty_like(source)
    return 2 * source.nbytes / measure(lambda: target.copy_(source), 1, repeats)["wall"] / 1e9


def machine(threads: int) -> Machine:
    torch.set_num_threads(threads)
    return Machine(threads, matmul_rate(), copy_bandwidth())


def gaps(counted: Operations) -> str:
    """A warning after a row whose count misses a product kernel (a new torch, another path)."""
    return f"  NOT COUNTED: {', '.join(sorted(counted.uncounted))}" if counted.uncounted else ""


def bound_by_memory(counted: Operations, at: Machine) -> bool:
    """The roofline: its bytes at the bandwidth take longer than its products at the product's rate."""
    return counted.gigabytes / at.bandwidth > counted.gmacs / at.product_rate


def goal(counted: Operations, at: Machine, seconds: float, one_thread: float | None) -> str:
    """The goal that applies at this thread count, and whether the step meets it."""
    if at.threads == 1:
        memory = bound_by_memory(counted, at)
        share = counted.gigabytes / seconds / at.bandwidth if memory else counted.gmacs / seconds / at.product_rate
        target = f">= {GOAL_SHARE:.0%} of {'bandwidth' if memory else 'product'}"
        return f"{target}: {'met' if share >= GOAL_SHARE else 'missed'}"
    if one_thread is None:
        return "-"
    wanted = GOAL_SCALING * at.threads
    return f">= {wanted:.1f}x 1 thread: {'met' if one_thread / seconds >= wanted else 'missed'}"


def far_below(counted: Operations, at: Machine, seconds: float) -> str:
    """Under FAR_BELOW of the product's rate: how much of the step's time its traffic explains."""
    if counted.gmacs / seconds >= FAR_BELOW * at.product_rate:
        return ""
    memory_ms, arithmetic_ms = 1000 * counted.gigabytes / at.bandwidth, 1000 * counted.gmacs / at.product_rate
    rest = 1000 * seconds - max(memory_ms, arithmetic_ms)
    return (f"\n{'':<15} far below the product: of its {1000 * seconds:.1f} ms a step, its "
            f"{counted.gigabytes:.3f} GB at {at.bandwidth:.1f} GB/s take {memory_ms:.1f}, its MACs at the "
            f"product's rate {arithmetic_ms:.1f}; the other {rest:.1f} ms neither bounds (many small "
            f"operations, the threads' waits)")


HEADER = (f"{'stage':<15} {'threads':>7} {'ms/item':>9} {'+-':>6} {'cpu ms/item':>12} {'faults/step':>12} "
          f"{'kernel':>7} {'GMAC/item':>10} {'torch GMAC':>10} {'GMAC/s':>8} {'of product':>10} "
          f"{'GB/item':>8} {'GB/s':>6} {'of bandwidth':>12} {'x 1 thread':>10} {'bound':>6}  goal  items/step")


def timed_row(stage: str, found: dict[str, float], counted: Operations, items: int, at: Machine,
              one_thread: float | None) -> str:
    """One stage's line at one thread count: times per item, rates against the machine, the goal."""
    seconds, per_item = found["wall"], 1000 / items
    scaling = f"{one_thread / seconds:9.2f}x" if one_thread is not None and at.threads > 1 else f"{'-':>10}"
    return (f"{stage:<15} {at.threads:7d} {per_item * seconds:9.1f} {per_item * found['spread']:6.1f} "
            f"{per_item * found['cpu']:12.1f} {found['faults']:12.0f} {found['kernel']:7.1%} "
            f"{counted.gmacs / items:10.3f} {counted.torch_gmacs / items:10.3f} {counted.gmacs / seconds:8.1f} "
            f"{counted.gmacs / seconds / at.product_rate:10.1%} {counted.gigabytes / items:8.3f} "
            f"{counted.gigabytes / seconds:6.1f} {counted.gigabytes / seconds / at.bandwidth:12.1%} {scaling} "
            f"{'memory' if bound_by_memory(counted, at) else 'MACs':>6}  {goal(counted, at, seconds, one_thread)}  "
            f"{items} {UNIT[stage.split('-')[0]]}s{gaps(counted)}{far_below(counted, at, seconds)}")


def thread_counts(text: str) -> list[int]:
    """`--threads`: positive whole numbers, comma-separated."""
    try:
        counts = [int(part) for part in text.split(",")]
    except ValueError:
        counts = []
    if not counts or min(counts) < 1:
        raise argparse.ArgumentTypeError(f"expected thread counts such as 1,2, got {text!r}")
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recipe", default="paper")
    parser.add_argument("--decoder-channels", type=int, default=0, help="override the recipe's")
    parser.add_argument("--stages", default=f"{registry.PERCEPTION},{registry.XPL},score")
    parser.add_argument("--frames", type=int, default=4, help="frames per perception step")
    parser.add_argument("--videos", type=int, default=8, help="videos per XPL step")
    parser.add_argument("--score-videos", type=int, default=2, help="videos per scoring pass")
    parser.add_argument("--phydnet-videos", type=int, default=8, help="videos per PhyDNet step (the recipes' 8)")
    parser.add_argument("--threads", type=thread_counts, default=[1, 2], help="thread counts, timed in turn")
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--count-only", action="store_true", help="count the operations, time nothing")
    args = parser.parse_args()

    chosen = recipe(args.recipe)
    perception = chosen.perception
    if args.decoder_channels:
        perception = replace(perception, decoder_channels=args.decoder_channels)
    builders = {registry.PERCEPTION: lambda rng: (perception_step(perception, args.frames, rng), args.frames),
                registry.XPL: lambda rng: (xpl_step(chosen.xpl, args.videos, rng), args.videos),
                "score": lambda rng: (score_step(perception, chosen.xpl, args.score_videos, rng), args.score_videos),
                "nll": lambda rng: (nll_step(perception, chosen.xpl, chosen.nll, rng), 1),
                "nll-least": lambda rng: (nll_step(perception, chosen.xpl, nll_least(chosen.nll), rng), 1),
                "nll-most": lambda rng: (nll_step(perception, chosen.xpl, nll_most(chosen.nll), rng), 1),
                registry.PHYDNET: lambda rng: (phydnet_step(chosen.phydnet, args.phydnet_videos, rng),
                                               args.phydnet_videos),
                "phydnet-widened": lambda rng: (phydnet_step(chosen.final_phydnet(), args.phydnet_videos, rng),
                                                args.phydnet_videos)}
    stages = args.stages.split(",")
    unknown = [stage for stage in stages if stage not in builders]
    if unknown:
        parser.error(f"unknown stage {', '.join(unknown)}; known: {', '.join(builders)}")

    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads[0])
    print(f"recipe {args.recipe}: {perception.image_size}px, decoder {perception.decoder_channels} channels, "
          f"threads {','.join(map(str, args.threads))}, allocator tuned: {allocator.tuned()}, "
          f"torch {torch.__version__}")
    if args.count_only:
        print(f"{'stage':<15} {'GMAC/item':>10} {'torch GMAC':>10} {'GB/item':>8}  items/step")
        for stage in stages:
            torch.manual_seed(args.seed)    # the same weights, so the NLL's path, whichever stages ran before
            step, items = builders[stage](np.random.default_rng(args.seed))
            counted = count_operations(step)
            print(f"{stage:<15} {counted.gmacs / items:10.3f} {counted.torch_gmacs / items:10.3f} "
                  f"{counted.gigabytes / items:8.3f}  {items} {UNIT[stage.split('-')[0]]}s{gaps(counted)}", flush=True)
        return
    machines = [machine(threads) for threads in args.threads]
    for at in machines:
        print(f"{at.threads} thread(s): a 2048x2048 matrix product runs at {at.product_rate:.1f} GMAC/s, "
              f"a large copy moves {at.bandwidth:.1f} GB/s")
    print(f"goals: at 1 thread >= {GOAL_SHARE:.0%} of the product's rate (of the bandwidth for a step bound "
          f"by memory); at N threads >= {GOAL_SCALING} N x the 1-thread items per second")
    print(HEADER)
    for stage in stages:
        torch.manual_seed(args.seed)        # the same weights whichever stages ran before
        torch.set_num_threads(args.threads[0])
        step, items = builders[stage](np.random.default_rng(args.seed))
        counted, one_thread = count_operations(step), None
        for at in machines:
            torch.set_num_threads(at.threads)
            found = measure(step, args.warmup, args.repeats)
            one_thread = found["wall"] if at.threads == 1 else one_thread
            print(timed_row(stage, found, counted, items, at, one_thread), flush=True)
    print(f"peak resident memory {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


if __name__ == "__main__":
    allocator.tune()        # timed as the command line runs: with its malloc settings
    main()
