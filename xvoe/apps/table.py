"""`xvoe metrics --table md|latex`: the metrics in the paper's layout, ready to paste.

Scenarios across, metric and setting down, in percent, one row per model in each: holistic,
comparative per setting, and relative per setting with the reference's sub-rows (S2-ext1 and
S2-ext2 under S2, S3-ext and S3-sur under S3; their mean is the setting's row). Every value is
of the `score` column; the intervals stay in metrics.csv.
"""
from __future__ import annotations

import math

from ..errors import XvoeError
from ..evaluation.metrics import OFFICIAL_RELATIVE, Estimate
from ..scenes.scenarios import SCENARIOS

__all__ = ["STYLES", "paper_table"]

STYLES = {"md": "table.md", "latex": "table.tex"}     # each style and the file it is written to
_SETTING_NAMES = {"S1": "S1 predictive", "S2": "S2 hypothetical", "S3": "S3 explicative"}
# (metric, setting or sub-row) in the table's order; a sub-row reads the members' estimates
_LAYOUT = (("holistic", ""), ("comparative", "S1"), ("comparative", "S2"), ("comparative", "S3"),
          ("relative", "S1"), ("relative", "S2"), ("relative", "S2-ext1"), ("relative", "S2-ext2"),
          ("relative", "S3"), ("relative", "S3-ext"), ("relative", "S3-sur"))
_SUB_ROWS = frozenset(OFFICIAL_RELATIVE.values())


def paper_table(rows: list[dict], members: dict[str, dict[tuple[str, str], Estimate]], style: str,
                column: str = "score") -> str:
    """The table of `rows` (metric_rows of one or more models) and `members` (each model's
    relative_members), as Markdown or a LaTeX tabular (booktabs)."""
    if style not in STYLES:
        raise XvoeError(f"--table must be one of {', '.join(STYLES)}, not {style!r}")
    values = {(r["model"], r["metric"], r["scenario"], r["setting"]): r["value"] for r in rows if r["column"] == column}
    for model, found in members.items():
        values |= {(model, "relative", scenario, name): e.value for (scenario, name), e in found.items()}
    models = list(dict.fromkeys(r["model"] for r in rows))
    present = {r["scenario"] for r in rows}
    scenarios = [s for s in (*SCENARIOS, "custom") if s in present]
    body, named = [], None
    for metric, setting in _LAYOUT:
        cells = [[values.get((model, metric, scenario, setting)) for scenario in scenarios] for model in models]
        if all(v is None for row in cells for v in row):
            continue
        for place, (model, row) in enumerate(zip(models, cells)):
            body.append((metric.capitalize() if metric != named else "", _setting(setting, style) if place == 0 else "",
                         model, [_percent(v, style) for v in row]))
            named = metric
    header = ["Metric", "Setting", "Model", *(s.capitalize() for s in scenarios)]
    return _markdown(header, body) if style == "md" else _latex(header, body)


def _setting(setting: str, style: str) -> str:
    if setting in _SUB_ROWS:
        return f"\\quad {setting}" if style == "latex" else setting
    return _SETTING_NAMES.get(setting, setting)


def _percent(value: float | None, style: str) -> str:
    if value is None or math.isnan(value):
        return "--" if style == "latex" else "–"
    return f"{100.0 * value:.1f}"


def _markdown(header: list[str], body: list[tuple]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * 3 + "---:|" * (len(header) - 3)]
    for metric, setting, model, cells in body:
        lines.append("| " + " | ".join([metric, setting, model, *cells]) + " |")
    return "\n".join(lines) + "\n"


def _latex(header: list[str], body: list[tuple]) -> str:
    lines = [f"\\begin{{tabular}}{{lll{'r' * (len(header) - 3)}}}", "\\toprule", " & ".join(header) + " \\\\",
             "\\midrule"]
    for index, (metric, setting, model, cells) in enumerate(body):
        if metric and index:
            lines.append("\\midrule")
        lines.append(" & ".join([metric, setting, _escape(model), *cells]) + " \\\\")
    lines += ["\\bottomrule", "\\end{tabular}"]
    return "\n".join(lines) + "\n"


def _escape(text: str) -> str:
    """A model name as LaTeX text (names hold letters, digits, `_`, `-` and `.`)."""
    for char in "&%$#_{}":
        text = text.replace(char, "\\" + char)
    return text
