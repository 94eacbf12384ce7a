"""The default recipe, the shipped models' (docs/models.md): 32x32 frames on a 2-core CPU.

A small CNN encoder and a light decoder; walls inert in the dynamics and unread by
Transformer 1, whose fills learn from rebuilding seen spans and objects outside the picture;
Transformer 2 trained in a stage of its own; moving averages of the XPL and proposal weights;
PLATO and PhyDNet trained longer, then with a share of each batch from the scenarios they
were weakest in (docs/decisions.md, "The default recipe").
"""
from dataclasses import replace

from ...models.nll import InferenceConfig
from ...models.perception import PerceptionConfig
from ...models.phydnet import PhyDNetConfig
from ...models.xpl import XPLConfig
from ..config import TrainConfig
from ..stages import PHYDNET, PLATO
from .recipe import Recipe

__all__ = ["RECIPE"]     # read by name: xvoe.training.recipes

# two fixed data shards: a stage's batches are then the same on one core, two or four
# (docs/decisions.md, "Processes and threads"); and fixed threads, which split
# the sums: a stage of two one-thread processes, or one process of two threads (docs/decisions.md,
# "One seed, one set of weights")
SHARDS = 2
PLATO_TRAIN = TrainConfig(steps=60_000, batch_size=32, warmup_steps=100, decay_steps=15_000, data_shards=SHARDS,
                    threads=1)
PHYDNET_TRAIN = TrainConfig(steps=9_000, batch_size=8, lr=2e-3, warmup_steps=100, decay_steps=2_500, data_shards=1,
                      threads=2)
LATER = replace(PHYDNET_TRAIN, decay_steps=10_000)      # the later phases' rates halve every 10,000 steps


# the NLL surprise's settings, chosen on the validation split for this recipe's models (docs/decisions.md,
# "The NLL's settings"); the xpl stage stores them in its checkpoint, and a checkpoint made before
# they were stored is scored with them (xvoe.training.xpl, `model_nll`)
NLL = InferenceConfig(
    prior_hidden=0.5, prior_two=0.1,
    pixel_sigma=0.5, motion_sigma=0.2, transition_sigma=0.1,
    exposure_penalty=12.0, presence_penalty=12.0, object_area=0.008,
    method="smc", particles=64, resample_threshold=0.5,
    smc_pilot=1, smc_pilot_margin=30.0, smc_pilot_skip_exists=0.5, smc_object_floor=0.05,
    proposal_widening=3.0, smc_proposal_widening=(3.0, 10.0),
    refine_steps=5, refine_rate=0.1, refine_tolerance=1.0, sure_runs=2, sure_runs_exists=0.95,
)


def _phydnet_phase(steps: int, lr: float, focus: str, share: float, **changes) -> tuple[str, TrainConfig]:
    return PHYDNET, replace(LATER, steps=steps, lr=lr, focus_group=focus, focus_share=share, **changes)


RECIPE = Recipe(
    name="cpu-short",
    nll=NLL,
    train_videos=10_000,
    perception=PerceptionConfig(),
    # a quarter of each batch shows a ball or cube off the floor (docs/decisions.md, "Training
    # choices")
    perception_train=TrainConfig(steps=4_000, decay_steps=3_333, airborne_share=0.25, data_shards=1, threads=2),
    xpl=XPLConfig(inert_walls=True, stop_input_gradient=True, outside_refill=True, refill_ignores_walls=True,
                  joint_proposal=False),
    xpl_train=TrainConfig(steps=9_000, batch_size=32, warmup_steps=100, decay_steps=6_000, average_decay=0.999,
                          data_shards=SHARDS, threads=1),
    # half of each batch from blocking videos with a wall, where a hidden cube's place shows in the
    # ball's path
    proposal_train=TrainConfig(steps=4_000, batch_size=32, warmup_steps=100, decay_steps=1_500,
                               average_decay=0.999, focus_group="blocking", focus_share=0.5, data_shards=SHARDS,
                               threads=1),
    plato_train=PLATO_TRAIN,
    # changing pixels weigh more in the training loss; 3x3 gates, widened to 5x5 in a later phase
    # (docs/decisions.md, "The baselines' training")
    phydnet=PhyDNetConfig(change_weight=20.0, lstm_kernel=3),
    phydnet_train=PHYDNET_TRAIN,
    # the scenarios each baseline was weakest in, a share of every batch (docs/decisions.md,
    # "The baselines' training")
    phases=(
        (PLATO, replace(PLATO_TRAIN, steps=75_000, focus_group="continuity", focus_share=0.5)),
        _phydnet_phase(10_000, 5.6e-4, "permanence", 0.5),
        _phydnet_phase(13_000, 1.1e-3, "permanence", 0.75),
        _phydnet_phase(15_000, 5.5e-4, "permanence", 0.5),
        _phydnet_phase(17_000, 5.5e-4, "permanence", 0.75),
        _phydnet_phase(19_500, 1.8e-3, "permanence", 0.75, lstm_kernel=5),
        _phydnet_phase(20_000, 9e-4, "permanence", 0.75),
        _phydnet_phase(20_500, 9e-4, "permanence", 0.5),
        _phydnet_phase(22_000, 4.5e-4, "permanence,continuity", 0.75),
        _phydnet_phase(25_000, 4.5e-4, "blocking,permanence", 0.5),
        _phydnet_phase(28_000, 4.5e-4, "permanence", 0.5),
    ),
)
