"""Do the NLL explanation figures draw what the score file says? xvoe.apps.rows, printed.

    xvoe generate --split test --pairs 20 --size 32 --seed 2026 --out fresh20.h5
    xvoe score --model xpl --data fresh20.h5 --surprise nll --out nll20.csv
    python benchmarks/explanation_rows.py --data fresh20.h5 --scores nll20.csv [--model xpl]

Every scored video's figure, drawn as `xvoe explain --surprise nll` draws it with the file's NLL
settings and seed: how many figures, how many drew the "hidden object" and the "two objects"
rows, how many the file's p_hidden and p_two put above DRAW_THRESHOLD, and how many figures
disagree with the file (a row drawn at p <= DRAW_THRESHOLD, or left out above it; goal 0).
Last line: figures=N hidden_object=N two_objects=N disagree=N
"""
from __future__ import annotations

import argparse
import time

from xvoe.apps.rows import ROW_COLUMNS, explanation_rows
from xvoe.errors import XvoeError
from xvoe.evaluation.explain import DRAW_THRESHOLD
from xvoe.training.stages import XPL


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, help="the scored test split")
    parser.add_argument("--scores", required=True, help="its score file, of --surprise nll or both")
    parser.add_argument("--model", default=XPL, help=f"the model that scored it (default {XPL})")
    args = parser.parse_args()
    start = time.perf_counter()
    try:
        found = explanation_rows(args.model, args.data, args.scores, progress=True)
    except XvoeError as error:
        raise SystemExit(f"explanation_rows.py: error: {error}") from None
    print(f"{len(found)} figures in {time.perf_counter() - start:.0f} s; a row is drawn where its p > {DRAW_THRESHOLD}")
    for kind, column in ROW_COLUMNS.items():
        drawn = sum(rows.drawn[kind] for rows in found)
        above = sum(rows.probability[kind] > DRAW_THRESHOLD for rows in found)
        print(f'"{kind}": drawn in {drawn} figures; {column} > {DRAW_THRESHOLD} in {above} rows of the file')
    disagree = [rows for rows in found if rows.disagree]
    for rows in disagree[:10]:
        print(f"  video {rows.index}: {', '.join(rows.disagree)} against p = {rows.probability}")
    counts = {kind.replace(" ", "_"): sum(rows.drawn[kind] for rows in found) for kind in ROW_COLUMNS}
    print(f"figures={len(found)} " + " ".join(f"{name}={count}" for name, count in counts.items())
          + f" disagree={len(disagree)}")


if __name__ == "__main__":
    main()
