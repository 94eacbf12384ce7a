"""What a particle costs in the NLL's SMC, by the number run together on one video.

    python benchmarks/smc_particles.py [--model xpl] --data val.h5 [--video 0] [--threads 1]

Batching particles (or several videos' particles) into larger tensors pays only where a
particle's cost falls as more run together. Prints, for 16, 64 and 128 particles, one whole
SMC run (median of 3) and its two costs per frame: the pixel likelihood (decoding each particle's
picture) and the dynamics' step. Last line: ms_per_particle_16=N.NN ms_per_particle_128=N.NN ratio=N.NN
"""
from __future__ import annotations

import statistics
import time

import torch
from nll_latency import one_video

from inference.model import InferenceConfig, Proposal
from inference.smc import HiddenTrajectory, XPLSteps, run_smc
from inference.surprise import hidden_object_scene


def median_seconds(call, repeats: int = 3) -> float:
    call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


@torch.no_grad()
def main() -> None:
    args, scorer, (frames, mean, visible, background, occluder) = one_video(__doc__.splitlines()[0])
    vae, xpl, config = scorer.vae, scorer.xpl, InferenceConfig()
    scene, loc, spread, _ = hidden_object_scene(vae, xpl, mean, visible, background, occluder)
    proposal = Proposal(torch.tensor(0.5), loc, spread, None)
    model = HiddenTrajectory(XPLSteps(scene, frames, config), config, proposal)
    per_particle = {}
    for n in (16, 64, 128):
        whole = median_seconds(lambda n=n: run_smc(model, n, generator=torch.Generator().manual_seed(0)))
        z = torch.randn(n, scene.dim, generator=torch.Generator().manual_seed(1))
        state, _ = model.step(0, model.start(n), torch.Generator().manual_seed(2))
        likelihood = median_seconds(lambda z=z: model.steps.frame_log_likelihood(1, z))
        dynamics = median_seconds(lambda z=z, state=state: model.steps.advance(1, z, state.carried))
        per_particle[n] = whole / n * 1000
        print(f"{n:4d} particles: SMC run {whole * 1000:7.1f} ms ({per_particle[n]:.2f} ms a particle); "
              f"a frame's likelihood {likelihood * 1000:.1f} ms, dynamics step {dynamics * 1000:.1f} ms")
    print(f"video {args.video} of {args.data}, {scene.frames} frames, {args.threads} thread(s)")
    print(f"ms_per_particle_16={per_particle[16]:.2f} ms_per_particle_128={per_particle[128]:.2f} "
          f"ratio={per_particle[16] / per_particle[128]:.2f}")


if __name__ == "__main__":
    main()
