"""A researcher's conventions: `xvoe --version`; every verb's --help without torch (the time is
benchmarks/cli_help.py's to measure); --quiet taken by every verb; the recipe names the --help
lists without loading a recipe are the recipes', and the models it offers those the verbs take."""
from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import pytest

import xvoe
from xvoe.apps.pipeline import MODELS, PipelineConfig
from xvoe.cli import build_parser, main
from xvoe.evaluation.surprise import EXPLANATIONS
from xvoe.training.checkpoints import SHIPPED
from xvoe.training.config import DEFAULT_RECIPE, RECIPE_NAMES
from xvoe.training.recipes import RECIPES

HEAVY = ("torch", "pyro", "h5py", "pymunk", "matplotlib")
ROOT = Path(__file__).resolve().parent.parent


def verbs() -> dict:
    return build_parser()._subparsers._group_actions[0].choices


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.strip() == f"xvoe {xvoe.__version__}"


def test_help_leaves_torch_out(tmp_path):
    code = ("import sys\nfrom xvoe.cli import main\n"
            "for argv in (['--help'], ['score', '--help'], ['train', 'xpl', '--help'], ['pipeline', '--help']):\n"
            "    try:\n        main(argv)\n    except SystemExit:\n        pass\n"
            f"print(*[m for m in {HEAVY!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path)
    assert "usage: xvoe score" in out.stdout and "--recipe" in out.stdout
    assert out.stdout.splitlines()[-1].strip() == ""        # none of them imported


def test_every_verb_takes_quiet():
    for name, parser in verbs().items():
        chosen = parser._subparsers._group_actions[0].choices.values() if name == "train" else [parser]
        for each in chosen:
            assert "--quiet" in each._option_string_actions, f"xvoe {name} has no --quiet"


def test_the_recipe_names_are_the_recipes():
    assert RECIPE_NAMES == tuple(RECIPES) and DEFAULT_RECIPE in RECIPE_NAMES


def test_the_inference_layer_is_imported_by_its_installed_name():
    # the wheel installs it as xvoe.inference only: a top-level `inference` import works in a checkout alone
    stray = [f"{path.relative_to(ROOT)}:{number}"
             for folder in ("xvoe", "inference", "tests", "benchmarks")
             for path in sorted((ROOT / folder).rglob("*.py"))
             for number, line in enumerate(path.read_text().splitlines(), 1)
             if re.match(r"\s*(from|import) inference\b", line)]
    assert stray == []


def _help_of(parser, dest: str) -> str:
    return next(action.help for action in parser._actions if action.dest == dest)


def test_the_help_offers_the_models_the_verbs_take():
    # the names are the registry's, not a copy: what the help lists is what the verbs accept
    offered = re.fullmatch(r"comma-separated: (.*) \(default (.*)\)", _help_of(verbs()["pipeline"], "models"))
    default = next(f.default for f in fields(PipelineConfig) if f.name == "models")
    assert offered[1].split(", ") == list(MODELS) and tuple(offered[2].split(",")) == default
    named = re.search(r"a stage checkpoint \((.*)\), (\S+), or a model of your own",
                      _help_of(verbs()["score"], "model"))
    assert named[1].split(", ") == [f"{name}.pt" for name in SHIPPED]
    assert xvoe.load_model(named[2]).name == named[2]


def test_the_explain_verb_offers_the_mse_explanations():
    # written out in the parser, as their module imports torch, which --help leaves out
    choices = next(a.choices for a in verbs()["explain"]._actions if a.dest == "explanation")
    assert sorted(choices) == sorted(EXPLANATIONS)


def test_the_help_lists_the_scenarios_of_the_registry():
    # written out in the help, as the registry loads pymunk, which --help leaves out
    listed = _help_of(verbs()["list"], "scenario")
    assert listed.replace(" or ", ", ").split(", ") == list(xvoe.SCENARIOS)
