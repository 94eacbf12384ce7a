"""The metrics on hand-worked cases; AUC against a brute-force count; seeded bootstrap."""
import csv
import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from xvoe.apps.report import report
from xvoe.benchmark.generate import GenerateConfig, generate
from xvoe.errors import XvoeError
from xvoe.evaluation.metrics import (
    auc,
    comparative,
    disagreements,
    has_both_surprises,
    holistic,
    metric_rows,
    read_scores,
    relative,
    side_by_side,
)


def table(rows):
    """rows: (scenario, setting, pair, member, possible, score)."""
    columns = list(zip(*rows))
    return {"scenario": np.array(columns[0]), "setting": np.array(columns[1]), "pair": np.array(columns[2]),
            "member": np.array(columns[3]), "possible": np.array(columns[4], dtype=bool),
            "score": np.array(columns[5], dtype=float), "index": np.arange(len(rows))}


HAND = table([
    # collision S1: pair 0 right, pair 1 tie, pair 2 wrong, pair 3 right  -> (1 + .5 + 0 + 1) / 4
    ("collision", "S1", 0, 0, True, 1.0), ("collision", "S1", 0, 1, False, 3.0),
    ("collision", "S1", 1, 0, True, 2.0), ("collision", "S1", 1, 1, False, 2.0),
    ("collision", "S1", 2, 0, True, 5.0), ("collision", "S1", 2, 1, False, 4.0),
    ("collision", "S1", 3, 0, True, 0.0), ("collision", "S1", 3, 1, False, 9.0),
    # collision S2: both possible; member 1 higher in 1 of 2 pairs -> 0.5
    ("collision", "S2", 0, 0, True, 1.0), ("collision", "S2", 0, 1, True, 2.0),
    ("collision", "S2", 1, 0, True, 2.0), ("collision", "S2", 1, 1, True, 1.0),
])


def test_comparative_hand_case():
    result = comparative(HAND, rounds=50)
    assert result["collision", "S1"].value == pytest.approx(2.5 / 4)
    assert result["collision", "S2"].value == pytest.approx(0.5)


def test_holistic_hand_case():
    # impossible: 3, 2, 4, 9; possible: 1, 2, 5, 0, 1, 2, 2, 1
    positive, negative = [3, 2, 4, 9], [1, 2, 5, 0, 1, 2, 2, 1]
    wins = sum((p > n) + 0.5 * (p == n) for p in positive for n in negative)
    assert holistic(HAND, rounds=50)["collision"].value == pytest.approx(wins / 32)


def test_relative_hand_case():
    # thresholds = S1 pair means: pair 0: 2, pair 1: 2, pair 2: 4.5, pair 3: 4.5
    result = relative(HAND, rounds=50)
    # S1 videos: p0 (1<2 ok, 3>2 ok), p1 (2=2 half, 2=2 half), p2 (5>4.5 wrong, 4<4.5 wrong), p3 (ok, ok)
    assert result["collision", "S1"].value == pytest.approx((2 + 1 + 0 + 2) / 8)
    # S2 videos (possible): p0: 1<2 ok, 2=2 half; p1: 2=2 half, 1<2 ok
    assert result["collision", "S2"].value == pytest.approx(3 / 4)


@given(st.lists(st.integers(0, 5), min_size=1, max_size=12), st.lists(st.integers(0, 5), min_size=1, max_size=12))
def test_auc_equals_brute_force_with_half_ties(positive, negative):
    brute = np.mean([(p > n) + 0.5 * (p == n) for p, n in itertools.product(positive, negative)])
    assert auc(np.array(positive), np.array(negative)) == pytest.approx(brute)


def random_scores(pairs=40, seed=0, signal=1.0):
    rng = np.random.default_rng(seed)
    rows = []
    for scenario, setting in (("blocking", "S1"), ("blocking", "S2"), ("blocking", "S3")):
        for pair in range(pairs):
            for member in (0, 1):
                possible = member == 0 or setting == "S2"
                rows.append((scenario, setting, pair, member, possible, rng.normal() + signal * (not possible)))
    return table(rows)


