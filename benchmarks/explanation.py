"""How good are the model's explanations? xvoe.evaluation.explanation_quality's measures, printed.

    python benchmarks/explanation.py --model RUN_DIR --data test.h5 [--pairs 100] [--figure fig5b.png]
                                     [--fills-figure fills.png] [--fills-video N]

hidden_iou (blocking S2's never-seen cube) and why it falls short, and its ceiling (a wholly
visible cube's own latent, decoded); the share of those videos in which the default verdict
(the better of two explanations) keeps the proposal; mae_iou (expected S1 videos, each object
dropped in turn); fill_iou (permanence S1: Transformer 1's fills of cubes hidden after they were seen,
by frames before the reveal); the dynamics' one-step error; and the paper's Fig. 5b (the
spread of the first ten principal components of the dynamics targets with and without the
residual).
Last line: hidden_iou=0.NN mae_iou=0.NN fill_iou=0.NN dyn_mse=...
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch

import xvoe
from xvoe.evaluation import explanation_quality as quality
from xvoe.evaluation.scorer import encode_videos
from xvoe.evaluation.surprise import dynamics_composites, explained_latents
from xvoe.models.slots import composite, scene_layers


@torch.no_grad()
def draw_fills(scorer: xvoe.Scorer, file, index: int, path: str, title: str) -> None:
    """A video's frames over the composite of its refined moving slots, each under a wall
    they stand behind drawn as in the MSE score's dynamics term (the wall left out), and the
    dynamics' prediction of it: where a fill took on a wall's shape, it shows."""
    video = encode_videos(scorer, file, index, index + 1)
    refined, slot, occupied = explained_latents(scorer.xpl, video["mean"], video["visible"], video["occluder"])
    frames = video["frames"].shape[1]
    background = scorer.vae.decode(video["background"][0])[None]
    layers, walls = scene_layers(scorer.vae, refined, occupied, video["visible"], video["occluder"])
    seen, expected = dynamics_composites(scorer.vae, scorer.xpl, refined, layers, walls, occupied, video["visible"],
                                         video["occluder"], background)
    first = composite(scorer.vae, background[:, :1], layers[:, :1], occupied & ~video["occluder"])[0]
    rows = [("frames", video["frames"][0]), ("fills", torch.cat([first, seen[0]])),
            ("predicted", torch.cat([background[0, :1], expected[0]]))]
    fig, axes = plt.subplots(3, frames, figsize=(frames * 0.62, 2.2))
    for row, (name, pictures) in enumerate(rows):
        for t in range(frames):
            axes[row, t].imshow(((pictures[t, :3].permute(1, 2, 0).numpy() + 1) / 2).clip(0, 1))
            axes[row, t].set_xticks([])
            axes[row, t].set_yticks([])
        axes[row, 0].set_ylabel(name, fontsize=6)
    fig.suptitle(f"{title}: video {index}", fontsize=7)
    fig.tight_layout(pad=0.2)
    fig.savefig(path, dpi=60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="a run directory or an xpl checkpoint")
    parser.add_argument("--data", required=True, help="a test split at the model's resolution")
    parser.add_argument("--pairs", type=int, default=100, help="videos of each kind to measure")
    parser.add_argument("--figure", help="where to draw Fig. 5b (PNG)")
    parser.add_argument("--fills-figure", help="where to draw a permanence S1 video's fills and their prediction (PNG)")
    parser.add_argument("--fills-video", type=int, help="that video's index (default: the measured one whose fill "
                        "is largest against its cube)")
    args = parser.parse_args()
    torch.set_num_threads(2)
    scorer = xvoe.load_model(args.model)
    start = time.perf_counter()
    with xvoe.open_dataset(args.data) as file:
        hidden = quality.hidden_explanations(scorer, file, quality.pick(file, "blocking", "S2", 0, args.pairs))
        ceiling = quality.perception_iou(scorer, file, quality.pick(file, "blocking", "S1", 0, args.pairs))
        expected = quality.expected_videos(file, args.pairs)
        mae = float(np.mean(quality.mae_iou(scorer, file, expected)))
        fills = quality.hidden_fills(scorer, file, quality.pick(file, "permanence", "S1", 0, args.pairs))
        if args.fills_figure:
            draw_fills(scorer, file, fills["largest"] if args.fills_video is None else args.fills_video,
                       args.fills_figure, Path(args.model).name)
        dyn, latent_rms, residual, direct = quality.dynamics_error(scorer, file, expected)
    spread_residual, spread_direct = quality.principal_spread(residual), quality.principal_spread(direct)
    print(f"videos: {args.pairs} blocking S2, {len(expected)} expected S1; {time.perf_counter() - start:.0f} s")
    print(f"dynamics' one-step RMS error per latent, occupied slots: {latent_rms:.3f}")
    print("PC spread (std) with residual:   ", " ".join(f"{v:.3f}" for v in spread_residual))
    print("PC spread (std) without residual:", " ".join(f"{v:.3f}" for v in spread_direct))
    if args.figure:
        fig, ax = plt.subplots(figsize=(4.5, 3))
        ax.plot(range(1, len(spread_direct) + 1), spread_direct, "o-", label="z(t+1): no residual")
        ax.plot(range(1, len(spread_residual) + 1), spread_residual, "o-", label="z(t+1) - z(t): residual")
        ax.set_xlabel("principal component")
        ax.set_ylabel("standard deviation")
        ax.set_title("Spread of the dynamics targets (Fig. 5b)")
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(args.figure, dpi=90)
    print(f"the never-seen cube: decoded centre {hidden['centre_px']:.2f} px off (median; {hidden['away_px']:+.2f} "
          f"px farther from the ball), area {hidden['area_ratio']:.2f} "
          f"of the true one, {100 * hidden['empty_share']:.0f}% of frames empty; the perception's own IoU of a "
          f"wholly visible cube {ceiling:.2f}; Transformer 1's fill of the ball behind the wall "
          f"{hidden['ball_fill_px']:+.2f} px beyond the true ball (median)")
    print(f"the default verdict (the better of two explanations) keeps the proposal (it explains the video "
          f"better than nothing hidden) in {100 * hidden['kept_share']:.0f}% of these videos; the IoU of the "
          f"explanation it draws (0 where it draws nothing hidden) {hidden['shown_iou']:.2f}")
    print(f"Transformer 1's fills of the cubes hidden after they were seen (permanence S1, expected; "
          f"{fills['frames']} frames): IoU {fills['iou']:.2f}, centre {fills['centre_px']:.2f} px off (median), "
          f"{fills['before_reveal_px']:.2f} px at the frame before the reveal, "
          f"{100 * fills['oversized_share']:.1f}% of them drawing over 3x the cube's area")
    print("  IoU by frames before the cube is seen again (the fall is the farthest): " + ", ".join(
        f"{d}: {value:.2f} ({count})" for d, (value, count) in fills["before_reveal_iou"].items()))
    print(f"hidden_iou={hidden['iou']:.2f} mae_iou={mae:.2f} fill_iou={fills['iou']:.2f} dyn_mse={dyn:.4f}")


if __name__ == "__main__":
    main()
