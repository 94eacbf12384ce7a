"""The scorecard's lines on hand-made score tables, and the shipping rule on hand-made cards."""
import numpy as np
import pytest

from xvoe.errors import XvoeError
from xvoe.evaluation.scorecard import (
    ROLES,
    TWO_DENIED,
    TWO_SAID,
    Line,
    compare,
    format_line,
    hypotheses_in_s2,
    identity_lines,
    lead_lines,
    read_card,
    repeat_lines,
    role_of,
    score_lines,
    write_card,
)
from xvoe.training.stages import MODEL_ROLES, RANDOM, STAGES


def table(rows, paper=None):
    """rows: (scenario, setting, pair, member, possible, score)."""
    columns = list(zip(*rows))
    found = {"scenario": np.array(columns[0]), "setting": np.array(columns[1]),
             "pair": np.array(columns[2], dtype=float), "member": np.array(columns[3], dtype=float),
             "possible": np.array(columns[4], dtype=bool), "score": np.array(columns[5], dtype=float),
             "index": np.arange(len(rows), dtype=float)}
    if paper is not None:
        found["paper_score"] = np.array(paper, dtype=float)
    return found


def pairs(scenario, setting, wins):
    """One row per member; member 1 (impossible outside S2) more surprising where `wins` is 1."""
    return [(scenario, setting, p, m, m == 0 or setting == "S2", float(m == w)) for p, w in enumerate(wins)
            for m in (0, 1)]


def goal(name, value, low, high, target=None, direction=">="):
    return Line(name, value, low, high, target, direction)


def test_a_line_is_met_by_its_direction():
    assert goal("a", 97.0, 95, 99, 97.0).met and not goal("a", 96.9, 95, 99, 97.0).met
    assert goal("b", 0.4, 0.3, 0.5, 0.5, "<=").met and not goal("b", 0.6, 0.5, 0.7, 0.5, "<=").met
    assert goal("c", 55.0, 45, 60, 50.0, "within").met and not goal("c", 60.0, 52, 68, 50.0, "within").met
    assert goal("d", 1.0, 0, 2).met is None       # reported


def test_worse_beyond_its_interval_by_hand():
    shipped = goal("a", 98.0, 96, 100, 97.0)
    assert goal("a", 95.0, 93, 97.5, 97.0).worse_than(shipped)          # 97.5 < 98
    assert not goal("a", 95.0, 93, 98.5, 97.0).worse_than(shipped)      # its interval reaches 98
    assert goal("b", 0.9, 0.7, 1.1, 0.5, "<=").worse_than(goal("b", 0.6, 0.5, 0.7, 0.5, "<="))
    # within: the nearest end of [53, 60] is 3 from 50, the shipped value 1 from it
    assert goal("c", 56.0, 53, 60, 50.0, "within").worse_than(goal("c", 51.0, 45, 57, 50.0, "within"))
    assert not Line("e", 0.0, target=1.0).worse_than(shipped)           # no interval: never


SHIPPED = [goal("S1", 98.0, 96, 100, 97.0), goal("S3", 96.0, 94, 98, 97.0),     # S3: not met by the shipped model
           goal("auc", 0.95, 0.93, 0.97, 0.9), goal("gap", 40.0, 30, 50)]         # gap: reported


def test_a_candidate_as_good_ships():
    candidate = [goal("S1", 97.5, 95, 99, 97.0), goal("S3", 90.0, 88, 97, 97.0),
                 goal("auc", 0.94, 0.92, 0.96, 0.9), goal("gap", 10.0, 5, 15)]
    decision = compare(candidate, SHIPPED)
    # S3 unmet as the shipped model's is, within its interval; the reported gap fell from 40 to
    # 10, beyond its interval: reported lines never block
    assert decision.ships and decision.unmet == [] and decision.worse == []


def test_a_goal_line_the_shipped_model_misses_must_not_get_worse():
    candidate = [goal("S1", 97.5, 95, 99, 97.0), goal("S3", 90.0, 88, 95, 97.0), goal("auc", 0.94, 0.92, 0.96, 0.9)]
    decision = compare(candidate, SHIPPED)      # S3's interval ends at 95, below the shipped 96
    assert not decision.ships and decision.worse == ["S3"] and decision.unmet == []