def test_bootstrap_is_reproducible_and_brackets_the_estimate():
    scores = random_scores()
    a = comparative(scores, seed=3)["blocking", "S1"]
    b = comparative(scores, seed=3)["blocking", "S1"]
    assert (a.low, a.high) == (b.low, b.high) and a.low < a.high
    for estimate in [a, holistic(scores, seed=3)["blocking"], relative(scores, seed=3)["blocking", "S3"]]:
        assert estimate.low <= estimate.value <= estimate.high and estimate.high - estimate.low < 0.5


def test_chance_scores_sit_at_one_half():
    scores = random_scores(pairs=400, signal=0.0)
    assert abs(holistic(scores, rounds=200)["blocking"].value - 0.5) < 0.05
    result = comparative(scores, rounds=200)["blocking", "S1"]
    assert result.low < 0.5 < result.high


def test_read_scores_round_trip_and_errors(tmp_path):
    path = tmp_path / "scores.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["index", "scenario", "setting", "pair", "member", "possible", "score"])
        writer.writerow([0, "collision", "S1", 0, 0, True, 1.5])
        writer.writerow([1, "collision", "S1", 0, 1, False, 2.5])
    scores = read_scores(path)
    assert scores["possible"].tolist() == [True, False] and scores["score"].tolist() == [1.5, 2.5]
    assert comparative(scores, rounds=10)["collision", "S1"].value == 1.0
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(XvoeError, match="not a scores file"):
        read_scores(tmp_path / "bad.csv")
    with pytest.raises(XvoeError, match="no such file"):
        read_scores(tmp_path / "missing.csv")


def write_scores(path, scores, model):
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["index", "model", "scenario", "setting", "pair", "member", "possible", "score", "s_img",
                         "s_dyn"])
        for i in range(len(scores["score"])):
            writer.writerow([i, model, scores["scenario"][i], scores["setting"][i], scores["pair"][i],
                             scores["member"][i], scores["possible"][i], scores["score"][i],
                             0.3 * scores["score"][i], 0.7 * scores["score"][i]])


def test_report_writes_table_and_figures(tmp_path):
    write_scores(tmp_path / "a.csv", random_scores(seed=1, signal=2.0), "strong")
    write_scores(tmp_path / "b.csv", random_scores(seed=2, signal=0.0), "chance")
    written = report([tmp_path / "a.csv", tmp_path / "b.csv"], tmp_path / "report", rounds=50)
    names = {p.name for p in written}
    assert {"metrics.csv", "metrics.json", "holistic.png", "comparative.png", "components-strong.png"} <= names
    rows = list(csv.DictReader(open(tmp_path / "report" / "metrics.csv")))
    strong = [r for r in rows if r["model"] == "strong" and r["metric"] == "holistic" and r["column"] == "score"]
    assert float(strong[0]["value"]) > 0.8
    with pytest.raises(XvoeError, match="two scores files"):
        report([tmp_path / "a.csv", tmp_path / "a.csv"], tmp_path / "again", rounds=5)


def with_nll(rows):
    """rows: (scenario, setting, pair, member, possible, score, nll)."""
    scores = table([r[:6] for r in rows])
    scores["nll"] = np.array([r[6] for r in rows], dtype=float)
    return scores


BOTH = with_nll([
    # blocking S1 (member 1 impossible): pair 0 both right; pair 1 only the score right; pair 2 only the NLL
    # right; pair 3 the score ties and the NLL is wrong: neither
    ("blocking", "S1", 0, 0, True, 1.0, 10.0), ("blocking", "S1", 0, 1, False, 2.0, 20.0),
    ("blocking", "S1", 1, 0, True, 1.0, 30.0), ("blocking", "S1", 1, 1, False, 2.0, 20.0),
    ("blocking", "S1", 2, 0, True, 3.0, 10.0), ("blocking", "S1", 2, 1, False, 2.0, 20.0),
    ("blocking", "S1", 3, 0, True, 2.0, 30.0), ("blocking", "S1", 3, 1, False, 2.0, 20.0),
    # blocking S2 (both possible): pair 0 agree, pair 1 disagree with no right answer
    ("blocking", "S2", 0, 0, True, 1.0, 10.0), ("blocking", "S2", 0, 1, True, 2.0, 20.0),
    ("blocking", "S2", 1, 0, True, 1.0, 30.0), ("blocking", "S2", 1, 1, True, 2.0, 20.0),
])


