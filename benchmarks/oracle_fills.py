"""How far would perfect fills take the MSE score? Transformer 1's fills against the truth.

    python benchmarks/oracle_fills.py --model xpl --data test.h5 [--pairs 60] [--threads 2]

Transformer 1 fills the frames in which a seen object is hidden (behind the wall). Here every
pair of a generated test split is simulated again from the split's seed, rendered a second
time without its walls, and encoded by the model's own perception: that gives each hidden
object's latent as the encoder would have seen it. Each pair is then scored three times with the
same MSE score (`xvoe.evaluation.surprise.latent_surprise`): with Transformer 1's fills (what `xvoe score`
does), with those true latents in their place ("oracle"), and with true latents also where
the wall hides an object only in part ("whole": the encoder's reading of a partly hidden
object replaced too). Where the oracle column is far above the first, the fills are what the
score lacks; where only the whole column is, it is the perception of partly hidden objects;
where all are low, it is the dynamics or the score itself (a possible collision costs the
dynamics more than a free roll).

Prints per setting the comparative accuracy (%) of the total score and of the excess (s_img -
s_rec + s_dyn) all three ways, of s_dyn the first two, and the fills' mean squared latent error
(summed over latents) in the possible and the other member. The rerun is checked against the
stored frames: a split that does not come out the same stops the benchmark.
"""
from __future__ import annotations

import argparse
import time

import h5py
import numpy as np
import torch

from xvoe.benchmark import store
from xvoe.benchmark.generate import GenerateConfig, unit_rng
from xvoe.benchmark.render import render
from xvoe.benchmark.scenes import SCENARIOS, TEST_SETTINGS
from xvoe.benchmark.world import WALL_KINDS
from xvoe.evaluation.metrics import excess, pairwise_win
from xvoe.evaluation.score import encode_videos, load_model
from xvoe.evaluation.surprise import explained_latents, latent_surprise
from xvoe.training.data import visible_threshold
from xvoe.training.latents import encode_frames

PARTLY = 0.99    # an object whose visible share of pixels is under this is hidden in part (or whole)


def generator_config(file: h5py.File) -> GenerateConfig:
    config = store.config_of(file)
    if file.attrs.get("split") != "test" or config.get("custom"):
        raise SystemExit("--data must be a test split made by `xvoe generate` (the pairs are simulated again)")
    return GenerateConfig(**config)


def true_latents(scorer, config: GenerateConfig, unit: int, stored: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """(2, T, K, D) latents and (2, T, K) visibility of the pair `unit`, its walls taken away."""
    scenario, setting = TEST_SETTINGS[unit // config.pairs]
    takes = SCENARIOS[scenario].test_pair(unit_rng(config, unit), setting, config.frames)
    means, visible = [], []
    for member, take in enumerate(takes):
        if not np.array_equal(render(take.scene, take.trajectory, config.size).rgbd, stored[member]):
            raise SystemExit(f"pair {unit} does not come out as stored: was the split made by another version?")
        scene = take.scene
        for index, thing in enumerate(scene.things):
            if thing.kind in WALL_KINDS:
                scene = scene.without(index)
        video = render(scene, take.trajectory, config.size)
        encoded = encode_frames(scorer.vae, video.rgbd, video.ids, video.states.shape[1])
        means.append(torch.from_numpy(encoded["mean"]))
        visible.append(torch.from_numpy(encoded["pixels"] > visible_threshold(config.size)))
    return torch.stack(means), torch.stack(visible)


def score_pair(scorer, batch: dict, truth: torch.Tensor, seen_without_walls: torch.Tensor,
               partly_hidden: torch.Tensor) -> dict[str, np.ndarray]:
    """Total score, excess and s_dyn of both members with Transformer 1's fills, with the true
    latents in the fills, and with them also in the entries `partly_hidden` (2, T, K) by a wall."""
    visible, occluder = batch["visible"], batch["occluder"]
    refined, _, occupied = explained_latents(scorer.xpl, batch["mean"], visible, batch["occluder"])
    hidden = ~visible & ~occluder[:, None, :] & seen_without_walls
    filled = hidden & visible.any(dim=1, keepdim=True)
    error = ((refined - truth) ** 2).sum(-1)
    out = {"fill_error": torch.where(filled, error, torch.nan)}
    oracle = torch.where(hidden[..., None], truth, refined)
    whole = torch.where((partly_hidden & visible & ~occluder[:, None, :])[..., None], truth, oracle)
    truly_occupied = occupied | (seen_without_walls.any(dim=1) & ~occluder)
    for name, latents, slots in (("t1", refined, occupied), ("oracle", oracle, truly_occupied),
                                 ("whole", whole, truly_occupied)):
        s_img, s_dyn, s_rec = latent_surprise(scorer.vae, scorer.xpl, batch["frames"], latents, slots, visible,
                                              batch["background"], occluder)
        out[name] = (s_img + s_dyn).sum(1).numpy()
        out[name + "_dyn"] = s_dyn.sum(1).numpy()
        out[name + "_excess"] = excess(s_img, s_dyn, s_rec).sum(1).numpy()
    return out


COLUMNS = {"t1": "score T1", "oracle": "oracle", "whole": "whole", "t1_excess": "excess T1",
           "oracle_excess": "oracle", "whole_excess": "whole", "t1_dyn": "s_dyn T1", "oracle_dyn": "oracle"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="xpl")
    parser.add_argument("--data", required=True)
    parser.add_argument("--pairs", type=int, default=60, help="the first N pairs of each setting")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    scorer = load_model(args.model)
    if scorer.is_random or scorer.xpl is None:
        raise SystemExit("--model must be an XPL run or shipped model (it fills with Transformer 1)")
    start = time.perf_counter()
    print(f"{'setting':<15} " + " ".join(f"{label:>9}" for label in COLUMNS.values()) + f" {'fill error 0 / 1':>17}")
    with h5py.File(args.data) as file, torch.no_grad():
        config = generator_config(file)
        seen_share = list(file["states"].attrs["state_columns"]).index("visible")
        for index, (scenario, setting) in enumerate(TEST_SETTINGS):
            wins: dict[str, list[float]] = {name: [] for name in COLUMNS}
            errors: list[list[float]] = [[], []]
            for pair in range(min(args.pairs, config.pairs)):
                unit = index * config.pairs + pair
                truth, seen = true_latents(scorer, config, unit, file["rgbd"][2 * unit:2 * unit + 2])
                share = torch.from_numpy(file["states"][2 * unit:2 * unit + 2, :, :, seen_share])
                result = score_pair(scorer, encode_videos(scorer, file, 2 * unit, 2 * unit + 2), truth, seen,
                                    share < PARTLY)
                for name in wins:
                    first, second = result[name]
                    wins[name].append(float(pairwise_win(second, first)))
                for member in (0, 1):
                    error = result["fill_error"][member]
                    if not error.isnan().all():
                        errors[member].append(float(error.nanmean()))
            accuracy = {name: 100 * np.mean(won) for name, won in wins.items()}
            fill = " / ".join(f"{np.mean(e):.2f}" if e else "-" for e in errors)
            print(f"{scenario + ' ' + setting:<15} " + " ".join(f"{accuracy[name]:9.1f}" for name in COLUMNS)
                  + f" {fill:>17}", flush=True)
    print(f"{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
