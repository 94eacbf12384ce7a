"""How good are the model's explanations? What the paper only shows in pictures, measured.

    python benchmarks/explanation.py --model RUN_DIR --data test.h5 [--pairs 100] [--figure fig5b.png]

(a) hidden_iou: blocking S2 member 0 holds a cube that is visible in no frame; the IoU of the
    decoded explanation (Transformer 2's never-seen slot) with the cube's true silhouette,
    rasterised from the saved states, frame by frame.
(b) mae_iou: on expected S1 videos, each ball or cube dropped from the input in all frames in
    turn (its slot emptied, as the proposal stage trains: Transformer 1 sees no trace of it);
    the IoU of Transformer 2's reconstruction with its silhouette.
(c) dyn_mse: the dynamics' one-step pixel error (mean squared error per pixel, [-1, 1] units)
    of the composite of predicted latents against the observed frame, expected S1 videos; and
    its RMS error per latent (the NLL model's motion_sigma stands for it).
Also the paper's Fig. 5b: the spread of the first ten principal components of the dynamics
targets with the residual (z(t+1) - z(t)) and without it (z(t+1)).
(d) fill_iou: permanence S1 expected videos, Transformer 1's fills of the cubes a wall hides
    after they were seen, against their true silhouettes (and the centre's offset, also at the
    frame before the wall is lifted: what the MSE score's dynamics term pays at the reveal), and the
    IoU by frames before each cube is seen again.
Also the share of those videos in which the MSE score with `--explanation better` keeps the
proposal (it explains the video better than nothing hidden: what `xvoe explain` then draws),
why hidden_iou falls short (the decoded centre's offset, area and empty frames) and its ceiling:
the IoU of a wholly visible cube's own latent, decoded (blocking S1).
Last line: hidden_iou=0.NN mae_iou=0.NN fill_iou=0.NN dyn_mse=...
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import torch

from xvoe.benchmark import store
from xvoe.benchmark.videos import silhouette
from xvoe.evaluation.explain import decoded_mask, iou
from xvoe.evaluation.score import encode_videos, load_model
from xvoe.evaluation.surprise import dynamics_composites, explained_latents, mse_surprise
from xvoe.models.reasoning import hide_slot
from xvoe.models.slots import composite, decode_slots, scene_layers


def pick(file, scenario: str, setting: str, member: int, limit: int) -> list[int]:
    chosen = (store.strings(file, "scenario") == scenario) & (store.strings(file, "setting") == setting)
    return list(np.flatnonzero(chosen & (file["member"][:] == member))[:limit])


def encode(scorer, file, index: int) -> dict:
    return encode_videos(scorer, file, index, index + 1)


@torch.no_grad()
def hidden_explanations(scorer, file, videos: list[int], names: list[str], columns: list[str]) -> dict:
    """The never-seen cube's explanation, frame by frame against its true silhouette: the IoU
    (hidden_iou), and why it falls short: how far the decoded centre is from the cube's (pixels,
    median over frames that draw something), how much of that lies along the ball's approach
    (`away_px`, signed: > 0 farther from the ball than the cube), the decoded area over the true
    one (median), the share of frames that draw nothing; and Transformer 1's fill of the ball in
    the frames the wall hides it (`ball_fill_px`: its x less the true x, > 0 beyond it, median)."""
    x = columns.index("x")
    scores, offsets, away, areas, empty, ball_fill, kept = [], [], [], [], [], [], []
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        states = file["states"][index]
        hidden = [k for k, kind in enumerate(kinds) if kind == "cube"
                  and states[:, k, columns.index("visible")].max() == 0]
        if len(hidden) != 1:
            continue
        video = encode(scorer, file, index)
        refined = scorer.xpl.refine(video["mean"], video["visible"], video["occluder"])
        explained, _, slot = scorer.xpl.explain(refined, video["visible"])
        kept.append(bool(mse_surprise(scorer.vae, scorer.xpl, video["frames"], video["mean"], video["visible"],
                                      video["background"], video["occluder"], "better").explained_slot[0] >= 0))
        if slot[0] < 0:
            scores.append(0.0)
            continue
        masks = decoded_mask(scorer.vae.decode(explained[0, :, slot[0]]))
        truth = silhouette(states[:, hidden[0]], columns, "cube", masks.shape[-1])
        scores.append(np.mean([iou(m, g) for m, g in zip(masks, truth)]))
        balls = [k for k, kind in enumerate(kinds) if kind == "ball"]
        # +1 where the ball starts right of the cube: "away from the ball" is then -x
        side = np.sign(states[0, balls[0], x] - states[0, hidden[0], x]) if balls else 0.0
        for mask, true in zip(masks, truth):
            empty.append(not mask.any())
            if mask.any() and true.any():
                (my, mx), (ty, tx) = np.argwhere(mask).mean(0), np.argwhere(true).mean(0)
                offsets.append(np.hypot(my - ty, mx - tx))
                away.append(-(mx - tx) * side)
                areas.append(mask.sum() / true.sum())
        if balls:
            ball = balls[0]
            drawn = decoded_mask(scorer.vae.decode(refined[0, :, ball]))
            present = states[:, ball, columns.index("present")] > 0
            for t in np.flatnonzero(~video["visible"][0, :, ball].numpy() & present):
                if drawn[t].any():     # the centre's x in pixels; states hold x in pixels too
                    ball_fill.append(-(np.argwhere(drawn[t]).mean(0)[1] + 0.5 - states[t, ball, x]) * side)

    def median(values: list) -> float:
        return float(np.median(values)) if values else float("nan")

    return {"iou": float(np.mean(scores)), "per_video": scores, "centre_px": median(offsets),
            "away_px": median(away), "area_ratio": median(areas), "empty_share": float(np.mean(empty)),
            "ball_fill_px": median(ball_fill), "kept_share": float(np.mean(kept)),
            "shown_iou": float(np.mean(np.where(kept, scores, 0.0)))}


@torch.no_grad()
def hidden_fills(scorer, file, videos: list[int], names: list[str], columns: list[str]) -> dict:
    """Transformer 1's fills of the cubes a wall hides after they were seen (permanence S1,
    expected member: they fall behind it, land, and are shown again), against their true
    silhouettes in the hidden frames: the mean IoU, the decoded centre's offset (pixels,
    median), the offset at the last hidden frame alone, the IoU by frames before the cube is
    seen again, and the share of fills that draw more than three times the cube's area (a fill
    that took on the wall's shape). The MSE score's dynamics term
    compares the frame after it with the prediction from that fill: a fill that is off costs the
    possible member at the reveal, and the impossible one, whose cube never shows again, does not
    pay it."""
    scores, offsets, before_reveal, oversized, worst = [], [], [], [], (0, -1)
    by_distance: dict[int, list[float]] = {}    # frames before the cube is seen again: IoUs
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        states = file["states"][index]
        video = encode(scorer, file, index)
        refined = scorer.xpl.refine(video["mean"], video["visible"], video["occluder"])
        for k, kind in enumerate(kinds):
            seen = video["visible"][0, :, k].numpy()
            hidden = ~seen & (states[:, k, columns.index("present")] > 0)
            if kind != "cube" or not seen.any():
                continue
            frames = [t for t in np.flatnonzero(hidden) if seen[:t].any()]     # hidden after it was seen
            if not frames:
                continue
            masks = decoded_mask(scorer.vae.decode(refined[0, frames, k]))
            truth = silhouette(states[frames, k], columns, "cube", masks.shape[-1])
            scores += [iou(m, g) for m, g in zip(masks, truth)]
            for t, mask, true in zip(frames, masks, truth):
                again = np.flatnonzero(seen[t + 1:])
                if len(again):
                    by_distance.setdefault(int(again[0]) + 1, []).append(iou(mask, true))
                if true.any():
                    oversized.append(mask.sum() > 3 * true.sum())
                    worst = max(worst, (mask.sum() / true.sum(), index))
                if mask.any() and true.any():
                    offset = float(np.hypot(*(np.argwhere(mask).mean(0) - np.argwhere(true).mean(0))))
                    offsets.append(offset)
                    if t + 1 < len(seen) and seen[t + 1]:
                        before_reveal.append(offset)

    def median(values: list) -> float:
        return float(np.median(values)) if values else float("nan")

    return {"iou": float(np.mean(scores)) if scores else float("nan"), "centre_px": median(offsets),
            "before_reveal_px": median(before_reveal), "oversized_share": float(np.mean(oversized)),
            "frames": len(scores), "largest": int(worst[1]),
            "before_reveal_iou": {d: (float(np.mean(v)), len(v)) for d, v in sorted(by_distance.items())}}


@torch.no_grad()
def draw_fills(scorer, file, index: int, path: str, title: str) -> None:
    """A video's frames over the composite of its refined moving slots, each under a wall
    they stand behind drawn as in the MSE score's dynamics term (the wall left out), and the
    dynamics' prediction of it: where a fill took on a wall's shape, it shows."""
    video = encode(scorer, file, index)
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


@torch.no_grad()
def perception_iou(scorer, file, videos: list[int], names: list[str], columns: list[str]) -> float:
    """The ceiling of any explanation this perception decodes: the IoU of a wholly visible
    cube's own encoded latent, decoded, with its silhouette (all such frames of the videos)."""
    scores = []
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        states = file["states"][index]
        cubes = [k for k, kind in enumerate(kinds) if kind == "cube"]
        if not cubes:
            continue
        video = encode(scorer, file, index)
        for k in cubes:
            frames = np.flatnonzero(states[:, k, columns.index("visible")] >= 0.999)
            if len(frames):
                masks = decoded_mask(scorer.vae.decode(video["mean"][0, frames, k]))
                truth = silhouette(states[frames, k], columns, "cube", masks.shape[-1])
                scores += [iou(m, g) for m, g in zip(masks, truth)]
    return float(np.mean(scores))