def test_disagreements_hand_case():
    rows = disagreements(BOTH)
    found = {(r["setting"], r["pair"]): (r["score_says"], r["nll_says"], r["right"]) for r in rows}
    assert found == {("S1", 1): ("member 1", "member 0", "score"), ("S1", 2): ("member 0", "member 1", "nll"),
                     ("S1", 3): ("tie", "member 0", "neither"), ("S2", 1): ("member 1", "member 0", "")}
    first = next(r for r in rows if r["setting"] == "S1" and r["pair"] == 1)
    assert (first["index_0"], first["index_1"], first["score_1"], first["nll_0"]) == (2, 3, 2.0, 30.0)


def test_side_by_side_table_counts_disagreeing_pairs():
    assert has_both_surprises(BOTH)
    assert not has_both_surprises({**BOTH, "nll": BOTH["score"]})     # --surprise nll: score is the NLL
    table_rows = side_by_side(BOTH, metric_rows(BOTH, "m", rounds=20), "m")
    s1 = next(r for r in table_rows if r["metric"] == "comparative" and r["setting"] == "S1")
    assert s1["score"] == pytest.approx(2.5 / 4) and s1["nll"] == pytest.approx(2 / 4)
    assert s1["difference"] == pytest.approx(-0.125) and (s1["pairs"], s1["disagreeing_pairs"]) == (4, 3)
    assert {r["metric"] for r in table_rows} == {"comparative", "holistic", "relative"}


def test_report_compares_the_two_surprises_and_draws_disagreements(test_data, test_file, tmp_path):
    rng = np.random.default_rng(0)
    count = len(test_data["pair"])
    path = tmp_path / "both.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["index", "model", "scenario", "setting", "pair", "member", "possible", "score", "nll"])
        for i, (score, nll) in enumerate(rng.random((count, 2))):
            writer.writerow([i, "both", test_data["scenario"][i], test_data["setting"][i], test_data["pair"][i],
                             test_data["member"][i], test_data["possible"][i], score, nll])
    written = {p.name for p in report([path], tmp_path / "report", rounds=10, data=test_file)}
    assert {"surprise-both.csv", "disagreements-both.csv", "disagreements-both.png"} <= written
    rows = list(csv.DictReader(open(tmp_path / "report" / "disagreements-both.csv")))
    assert rows and all(r["score_says"] != r["nll_says"] for r in rows)
    other = tmp_path / "other.h5"

    generate(GenerateConfig("test", pairs=1, size=16, seed=3), other, workers=1, progress=False)
    with pytest.raises(XvoeError, match="does not hold the videos"):
        report([path], tmp_path / "again", rounds=5, data=other)


def test_violation_onset_on_hand_made_curves():
    from xvoe.evaluation.metrics import onset, onset_pairs

    # two collision S1 pairs (rows: pair 0 possible, impossible; pair 1 possible, impossible), event at frame 2
    scores = {"scenario": np.array(["collision"] * 4), "setting": np.array(["S1"] * 4),
              "pair": np.array([0.0, 0.0, 1.0, 1.0]), "possible": np.array([True, False, True, False])}
    per_frame = np.array([[1, 1, 1, 1, 1, 1],
                          [1, 1, 1, 5, 9, 1],      # rises at 3, peaks at 4: timely, 2 after the event
                          [1, 1, 1, 1, 1, 1],
                          [1, 4, 1, 1, 1, 1]], dtype=float)   # rises and peaks at 1: before the event
    event = np.array([2, 2, 2, 2])
    pairs = onset_pairs(scores, per_frame, event)
    assert [(p["first_positive"], p["timely"], p["peak_offset"]) for p in pairs] == [(3, True, 2), (1, False, -1)]
    row, = onset(scores, per_frame, event, "m", rounds=50)
    assert (row["pairs"], row["timely"], row["median_peak_offset"]) == (2, 0.5, 0.5)
    noise = per_frame.copy()
    noise[1, 0] += 0.3      # under a tenth of the peak difference (8): no rise yet
    assert onset_pairs(scores, noise, event)[0]["timely"]
