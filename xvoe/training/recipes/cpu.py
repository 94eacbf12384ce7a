"""The CPU-scale recipe that `cpu-walls` and the default `cpu-short` build on, and the
baselines' recipes they keep (docs/decisions.md, "The default recipe").

32x32 RGBD frames, a small CNN encoder and a light decoder with the whole latent broadcast;
walls inert in the dynamics, Transformer 1 trained by the refill loss alone, its fills of
objects outside the picture trained; PLATO and PhyDNet trained longer, then with a share of
each batch from the scenarios they were weakest in.
"""
from dataclasses import replace

from ...models.perception import PerceptionConfig
from ...models.phydnet import PhyDNetConfig
from ...models.xpl import XPLConfig
from .recipe import Recipe, TrainConfig

# The stages the pipeline trains in one process per core draw their batches from two fixed data
# shards, the others from one: a stage's batches are then the same on one core, two or four (its
# weights only up to float order: docs/decisions.md, "Batches that do not depend on the cores").
SHARDS = 2
PLATO = TrainConfig(steps=60_000, batch_size=32, warmup_steps=100, decay_steps=15_000, data_shards=SHARDS)
PHYDNET = TrainConfig(steps=9_000, batch_size=8, lr=2e-3, warmup_steps=100, decay_steps=2_500, data_shards=1)
# the later phases' rates halve every 10,000 steps, not PHYDNET's 2,500 (which leaves them near 1e-5)
LATER = replace(PHYDNET, decay_steps=10_000)

RECIPE = Recipe(
    name="cpu",
    train_videos=10_000,
    perception=PerceptionConfig(),
    perception_train=TrainConfig(data_shards=1),
    xpl=XPLConfig(inert_walls=True, stop_input_gradient=True, outside_refill=True),
    xpl_train=TrainConfig(steps=12_000, batch_size=32, warmup_steps=100, decay_steps=8_000, data_shards=SHARDS),
    proposal_train=TrainConfig(steps=4_000, batch_size=32, warmup_steps=100, decay_steps=1_500, data_shards=SHARDS),
    # the NLL's learned trajectory proposal (docs/decisions.md, "The trajectory proposal: mixed
    # with the fused ones, off by default")
    trajectory_train=TrainConfig(steps=4_000, batch_size=32, lr=1e-3, warmup_steps=100, decay_steps=1_500),
    # PLATO's predictive accuracy grows with its training time (docs/decisions.md, "PLATO's
    # training length")
    plato_train=PLATO,
    # changing pixels weighed more in the training loss; 3x3 gates, widened to 5x5 in a later
    # phase so that a memory can follow a falling cube (docs/decisions.md, "PhyDNet's loss weight
    # on changing pixels", "PhyDNet's ConvLSTM kernel")
    phydnet=PhyDNetConfig(change_weight=20.0, lstm_kernel=3),
    phydnet_train=PHYDNET,
    phases=(
        # the scenarios each baseline was weakest in, a share of every batch (docs/decisions.md,
        # "The baselines' later phases")
        ("plato", replace(PLATO, steps=75_000, focus_group="continuity", focus_share=0.5)),
        ("phydnet", replace(LATER, steps=10_000, lr=5.6e-4, focus_group="permanence", focus_share=0.5)),
        ("phydnet", replace(LATER, steps=13_000, lr=1.1e-3, focus_group="permanence", focus_share=0.75)),
        ("phydnet", replace(LATER, steps=15_000, lr=5.5e-4, focus_group="permanence", focus_share=0.5)),
        ("phydnet", replace(LATER, steps=17_000, lr=5.5e-4, focus_group="permanence", focus_share=0.75)),
        ("phydnet", replace(LATER, steps=19_500, lr=1.8e-3, focus_group="permanence", focus_share=0.75,
                            lstm_kernel=5)),
        ("phydnet", replace(LATER, steps=20_000, lr=9e-4, focus_group="permanence", focus_share=0.75)),
        ("phydnet", replace(LATER, steps=20_500, lr=9e-4, focus_group="permanence", focus_share=0.5)),
        ("phydnet", replace(LATER, steps=22_000, lr=4.5e-4, focus_group="permanence,continuity",
                            focus_share=0.75)),
        ("phydnet", replace(LATER, steps=25_000, lr=4.5e-4, focus_group="blocking,permanence", focus_share=0.5)),
        ("phydnet", replace(LATER, steps=28_000, lr=4.5e-4, focus_group="permanence", focus_share=0.5)),
    ),
)
