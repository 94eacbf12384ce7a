"""The weight digests of a tiny run of the default recipe: every stage a few steps, as the pipeline
trains them (its threads, processes, data shards and phases), at small sizes.

Run as a script in a fresh process (`python tests/digests.py OUT`), since a process's kernels
are chosen at its first one: it prints a JSON object, each stage's digest and the kernels used.
tests/test_digests.py compares it with the digests stored there.
"""
from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

import torch

from xvoe.apps.pipeline import PipelineConfig, run_pipeline
from xvoe.fingerprints import arrays_hash
from xvoe.training.checkpoints import load_checkpoint
from xvoe.training.recipes import DEFAULT_RECIPE, RECIPES

STAGES = ("perception", "xpl", "proposal", "plato", "xpl-noresidual", "phydnet")


def tiny_recipe():
    """The default recipe at small sizes and a few steps a stage, every other setting its own."""
    cpu = RECIPES[DEFAULT_RECIPE]

    def few(config, steps=4, batch=8):
        return replace(config, steps=steps, batch_size=batch, warmup_steps=1, log_every=2,
                       decay_steps=min(config.decay_steps, 3))

    reasoning = replace(cpu.xpl.reasoning, width=16, layers=1, heads=2, mlp=16)
    dynamics = replace(cpu.xpl.dynamics, hidden=16, lstm=16, buffer_heads=2)
    plato_phase = next(config for stage, config in cpu.phases if stage == "plato")
    widening = next(config for stage, config in cpu.phases if stage == "phydnet" and config.lstm_kernel)
    return replace(cpu, perception=replace(cpu.perception, latent_dim=8, cnn_channels=(8, 8), cnn_hidden=16,
                                           decoder_channels=8),
                   perception_train=few(cpu.perception_train),
                   xpl=replace(cpu.xpl, reasoning=reasoning, dynamics=dynamics),
                   xpl_train=few(cpu.xpl_train, batch=4), proposal_train=few(cpu.proposal_train, batch=4),
                   plato_train=few(cpu.plato_train, batch=4),
                   phydnet=replace(cpu.phydnet, encoder_channels=(8, 8), lstm_channels=(8,)),
                   phydnet_train=few(cpu.phydnet_train, batch=2),
                   phases=(("plato", few(plato_phase, steps=6, batch=4)),
                           ("phydnet", few(widening, steps=6, batch=2))))


def digests(out: Path, processes: int = 0) -> dict[str, str]:
    """`processes`: of the stages that train in one-thread processes (0: the pipeline's choice)."""
    RECIPES[DEFAULT_RECIPE] = tiny_recipe()
    run_pipeline(PipelineConfig(str(out), train_videos=160, pairs=1, models=("xpl", "plato", "xpl-noresidual",
                                                                                  "phydnet"), workers=1,
                                progress=False, train_processes=processes))
    found = {}
    for stage in STAGES:
        state = load_checkpoint(out / f"{stage}.pt", stage)
        arrays = {name: value.numpy() for name, value in state["model"].items()}
        found[stage] = arrays_hash(arrays, {})
        found[f"{stage} kernels"] = state["kernels"]
    return found


if __name__ == "__main__":
    torch.set_num_threads(2)
    print(json.dumps(digests(Path(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) > 2 else 0)))
