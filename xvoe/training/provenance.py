"""Whether a checkpoint is what its recipe makes: the stored configs against the recipe's.

A checkpoint names its recipe; its network config, its last training config and (for xpl.pt)
its NLL settings must be the ones the recipe gives its stage, so that `xvoe pipeline --recipe
NAME --seed S` makes it again from nothing. What the data decide (the frames, slots and latent
size a cache has) and what a run decides (its seed, data shards and threads) are taken from the
checkpoint.
"""
from __future__ import annotations

from ..models.config import from_dict, to_dict
from ..models.xpl import XPLConfig
from .config import TrainConfig
from .recipes import NETWORKS, recipe, recipe_of
from .stages import PERCEPTION, PHYDNET, XPL, stage
from .xpl import model_nll, stage_config

__all__ = ["RUN_FIELDS", "expected_configs", "recipe_differences"]

RUN_FIELDS = ("seed", "data_shards", "threads")


def expected_configs(state: dict) -> tuple[dict, dict]:
    """The stored config and training config the checkpoint's recipe gives its stage."""
    entry, config = stage(state["stage"]), state["config"]
    chosen = recipe(recipe_of(config))
    if entry.config_key == PERCEPTION:
        model = {PERCEPTION: to_dict(chosen.perception)}
    elif entry.config_key == PHYDNET:
        model = {PHYDNET: to_dict(chosen.final_phydnet())}
    else:
        stored = from_dict(XPLConfig, config[XPL])
        shape = (stored.reasoning.frames, stored.reasoning.slots, stored.reasoning.latent_dim)
        model = {XPL: to_dict(stage_config(chosen.xpl, entry.name, shape))}
        if entry.nll:
            model["nll"] = to_dict(chosen.nll)
    model["recipe"] = chosen.name
    train = to_dict(chosen.final_training(entry.name)) | {k: state["train"][k] for k in RUN_FIELDS}
    return model, train


def recipe_differences(state: dict) -> list[str]:
    """Each setting in which the checkpoint differs from its recipe ("xpl.inert_walls: True != False");
    empty when the recipe made it."""
    model, train = expected_configs(state)
    config = state["config"]
    stored = {"recipe": recipe_of(config)}      # read as the loaders read it: a field added since takes its default
    entry = stage(state["stage"])
    stored[entry.config_key] = to_dict(from_dict(NETWORKS[entry.config_key], config[entry.config_key]))
    if entry.nll:
        stored["nll"] = to_dict(model_nll(config))
    lines = _differences(stored, model, "") + _differences(to_dict(from_dict(TrainConfig, state["train"])), train,
                                                          "train.")
    if "step" in state and state["step"] != train["steps"]:     # a run stopped, or still going, inside its last phase
        lines.append(f"step: {state['step']} != {train['steps']} (the run has not finished)")
    return lines


def _differences(found: dict, wanted: dict, prefix: str) -> list[str]:
    lines = []
    for key in sorted(set(found) | set(wanted)):
        a, b = found.get(key), wanted.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            lines += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            lines.append(f"{prefix}{key}: {a!r} != {b!r}")
    return lines
