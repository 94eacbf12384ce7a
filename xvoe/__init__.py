"""xvoe: the X-VoE benchmark and the XPL intuitive-physics model in PyTorch and Pyro.

The public API, one import for notebooks, scripts and the command line alike:

    import xvoe
    xvoe.generate(xvoe.GenerateConfig(split="test", pairs=20, size=32, seed=7), "test.h5")
    scorer = xvoe.load_model("xpl")                       # a shipped name or a run directory
    xvoe.score(scorer, "test.h5", "xpl.csv")              # surprise="nll" for the Pyro model's
    xvoe.report(["xpl.csv"], "report")                    # the paper's metrics and figures
    xvoe.plot_explanation(xvoe.explain(scorer, "test.h5", 160))

The layers underneath (xvoe.scenes, models, training, evaluation, inference, xvoe.apps)
are importable too; the imports below name what a user needs. They run on first use of a name
(PEP 562), so that `import xvoe` and the benchmark layer stay free of torch; the block under
TYPE_CHECKING is the same imports, for editors and type checkers to follow.
"""
from __future__ import annotations

from types import ModuleType
from typing import TYPE_CHECKING, Any

from .allocator import follow as _follow_allocator
from .processes import interrupts_held as _interrupts_held
from .progress import quiet_widget_warning as _quiet_widget_warning

_follow_allocator()     # a worker of a tuned process keeps its malloc settings; else glibc's stay (xvoe/allocator.py)
_quiet_widget_warning()     # before pyro is imported (xvoe/progress.py)

__version__ = "0.1.0"

# the public API: the names imported below, each from its home (a test keeps the three lists in step)
__all__ = ["DEFAULT_RECIPE", "DISPLAY_SIZE", "GenerateConfig", "PipelineConfig", "RECIPES", "SCENARIOS", "STAGES",
           "ScoreTable", "Scorer", "SplitDataset", "SurpriseModel", "TEST_SETTINGS", "Videos", "XvoeError",
           "animate_pair", "available_models", "check_same_split", "check_scored_by", "comparative", "custom",
           "describe", "disagreements", "display_video", "encode_split", "explain", "find_pair", "frame_rows",
           "generate", "holistic", "import_released", "latent_cache_for", "list_videos", "load_model", "merge",
           "merge_scores", "metric_rows", "model_identity", "nll_defaults_note", "nll_settings", "onset",
           "onset_pairs", "open_dataset", "plot_comparative", "plot_components", "plot_disagreements",
           "plot_explanation", "plot_holistic", "plot_onset", "plot_predictions", "plot_settings",
           "plot_surprise_curves", "plot_surprise_definitions", "read_scores", "recipe", "recipe_differences",
           "relative", "report", "run_pipeline", "save_figure", "save_gif", "save_video", "score", "score_header",
           "ship", "show", "show_video", "split_identity", "stage_settings", "train_perception", "train_phydnet",
           "train_proposal", "train_xpl", "true_objects", "verify", "with_display"]

if TYPE_CHECKING:
    from .apps.comparisons import plot_disagreements, plot_predictions, plot_settings
    from .apps.curves import animate_pair, plot_surprise_curves, plot_surprise_definitions
    from .apps.explanation_figure import plot_explanation
    from .apps.frames import frame_rows, save_figure, save_gif, show_video
    from .apps.metric_plots import plot_comparative, plot_components, plot_holistic, plot_onset
    from .apps.pipeline import PipelineConfig, run_pipeline
    from .apps.report import report
    from .apps.show_pair import save_video, show
    from .apps.verbs import explain, score, with_display
    from .apps.verify import verify
    from .apps.zoo import available_models, ship
    from .errors import XvoeError
    from .evaluation.disagreements import disagreements
    from .evaluation.metrics import comparative, holistic, metric_rows, relative
    from .evaluation.onset import onset, onset_pairs
    from .evaluation.score_headers import check_same_split, check_scored_by, model_identity, score_header
    from .evaluation.score_tables import ScoreTable, read_scores
    from .evaluation.scorer import Scorer, load_model
    from .evaluation.shards import merge_scores
    from .evaluation.user_models import SurpriseModel, Videos
    from .fingerprints import split_identity
    from .inference.score import nll_defaults_note, nll_settings
    from .scenes import custom  # make your own VoE event: xvoe.custom.make_pair(...)
    from .scenes.display import DISPLAY_SIZE, display_video
    from .scenes.generate import GenerateConfig, generate, merge
    from .scenes.released import import_released
    from .scenes.scenarios import SCENARIOS, TEST_SETTINGS
    from .scenes.store import open_dataset
    from .scenes.videos import describe, find_pair, list_videos, true_objects
    from .training.dataset import SplitDataset
    from .training.latents import encode_split
    from .training.perception import train_perception
    from .training.phydnet import train_phydnet
    from .training.proposal import train_proposal
    from .training.provenance import recipe_differences
    from .training.recipes import DEFAULT_RECIPE, RECIPES, recipe, stage_settings
    from .training.stages import STAGES
    from .training.xpl import latent_cache_for, train_xpl


