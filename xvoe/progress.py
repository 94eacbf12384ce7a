"""One progress bar for every long loop: text on stderr in a terminal, and in a notebook a
widget where ipywidgets is installed, else the text bar on stdout.

tqdm.auto in a notebook without ipywidgets warns (`TqdmWarning: IProgress not found`) and
draws a new text block on stderr at every update: red boxes in the saved notebook. Here a
notebook without the widget gets the plain bar on stdout, redrawn in place.
"""
from __future__ import annotations

import importlib.util
import sys
import warnings

from tqdm import TqdmWarning
from tqdm import tqdm as _text_bar

__all__ = ["quiet_widget_warning", "progress_bar"]


def quiet_widget_warning() -> None:
    """Silence tqdm's warning that a notebook lacks ipywidgets, which `import pyro` raises (its
    MCMC logger imports tqdm.auto) though xvoe draws no widget there: a red box about nothing."""
    warnings.filterwarnings("ignore", message="IProgress not found", category=TqdmWarning)


def _in_notebook() -> bool:
    """True inside a Jupyter kernel (IPython with a kernel attached), not in IPython's terminal."""
    shell = sys.modules.get("IPython")
    get = getattr(shell, "get_ipython", None)
    return get is not None and getattr(get(), "kernel", None) is not None


def progress_bar(iterable=None, **kwargs) -> _text_bar:
    """tqdm(iterable, **kwargs), drawn as the place it runs in allows (module docstring)."""
    if _in_notebook():
        if importlib.util.find_spec("ipywidgets") is not None:
            from tqdm.notebook import tqdm as widget_bar
            return widget_bar(iterable, **kwargs)
        kwargs.setdefault("file", sys.stdout)
    return _text_bar(iterable, **kwargs)
