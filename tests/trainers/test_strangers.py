"""Evaluation beside a zoo's held-out strangers: known counts in booths, the normalised score, the IQM and its
interval, the heat map, and one-line refusals of a zoo that does not fit."""

import csv

import numpy as np
import pytest
from scripted_cook import TWO_BOOTHS, save_scripted_team

from jax_env import save_layout
from torch_kitchen.partners.conventions import STRANGER, TRAIN, Convention, Zoo, ZooMember, generator_settings, save_zoo
from trainers.config import EvalConfig
from trainers.evaluation import evaluate, main
from trainers.evaluation.intervals import interquartile_mean, interval, iqm
from trainers.evaluation.strangers import StrangerOutcomes, markdown_strangers, seeds_interval, stranger_rows
from trainers.evaluation.teams import convention_team

STRANGERS = [Convention(name="left_first", move_order="WENS"), Convention(name="server", role="server")]


def _zoo(path, size=7, generator=None):
    members = [ZooMember(c, STRANGER, 1.0, 1.0, {}) for c in STRANGERS]
    members.append(ZooMember(Convention(name="trainee", move_order="SNWE"), TRAIN, 1.0, 1.0, {}))
    return save_zoo(Zoo(0, size, generator or generator_settings(size), members), path)


def test_the_iqm_beside_strangers_resamples_seeds_within_each_stranger_over_seat_averaged_scores():
    scores = np.array([[[8, 6], [1, np.nan]], [[1, 3], [7, 5]], [[2, 2], [4, 4]]], dtype=float)  # [teams, S, seats]
    middle, low, high = seeds_interval(scores)
    assert middle == pytest.approx(interquartile_mean(np.array([7, 2, 2])))  # stranger 1 has a NaN: left out
    assert (middle, low, high) == tuple(interval(np.array([[7.0], [2.0], [2.0]]), iqm))  # rliable's interval
    assert np.isnan(seeds_interval(np.full((2, 1, 2), np.nan))[0])


def test_the_normalised_score_divides_by_two_of_the_stranger_and_rows_aggregate_teams_x_strangers_x_seats():
    teams = [convention_team(Convention(name=f"t{i}"), (7, 7, 26), condition="c") for i in range(2)]
    strangers = [convention_team(Convention(name=f"s{i}"), (7, 7, 26)) for i in range(2)]
    with_team = np.array([[[[3.0], [1.0]], [[2.0], [2.0]]], [[[4.0], [4.0]], [[0.0], [6.0]]]])  # [T, S, 2, G]
    alone = np.array([[2.0], [4.0]])  # [S, G]
    outcomes = StrangerOutcomes(teams, strangers, [("held-out (1)", ["heldout_000"])], with_team, alone)
    expected = np.array([1.5, 0.5, 0.5, 0.5, 2.0, 2.0, 0.0, 1.5])  # t0s0 seats, t0s1, t1s0, t1s1
    np.testing.assert_allclose(outcomes.normalised.ravel(), expected)
    (row,) = stranger_rows(outcomes)
    assert row["pairs"] == 8 and row["deliveries"] == pytest.approx(with_team.mean()) and row["left_out"] == ""
    assert row["normalised"] == pytest.approx(with_team.mean() / alone.mean())  # a ratio of the columns' means
    # Seats averaged, a score per team and stranger: 1.0, 0.5, 2.0, 0.75; the middle half 0.75 and 1.0.
    assert row["iqm"] == pytest.approx(0.875)


def test_a_stranger_that_never_delivers_with_itself_is_left_out_of_the_normalised_score_and_named():
    teams = [convention_team(Convention(name=f"t{i}"), (7, 7, 26), condition="c") for i in range(2)]
    strangers = [convention_team(Convention(name=name), (7, 7, 26)) for name in ("cooks", "idle")]
    with_team = np.array([[[[3.0], [1.0]], [[2.0], [2.0]]], [[[4.0], [4.0]], [[0.0], [6.0]]]])  # [T, S, 2, G]
    alone = np.array([[2.0], [0.0]])  # "idle" never delivers with itself
    outcomes = StrangerOutcomes(teams, strangers, [("held-out (1)", ["heldout_000"])], with_team, alone)
    (row,) = stranger_rows(outcomes)
    assert row["left_out"] == "idle" and row["pairs"] == 4  # teams x the one stranger that cooks x seats
    assert row["deliveries"] == pytest.approx(with_team.mean())  # beside every stranger
    assert (row["scored_deliveries"], row["scored_alone"]) == (pytest.approx(3.0), pytest.approx(2.0))
    assert row["normalised"] == pytest.approx(1.5)  # the two columns beside it, 3.0 / 2.0
    assert row["iqm"] == pytest.approx(interquartile_mean(np.array([1.0, 2.0])))  # the two teams' seats averaged
    table = markdown_strangers([row], ["cooks", "idle"], rollouts=1)
    assert "| 2.75 | 3.00 | 2.00 | 1.50 |" in table and "| 4 | idle |" in table


