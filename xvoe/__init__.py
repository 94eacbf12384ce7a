"""xvoe: the X-VoE benchmark and the XPL intuitive-physics model in PyTorch and Pyro.

The public API, one import for notebooks, scripts and the command line alike:

    import xvoe
    xvoe.generate(xvoe.GenerateConfig(split="test", pairs=20, size=32, seed=7), "test.h5")
    scorer = xvoe.load_model("xpl")                       # a shipped name or a run directory
    xvoe.score(scorer, "test.h5", "xpl.csv")              # surprise="nll" for the Pyro model's
    xvoe.report(["xpl.csv"], "report")                    # the paper's metrics and figures
    xvoe.plot_explanation(xvoe.explain(scorer, "test.h5", 160))

The layers underneath (xvoe.scenes, models, training, evaluation, inference, xvoe.apps)
are importable too; this table names what a user needs. Names load on first use, so that
`import xvoe` and the benchmark layer stay free of torch.
"""
from __future__ import annotations

import importlib
from typing import Any

from .allocator import follow as _follow_allocator
from .processes import interrupts_held as _interrupts_held
from .progress import quiet_widget_warning as _quiet_widget_warning

_follow_allocator()     # a worker of a tuned process keeps its malloc settings; else glibc's stay (xvoe/allocator.py)
_quiet_widget_warning()     # before pyro is imported (xvoe/progress.py)

__version__ = "0.1.0"

_HOMES = {
    "xvoe.errors": ("XvoeError",),
    "xvoe.scenes.generate": ("GenerateConfig", "generate", "merge"),
    "xvoe.scenes.scenarios": ("SCENARIOS", "TEST_SETTINGS"),
    "xvoe.scenes.store": ("open_dataset",),
    "xvoe.scenes.released": ("import_released",),
    "xvoe.scenes.videos": ("describe", "find_pair", "list_videos", "true_objects"),
    "xvoe.scenes.display": ("DISPLAY_SIZE", "display_video"),
    "xvoe.training.recipes": ("DEFAULT_RECIPE", "RECIPES", "recipe", "stage_settings"),
    "xvoe.training.stages": ("STAGES",),
    "xvoe.training.provenance": ("recipe_differences",),
    "xvoe.training.perception": ("train_perception",),
    "xvoe.training.latents": ("encode_split",),
    "xvoe.training.xpl": ("train_xpl", "latent_cache_for"),
    "xvoe.training.proposal": ("train_proposal",),
    "xvoe.training.phydnet": ("train_phydnet",),
    "xvoe.training.dataset": ("SplitDataset",),
    "xvoe.evaluation.score": ("Scorer", "load_model", "SurpriseModel", "Videos", "merge_scores", "score_header",
                              "model_identity", "check_scored_by", "check_same_split"),
    "xvoe.fingerprints": ("split_identity",),
    "xvoe.evaluation.score_tables": ("ScoreTable", "read_scores"),
    "xvoe.evaluation.metrics": ("metric_rows", "comparative", "holistic", "relative"),
    "xvoe.evaluation.disagreements": ("disagreements",),
    "xvoe.evaluation.onset": ("onset", "onset_pairs"),
    "xvoe.apps.verbs": ("score", "explain", "with_display"),
    "xvoe.inference.score": ("nll_settings", "nll_defaults_note"),
    "xvoe.apps.report": ("report",),
    "xvoe.apps.verify": ("verify",),
    "xvoe.apps.zoo": ("available_models", "ship"),
    "xvoe.apps.pipeline": ("PipelineConfig", "run_pipeline"),
    "xvoe.apps.frames": ("show_video", "save_gif", "save_figure", "frame_rows"),
    "xvoe.apps.show_pair": ("show", "save_video"),
    "xvoe.apps.explanation_figure": ("plot_explanation",),
    "xvoe.apps.metric_plots": ("plot_comparative", "plot_components", "plot_holistic", "plot_onset"),
    "xvoe.apps.comparisons": ("plot_disagreements", "plot_settings", "plot_predictions"),
    "xvoe.apps.curves": ("plot_surprise_curves", "plot_surprise_definitions", "animate_pair"),
}
_MODULES = {"custom": "xvoe.scenes.custom"}     # make your own VoE event: xvoe.custom.make_pair(...)
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}
__all__ = sorted([*_HOME_OF, *_MODULES])


def __getattr__(name: str) -> Any:
    if name not in _MODULES and name not in _HOME_OF:
        raise AttributeError(f"module 'xvoe' has no attribute {name!r}")
    with _interrupts_held():    # a Ctrl-C inside torch's extension modules' import aborts the process
        module = importlib.import_module(_MODULES.get(name) or _HOME_OF[name])
    value = module if name in _MODULES else getattr(module, name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
