"""The training stages, named once: what each trains, from what, and into which checkpoint.

The command line, the pipeline, the model zoo, the recipes, provenance and scoring read this
table, so that a stage's name and its facts are written nowhere else.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass

from ..errors import XvoeError


@dataclass(frozen=True)
class Stage:
    name: str                   # the checkpoint is NAME.pt, its losses NAME.csv
    help: str
    # the network config its checkpoint stores, "module:class", loaded on use: the networks'
    # modules import torch, and the command line reads this table to build its --help
    config_home: str
    config_key: str             # where: checkpoint["config"][config_key]
    # what it trains on: "pixels" (a training split), "latents" (the perception's latent cache of
    # one) or "xpl" (the run's xpl.pt, on that cache)
    reads: str
    train_field: str            # the Recipe field of its first training run
    scored: bool = False        # a model `xvoe score --model NAME` scores
    variant: str = ""           # XPL-family stages: the network XPL is fitted to ("xpl" or "plato")
    residual: bool = True       # ... and whether its dynamics predict a change (XPL) or the latent itself (PLATO)

    @property
    def config(self) -> type:
        module, _, name = self.config_home.partition(":")
        return getattr(importlib.import_module(module), name)

    @property
    def checkpoint(self) -> str:
        return f"{self.name}.pt"

    @property
    def reads_latents(self) -> bool:
        """Whether it reads the perception's latents: a new perception.pt strands its checkpoint."""
        return self.reads in ("latents", "xpl")


_PERCEPTION, _XPL, _PHYDNET = ("xvoe.models.perception:PerceptionConfig", "xvoe.models.xpl:XPLConfig",
                               "xvoe.models.phydnet:PhyDNetConfig")
STAGES: dict[str, Stage] = {stage.name: stage for stage in (
    Stage("perception", "the Component VAE, on a training split's frames", _PERCEPTION, "perception",
          "pixels", "perception_train"),
    Stage("xpl", "Transformer 1 and the dynamics (Transformer 2 too where the recipe trains it jointly), on the "
          "latent cache (a split is encoded first)",
          _XPL, "xpl", "latents", "xpl_train", scored=True, variant="xpl"),
    Stage("proposal", "Transformer 2 and the existence head further, on hidden objects (after xpl)",
          _XPL, "xpl", "xpl", "proposal_train", variant="xpl"),
    Stage("plato", "the PLATO baseline: the dynamics alone, on the latent cache", _XPL, "xpl", "latents",
          "plato_train", scored=True, variant="plato", residual=False),
    Stage("xpl-noresidual", "XPL without the dynamics' residual (the paper's ablation), on the latent cache",
          _XPL, "xpl", "latents", "xpl_train", scored=True, variant="xpl", residual=False),
    Stage("phydnet", "the PhyDNet baseline, on a training split's pixels", _PHYDNET, "phydnet", "pixels",
          "phydnet_train", scored=True),
)}
SCORED = tuple(name for name, stage in STAGES.items() if stage.scored)     # the models a checkpoint can be
XPL_FAMILY = tuple(name for name, stage in STAGES.items() if stage.variant)


def stage(name: str) -> Stage:
    """The named stage, or a one-line error listing them."""
    if name not in STAGES:
        raise XvoeError(f"unknown stage {name!r}; choose one of {', '.join(STAGES)}")
    return STAGES[name]
