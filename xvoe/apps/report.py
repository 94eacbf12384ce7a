"""What `xvoe metrics` writes: the metrics table (CSV, JSON) and its figures for one or more
models' scores files, and, for scores holding both surprise definitions, where they differ."""
from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np

from ..errors import XvoeError
from ..evaluation.disagreements import (
    SURPRISES,
    VERDICTS,
    disagreement_fields,
    disagreements,
    has_both_surprises,
    side_by_side,
)
from ..evaluation.metrics import metric_rows, relative_members
from ..evaluation.onset import ONSET_FIELDS, onset, onset_pairs
from ..evaluation.score_curves import read_curves
from ..evaluation.score_headers import check_same_split, score_header, scored_split, warn_unchecked
from ..evaluation.score_tables import model_name, read_scores
from ..fingerprints import describe_split, split_identity
from ..outputs import (
    claim_directory,
    claim_scope,
    remove_stale_temporaries,
    replace_together,
    temporary_name,
    writing,
)
from ..scenes import store
from .comparisons import plot_disagreements
from .frames import save_figure
from .metric_plots import plot_comparative, plot_components, plot_holistic, plot_onset
from .table import STYLES, paper_table

__all__ = ["report", "header_lines"]

# what a report writes, so that a rerun into the same directory leaves nothing of the last one
_REPORT_FILES = ("metrics.csv", "metrics.json", "headers.json", "holistic.png", "comparative.png", "components-*.png",
                "disagreements-*.png", "surprise-*.csv", "disagreements-*.csv", "verdicts-*.csv", "onset.csv",
                "onset.png", *STYLES.values())


@claim_scope()
def report(paths: list[str | Path], out_dir: str | Path, rounds: int = 1000, seed: int = 0,
           data: str | Path | None = None, overwrite: bool = False, table: str | None = None) -> list[Path]:
    """What `xvoe metrics` does: the table (CSV and JSON) and the figures, for one or more
    models' scores files. A scores file holding both surprise definitions (`xvoe score
    --surprise both`) also gets them side by side (surprise-MODEL.csv) and the pairs they
    judge differently (disagreements-MODEL.csv); one whose default verdict and paper's score
    differ gets the same for those two (verdicts-MODEL.csv, verdicts-disagreements-MODEL.csv);
    with `data`, the test split the scores
    came from, a figure of a few of those pairs too, and for every model whose per-frame
    curves lie beside its scores, the violation onset (onset.csv, onset.png) of each definition
    they hold: the MSE's, and the NLL's where it was scored. Scores of another split than `data`,
    or than each other, are refused; headers.json repeats every scores file's header
    (`score_header`). With `table` ("md" or "latex"), table.md or table.tex holds the paper's
    layout of every model's metrics, in percent (xvoe/apps/table.py)."""
    if table is not None and table not in STYLES:
        raise XvoeError(f"table must be one of {', '.join(STYLES)}, not {table!r}")
    _check_one_split(paths, data)
    rows = []
    names = []
    compared, verdicts, members = {}, {}, {}
    timing, timed_pairs = [], {}
    events = _event_frames(data) if data is not None else None
    for path in paths:
        scores = read_scores(path, data)
        warn_unchecked(path)
        name = model_name(path, scores)
        if name in names:
            raise XvoeError(f"two scores files name the model {name!r}; give each model its own name")
        names.append(name)
        rows += metric_rows(scores, name, rounds=rounds, seed=seed)
        if table is not None:
            members[name] = relative_members(scores)
        if has_both_surprises(scores):
            compared[name] = scores
        if has_both_surprises(scores, VERDICTS):
            verdicts[name] = scores
        if events is not None:
            event = events[scores["index"].astype(int)]
            definitions = _per_frame(Path(path), len(scores["index"]))
            for surprise, per_frame in definitions.items():
                timing += onset(scores, per_frame, event, name, rounds=rounds, seed=seed, surprise=surprise)
                series = name if len(definitions) == 1 else f"{name} {surprise}"
                timed_pairs[series] = onset_pairs(scores, per_frame, event)
    if not rows:
        raise XvoeError("the scores hold no test pairs to measure")
    out_dir = claim_directory(out_dir, whole=True)
    earlier = [p for pattern in _REPORT_FILES for p in out_dir.glob(pattern)]
    if earlier and not overwrite:
        raise XvoeError(f"{out_dir} holds a report already ({earlier[0].name}); pass --overwrite to replace it")
    # written whole in a folder of this run's first, then put in place together: a full disk
    # or an interruption leaves the last report or none, never part of a new one
    staging = temporary_name(out_dir / "report")
    remove_stale_temporaries(out_dir / "report")
    staging.mkdir()
    try:
        with writing(out_dir):
            written = _write_report(staging, paths, rows, names, compared, verdicts, timing, timed_pairs, data,
                                    members, table)
            placed = [out_dir / path.name for path in written]
            replace_together(written, placed)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    for path in set(earlier) - set(placed):
        path.unlink()
    return placed