def _home(name: str) -> ModuleType:
    """The module that defines the public `name`, imported now; each import is written out, for
    an editor and the import graph to follow as they follow the block above."""
    match name:
        case "plot_disagreements" | "plot_predictions" | "plot_settings":
            from .apps import comparisons as home
        case "animate_pair" | "plot_surprise_curves" | "plot_surprise_definitions":
            from .apps import curves as home
        case "plot_explanation":
            from .apps import explanation_figure as home
        case "frame_rows" | "save_figure" | "save_gif" | "show_video":
            from .apps import frames as home
        case "plot_comparative" | "plot_components" | "plot_holistic" | "plot_onset":
            from .apps import metric_plots as home
        case "PipelineConfig" | "run_pipeline":
            from .apps import pipeline as home
        case "report":
            from .apps import report as home
        case "save_video" | "show":
            from .apps import show_pair as home
        case "explain" | "score" | "with_display":
            from .apps import verbs as home
        case "verify":
            from .apps import verify as home
        case "available_models" | "ship":
            from .apps import zoo as home
        case "XvoeError":
            from . import errors as home
        case "disagreements":
            from .evaluation import disagreements as home
        case "comparative" | "holistic" | "metric_rows" | "relative":
            from .evaluation import metrics as home
        case "onset" | "onset_pairs":
            from .evaluation import onset as home
        case "check_same_split" | "check_scored_by" | "model_identity" | "score_header":
            from .evaluation import score_headers as home
        case "ScoreTable" | "read_scores":
            from .evaluation import score_tables as home
        case "Scorer" | "load_model":
            from .evaluation import scorer as home
        case "merge_scores":
            from .evaluation import shards as home
        case "SurpriseModel" | "Videos":
            from .evaluation import user_models as home
        case "split_identity":
            from . import fingerprints as home
        case "nll_defaults_note" | "nll_settings":
            from .inference import score as home
        case "DISPLAY_SIZE" | "display_video":
            from .scenes import display as home
        case "GenerateConfig" | "generate" | "merge":
            from .scenes import generate as home
        case "import_released":
            from .scenes import released as home
        case "SCENARIOS" | "TEST_SETTINGS":
            from .scenes import scenarios as home
        case "open_dataset":
            from .scenes import store as home
        case "describe" | "find_pair" | "list_videos" | "true_objects":
            from .scenes import videos as home
        case "SplitDataset":
            from .training import dataset as home
        case "encode_split":
            from .training import latents as home
        case "train_perception":
            from .training import perception as home
        case "train_phydnet":
            from .training import phydnet as home
        case "train_proposal":
            from .training import proposal as home
        case "recipe_differences":
            from .training import provenance as home
        case "DEFAULT_RECIPE" | "RECIPES" | "recipe" | "stage_settings":
            from .training import recipes as home
        case "STAGES":
            from .training import stages as home
        case "latent_cache_for" | "train_xpl":
            from .training import xpl as home
        case "custom":
            from . import scenes as home
            from .scenes import custom  # noqa: F401 - the submodule, an attribute of scenes once imported
        case _:
            raise AttributeError(f"module 'xvoe' has no attribute {name!r}")
    return home


def __getattr__(name: str) -> Any:
    with _interrupts_held():    # a Ctrl-C inside torch's extension modules' import aborts the process
        value = getattr(_home(name), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
