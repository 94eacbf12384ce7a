"""The paper's metric figures: comparative and holistic accuracy against the ideal, with
their intervals and counts, the score's components, and when a violation's surprise peaks.
"""
from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from ..errors import XvoeError
from ..scenes.scenarios import SCENARIOS

__all__ = ["COLUMN_COLORS", "IDEAL_COLOR", "HOLISTIC_N", "plot_holistic", "plot_comparative", "plot_components",
           "plot_onset"]


# One colour per score column in every chart, so that a colour means one quantity throughout:
# a series named after a column ("nll", or "nll (NLL)") takes its colour, any other the next
# colour no column holds.
COLUMN_COLORS = {"score": "tab:blue", "paper_score": "tab:orange", "excess": "tab:red", "nll": "tab:purple",
                 "nll_excess": "tab:brown", "s_img": "tab:olive", "s_dyn": "tab:cyan"}
_FREE_COLORS = ("tab:green", "tab:gray", "gold", "navy", "lime", "teal")
IDEAL_COLOR = "magenta"     # the ideal's dashed line: no bar, cap or interval is drawn in it


def _select(rows: list[dict], metric: str, column: str) -> list[dict]:
    return [r for r in rows if r["metric"] == metric and r["column"] == column]


def _models(rows: list[dict]) -> list[str]:
    return list(dict.fromkeys(r["model"] for r in rows))


