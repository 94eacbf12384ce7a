"""The metrics on hand-worked cases; AUC against a brute-force count and scipy's Mann-Whitney U;
seeded bootstrap intervals; the permutation p-value; the paper's score beside the default verdict."""
import csv
import itertools

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import mannwhitneyu

from xvoe.apps.report import report
from xvoe.errors import XvoeError
from xvoe.evaluation.disagreements import VERDICTS, disagreements, has_both_surprises, side_by_side
from xvoe.evaluation.metrics import auc, comparative, holistic, metric_rows, relative
from xvoe.evaluation.resampling import chance_p, values_interval, wilson
from xvoe.evaluation.score_tables import read_scores
from xvoe.scenes.generate import GenerateConfig, generate


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


def test_relative_midpoint_of_the_largest_scores_does_not_overflow():
    """A constant model at 1e308: every video sits on its S1 pair's midpoint, a tie (one half),
    not below an infinite midpoint (which had judged every possible video right)."""
    constant = {**HAND, "score": np.full(len(HAND["score"]), 1e308)}
    result = relative(constant, rounds=20)
    assert result["collision", "S1"].value == 0.5 and result["collision", "S2"].value == 0.5
    mixed = {**HAND, "score": np.where(HAND["member"] == 1, 1.7e308, 1.5e308)}     # the sum of a pair overflows
    assert relative(mixed, rounds=20)["collision", "S2"].value == 0.5


def test_a_scores_file_saved_with_a_byte_order_mark_reads_as_without(tmp_path):
    write_scores(tmp_path / "plain.csv", random_scores(seed=1), "bom")
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + (tmp_path / "plain.csv").read_bytes())
    plain, bom = read_scores(tmp_path / "plain.csv"), read_scores(tmp_path / "bom.csv")
    assert list(bom) == list(plain) and all(np.array_equal(bom[name], plain[name]) for name in plain)


@given(st.lists(st.integers(0, 5), min_size=1, max_size=12), st.lists(st.integers(0, 5), min_size=1, max_size=12))
def test_auc_equals_brute_force_with_half_ties(positive, negative):
    brute = np.mean([(p > n) + 0.5 * (p == n) for p, n in itertools.product(positive, negative)])
    assert auc(np.array(positive), np.array(negative)) == pytest.approx(brute)


@given(st.lists(st.floats(-5, 5), min_size=1, max_size=15), st.lists(st.floats(-5, 5), min_size=1, max_size=15))
def test_auc_is_mann_whitney_u_over_the_pair_count(positive, negative):
    u = mannwhitneyu(positive, negative).statistic      # U of the first sample: wins plus half the ties
    assert auc(np.array(positive), np.array(negative)) == pytest.approx(u / (len(positive) * len(negative)))


def test_permutation_p_value_by_hand():
    # 3 pairs, member 1 higher in all: of the 2^3 swaps of members, the share is 1 in one and 0 in
    # one; two-sided p = 2 * P(share >= 1) = 2/8
    assert chance_p(np.zeros(3), np.ones(3), rounds=100) == pytest.approx(0.25)
    # 4 pairs all right: 2/16; in a table, comparative reports it as p
    right = table([("blocking", "S1", p, m, m == 0, float(m)) for p in range(4) for m in (0, 1)])
    assert comparative(right, rounds=100)["blocking", "S1"].p == pytest.approx(0.125)
    # HAND's collision S1 (wins 1, 1/2, 0, 1): shares (k + 1/2)/4 with k ~ Binomial(3, 1/2); the
    # observed k = 2: P(>=) = 4/8, P(<=) = 7/8, p = min(1, 2 * 4/8)
    assert comparative(HAND, rounds=100)["collision", "S1"].p == pytest.approx(1.0)
    assert chance_p(np.zeros(1), np.ones(1)) == 1.0       # a single pair's two orders: no evidence


def test_bootstrap_interval_of_a_mean_matches_the_normal_closed_form():
    # 400 units, half 1: the mean's standard error is sqrt(0.25 / 400) = 0.025, the interval
    # about 0.5 -+ 1.96 * 0.025
    values = np.tile([0.0, 1.0], 200)
    low, high = values_interval(values, rounds=2000, seed=1)
    assert low == pytest.approx(0.5 - 1.96 * 0.025, abs=0.01) and high == pytest.approx(0.5 + 1.96 * 0.025, abs=0.01)
    assert values_interval(values, rounds=2000, seed=1) == (low, high)
    assert values_interval(np.full(10, 0.7), rounds=50) == pytest.approx((0.7, 0.7))