def test_a_goal_the_shipped_model_meets_must_be_met():
    candidate = [goal("S1", 96.5, 94, 99, 97.0), goal("S3", 96.0, 94, 98, 97.0), goal("auc", 0.95, 0.93, 0.97, 0.9)]
    decision = compare(candidate, SHIPPED)
    assert not decision.ships and decision.unmet == ["S1"] and decision.worse == []
    decision = compare(candidate[1:], SHIPPED)          # no S1 line at all: unmet too
    assert decision.unmet == ["S1"]


def test_a_goal_line_worse_beyond_its_interval_blocks_even_when_met():
    candidate = [goal("S1", 98.0, 96, 100, 97.0), goal("S3", 96.0, 94, 98, 97.0), goal("auc", 0.91, 0.9, 0.92, 0.9)]
    decision = compare(candidate, SHIPPED)
    assert not decision.ships and decision.worse == ["auc"] and decision.unmet == []


def test_score_lines_carry_the_goals_of_the_role():
    rows = pairs("collision", "S1", [1, 1, 1, 0]) + pairs("collision", "S2", [1, 0]) + pairs("collision", "S3", [1] * 4)
    # the paper's score ties every S1 pair
    paper = [value if setting != "S1" else 0.0 for (_, setting, _, _, _, value) in rows]
    scores = table(rows, paper)
    lines = {line.name: line for line in score_lines(scores, "xpl", rounds=50)}
    s1 = lines["MSE verdict collision S1 comparative (%)"]
    assert (s1.value, s1.target, s1.met) == (75.0, 97.0, False) and s1.p == pytest.approx(0.625)
    assert lines["MSE verdict collision S3 comparative (%)"].met
    paper_s1 = lines["paper's MSE score collision S1 comparative (%)"]
    assert (paper_s1.value, paper_s1.target) == (50.0, None)
    assert lines["S3 - S2 gap collision (points)"].value == pytest.approx(100 - 50)
    # holistic: impossible (member 1 of S1, S3) 1,1,1,0, 1,1,1,1 against possible 0,0,0,1, 0,1,1,0, 0,0,0,0
    impossible, possible = [1, 1, 1, 0, 1, 1, 1, 1], [0, 0, 0, 1, 0, 1, 1, 0, 0, 0, 0, 0]
    wins = sum((a > b) + 0.5 * (a == b) for a in impossible for b in possible)
    assert lines["MSE verdict collision holistic AUC"].value == pytest.approx(wins / (8 * 12))
    baseline = {line.name: line for line in score_lines(scores, "baseline", rounds=50)}
    assert baseline["MSE verdict collision S1 comparative (%)"].target == 90.0
    assert baseline["MSE verdict collision S3 comparative (%)"].target is None
    chance = {line.name: line for line in score_lines(scores, "chance", rounds=50)}
    assert chance["MSE verdict collision S1 comparative (%)"].direction == "within"
    # a model with no choice of explanation writes its score twice: no second set of lines
    twice = score_lines(table(rows, [value for (*_, value) in rows]), "baseline", rounds=50)
    assert [line.name for line in twice] == [name for name in baseline if not name.startswith("paper's")]


def test_xpl_s3_lead_over_a_baseline_by_hand():
    xpl = table(pairs("collision", "S3", [1, 1, 1, 1]) + pairs("blocking", "S3", [1, 1, 0, 1]))
    plato = table(pairs("collision", "S3", [1, 0, 0, 1]) + pairs("blocking", "S3", [1, 1, 1, 1]))
    lines = {line.name: line for line in lead_lines(xpl, {"plato": plato}, rounds=200)}
    collision = lines["XPL S3 lead over plato collision (points)"]
    blocking = lines["XPL S3 lead over plato blocking (points)"]
    assert (collision.value, collision.met) == (50.0, True) and (blocking.value, blocking.met) == (-25.0, False)
    # per pair the lead is 0, 100, 100, 0 points: a resample's mean lies in [0, 100]
    assert 0.0 <= collision.low <= 50.0 <= collision.high <= 100.0