def test_every_team_plays_beside_every_stranger_in_both_seats_and_is_scored_against_two_of_it(tmp_path):
    booths = save_layout(TWO_BOOTHS, str(tmp_path / "two_booths.txt"))
    runs = [save_scripted_team(tmp_path / f"{name}.pt", name, seed=k)
            for k, name in enumerate(["scripted_cooks", "scripted_idle"])]
    config = EvalConfig(conditions={"cooks": runs}, layouts=[booths], heldout=0, rollouts=2, partner=False,
                        strangers=str(_zoo(tmp_path / "zoo.yaml")), out_dir=str(tmp_path / "out"),
                        progress=False).check()
    out = evaluate(config)
    with open(out / "strangers_pairs.csv") as handle:
        pairs = list(csv.DictReader(handle))
    assert len(pairs) == 2 * 2 * 2  # teams x strangers x seats; the training convention never plays
    assert {row["stranger"] for row in pairs} == {"left_first", "server"}
    for row in pairs:
        # Each cook keeps to its booth: a stranger alone delivers 2p, beside the working team 7 + p, beside the
        # idle team p.
        pace = float(row["stranger_alone"]) / 2
        assert pace > 0
        working = row["team"] == "cooks/seed0"
        assert float(row["deliveries"]) == pytest.approx(7 + pace if working else pace)
        assert float(row["normalised"]) == pytest.approx((7 + pace if working else pace) / (2 * pace))
    with open(out / "strangers.csv") as handle:
        (summary,) = list(csv.DictReader(handle))
    assert int(summary["pairs"]) == 8 and float(summary["iqm_low"]) <= float(summary["iqm"])
    report = (out / "eval.md").read_text()
    assert "held-out strangers (2: left_first, server)" in report and "| IQM normalised |" in report
    assert (out / "heatmap_strangers.png").stat().st_size > 0


def test_a_zoo_of_another_size_or_generator_and_a_missing_zoo_are_refused_in_one_line(tmp_path, capsys):
    booths = save_layout(TWO_BOOTHS, str(tmp_path / "two_booths.txt"))
    run = save_scripted_team(tmp_path / "cooks.pt", "scripted_cooks")
    other_generator = {**generator_settings(7), "p_smaller": 0.5}
    for zoo, words in [(_zoo(tmp_path / "nine.yaml", size=9), "drawn for 9x9 kitchens, not 7x7"),
                       (_zoo(tmp_path / "other.yaml", generator=other_generator), "with another generator"),
                       (tmp_path / "none.yaml", "does not exist")]:
        out = tmp_path / f"out_{zoo.stem}"
        code = main(["configs/eval/paper.yaml", f"conditions={{cooks: {run}}}", f"layouts=[{booths}]", "heldout=0",
                     f"strangers={zoo}", f"out_dir={out}", "progress=false", "cross=[]", "gifs=[]"])
        error = capsys.readouterr().err
        assert code == 2 and words in error and error.count("\n") == 1, error
        assert not out.exists()


def test_teams_are_scored_over_a_strangers_best_response_which_is_never_a_team_to_evaluate(tmp_path, capsys):
    booths = save_layout(TWO_BOOTHS, str(tmp_path / "two_booths.txt"))
    runs = [save_scripted_team(tmp_path / f"{name}.pt", name, seed=k)
            for k, name in enumerate(["scripted_cooks", "scripted_idle"])]
    best = save_scripted_team(tmp_path / "best.pt", "scripted_cooks", algorithm="zoo_ippo",
                              algorithm_config={"best_response_to": "server"})
    zoo = str(_zoo(tmp_path / "zoo.yaml"))
    config = EvalConfig(conditions={"cooks": runs}, layouts=[booths], heldout=0, rollouts=1, partner=False,
                        strangers=zoo, best_responses={"server": best}, out_dir=str(tmp_path / "out"),
                        progress=False).check()
    out = evaluate(config)
    with open(out / "strangers_pairs.csv") as handle:
        pairs = list(csv.DictReader(handle))
    for row in pairs:
        pace = float(row["stranger_alone"]) / 2
        working = row["team"] == "cooks/seed0"
        if row["stranger"] == "server":  # its best response cooks in its booth beside it: 7 + p
            assert float(row["over_best_response"]) == pytest.approx((7 + pace if working else pace) / (7 + pace))
        else:
            assert row["over_best_response"] == "nan"
    assert "| over the best response (IQM) |" in (out / "eval.md").read_text()
    for conditions, responses, words in [({"cooks": [best]}, {}, "is a best response to the stranger 'server'"),
                                         ({"cooks": runs}, {"left_first": best}, "not trained as the best response"),
                                         ({"cooks": runs}, {"nobody": best}, "'nobody', which is not a stranger")]:
        code = main(["configs/eval/paper.yaml", f"conditions={conditions}", f"best_responses={responses}",
                     f"layouts=[{booths}]", "heldout=0", f"strangers={zoo}", f"out_dir={tmp_path / 'bad'}",
                     "progress=false", "cross=[]", "gifs=[]"])
        error = capsys.readouterr().err
        assert code == 2 and words in error and error.count("\n") == 1, error
        assert not (tmp_path / "bad").exists()
