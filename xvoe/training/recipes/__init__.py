"""The recipes, one small module each: every stage and setting of the models, as code.

`xvoe pipeline --recipe NAME --seed S` makes every model of a recipe from nothing; each
checkpoint names its recipe (and its training config holds the seed), and a test checks
that the shipped checkpoints' configs are their recipe's.
"""
from __future__ import annotations

from ...errors import XvoeError
from ..config import DEFAULT_RECIPE
from . import cpu_short, paper
from .recipe import NETWORKS, Recipe, stage_settings

RECIPES: dict[str, Recipe] = {r.name: r for r in (cpu_short.RECIPE, paper.RECIPE)}     # named in ..config too


def recipe(name: str) -> Recipe:
    """The named recipe, or a one-line error listing the known ones."""
    if name not in RECIPES:
        raise XvoeError(f"unknown recipe {name!r}; choose one of {', '.join(RECIPES)}")
    return RECIPES[name]


def recipe_of(config: dict) -> str:
    """The recipe a checkpoint's config names."""
    return config["recipe"]


__all__ = ["DEFAULT_RECIPE", "NETWORKS", "RECIPES", "Recipe", "recipe", "recipe_of", "stage_settings"]
