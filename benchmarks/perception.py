"""Benchmark of a trained perception module on held-out frames.

Prints the composite reconstruction PSNR (RGB, depth, and RGB on object pixels only), the R^2
of a linear probe from the latent means to each visible object's x and y (one probe for all
objects, fitted on half of the videos and scored on the other half; then one per kind), the
training throughput in object images per second,
the decoder throughput, and the training time recorded in the checkpoint. Last line:
`psnr=NN.N probe_r2=0.NNN` (RGB PSNR; the smaller of the x and y R^2 of the one probe).

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

from xvoe.apps.figures import save_reconstructions
from xvoe.benchmark import store
from xvoe.errors import XvoeError
from xvoe.models.config import from_dict
from xvoe.models.perception import ComponentVAE, to_uint8
from xvoe.training.data import ShardedFrames, check_size, perception_batch, visible_threshold
from xvoe.training.latents import encode_means
from xvoe.training.perception import load_perception
from xvoe.training.recipes import TrainConfig, recipe_of


def psnr(error_sum: float, count: int) -> float:
    return 10 * np.log10(255.0 ** 2 / max(error_sum / max(count, 1), 1e-12))


def reconstruction(model: ComponentVAE, rgbd: np.ndarray, ids: np.ndarray, slots: int,
                   batch: int = 256) -> dict[str, float]:
    """Squared errors of the decoded composites (posterior means), pooled over all frames."""
    sums = {"rgb": 0.0, "depth": 0.0, "objects": 0.0}
    counts = {"rgb": 0, "depth": 0, "objects": 0}
    for start in range(0, len(rgbd), batch):
        frames, maps = rgbd[start:start + batch], ids[start:start + batch]
        noise = np.zeros((len(frames), slots + 1, model.config.latent_dim), np.float32)
        parts = perception_batch(frames, maps, slots, noise, noise[:1, 0])
        with torch.no_grad():
            composite = to_uint8(model.forward_batch(parts, sample=False)["composite"]).numpy()
        error = (composite.astype(np.float64) - frames) ** 2
        sums["rgb"] += error[..., :3].sum()
        counts["rgb"] += error[..., :3].size
        sums["depth"] += error[..., 3].sum()
        counts["depth"] += error[..., 3].size
        on = maps > 0
        sums["objects"] += error[..., :3][on].sum()
        counts["objects"] += 3 * int(on.sum())
    return {name: psnr(sums[name], counts[name]) for name in sums}


def probe(means: np.ndarray, targets: np.ndarray, chosen: np.ndarray) -> list[float]:
    """R^2 per target column of a least-squares fit on the first half of the videos, scored on
    the second half, over the slots `chosen` (V,T,K); nan where the target does not vary."""
    half = len(means) // 2
    fit_rows, test_rows = chosen[:half], chosen[half:]
    x_fit = np.c_[means[:half][fit_rows], np.ones(fit_rows.sum())]
    x_test = np.c_[means[half:][test_rows], np.ones(test_rows.sum())]
    weights, *_ = np.linalg.lstsq(x_fit, targets[:half][fit_rows], rcond=None)
    truth, guess = targets[half:][test_rows], x_test @ weights
    spread = ((truth - truth.mean(0)) ** 2).sum(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        r2 = np.where(spread > 1e-6 * len(truth), 1 - ((truth - guess) ** 2).sum(0) / spread, np.nan)
    return [float(v) for v in r2]


def hidden_part_error(means: np.ndarray, targets: np.ndarray, seen: np.ndarray, fraction: np.ndarray,
                      edge: np.ndarray) -> dict:
    """RMS error (pixels) of x and y read linearly from the latents, by how much of the object is
    in view: the probe is fitted on wholly visible objects of the first half of the videos and
    applied to the second half's wholly visible ones, the partly hidden ones (behind another
    object) and the ones the frame's edge cuts. A position code that follows the visible part,
    not the object, shows as a larger error in the last two."""
    half = len(means) // 2
    groups = {"whole": seen & (fraction >= 0.99) & ~edge, "partly hidden": seen & (fraction < 0.9) & ~edge,
              "cut by the frame's edge": seen & edge}
    whole = groups["whole"][:half]
    weights, *_ = np.linalg.lstsq(np.c_[means[:half][whole], np.ones(whole.sum())], targets[:half][whole], rcond=None)
    errors = {}
    for name, chosen in groups.items():
        chosen = chosen[half:]
        guess = np.c_[means[half:][chosen], np.ones(chosen.sum())] @ weights
        errors[name] = (int(chosen.sum()), np.sqrt(((guess - targets[half:][chosen]) ** 2).mean(0)))
    return errors


def train_throughput(model: ComponentVAE, data: str, config: TrainConfig, steps: int) -> float:
    """Median object images per second of full training steps (forward, backward, Adam)."""
    frames = ShardedFrames(data, image_size=model.config.image_size, latent_dim=model.config.latent_dim,
                           batch_size=config.batch_size, shards=1, max_videos=200, seed=1)
    trainee = ComponentVAE(model.config)
    trainee.load_state_dict(model.state_dict())
    optimiser = torch.optim.Adam(trainee.parameters(), lr=config.lr)
    rates = []
    for step in range(steps + 3):
        start = time.perf_counter()
        batch = frames.batch(step)
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
    parser.add_argument("--data", required=True, help="held-out split file at the model's resolution")
    parser.add_argument("--videos", type=int, default=300, help="videos of --data to use (default 300)")
    parser.add_argument("--steps", type=int, default=20, help="training steps timed for throughput")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--figure", help="also draw originals against reconstructions to this PNG")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        model, state = load_perception(args.model)
        with store.open_dataset(args.data) as file:
            check_size(file, model.config.image_size, f"the checkpoint {state['path']}")
            count = min(args.videos, file["rgbd"].shape[0])
            rgbd, ids, states = file["rgbd"][:count], file["ids"][:count], file["states"][:count]
            columns = list(file["states"].attrs["state_columns"])
            kind, kind_names = file["kind"][:count], list(file.attrs["kind_names"])
    except XvoeError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    size, frames, slots = rgbd.shape[2], rgbd.shape[1], states.shape[2]
    if Path(args.data).resolve() == Path(state["meta"].get("data", "")):
        print(f"warning: {args.data} is the file this model was trained on; its frames are not held out")
    train_config = from_dict(TrainConfig, state["train"])
    took = f" in {state['elapsed'] / 60:.1f} min" if "elapsed" in state else ""    # shipped weights keep no timing
    print(f"model {state['path']}: {recipe_of(state['config'])} recipe, {model.config.encoder} encoder, "
          f"{size}x{size}, D={model.config.latent_dim}, {state['step']} steps{took} "
          f"(batch {train_config.batch_size} frames, {state.get('world', 1)} process(es))")
    print(f"data {args.data}: {count} videos x {frames} frames")
    quality = reconstruction(model, rgbd.reshape(-1, size, size, 4), ids.reshape(-1, size, size), slots)
    print(f"composite PSNR: RGB {quality['rgb']:.2f} dB, depth {quality['depth']:.2f} dB, "
          f"RGB on object pixels {quality['objects']:.2f} dB")
    means, pixels = encode_means(model, rgbd, ids, slots)
    visible = pixels > visible_threshold(size)
    targets = states[..., [columns.index("x"), columns.index("y")]]
    r2_x, r2_y = probe(means, targets, visible)
    print(f"linear probe (latent mean -> x, y), one for all {int(visible[count // 2:].sum())} visible objects "
          f"of the held-out half of the videos: R^2 x {r2_x:.4f}, y {r2_y:.4f}")
    fraction = states[..., columns.index("visible")]
    x, radius = targets[..., 0], states[..., columns.index("size")]
    edge = (x - radius < 0) | (x + radius > size)
    for name, (count_in, rms) in hidden_part_error(means, targets, visible, fraction, edge).items():
        print(f"  position read from the latents, {name} objects ({count_in}): RMS error x {rms[0]:.2f} px, "
              f"y {rms[1]:.2f} px")
    kinds = np.broadcast_to(kind[:, None, :], visible.shape)
    for code, name in enumerate(kind_names):
        chosen = visible & (kinds == code)
        if code and chosen[count // 2:].sum() > 10 and chosen[:count // 2].sum() > 10:
            x, y = probe(means, targets, chosen)
            print(f"  probe fitted to {name} alone ({int(chosen[count // 2:].sum())}): R^2 x {x:.4f}, y {y:.4f}")
    rate = train_throughput(model, args.data, train_config, args.steps)
    print(f"training throughput: {rate:.0f} object images/s ({args.threads} threads, batch "
          f"{train_config.batch_size} frames)")
    print(f"decoder throughput: {decode_throughput(model):.0f} object decodes/s (batch 32)")
    if args.figure:

        print(f"figure: {save_reconstructions(model, rgbd, ids, args.figure)}")
    print(f"psnr={quality['rgb']:.1f} probe_r2={min(r2_x, r2_y):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