def test_a_card_round_trips_and_prints(tmp_path):
    lines = [goal("S1", 98.0, 96, 100, 97.0), Line("speed", 12.0, target=10.0), Line("gap", 3.0),
             Line("probe", float("nan"), target=0.95, note="too few objects")]
    path = write_card(tmp_path / "card.json", lines, model="xpl")
    assert repr(read_card(path)) == repr(lines)      # repr: nan (no interval, no p) equals itself
    assert format_line(lines[3]) == "probe: nan (too few objects) (goal >= 0.95) NOT MET"
    text = format_line(goal("S1", 95.0, 93, 97.5, 97.0), lines[0])
    assert "NOT MET" in text and "WORSE BEYOND ITS INTERVAL" in text
    assert (role_of("plato"), role_of("random"), role_of("runs/s0"), role_of("xpl")) == (
        "baseline", "chance", "xpl", "xpl")


def test_every_model_known_by_name_carries_a_role_of_the_scorecard():
    """The registry's roles are the scorecard's: a model named there is held to goals that exist,
    and the random agent, made by no stage, to chance's."""
    assert set(MODEL_ROLES.values()) <= set(ROLES)
    assert RANDOM not in STAGES and role_of(f"runs/{RANDOM}") == "chance"


def test_the_identity_lines_count_the_videos_only_two_objects_explain_and_those_a_wall_shows_one():
    rows = [("continuity", "S2", 0, 1, True, 0.0), ("continuity", "S2", 1, 1, True, 0.0),
            ("continuity", "S2", 2, 1, True, 0.0), ("continuity", "S2", 3, 1, True, 0.0),
            ("continuity", "S2", 0, 0, True, 0.0),                                        # seen in the window
            ("collision", "S1", 0, 0, True, 0.0), ("continuity", "S3", 0, 0, True, 0.0),
            ("blocking", "S3", 0, 0, True, 0.0), ("permanence", "S1", 0, 0, True, 0.0),
            ("collision", "S1", 0, 1, False, 0.0), ("collision", "S2", 0, 0, True, 0.0)]  # neither
    scores = table(rows)
    scores["p_two"] = np.array([0.9, 0.8, 0.2, 0.7, 0.9, 0.1, 0.2, 0.6, 0.0, 0.9, 0.9])
    said, denied = identity_lines(scores, rounds=200)
    assert said.value == pytest.approx(75.0) and said.target == TWO_SAID and not said.met
    assert denied.value == pytest.approx(75.0) and denied.target == TWO_DENIED
    assert said.low <= said.value <= said.high
    scores["p_hidden"] = np.array([0.0, 0.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.6])
    shares = {line.name: line.value for line in hypotheses_in_s2(scores)}
    assert shares["S2 continuity member 1: two objects (% of videos)"] == pytest.approx(75.0)
    assert shares["S2 continuity member 0: a hidden object (% of videos)"] == 100.0
    assert shares["S2 collision member 0: a hidden object (% of videos)"] == 100.0
    assert "S2 collision member 1: two objects (% of videos)" not in shares         # no such videos


def test_the_repeat_is_measured_on_the_videos_both_seeds_scored():
    scores = {"index": np.arange(6, dtype=float), "nll": np.array([10.0, 11.0, 12.0, 13.0, 14.0, 15.0])}
    repeat = {"index": np.array([4.0, 1.0, 2.0]), "nll": np.array([14.0, 13.0, 12.5])}     # part, in another order
    median, p99 = repeat_lines(scores, repeat, rounds=200)
    assert median.value == pytest.approx(0.5) and median.met        # differences 0, 2, 0.5
    assert p99.value == pytest.approx(np.percentile([0.0, 2.0, 0.5], 99)) and p99.met
    with pytest.raises(XvoeError, match="share no video"):
        repeat_lines(scores, {"index": np.array([9.0]), "nll": np.array([1.0])})