@torch.no_grad()
def mae_iou(scorer, file, videos: list[int], names: list[str], columns: list[str]) -> list[float]:
    """The IoU of each ball or cube rebuilt by Transformer 2 with its silhouette (mae_iou is their mean)."""
    empty = scorer.vae.posterior(scorer.vae.blank())[0][0]      # the encoder's latent of a slot with no pixels
    scores = []
    for index in videos:
        kinds = [names[k] for k in file["kind"][index]]
        video, states = encode(scorer, file, index), file["states"][index]
        for slot, kind in enumerate(kinds):
            if kind not in ("ball", "cube"):
                continue
            visible, mean = video["visible"].clone(), video["mean"].clone()
            visible[0, :, slot] = False
            mean[0, :, slot] = empty
            refined = scorer.xpl.refine(mean, visible, video["occluder"])
            keep = scorer.xpl.proposal_keep(visible, ~hide_slot(visible.shape, torch.tensor([slot])))
            rebuilt, _ = scorer.xpl.transformer2(refined, keep)
            masks = decoded_mask(scorer.vae.decode(rebuilt[0, :, slot]))
            truth = silhouette(states[:, slot], columns, kind, masks.shape[-1])
            scores.append(np.mean([iou(m, g) for m, g in zip(masks, truth)]))
    return scores


