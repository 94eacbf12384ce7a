"""Progress bars: plain text on stdout in a notebook without ipywidgets (no warning, no red
stderr blocks), on stderr elsewhere; counted in videos."""
import io
import re
import sys
import types
import warnings

import tqdm

from xvoe import progress


def kernel_without_widgets(monkeypatch) -> None:
    shell = types.SimpleNamespace(kernel=object())
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    real = progress.importlib.util.find_spec
    monkeypatch.setattr(progress.importlib.util, "find_spec", lambda name: None if name == "ipywidgets" else real(name))


def test_a_notebook_without_widgets_gets_the_text_bar_on_stdout(monkeypatch):
    kernel_without_widgets(monkeypatch)
    out = io.StringIO()
    monkeypatch.setattr(sys, "stdout", out)
    with warnings.catch_warnings():
        warnings.simplefilter("error")      # no TqdmWarning
        with progress.progress_bar(total=88, unit="video", desc="score") as bar:
            bar.update(80)
            bar.update(8)
    counts = re.findall(r"(\d+)/(\d+) \[", out.getvalue())        # "N/TOTAL [": the rate may hold any digits
    assert ("88", "88") in counts and {total for _, total in counts} == {"88"}


def test_outside_a_notebook_the_bar_is_on_stderr(monkeypatch):
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: None))
    err = io.StringIO()
    monkeypatch.setattr(sys, "stderr", err)
    monkeypatch.setattr(sys, "stdout", io.StringIO())
    for _ in progress.progress_bar(range(3), desc="encode"):
        pass
    assert "3/3" in err.getvalue() and not sys.stdout.getvalue()


def test_the_widget_warning_a_pyro_import_raises_is_silenced_and_no_other():
    """`import xvoe` calls quiet_widget_warning, before anything imports pyro."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        progress.quiet_widget_warning()
        warnings.warn("IProgress not found. Please update jupyter and ipywidgets.", tqdm.TqdmWarning, stacklevel=1)
        warnings.warn("another tqdm warning", tqdm.TqdmWarning, stacklevel=1)
    assert [str(w.message) for w in caught] == ["another tqdm warning"]