def random_scores(pairs=40, seed=0, signal=1.0):
    rng = np.random.default_rng(seed)
    rows = []
    for scenario, setting in (("blocking", "S1"), ("blocking", "S2"), ("blocking", "S3")):
        for pair in range(pairs):
            for member in (0, 1):
                possible = member == 0 or setting == "S2"
                rows.append((scenario, setting, pair, member, possible, rng.normal() + signal * (not possible)))
    return table(rows)


def test_wilson_interval_against_its_closed_form():
    # 5 of 10: 0.5 -/+ 1.96 sqrt(0.25/10 + 1.96^2/400) / (1 + 1.96^2/10) = [0.2366, 0.7634]
    assert wilson(5, 10) == pytest.approx((0.236593, 0.763407), abs=1e-5)
    # none of n: [0, z^2 / (n + z^2)]; all of n: its mirror image; never of zero width
    z2 = 1.959964 ** 2
    assert wilson(0, 4) == pytest.approx((0.0, z2 / (4 + z2)), abs=1e-6)
    assert wilson(4, 4) == pytest.approx((4 / (4 + z2), 1.0), abs=1e-6)
    assert wilson(3.5, 4)[0] < 3.5 / 4 < wilson(3.5, 4)[1]      # a tie counts one half
    assert np.isnan(wilson(0, 0)).all()


def test_four_pairs_all_right_get_a_wide_interval_and_their_count():
    scores = table([("blocking", "S1", pair, member, member == 0, float(member)) for pair in range(4)
                    for member in (0, 1)])
    rows = {r["metric"]: r for r in metric_rows(scores, "m", columns=("score",), rounds=50)}
    for metric in ("comparative", "holistic"):
        assert rows[metric]["value"] == 1.0 and rows[metric]["count"] == 4
        assert rows[metric]["low"] == pytest.approx(0.510, abs=1e-3) and rows[metric]["high"] == 1.0
    assert rows["relative"]["count"] == 8       # videos


def test_intervals_are_reproducible_and_bracket_the_estimate():
    scores = random_scores()
    a = holistic(scores, seed=3)["blocking"]
    b = holistic(scores, seed=3)["blocking"]
    assert (a.low, a.high) == (b.low, b.high) and a.low < a.high
    for estimate in [a, comparative(scores)["blocking", "S1"], relative(scores)["blocking", "S3"]]:
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


def with_second(column, rows):
    """rows: (scenario, setting, pair, member, possible, score, the second column's value)."""
    scores = table([r[:6] for r in rows])
    scores[column] = np.array([r[6] for r in rows], dtype=float)
    return scores


BOTH = with_second("nll", [
    # blocking S1 (member 1 impossible): pair 0 both right; pair 1 only the score right; pair 2 only the NLL
    # right; pair 3 the score ties and the NLL is wrong: no disagreement (the score picks no member)
    ("blocking", "S1", 0, 0, True, 1.0, 10.0), ("blocking", "S1", 0, 1, False, 2.0, 20.0),
    ("blocking", "S1", 1, 0, True, 1.0, 30.0), ("blocking", "S1", 1, 1, False, 2.0, 20.0),
    ("blocking", "S1", 2, 0, True, 3.0, 10.0), ("blocking", "S1", 2, 1, False, 2.0, 20.0),
    ("blocking", "S1", 3, 0, True, 2.0, 30.0), ("blocking", "S1", 3, 1, False, 2.0, 20.0),
    # blocking S2 (both possible): pair 0 agree, pair 1 disagree with no right answer, pair 2 the NLL's
    # members within the tolerance (787.3 against 787.5 nats): no disagreement
    ("blocking", "S2", 0, 0, True, 1.0, 10.0), ("blocking", "S2", 0, 1, True, 2.0, 20.0),
    ("blocking", "S2", 1, 0, True, 1.0, 30.0), ("blocking", "S2", 1, 1, True, 2.0, 20.0),
    ("blocking", "S2", 2, 0, True, 1.0, 787.5), ("blocking", "S2", 2, 1, True, 2.0, 787.3),
])


def test_disagreements_hand_case():
    rows = disagreements(BOTH)
    found = {(r["setting"], r["pair"]): (r["score_says"], r["nll_says"], r["right"]) for r in rows}
    assert found == {("S1", 1): ("member 1", "member 0", "score"), ("S1", 2): ("member 0", "member 1", "nll"),
                     ("S2", 1): ("member 1", "member 0", "")}
    first = next(r for r in rows if r["setting"] == "S1" and r["pair"] == 1)
    assert (first["index_0"], first["index_1"], first["score_1"], first["nll_0"]) == (2, 3, 2.0, 30.0)


