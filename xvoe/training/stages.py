"""The training stages and the models scored by name, each named once: what each stage trains,
from what, into which checkpoint, and what the scorecard expects of the model it makes.

The command line, the pipeline, the model zoo, the recipes, provenance, scoring and the
scorecard read these tables, so that a stage's or a model's name and its facts are written
nowhere else. Every model but one is a stage's checkpoint; the chance baseline (`RANDOM`) is
drawn, not trained, and is a model of its own kind here.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..errors import XvoeError

__all__ = ["Stage", "PERCEPTION", "XPL", "PROPOSAL", "PLATO", "XPL_NORESIDUAL", "PHYDNET", "RANDOM", "BASELINE",
           "CHANCE", "REPORTED", "ROLES", "STAGES", "SCORED", "MODEL_ROLES", "MODELS", "DEFAULT_MODELS", "stage",
           "continued_by", "resting_on"]


@dataclass(frozen=True)
class Stage:
    name: str                   # the checkpoint is NAME.pt, its losses NAME.csv
    help: str
    # where its checkpoint stores its network's config: checkpoint["config"][config_key], a config
    # class of xvoe.training.recipes.recipe's NETWORKS (not imported here: the networks' modules
    # import torch, and the command line reads this table to build its --help)
    config_key: str
    # what it trains on: "pixels" (a training split), "latents" (the perception's latent cache of
    # one) or XPL (the run's xpl.pt, on that cache)
    reads: str
    train_field: str            # the Recipe field of its first training run
    # the goals the scorecard holds the model it makes to (one of ROLES but CHANCE); empty for a stage that
    # makes no model of its own (`xvoe score --model NAME` scores the others)
    role: str = ""
    # `xvoe pipeline --jobs` lanes start the lowest first: the longest training, so that the last lane does
    # not start it late (docs/decisions.md, "Processes and threads")
    lane: int = 0
    nll: bool = False           # its checkpoint stores the recipe's NLL settings: the model the NLL surprise runs on
    variant: str = ""           # XPL-family stages: the network XPL is fitted to (XPL or PLATO)
    residual: bool = True       # ... and whether its dynamics predict a change (XPL) or the latent itself (PLATO)

    @property
    def scored(self) -> bool:
        return bool(self.role)

    @property
    def checkpoint(self) -> str:
        return f"{self.name}.pt"

    @property
    def reads_latents(self) -> bool:
        """Whether it reads the perception's latents: a new perception.pt strands its checkpoint."""
        return self.reads in ("latents", XPL)


# every stage's and model's name, written here once: code elsewhere names them by these constants
PERCEPTION = "perception"       # the stage whose latents the others on the latent cache read
XPL, PROPOSAL, PLATO, XPL_NORESIDUAL, PHYDNET = "xpl", "proposal", "plato", "xpl-noresidual", "phydnet"
# the chance baseline: per-frame surprise drawn at random (xvoe.evaluation.scorer), scored by name like
# any model and made by no stage: nothing to train, no checkpoint
RANDOM = "random"
# the goals the scorecard holds a model to (xvoe.evaluation.scorecard): XPL's own, a baseline's, chance's
# (50% inside the interval), or reported without goals
BASELINE, CHANCE, REPORTED = "baseline", "chance", "reported"
ROLES = (XPL, BASELINE, CHANCE, REPORTED)
STAGES: dict[str, Stage] = {stage.name: stage for stage in (
    Stage(PERCEPTION, "the Component VAE, on a training split's frames", PERCEPTION,
          "pixels", "perception_train"),
    Stage(XPL, "Transformer 1 and the dynamics (Transformer 2 too where the recipe trains it jointly), on the "
          "latent cache (a split is encoded first)",
          XPL, "latents", "xpl_train", role=XPL, lane=3, nll=True, variant=XPL),
    Stage(PROPOSAL, "Transformer 2 and the existence head further, on hidden objects (after xpl)",
          XPL, XPL, "proposal_train", variant=XPL),
    Stage(PLATO, "the PLATO baseline: the dynamics alone, on the latent cache", XPL, "latents",
          "plato_train", role=BASELINE, lane=1, variant=PLATO, residual=False),
    Stage(XPL_NORESIDUAL, "XPL without the dynamics' residual (the paper's ablation), on the latent cache",
          XPL, "latents", "xpl_train", role=REPORTED, lane=2, variant=XPL, residual=False),
    Stage(PHYDNET, "the PhyDNet baseline, on a training split's pixels", PHYDNET, "pixels",
          "phydnet_train", role=BASELINE, lane=0),
)}
SCORED = tuple(name for name, stage in STAGES.items() if stage.scored)     # the models a checkpoint can be
# every model scored by name, with the goals the scorecard holds it to
MODEL_ROLES: dict[str, str] = {**{name: STAGES[name].role for name in SCORED}, RANDOM: CHANCE}
MODELS = tuple(MODEL_ROLES)
# what `xvoe pipeline` scores unless told: the XPL model against chance (here, below torch, for its --help)
DEFAULT_MODELS = (XPL, RANDOM)


def stage(name: str) -> Stage:
    """The named stage, or a one-line error listing them."""
    if name not in STAGES:
        raise XvoeError(f"unknown stage {name!r}; choose one of {', '.join(STAGES)}")
    return STAGES[name]


def continued_by(name: str) -> tuple[str, ...]:
    """The stages that continue from the stage's checkpoint (xpl's proposal stage): its scores rest on them too."""
    return tuple(other for other, entry in STAGES.items() if entry.reads == name)


def resting_on(model: str) -> tuple[str, ...]:
    """The stages a model's scores rest on: its own, those that continue from it, and the perception whose
    latents it reads; none for the random agent."""
    if model not in STAGES:
        return ()
    return (model, *continued_by(model), *((PERCEPTION,) if STAGES[model].reads_latents else ()))