def _write_report(out_dir: Path, paths: list[str | Path], rows: list[dict], names: list[str], compared: dict,
                  verdicts: dict, timing: list[dict], timed_pairs: dict, data: str | Path | None,
                  members: dict, table: str | None) -> list[Path]:
    """Every file of the report, written into `out_dir`."""
    written = list(_write_table(rows, out_dir))
    written.append(_write_headers(paths, names, out_dir / "headers.json"))
    if table is not None:
        written.append(out_dir / STYLES[table])
        written[-1].write_text(paper_table(rows, members, table))
    drawn = {"holistic.png": plot_holistic(rows), "comparative.png": plot_comparative(rows)}
    for name in names:
        if any(r["model"] == name and r["column"] != "score" for r in rows):
            drawn[f"components-{name}.png"] = plot_components(rows, name)
    if timing:
        written.append(_write_csv(timing, out_dir / "onset.csv", ONSET_FIELDS))
        drawn["onset.png"] = plot_onset(timed_pairs)
    for name, scores in compared.items():
        differ = disagreements(scores)
        written += _write_comparison(scores, rows, name, SURPRISES, out_dir, "surprise", "disagreements")
        if data is not None and differ:
            drawn[f"disagreements-{name}.png"] = _disagreement_figure(data, scores, differ)
    for name, scores in verdicts.items():
        written += _write_comparison(scores, rows, name, VERDICTS, out_dir, "verdicts", "verdicts-disagreements")
    for filename, figure in drawn.items():
        written.append(save_figure(figure, out_dir / filename, dpi=90))
    return written


def _check_one_split(paths: list[str | Path], data: str | Path | None) -> None:
    """Refuse, before any work, scores whose curves were written with other scores (`score_header`),
    and scores made on another split than `data` (with `data`) or than the first scores file that
    records its split."""
    for path in paths:
        if Path(path).with_suffix(".curves.npz").is_file():
            score_header(path)
    if data is not None:
        with store.open_dataset(data, split="test") as file:
            identity = split_identity(file)
        for path in paths:
            check_same_split(path, identity, data)
        return
    first = None
    for path in paths:
        found = scored_split(path)
        if found is None:
            continue
        if first is not None and found != first[1]:
            raise XvoeError(f"{path} and {first[0]} were scored on different splits ({describe_split(found)}; "
                            f"{describe_split(first[1])}); score both on one split")
        first = first or (path, found)


def _write_headers(paths: list[str | Path], names: list[str], out: Path) -> Path:
    """headers.json: for each model, its scores file (an absolute path, for `xvoe verify`) and
    what the file says it was made with ({} for a file that records nothing)."""
    headers = [{"model": name, "scores": str(Path(path).resolve()),
                "header": score_header(path) if Path(path).with_suffix(".curves.npz").is_file() else {}}
               for name, path in zip(names, paths)]
    out.write_text(json.dumps(headers, indent=1, sort_keys=True))
    return out


def header_lines(header: dict) -> list[str]:
    """A score file's header in a few lines of Markdown, for a report page."""
    if not header:
        return ["- records nothing of how it was made (scored elsewhere, or by an older xvoe)"]
    model = header.get("model_identity", {})
    made_by = ", ".join(f"{key} {value}" for key, value in sorted(model.items()) if key != "source")
    lines = [f"- xvoe {header.get('xvoe')}; model {header.get('model')} ({made_by or 'no identity recorded'})"]
    if "split" in header:
        lines.append(f"- split: {describe_split(header['split'])}")
    lines.append(f"- surprise: {json.dumps(header.get('surprise', {}), sort_keys=True)}; score column "
                 f"`{header.get('score')}`, {header.get('aggregate')} over frames")
    if "nll" in header:
        lines.append(f"- NLL settings (seed {header.get('nll_seed')}): {json.dumps(header['nll'], sort_keys=True)}")
        sources = header.get("nll_source", {})
        for source in sorted(set(sources.values())):
            lines.append(f"  - from the {source}: {', '.join(sorted(k for k, v in sources.items() if v == source))}")
    return lines


def _write_comparison(scores: dict[str, np.ndarray], rows: list[dict], name: str, columns: tuple[str, str],
                     out_dir: Path, side: str, differ: str) -> list[Path]:
    """Two score columns of one model side by side (SIDE-NAME.csv) and the pairs they judge
    differently (DIFFER-NAME.csv)."""
    return [_write_csv(side_by_side(scores, rows, name, columns), out_dir / f"{side}-{name}.csv"),
            _write_csv(disagreements(scores, columns), out_dir / f"{differ}-{name}.csv", disagreement_fields(columns))]


def _write_table(rows: list[dict], out_dir: str | Path) -> tuple[Path, Path]:
    """metrics.csv and metrics.json in out_dir."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    csv_path, json_path = out_dir / "metrics.csv", out_dir / "metrics.json"
    _write_csv(rows, csv_path)
    json_path.write_text(json.dumps(rows, indent=1))
    return csv_path, json_path


def _write_csv(rows: list[dict], path: Path, fields: tuple[str, ...] | None = None) -> Path:
    """Rows of dicts as a CSV (a header alone when there are none, from `fields`)."""
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, list(fields or rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def _disagreement_figure(data: str | Path, scores: dict[str, np.ndarray], differ: list[dict]):
    """The example figure of disagreeing pairs, from the test split the scores came from (its
    labels were checked against the scores when they were read)."""
    with store.open_dataset(data) as file:
        return plot_disagreements(file, differ)


def _event_frames(data: str | Path) -> np.ndarray:
    with store.open_dataset(data, split="test") as file:
        return file["event_frame"][:]


def _per_frame(path: Path, rows: int) -> dict[str, np.ndarray]:
    """The per-frame surprise saved beside a scores file, row by row (`read_curves`), by
    definition: "mse" (s_img + s_dyn, or a model's own curve) and, where the NLL was scored,
    "nll"; none without a curves file."""
    curves = path.with_suffix(".curves.npz")
    if not curves.is_file():
        return {}
    saved = read_curves(curves, rows, path)
    return {"mse": saved.total} | ({"nll": saved.arrays["nll"]} if "nll" in saved.arrays else {})
