"""The recipes, one small module each: every stage and setting of the models, as code.

`xvoe pipeline --recipe NAME --seed S` makes every model of a recipe from nothing; each
checkpoint names its recipe (and its training config holds the seed), and a test checks
that the shipped checkpoints' configs are their recipe's.
"""
from __future__ import annotations

from ...errors import XvoeError
from . import cpu, cpu_line, cpu_short, cpu_walls, paper
from .recipe import MODEL_CONFIGS, PROPOSAL_FIELDS, Recipe, TrainConfig, stage_settings

RECIPES: dict[str, Recipe] = {r.name: r for r in (cpu.RECIPE, cpu_walls.RECIPE, cpu_short.RECIPE, cpu_line.RECIPE,
                                                  paper.RECIPE)}
# what `xvoe pipeline` runs and the shipped models come from (docs/decisions.md, "The default recipe")
DEFAULT_RECIPE = "cpu-short"
# checkpoints written before recipes named their preset; `cpu-broadcast` is today's `cpu`
RENAMED = {"cpu-broadcast": "cpu"}


def recipe(name: str) -> Recipe:
    """The named recipe, or a one-line error listing the known ones."""
    if name not in RECIPES:
        raise XvoeError(f"unknown recipe {name!r}; choose one of {', '.join(RECIPES)}")
    return RECIPES[name]


def recipe_of(config: dict) -> str:
    """The recipe a checkpoint's config names (older checkpoints: the preset, renamed)."""
    if "recipe" in config:
        return config["recipe"]
    return RENAMED.get(config["preset"], config["preset"])


__all__ = ["DEFAULT_RECIPE", "MODEL_CONFIGS", "PROPOSAL_FIELDS", "RECIPES", "Recipe", "TrainConfig", "recipe",
           "recipe_of", "stage_settings"]
