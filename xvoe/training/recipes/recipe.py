"""What a recipe is: every setting of every stage that makes a model, as data.

A `Recipe` holds the training data's size, one network config and one training config per
stage, and the phases that continue a stage (a resume with a new batch focus or learning
rate is a written phase, not a hand-run step). The recipes themselves are the modules beside
this one.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

from ...models.config import parse_field, split_assignment
from ...models.nll import InferenceConfig
from ...models.perception import PerceptionConfig
from ...models.phydnet import PhyDNetConfig
from ...models.xpl import XPLConfig
from ..config import TrainConfig
from ..stages import STAGES, stage


@dataclass(frozen=True)
class Recipe:
    """Everything needed to make every model from nothing: `xvoe pipeline --recipe NAME`."""

    name: str
    # the NLL surprise's settings for the models it makes, written in each recipe's file: the xpl
    # stage stores them in its checkpoint, and a score reads them back from there
    nll: InferenceConfig
    train_videos: int = 10_000      # the training split the pipeline generates (frames: perception.image_size)
    perception: PerceptionConfig = field(default_factory=PerceptionConfig)
    perception_train: TrainConfig = field(default_factory=TrainConfig)
    xpl: XPLConfig = field(default_factory=XPLConfig)
    xpl_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=1500, batch_size=32, warmup_steps=100,
                                                                       decay_steps=1000))
    # Transformer 2 and the existence head trained further on hidden objects (the proposal stage)
    proposal_train: TrainConfig = field(default_factory=lambda: TrainConfig(steps=4000, batch_size=32,
                                                                            warmup_steps=100, decay_steps=1500))
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

    def training(self, name: str) -> TrainConfig:
        """The first phase of a stage: where a fresh run of it starts."""
        train = getattr(self, stage(name).train_field)
        return self.xpl_train if train is None else train

    def final_phydnet(self) -> PhyDNetConfig:
        """The PhyDNet a finished run holds: the recipe's, its gates as wide as a phase widened them."""
        kernels = [train.lstm_kernel for train in (self.phydnet_train, *self.phases_of("phydnet")) if train.lstm_kernel]
        return replace(self.phydnet, lstm_kernel=kernels[-1]) if kernels else self.phydnet

    def final_training(self, stage: str) -> TrainConfig:
        """The training config a finished run of the stage holds: its last phase's."""
        return (self.training(stage), *self.phases_of(stage))[-1]


def stage_settings(stage: str, assignments: list[str]) -> tuple[dict, dict]:
    """`--set FIELD=VALUE` as typed overrides of the stage's TrainConfig and model config.
    A field is looked up in TrainConfig, then in the model's config; `train.` or `model.`
    before it picks one, and a dotted name reaches a nested config (`model.dynamics.hidden`)."""
    train, model = {}, {}
    owners = {"train": TrainConfig, "model": STAGES[stage].config}
    for text in assignments:
        name, value = split_assignment(text, "--set")
        where, _, rest = name.partition(".")
        if where in owners and rest:
            chosen = where
            name = rest
        else:
            chosen = "train" if name.partition(".")[0] in {f.name for f in fields(TrainConfig)} else "model"
        config = owners[chosen]
        target = train if chosen == "train" else model
        target[name] = parse_field(config, name, value)
    return train, model
