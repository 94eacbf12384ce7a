"""Recipes are code: each shipped checkpoint names a recipe whose configs are its own, the
pipeline runs a recipe's later phases, and the defaults agree with the default recipe."""
from __future__ import annotations

from dataclasses import replace

import pytest

from xvoe.apps.pipeline import stage_processes
from xvoe.errors import XvoeError
from xvoe.models.config import to_dict
from xvoe.scenes.generate import GenerateConfig
from xvoe.training.checkpoints import WEIGHTS, load_checkpoint
from xvoe.training.config import TrainConfig
from xvoe.training.provenance import RUN_FIELDS, recipe_differences
from xvoe.training.recipes import DEFAULT_RECIPE, RECIPES, recipe, recipe_of
from xvoe.training.stages import STAGES

FROM_THE_RECIPE = tuple(STAGES)


@pytest.mark.parametrize("name", FROM_THE_RECIPE)
def test_a_shipped_checkpoint_holds_its_recipes_configs(name):
    state = load_checkpoint(WEIGHTS / f"{name}.pt")
    assert recipe_of(state["config"]) == DEFAULT_RECIPE
    assert recipe_differences(state) == []


def test_every_shipped_checkpoint_is_listed():
    assert sorted(p.stem for p in WEIGHTS.glob("*.pt")) == sorted(FROM_THE_RECIPE)


def test_a_changed_setting_is_a_difference():
    state = load_checkpoint(WEIGHTS / "xpl.pt")
    state["config"] = {**state["config"], "xpl": {**state["config"]["xpl"], "inert_walls": False}}
    state["train"] = {**state["train"], "lr": 0.5}
    assert recipe_differences(state) == ["xpl.inert_walls: False != True", "train.lr: 0.5 != 0.001"]


def test_the_nll_settings_are_the_recipes_and_a_changed_one_is_a_difference():
    """xpl.pt holds the NLL settings its recipe gives it (one shipped before they were stored reads
    as InferenceConfig's defaults, which the default recipe writes out), so that a score file can
    be made again from the checkpoint it names."""
    state = load_checkpoint(WEIGHTS / "xpl.pt")
    stored = {**state, "config": {**state["config"], "nll": {**to_dict(recipe(DEFAULT_RECIPE).nll)}}}
    assert recipe_differences(stored) == []
    stored["config"]["nll"]["pixel_sigma"] = 0.25
    assert recipe_differences(stored) == ["nll.pixel_sigma: 0.25 != 0.5"]


def test_an_unfinished_run_is_a_difference():
    """Stopped inside its last phase, a run holds that phase's configs but not its model."""
    state = load_checkpoint(WEIGHTS / "xpl.pt")
    assert recipe_differences({**state, "step": 5000}) == ["step: 5000 != 9000 (the run has not finished)"]


def test_the_seed_is_the_runs_own():
    state = load_checkpoint(WEIGHTS / "xpl.pt")
    assert recipe_differences({**state, "train": {**state["train"], "seed": 3}}) == []


def test_generate_makes_the_frames_the_default_model_reads():
    assert GenerateConfig().size == recipe(DEFAULT_RECIPE).perception.image_size


def test_phases_continue_a_stage_and_the_last_is_what_a_run_holds():
    base = TrainConfig(steps=10)
    later = (("plato", TrainConfig(steps=20, focus_group="continuity", focus_share=0.5)),
             ("plato", TrainConfig(steps=30)))
    made = replace(RECIPES[DEFAULT_RECIPE], plato_train=base, phases=later)
    assert made.training("plato") == base
    assert made.phases_of("plato") == tuple(t for _, t in later)
    assert made.final_training("plato").steps == 30
    assert made.final_training("xpl") == made.xpl_train


def test_a_phydnet_widened_by_a_phase_is_what_its_recipe_makes():
    """The recipe's PhyDNet starts with 3x3 gates and a phase widens them: a finished run holds 5x5."""
    made = recipe(DEFAULT_RECIPE)
    assert made.phydnet.lstm_kernel == 3 and made.final_phydnet().lstm_kernel == 5
    state = load_checkpoint(WEIGHTS / "phydnet.pt")
    widened = {**state, "config": {"recipe": DEFAULT_RECIPE, "phydnet": state["config"]["phydnet"]},
               "train": {**state["train"], **{k: v for k, v in vars(made.final_training("phydnet")).items()
                                              if k not in RUN_FIELDS}},
               "step": made.final_training("phydnet").steps}
    assert recipe_differences(widened) == []
    narrow = {**widened, "config": {**widened["config"], "phydnet": {**state["config"]["phydnet"], "lstm_kernel": 3}}}
    assert recipe_differences(narrow) == ["phydnet.lstm_kernel: 3 != 5"]


def test_an_unknown_recipe_is_a_one_line_error():
    known = "cpu-short, paper"
    with pytest.raises(XvoeError, match=f"unknown recipe 'gpu'; choose one of {known}"):
        recipe("gpu")


def test_each_recipe_is_one_file_that_builds_on_no_other():
    import ast
    from pathlib import Path

    import xvoe.training.recipes as recipes

    for module in Path(recipes.__file__).parent.glob("*.py"):
        if module.stem in ("__init__", "recipe"):
            continue
        imported = {node.module for node in ast.walk(ast.parse(module.read_text())) if isinstance(node, ast.ImportFrom)}
        assert not any(name in RECIPES or name.replace("_", "-") in RECIPES for name in filter(None, imported)), module


def test_the_default_recipe_fixes_every_stages_data_shards():
    """Left at 0, a stage's shards are the processes of its first launch, one per core in the
    pipeline: the same command would draw other batches, and make another model, on another machine."""
    made = recipe(DEFAULT_RECIPE)
    trainings = [made.training(stage) for stage in STAGES] + [train for _, train in made.phases]
    assert all(train.data_shards > 0 for train in trainings)


@pytest.mark.parametrize(("wanted", "shards", "processes"), [(1, 2, 1), (2, 2, 2), (8, 2, 2), (3, 4, 2),
                                                              (4, 4, 4), (3, 0, 3), (5, 1, 1)])
def test_a_stage_trains_in_as_many_processes_as_split_its_shards(wanted, shards, processes):
    assert stage_processes(wanted, TrainConfig(batch_size=8, data_shards=shards)) == processes