def test_side_by_side_table_counts_disagreeing_pairs():
    assert has_both_surprises(BOTH)
    assert not has_both_surprises({**BOTH, "nll": BOTH["score"]})     # --surprise nll: score is the NLL
    table_rows = side_by_side(BOTH, metric_rows(BOTH, "m", rounds=20), "m")
    s1 = next(r for r in table_rows if r["metric"] == "comparative" and r["setting"] == "S1")
    assert s1["score"] == pytest.approx(2.5 / 4) and s1["nll"] == pytest.approx(2 / 4)
    assert s1["difference"] == pytest.approx(-0.125) and (s1["pairs"], s1["disagreeing_pairs"]) == (4, 2)
    assert {r["metric"] for r in table_rows} == {"comparative", "holistic", "relative"}


def test_report_compares_the_two_surprises_and_draws_disagreements(test_data, test_file, tmp_path):
    rng = np.random.default_rng(0)
    count = len(test_data["pair"])
    path = tmp_path / "both.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["index", "model", "scenario", "setting", "pair", "member", "possible", "score", "nll",
                         "paper_score"])
        for i, (score, nll, paper) in enumerate(rng.random((count, 3))):
            writer.writerow([i, "both", test_data["scenario"][i], test_data["setting"][i], test_data["pair"][i],
                             test_data["member"][i], test_data["possible"][i], score, nll, paper])
    written = {p.name for p in report([path], tmp_path / "report", rounds=10, data=test_file)}
    assert {"surprise-both.csv", "disagreements-both.csv", "disagreements-both.png"} <= written
    # the default verdict beside the paper's score, in every report of a file that holds both
    assert {"verdicts-both.csv", "verdicts-disagreements-both.csv"} <= written
    verdicts = list(csv.DictReader(open(tmp_path / "report" / "verdicts-disagreements-both.csv")))
    assert verdicts and all(r["score_says"] != r["paper_score_says"] for r in verdicts)
    rows = list(csv.DictReader(open(tmp_path / "report" / "disagreements-both.csv")))
    assert rows and all(r["score_says"] != r["nll_says"] for r in rows)
    other = tmp_path / "other.h5"

    generate(GenerateConfig("test", pairs=1, size=16, seed=3), other, workers=1, progress=False)
    with pytest.raises(XvoeError, match="does not hold the videos"):
        report([path], tmp_path / "again", rounds=5, data=other)


def test_the_report_times_the_onset_of_each_definition_the_curves_hold(test_data, test_file, tmp_path):
    """onset.csv has rows for the MSE's curves and, where they were scored, the NLL's: here every
    impossible member's NLL rises at the event frame and its MSE at frame 0, before it."""
    count, frames = test_data["rgbd"].shape[:2]
    path = tmp_path / "m.csv"
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["index", "model", "scenario", "setting", "pair", "member", "possible", "score", "nll"])
        for i in range(count):
            writer.writerow([i, "m", test_data["scenario"][i], test_data["setting"][i], test_data["pair"][i],
                             test_data["member"][i], test_data["possible"][i], i, -i])
    impossible, after = ~test_data["possible"][:, None], np.arange(frames) >= test_data["event_frame"][:, None]
    mse = np.where(impossible & (np.arange(frames) == 0), 5.0, 1.0)
    np.savez(path.with_suffix(".curves.npz"), s_img=mse, s_dyn=np.zeros_like(mse),
             nll=np.where(impossible & after, 5.0, 1.0))
    report([path], tmp_path / "report", rounds=10, data=test_file)
    rows = list(csv.DictReader(open(tmp_path / "report" / "onset.csv")))
    timely = {surprise: {float(r["timely"]) for r in rows if r["surprise"] == surprise} for surprise in ("mse", "nll")}
    assert timely == {"mse": {0.0}, "nll": {1.0}}
    assert len(rows) == 2 * len({(r["scenario"], r["setting"]) for r in rows}) == 2 * 7