@torch.no_grad()
def dynamics_error(scorer, file, videos: list[int]) -> tuple[float, float, np.ndarray, np.ndarray]:
    """One-step pixel error, the one-step RMS error per latent of the occupied slots (what the
    NLL's motion_sigma stands for), and the dynamics targets with and without the residual."""
    errors, latent_errors, residual_targets, direct_targets = [], [], [], []
    for index in videos:
        video = encode(scorer, file, index)
        refined = scorer.xpl.refine(video["mean"], video["visible"], video["occluder"])
        occupied = video["visible"].any(1)
        predicted = scorer.xpl.predict(refined, video["occluder"])
        background = scorer.vae.decode(video["background"][0])[None]
        expected = composite(scorer.vae, background[:, 1:], decode_slots(scorer.vae, predicted, occupied), occupied)
        errors.append(float((expected - video["frames"][:, 1:]).pow(2).mean()))
        latent_errors.append((predicted - refined[:, 1:])[0][:, occupied[0]].pow(2).flatten().numpy())
        present = occupied[0].numpy()
        z = refined[0][:, present].numpy()                       # (T, objects, D)
        residual_targets.append((z[1:] - z[:-1]).reshape(-1, z.shape[-1]))
        direct_targets.append(z[1:].reshape(-1, z.shape[-1]))
    latent_rms = float(np.sqrt(np.concatenate(latent_errors).mean()))
    return float(np.mean(errors)), latent_rms, np.concatenate(residual_targets), np.concatenate(direct_targets)


def principal_spread(targets: np.ndarray, components: int = 10) -> np.ndarray:
    """Standard deviation along the first principal components."""
    centred = targets - targets.mean(0)
    values = np.linalg.svd(centred, compute_uv=False) / np.sqrt(len(targets) - 1)
    return values[:components]


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
    scorer = load_model(args.model)
    start = time.perf_counter()
    with store.open_dataset(args.data) as file:
        names, columns = list(file.attrs["kind_names"]), list(file["states"].attrs["state_columns"])
        hidden = hidden_explanations(scorer, file, pick(file, "blocking", "S2", 0, args.pairs), names, columns)
        ceiling = perception_iou(scorer, file, pick(file, "blocking", "S1", 0, args.pairs), names, columns)
        expected = [i for scenario in ("collision", "blocking", "permanence", "continuity")
                    for i in pick(file, scenario, "S1", 0, max(1, args.pairs // 4))]
        mae = float(np.mean(mae_iou(scorer, file, expected, names, columns)))
        fills = hidden_fills(scorer, file, pick(file, "permanence", "S1", 0, args.pairs), names, columns)
        if args.fills_figure:
            draw_fills(scorer, file, fills["largest"] if args.fills_video is None else args.fills_video,
                       args.fills_figure, Path(args.model).name)
        dyn, latent_rms, residual, direct = dynamics_error(scorer, file, expected)
    spread_residual, spread_direct = principal_spread(residual), principal_spread(direct)
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
    print(f"the MSE score with --explanation better keeps the proposal (it explains the video better than nothing "
          f"hidden) in {100 * hidden['kept_share']:.0f}% of these videos; the IoU of the explanation it draws "
          f"(0 where it draws nothing hidden) {hidden['shown_iou']:.2f}")
    print(f"Transformer 1's fills of the cubes hidden after they were seen (permanence S1, expected; "
          f"{fills['frames']} frames): IoU {fills['iou']:.2f}, centre {fills['centre_px']:.2f} px off (median), "
          f"{fills['before_reveal_px']:.2f} px at the frame before the reveal, "
          f"{100 * fills['oversized_share']:.1f}% of them drawing over 3x the cube's area")
    print("  IoU by frames before the cube is seen again (the fall is the farthest): " + ", ".join(
        f"{d}: {value:.2f} ({count})" for d, (value, count) in fills["before_reveal_iou"].items()))
    print(f"hidden_iou={hidden['iou']:.2f} mae_iou={mae:.2f} fill_iou={fills['iou']:.2f} dyn_mse={dyn:.4f}")


if __name__ == "__main__":
    main()
