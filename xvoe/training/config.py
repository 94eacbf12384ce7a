"""A training stage's run settings: what the shared loop reads (xvoe.training.loop) and what a
checkpoint stores beside its weights (xvoe.training.checkpoints checks it on load)."""
from __future__ import annotations

from dataclasses import dataclass

from ..domains import COUNT, NON_NEGATIVE, POSITIVE, SEED, SHARE, Domain, check_config, within

__all__ = ["RECIPE_NAMES", "DEFAULT_RECIPE", "TrainConfig"]

# the recipes' names (a module each in xvoe/training/recipes/, whose RECIPES must hold these),
# named here too because a recipe builds network configs, which import torch, and the command
# line lists them in its --help
RECIPE_NAMES = ("cpu-short", "paper")
# what `xvoe pipeline` runs and the shipped models come from (docs/decisions.md, "The default recipe")
DEFAULT_RECIPE = "cpu-short"


@dataclass(frozen=True)
class TrainConfig:
    """One training run of one stage: the shared loop reads only these fields."""

    steps: int = within(6000, COUNT)
    batch_size: int = within(32, COUNT)            # frames per step, summed over all processes
    lr: float = within(1e-3, POSITIVE)
    warmup_steps: int = within(200, NON_NEGATIVE)         # linear warm-up of the learning rate
    decay_steps: int = within(5000, COUNT)         # the learning rate halves every decay_steps after warm-up
    grad_clip: float = within(0.0, NON_NEGATIVE)          # clip the gradient norm to this (0 = no clipping)
    # the checkpoint's weights are a moving average of the trained ones, each step's weighed this
    # much less than the next one's (0 = the last step's weights); training resumes from the trained ones
    average_decay: float = within(0.0, Domain(0, 1, open_high=True))
    seed: int = within(0, SEED)
    checkpoint_minutes: float = within(3.0, POSITIVE)  # a checkpoint is written at least this often
    log_every: int = within(10, COUNT)             # steps between rows of the loss CSV
    max_minutes: float = within(0.0, NON_NEGATIVE)        # stop early after this much training time (0 = no limit)
    max_videos: int = within(0, NON_NEGATIVE)             # videos of the data file to load (0 = all)
    # slices of the file that each feed batch_size/data_shards frames per step; 0 = the number of
    # processes of the first launch
    data_shards: int = within(0, NON_NEGATIVE)
    threads: int = within(0, NON_NEGATIVE)                # torch threads per process (0 = cores / processes):
                                                          # the count splits sums, so a recipe fixes it
    # this share of each batch comes from the training videos of `focus_group` that have a wall
    # (e.g. permanence, where cubes must be remembered behind it; several: permanence,continuity);
    # 0 = uniform. PhyDNet, and the XPL, PLATO and proposal stages (through the split file the latent cache
    # was encoded from)
    focus_group: str = ""
    focus_share: float = within(0.0, SHARE)
    # the perception stage alone: this share of each batch's frames shows a ball or cube off the
    # floor (0 = frames drawn uniformly)
    airborne_share: float = within(0.0, SHARE)
    # the PhyDNet stage alone: at the start of this phase its ConvLSTM gates widen to this size,
    # the trained taps in the centre (0 = as they are)
    lstm_kernel: int = within(0, NON_NEGATIVE)

    def __post_init__(self) -> None:
        check_config(self)      # one built in Python is refused as one built from the command line is
