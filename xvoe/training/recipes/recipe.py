"""What a recipe is: every setting of every stage that makes a model, as data.

A `Recipe` holds the training data's size, one network config and one training config per
stage, and the phases that continue a stage (a resume with a new batch focus or learning
rate is a written phase, not a hand-run step). The recipes themselves are the modules beside
this one.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from ...errors import XvoeError
from ...models.config import field_type, parse_value, split_assignment
from ...models.perception import PerceptionConfig
from ...models.phydnet import PhyDNetConfig
from ...models.trajectory import TrajectoryConfig
from ...models.xpl import XPLConfig


@dataclass(frozen=True)
class TrainConfig:
    """One training run of one stage: the shared loop reads only these fields."""

    steps: int = 6000
    batch_size: int = 32            # frames per step, summed over all processes
    lr: float = 1e-3
    warmup_steps: int = 200         # linear warm-up of the learning rate
    decay_steps: int = 5000         # the learning rate halves every decay_steps after warm-up
    grad_clip: float = 0.0          # clip the gradient norm to this (0 = no clipping)
    # the checkpoint's weights are a moving average of the trained ones, each step's weighed this
    # much less than the next one's (0 = the last step's weights); training resumes from the trained ones
    average_decay: float = 0.0
    seed: int = 0
    checkpoint_minutes: float = 3.0  # a checkpoint is written at least this often
    log_every: int = 10             # steps between rows of the loss CSV
    max_minutes: float = 0.0        # stop early after this much training time (0 = no limit)
    max_videos: int = 0             # videos of the data file to load (0 = all)
    data_shards: int = 0            # slices of the file that each feed batch_size/data_shards frames
                                    # per step; 0 = the number of processes of the first launch
    threads: int = 0                # torch threads per process (0 = cores / processes)
    # this share of each batch comes from the training videos of `focus_group` that have a wall
    # (e.g. permanence, where cubes must be remembered behind it; several: permanence,continuity);
    # 0 = uniform. PhyDNet, and the XPL, PLATO and proposal stages (through the split file the latent cache
    # was encoded from)
    focus_group: str = ""
    focus_share: float = 0.0
    # the perception stage alone: this share of each batch's frames shows a ball or cube off the
    # floor (0 = frames drawn uniformly)
    airborne_share: float = 0.0
    # the PhyDNet stage alone: at the start of this phase its ConvLSTM gates widen to this size,
    # the trained taps in the centre (0 = as they are)
    lstm_kernel: int = 0


@dataclass(frozen=True)
class Recipe:
    """Everything needed to make every model from nothing: `xvoe pipeline --recipe NAME`."""

    name: str
    train_videos: int = 10_000      # the training split the pipeline generates (frames: perception.image_size)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    perception_train: TrainConfig = field(default_factory=TrainConfig)
    xpl: XPLConfig = field(default_factory=XPLConfig)
    xpl_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=1500, batch_size=32, warmup_steps=100,
                                                                       decay_steps=1000))
    # Transformer 2 and the existence head trained further on hidden objects (the proposal stage)
    proposal_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=4000, batch_size=32,
                                                                            warmup_steps=100, decay_steps=1500))
    # the NLL's learned proposal of whole trajectories (the trajectory stage, after proposal)
    trajectory_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=2000, batch_size=32,
                                                                              warmup_steps=100, decay_steps=1000))
    # the PLATO baseline's training (None: xpl_train's). Without Transformer 1 it predicts the
    # raw latents directly, and every visible object costs its prediction error in every frame:
    # trained no longer than XPL, that cost outweighs the violations of the predictive settings
    plato_train: TrainConfig | None = None
    # the PhyDNet baseline: batch_size counts videos
    phydnet: PhyDNetConfig = field(default_factory=PhyDNetConfig)
    phydnet_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=300, batch_size=8, lr=3e-3,
                                                                           warmup_steps=20, decay_steps=300))
    # phases that continue a stage's run, in order: (stage, its training from there on), each
    # resumed from the checkpoint the phase before left, to `steps` in all
    phases: tuple[tuple[str, TrainConfig], ...] = ()

    def phases_of(self, stage: str) -> tuple[TrainConfig, ...]:
        return tuple(train for name, train in self.phases if name == stage)

    def training(self, stage: str) -> TrainConfig:
        """The first phase of a stage: where a fresh run of it starts."""
        if stage == "plato" and self.plato_train is not None:
            return self.plato_train
        return {"perception": self.perception_train, "xpl": self.xpl_train, "plato": self.xpl_train,
                "xpl-noresidual": self.xpl_train, "proposal": self.proposal_train,
                "trajectory": self.trajectory_train,
                "phydnet": self.phydnet_train}[stage]

    def final_phydnet(self) -> PhyDNetConfig:
        """The PhyDNet a finished run holds: the recipe's, its gates as wide as a phase widened them."""
        kernels = [train.lstm_kernel for train in (self.phydnet_train, *self.phases_of("phydnet")) if train.lstm_kernel]
        return replace(self.phydnet, lstm_kernel=kernels[-1]) if kernels else self.phydnet

    def final_training(self, stage: str) -> TrainConfig:
        """The training config a finished run of the stage holds: its last phase's."""
        return (self.training(stage), *self.phases_of(stage))[-1]


MODEL_CONFIGS = {"perception": PerceptionConfig, "xpl": XPLConfig, "plato": XPLConfig, "phydnet": PhyDNetConfig,
                 "proposal": XPLConfig, "trajectory": TrajectoryConfig}
# what the proposal stage may change of the XPL it trains on: how Transformer 2 is used, not its network
PROPOSAL_FIELDS = ("proposal_sees_seen",)


def stage_settings(stage: str, assignments: list[str]) -> tuple[dict, dict]:
    """`--set FIELD=VALUE` as typed overrides of the stage's TrainConfig and model config.
    A field is looked up in TrainConfig, then in the model's config; `train.` or `model.`
    before it picks one, and a dotted name reaches a nested config (`model.dynamics.hidden`)."""
    train, model = {}, {}
    owners = {"train": TrainConfig, "model": MODEL_CONFIGS.get(stage)}
    for text in assignments:
        name, value = split_assignment(text, "--set")
        where, _, rest = name.partition(".")
        if where in owners and rest:
            chosen = where
            name = rest
        else:
            chosen = "train" if name.partition(".")[0] in {f.name for f in fields(TrainConfig)} else "model"
        config = owners[chosen]
        if config is None:
            raise XvoeError(f"the {stage} stage builds no network of its own: only TrainConfig fields may be set")
        target = train if chosen == "train" else model
        target[name] = parse_value(field_type(config, name), value)
    return train, model
