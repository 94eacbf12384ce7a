"""What a recipe is: every setting of every stage that makes a model, as data.

A `Recipe` holds the training data's size, one network config and one training config per
stage, the NLL's settings, and the phases that continue a stage (a resume with a new batch
focus or learning rate is a written phase, not a hand-run step). Every field is written in each
recipe's module beside this one (none has a default here but the phases, of which a recipe may
have none): a setting is decided there, stored in the checkpoint a stage makes, and changed
only by an explicit `--set` or `--nll-set`.
"""
from __future__ import annotations

from dataclasses import dataclass, fields, replace

from ...models.config import parse_field, split_assignment
from ...models.nll import InferenceConfig
from ...models.perception import PerceptionConfig
from ...models.phydnet import PhyDNetConfig
from ...models.xpl import XPLConfig
from ..config import TrainConfig
from ..stages import PERCEPTION, PHYDNET, STAGES, XPL, stage

__all__ = ["NETWORKS", "Recipe", "stage_settings"]

# the network config each stage's checkpoint stores, by its config_key (xvoe.training.stages)
NETWORKS: dict[str, type] = {PERCEPTION: PerceptionConfig, XPL: XPLConfig, PHYDNET: PhyDNetConfig}


@dataclass(frozen=True)
class Recipe:
    """Everything needed to make every model from nothing: `xvoe pipeline --recipe NAME`."""

    name: str
    # the NLL surprise's settings for the models it makes: the xpl stage stores them in its
    # checkpoint, and a score reads them back from there
    nll: InferenceConfig
    train_videos: int           # the training split the pipeline generates (frames: perception.image_size)
    perception: PerceptionConfig
    perception_train: TrainConfig
    xpl: XPLConfig
    xpl_train: TrainConfig
    # Transformer 2 and the existence head trained further on hidden objects (the proposal stage)
    proposal_train: TrainConfig
    # the PLATO baseline's training. Without Transformer 1 it predicts the raw latents directly, and
    # every visible object costs its prediction error in every frame: trained no longer than XPL,
    # that cost outweighs the violations of the predictive settings
    plato_train: TrainConfig
    phydnet: PhyDNetConfig      # the PhyDNet baseline
    phydnet_train: TrainConfig  # ... whose batch_size counts videos
    # phases that continue a stage's run, in order: (stage, its training from there on), each
    # resumed from the checkpoint the phase before left, to `steps` in all
    phases: tuple[tuple[str, TrainConfig], ...] = ()

    def phases_of(self, stage: str) -> tuple[TrainConfig, ...]:
        return tuple(train for name, train in self.phases if name == stage)

    def training(self, name: str) -> TrainConfig:
        """The first phase of a stage: where a fresh run of it starts."""
        return getattr(self, stage(name).train_field)

    def final_phydnet(self) -> PhyDNetConfig:
        """The PhyDNet a finished run holds: the recipe's, its gates as wide as a phase widened them."""
        kernels = [train.lstm_kernel for train in (self.phydnet_train, *self.phases_of(PHYDNET)) if train.lstm_kernel]
        return replace(self.phydnet, lstm_kernel=kernels[-1]) if kernels else self.phydnet

    def final_training(self, stage: str) -> TrainConfig:
        """The training config a finished run of the stage holds: its last phase's."""
        return (self.training(stage), *self.phases_of(stage))[-1]


def stage_settings(stage: str, assignments: list[str]) -> tuple[dict, dict]:
    """`--set FIELD=VALUE` as typed overrides of the stage's TrainConfig and model config.
    A field is looked up in TrainConfig, then in the model's config; `train.` or `model.`
    before it picks one, and a dotted name reaches a nested config (`model.dynamics.hidden`)."""
    train, model = {}, {}
    owners = {"train": TrainConfig, "model": NETWORKS[STAGES[stage].config_key]}
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
