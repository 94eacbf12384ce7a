"""Whether the NLL explanation figures draw what the score file says. A figure of `xvoe explain
--surprise nll` draws its "hidden object" row only where p(hidden object) exceeds DRAW_THRESHOLD
and its "two objects" row only where p(two identical objects) does; the explanation is the
score's own posterior (the same latents, NLL settings and seed: the same numbers to the bit), so
each figure's drawn rows can be read against the file's p_hidden and p_two.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import matplotlib.pyplot as plt

from ..errors import XvoeError
from ..evaluation.explain import DRAW_THRESHOLD
from ..evaluation.score_headers import check_same_split, check_scored_by, score_header, scored_nll
from ..evaluation.score_tables import read_scores
from ..evaluation.scorer import Scorer, as_scorer, encode_chunk
from ..fingerprints import split_identity
from ..progress import progress_bar
from ..scenes import store
from ..scenes.display import DISPLAY_SIZE
from .explanation_figure import plot_explanation
from .verbs import explain

__all__ = ["ROW_COLUMNS", "DrawnRows", "read_rows", "nll_scorer", "explanation_rows"]

# a figure's row kind -> the score file's column whose probability decides whether it is drawn
ROW_COLUMNS = {"hidden object": "p_hidden", "two objects": "p_two"}


@dataclass
class DrawnRows:
    """One video's NLL figure against its row of the score file."""

    index: int
    probability: dict[str, float]   # row kind -> the score file's probability of it
    drawn: dict[str, bool]          # row kind -> whether the figure drew the row

    @property
    def disagree(self) -> list[str]:
        """The row kinds drawn where the file's probability is at most DRAW_THRESHOLD, or left
        out where it exceeds it."""
        return [kind for kind, p in self.probability.items() if self.drawn[kind] != (p > DRAW_THRESHOLD)]


def read_rows(figure: plt.Figure, index: int, scores: dict) -> DrawnRows:
    """The rows of ROW_COLUMNS that `figure` (of `plot_explanation`) drew, with the probabilities
    the score file's columns (`read_scores`) give video `index`."""
    row = list(scores["index"]).index(index)
    drawn = {kind for kind, _ in figure.drawn_rows}
    return DrawnRows(index, {kind: float(scores[column][row]) for kind, column in ROW_COLUMNS.items()},
                     {kind: kind in drawn for kind in ROW_COLUMNS})


def nll_scorer(model: str | Scorer, data: str | Path, scores: str | Path) -> tuple[Scorer, int]:
    """The model with the NLL settings a score file of it was made with, and its NLL seed: what
    explains each of its videos as the score did. Refused in one line: a file without the NLL's
    columns, of another model or of another split."""
    header = score_header(scores)
    if "nll" not in header:
        raise XvoeError(f"{scores} has no NLL columns; score it with --surprise nll (or both)")
    scorer = as_scorer(model)
    check_scored_by(scores, scorer, header)
    with store.open_dataset(data) as file:
        check_same_split(scores, split_identity(file), data, header)
    return replace(scorer, nll=scored_nll(scores, header)), int(header["nll_seed"])


def explanation_rows(model: str | Scorer, data: str | Path, scores: str | Path, indices: list[int] | None = None,
                     display_size: int | None = DISPLAY_SIZE, progress: bool = False) -> list[DrawnRows]:
    """Every scored video's NLL explanation figure (`indices`: those videos alone), drawn as
    `xvoe explain --surprise nll` draws it with the score file's settings and seed, read against
    the file's p_hidden and p_two (`DrawnRows.disagree`: where a row is drawn that should not be,
    or left out)."""
    scorer, seed = nll_scorer(model, data, scores)
    table = read_scores(scores)
    chosen = [int(i) for i in table["index"]] if indices is None else indices
    found, chunk = [], None
    with store.open_dataset(data) as file:
        for index in progress_bar(chosen, desc="explain", unit="video", disable=not progress):
            if chunk is None or not chunk.holds(index):     # each chunk of the latent cache encoded once
                chunk = encode_chunk(scorer, file, index)
            figure = plot_explanation(explain(scorer, data, index, surprise="nll", seed=seed,
                                              display_size=display_size, chunk=chunk))
            found.append(read_rows(figure, index, table))
            plt.close(figure)
    return found
