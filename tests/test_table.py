"""`xvoe metrics --table md|latex`: the paper's layout of a hand-made score file, cell by cell
(percent; the reference's relative sub-rows under the per-setting means; a setting a scenario
lacks shown as a dash)."""
from __future__ import annotations

import csv
from pathlib import Path

import pytest

from xvoe.cli import main

# (scenario, setting, pair) -> scores of member 0 and member 1; member 1 is impossible in S1 and S3
HAND = {
    ("collision", "S1", 0): (1, 2), ("collision", "S1", 1): (3, 1),
    ("collision", "S2", 0): (0, 5), ("collision", "S2", 1): (2, 0),
    ("collision", "S3", 0): (1, 4), ("collision", "S3", 1): (1, 1),
    ("permanence", "S1", 0): (0, 1), ("permanence", "S2", 0): (0, 1),
}
# worked out by hand from HAND: collision, then permanence ("-": no S3 in permanence)
EXPECTED = [
    ("Holistic", "", "60.9", "83.3"),           # 19.5 of the 32 (impossible, possible) pairs; 2.5 of 3
    ("Comparative", "S1 predictive", "50.0", "100.0"),
    ("", "S2 hypothetical", "50.0", "100.0"),
    ("", "S3 explicative", "75.0", "-"),        # a tie counts one half
    ("Relative", "S1 predictive", "50.0", "100.0"),
    ("", "S2 hypothetical", "62.5", "50.0"),    # the mean of its two sub-rows
    ("", "S2-ext1", "75.0", "100.0"),           # member 0 below its S1 pair's mean (2 = 2 counts a half)
    ("", "S2-ext2", "50.0", "0.0"),
    ("", "S3 explicative", "75.0", "-"),
    ("", "S3-ext", "100.0", "-"),
    ("", "S3-sur", "50.0", "-"),                # member 1 above its S1 pair's mean
]


def write_scores(path: Path, model: str) -> Path:
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["index", "model", "scenario", "setting", "pair", "member", "possible", "score"])
        for index, ((scenario, setting, pair), values) in enumerate(HAND.items()):
            for member, value in enumerate(values):
                possible = setting == "S2" or member == 0
                writer.writerow([2 * index + member, model, scenario, setting, pair, member, possible, value])
    return path


@pytest.mark.filterwarnings("ignore:.*does not record the split")
def test_the_markdown_table_holds_the_papers_layout(tmp_path):
    scores = write_scores(tmp_path / "hand.csv", "hand")
    assert main(["metrics", str(scores), "--out", str(tmp_path / "report"), "--rounds", "10", "--table", "md"]) == 0
    lines = (tmp_path / "report" / "table.md").read_text().splitlines()
    assert lines[0] == "| Metric | Setting | Model | Collision | Permanence |"
    rows = [[cell.strip().replace("–", "-") for cell in line.split("|")[1:-1]] for line in lines[2:]]
    assert rows == [[metric, setting, "hand", *cells] for metric, setting, *cells in EXPECTED]


@pytest.mark.filterwarnings("ignore:.*does not record the split")
def test_the_latex_table_is_a_booktabs_tabular(tmp_path):
    scores = write_scores(tmp_path / "my_model.csv", "my_model")
    assert main(["metrics", str(scores), "--out", str(tmp_path / "report"), "--rounds", "10", "--table",
                 "latex"]) == 0
    text = (tmp_path / "report" / "table.tex").read_text()
    assert text.startswith("\\begin{tabular}{lllrr}\n\\toprule\n") and text.endswith("\\bottomrule\n\\end{tabular}\n")
    assert " & \\quad S2-ext1 & my\\_model & 75.0 & 100.0 \\\\" in text
    assert " & \\quad S3-sur & my\\_model & 50.0 & -- \\\\" in text
    assert text.count("\\midrule") == 3        # after the header, before comparative and relative