VERDICT_PAIRS = with_second("paper_score", [
    # blocking S1 (member 1 impossible): the default verdict right in 3 of 4 pairs, the paper's
    # score in 1 (pair 0 both right; pairs 1, 2 only the verdict; pair 3 a paper's tie, no disagreement)
    ("blocking", "S1", 0, 0, True, 1.0, 1.0), ("blocking", "S1", 0, 1, False, 2.0, 2.0),
    ("blocking", "S1", 1, 0, True, 1.0, 5.0), ("blocking", "S1", 1, 1, False, 2.0, 2.0),
    ("blocking", "S1", 2, 0, True, 1.0, 5.0), ("blocking", "S1", 2, 1, False, 2.0, 2.0),
    ("blocking", "S1", 3, 0, True, 3.0, 2.0), ("blocking", "S1", 3, 1, False, 2.0, 2.0),
])


def test_the_paper_score_is_measured_beside_the_default_verdict():
    rows = metric_rows(VERDICT_PAIRS, "m", rounds=20)
    value = {(r["metric"], r["column"]): r["value"] for r in rows if r["setting"] in ("S1", "")}
    assert value["comparative", "score"] == pytest.approx(3 / 4)
    assert value["comparative", "paper_score"] == pytest.approx((1 + 0 + 0 + 0.5) / 4)
    # holistic, paper's score: impossible 2, 2, 2, 2 against possible 1, 5, 5, 2: wins 1 + 0 + 0 + 1/2 each
    assert value["holistic", "paper_score"] == pytest.approx(1.5 / 4)
    assert has_both_surprises(VERDICT_PAIRS, VERDICTS)
    s1 = next(r for r in side_by_side(VERDICT_PAIRS, rows, "m", VERDICTS)
              if r["metric"] == "comparative" and r["setting"] == "S1")
    assert (s1["score"], s1["paper_score"], s1["disagreeing_pairs"]) == (0.75, 0.375, 2)
    differ = disagreements(VERDICT_PAIRS, VERDICTS)
    assert [(r["pair"], r["score_says"], r["paper_score_says"], r["right"]) for r in differ] == [
        (1, "member 1", "member 0", "score"), (2, "member 1", "member 0", "score")]


def test_without_the_paper_score_the_metrics_are_as_before():
    plain = {k: v for k, v in VERDICT_PAIRS.items() if k != "paper_score"}
    rows = metric_rows(plain, "m", rounds=20)
    assert {r["column"] for r in rows} == {"score"} and not has_both_surprises(plain, VERDICTS)
    # a model with no choice of explanation writes the same value twice: nothing to set side by side
    assert not has_both_surprises({**plain, "paper_score": plain["score"]}, VERDICTS)


def test_violation_onset_on_hand_made_curves():
    from xvoe.evaluation.onset import onset, onset_pairs

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


# --- the metric charts say what they draw ----------------------------------------------------

def _chart_rows(models: list[str], column: str = "score") -> list[dict]:
    return [{"model": model, "metric": "comparative", "column": column, "scenario": "blocking", "setting": setting,
             "value": 1.0, "low": 0.51, "high": 1.0, "count": 4, "ideal": ideal, "p": 1.0}
            for model in models for setting, ideal in (("S1", 1.0), ("S2", 0.5))]


def test_the_ideal_is_a_dashed_line_across_each_group_and_a_column_keeps_its_colour():
    """Not short black dashes, which read as the intervals' caps; the NLL in the same colour in
    a chart of variants and in one of components."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import to_rgba

    from xvoe.apps.metric_plots import COLUMN_COLORS, IDEAL_COLOR, plot_comparative, plot_components

    figure = plot_comparative(_chart_rows(["score (MSE, sum)", "nll (NLL)"]))
    top = figure.axes[0]
    ideal = [c for c in top.collections if c.get_label() == "ideal"][0]
    segments = ideal.get_segments()
    assert [s[0][1] for s in segments] == [100, 50] and all(s[1][0] - s[0][0] >= 0.8 for s in segments)
    assert to_rgba(ideal.get_color()[0]) == to_rgba(IDEAL_COLOR) and ideal.get_linestyle()[0][1] is not None
    assert "(score)" not in top.get_title()
    nll_bar = top.patches[-1]       # the last series' last bar
    assert to_rgba(nll_bar.get_facecolor()) == to_rgba(COLUMN_COLORS["nll"])
    rows = [{**row, "model": "xpl", "column": row["model"].split(" (")[0]}
            for row in _chart_rows(["score (MSE, sum)", "nll (NLL)"])]
    components = plot_components(rows, "xpl")
    assert to_rgba(components.axes[0].patches[-1].get_facecolor()) == to_rgba(COLUMN_COLORS["nll"])
    plt.close(figure)
    plt.close(components)