def _series_colors(names: list[str]) -> list[str]:
    """The colour of each series: its column's (COLUMN_COLORS), else the next free one."""
    free = iter(_FREE_COLORS * (1 + len(names) // len(_FREE_COLORS)))
    return [COLUMN_COLORS.get(name.split(" (")[0]) or next(free) for name in names]


def _bars(ax, groups: list[str], models: list[str], lookup, width: float = 0.8,
          names: list[str] | None = None) -> None:
    """Grouped bars with 95% intervals: lookup(model, group) -> row or None. Each bar's value is
    also marked by a dash in its colour, so that a bar of height 0 is seen; each group's tick
    (its `names`, default the groups) says how many units (pairs, or videos) its bars rest on."""
    step = width / max(1, len(models))
    counts: dict[int, set[int]] = {}
    for m, (model, colour) in enumerate(zip(models, _series_colors(models))):
        xs, values, errors = [], [], [[], []]
        for g, group in enumerate(groups):
            row = lookup(model, group)
            if row is None:
                continue
            xs.append(g - width / 2 + step * (m + 0.5))
            values.append(100 * row["value"])
            # a percentile interval of a statistic full of ties may stop short of the value itself
            errors[0].append(max(0.0, 100 * (row["value"] - row["low"])))
            errors[1].append(max(0.0, 100 * (row["high"] - row["value"])))
            if row.get("count"):
                counts.setdefault(g, set()).add(int(row["count"]))
        ax.bar(xs, values, step * 0.95, yerr=errors, capsize=2, label=model, color=colour)
        ax.scatter(xs, values, marker="_", s=(72 * step * 0.9) ** 2 / 4, linewidths=2, zorder=3, color=colour)
    names = groups if names is None else names
    ax.set_xticks(range(len(groups)), [f"{name}\n(n={'/'.join(map(str, sorted(counts[g])))})" if g in counts
                                       else name for g, name in enumerate(names)])


def _ideal_lines(ax, ideals: list[float], width: float = 0.8) -> None:
    """Each group's ideal (a share) as a dashed line across the whole group, in a colour no bar
    or interval has: short black dashes would read as the intervals' caps."""
    groups = np.arange(len(ideals))
    ax.hlines(100 * np.asarray(ideals), groups - width / 2 - 0.05, groups + width / 2 + 0.05, colors=IDEAL_COLOR,
              linestyles="--", linewidth=1.8, zorder=4, label="ideal")


def _title_column(column: str) -> str:
    """The column in a chart's title: none for `score`, which a legend of variants renames."""
    return "" if column == "score" else f" ({column})"


HOLISTIC_N = "n: pair indices, each pooling the settings named under its scenario"


def _pooled(scenario: str) -> str:
    """A holistic group's label: the scenario and the settings it pools (permanence has no S3)."""
    settings = SCENARIOS[scenario].SETTINGS if scenario in SCENARIOS else ()
    return f"{scenario}\n{settings[0]}-{settings[-1]}" if settings else scenario


def _legend_outside(ax, **kwargs) -> None:
    """The legend right of the axes, where no bar or interval can be under it."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1), borderaxespad=0, **kwargs)


def plot_holistic(rows: list[dict], column: str = "score") -> plt.Figure:
    """Fig. 5a: holistic accuracy (AUC) per scenario, models side by side, ideal and chance."""
    chosen = _select(rows, "holistic", column)
    scenarios = list(dict.fromkeys(r["scenario"] for r in chosen))
    index = {(r["model"], r["scenario"]): r for r in chosen}
    fig, ax = plt.subplots(figsize=(1.6 + 1.3 * len(scenarios), 3.2))
    _bars(ax, scenarios, _models(chosen), lambda m, s: index.get((m, s)), names=[_pooled(s) for s in scenarios])
    ax.axhline(100, color=IDEAL_COLOR, linestyle="--", linewidth=1.8, label="ideal")
    ax.axhline(50, color="grey", linestyle=":", linewidth=1, label="chance")
    ax.set_ylim(-4, 105)      # below 0: a bar at 0 shows its dash
    ax.set_ylabel("holistic accuracy (%)")
    ax.set_title(f"Holistic metric{_title_column(column)}, 95% intervals;\n{HOLISTIC_N}", fontsize=9)
    _legend_outside(ax)
    fig.tight_layout()
    return fig


def plot_comparative(rows: list[dict], column: str = "score") -> plt.Figure:
    """Fig. 6: comparative accuracy per setting against the ideal (100/50/100), and below it
    the distance from the ideal, either side alike (`_off_ideal`)."""
    chosen = _select(rows, "comparative", column)
    settings = list(dict.fromkeys(f"{r['scenario']} {r['setting']}" for r in chosen))
    index = {(r["model"], f"{r['scenario']} {r['setting']}"): r for r in chosen}
    ideal = {f"{r['scenario']} {r['setting']}": r["ideal"] for r in chosen}
    models = _models(chosen)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(1.5 + 0.75 * len(settings), 5.2), sharex=True,
                                      gridspec_kw={"height_ratios": [2, 1]})
    _bars(top, settings, models, lambda m, s: index.get((m, s)))
    _ideal_lines(top, [ideal[s] for s in settings])
    top.set_ylim(-4, 105)
    top.set_ylabel("comparative accuracy (%)")
    top.set_title(f"Comparative metric{_title_column(column)}, 95% Wilson intervals; n: pairs", fontsize=9)
    _legend_outside(top)

    _bars(bottom, settings, models, lambda m, s: _off_ideal(index.get((m, s))))
    bottom.axhline(0, color=IDEAL_COLOR, linestyle="--", linewidth=1.8)
    bottom.set_ylim(top=4)
    bottom.set_ylabel("off the ideal\n(points)")
    bottom.set_title("how far from the ideal, above or below alike (0: ideal)", fontsize=8)
    bottom.tick_params(axis="x", labelrotation=45, labelsize=8)
    fig.tight_layout()
    return fig


def _off_ideal(row: dict | None) -> dict | None:
    """A metric row as its distance from the ideal, negated: in S2, whose ideal is 50%, 100% is
    as far off as 0%, and a bar above the line would read as better than ideal. The interval is
    the distances its ends and the ideal span (0 where it holds the ideal)."""
    if row is None:
        return None
    ends = [row["low"] - row["ideal"], row["high"] - row["ideal"]]
    nearest = 0.0 if ends[0] <= 0 <= ends[1] else min(map(abs, ends))
    return {**row, "value": -abs(row["value"] - row["ideal"]), "low": -max(map(abs, ends)), "high": -nearest}


def plot_components(rows: list[dict], model: str, metric: str = "comparative") -> plt.Figure:
    """Fig. 5c: the metric of the whole score against s_img alone and s_dyn alone."""
    chosen = [r for r in rows if r["model"] == model and r["metric"] == metric]
    key = (lambda r: r["scenario"]) if metric == "holistic" else (lambda r: f"{r['scenario']} {r['setting']}")
    groups = list(dict.fromkeys(key(r) for r in chosen))
    index = {(r["column"], key(r)): r for r in chosen}
    columns = list(dict.fromkeys(r["column"] for r in chosen))
    fig, ax = plt.subplots(figsize=(1.5 + 0.75 * len(groups), 3.2))
    _bars(ax, groups, columns, lambda c, g: index.get((c, g)),
          names=[_pooled(g) for g in groups] if metric == "holistic" else None)
    ideals = {key(r): r["ideal"] for r in chosen}
    _ideal_lines(ax, [ideals[g] for g in groups])
    ax.set_ylim(-4, 105)
    ax.set_ylabel(f"{metric} accuracy (%)")
    n = HOLISTIC_N if metric == "holistic" else "n: pairs"
    ax.set_title(f"Score components: {model}, 95% intervals; {n}", fontsize=9)
    ax.tick_params(axis="x", labelrotation=45, labelsize=8)
    _legend_outside(ax)
    fig.tight_layout()
    return fig


def plot_onset(pairs: dict[str, list[dict]]) -> plt.Figure:
    """Violation onset: for each scenario, how many S1/S3 pairs' surprise difference peaks how
    many frames after the event (0: at the event frame; negative: before it), one series per
    model (`xvoe.evaluation.onset.onset_pairs`)."""
    scenarios = list(dict.fromkeys(p["scenario"] for found in pairs.values() for p in found))
    if not scenarios:
        raise XvoeError("no S1 or S3 pair with an event frame to time")
    offsets = [p["peak_offset"] for found in pairs.values() for p in found]
    edges = np.arange(min(offsets) - 0.5, max(offsets) + 1.5)
    fig, axes = plt.subplots(1, len(scenarios), figsize=(3.2 * len(scenarios), 2.8), sharey=True, squeeze=False)
    for ax, scenario in zip(axes[0], scenarios):
        for model, found in pairs.items():
            ax.hist([p["peak_offset"] for p in found if p["scenario"] == scenario], bins=edges, alpha=0.6,
                    label=model)
        ax.axvline(0, color="red", linewidth=1)
        ax.set_title(scenario, fontsize=9)
        ax.set_xlabel("frames from event to peak", fontsize=8)
    axes[0][0].set_ylabel("S1/S3 pairs", fontsize=8)
    _legend_outside(axes[0][-1])
    fig.tight_layout()
    return fig
