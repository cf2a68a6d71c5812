"""The paper's claims decided by intervals over seeds: crafted per-seed tables whose verdicts are known."""

import numpy as np
import pytest

from trainers.evaluation.claims import (
    SeedScores,
    beside_every_stranger,
    beyond_teacher,
    family_claims,
    shared_teacher,
    stranger_claims,
)
from trainers.evaluation.intervals import DOES_NOT_HOLD, HOLDS, INCONCLUSIVE, difference

HELD = "held-out (100)"
LAYOUTS = ["cramped_room_7x7", "coord_ring_7x7"]
SK = {"cramped_room_7x7": "sk_a", "coord_ring_7x7": "sk_b"}


def seed_rows(condition, grids, kind, values, partner=""):
    return [{"condition": condition, "team": f"{condition}/seed{k}", "grids": grids, "kind": kind, "with": partner,
             "deliveries": str(v)} for k, v in enumerate(values)]


def population(ik_xp, sk_xp, sk_sp_heldout=(0.0, 0.1, 0.0)):
    rows = []
    for layout, condition in SK.items():
        rows += seed_rows("ik", layout, "xp", ik_xp) + seed_rows(condition, layout, "xp", sk_xp)
        rows += seed_rows("ik", layout, "sp", [v + 1 for v in ik_xp]) + seed_rows(condition, layout, "sp",
                                                                               [v + 3 for v in sk_xp])
        rows += seed_rows(condition, HELD, "sp", sk_sp_heldout)
    return rows + seed_rows("ik", HELD, "xp", [3.0, 3.5, 4.0]) + seed_rows("ik", HELD, "sp", [4.0, 4.5, 5.0])


@pytest.mark.parametrize("ik_xp, sk_xp, expected", [
    ([3.0, 3.2, 3.4], [1.0, 1.1, 1.2], HOLDS),  # every IK seed above every SK seed
    ([1.0, 1.1, 1.2], [3.0, 3.2, 3.4], DOES_NOT_HOLD),
    ([1.0, 3.0, 2.0], [1.5, 2.5, 2.0], INCONCLUSIVE),  # the seeds overlap
])  # fmt: skip
def test_ik_against_sk_is_decided_by_the_interval_of_the_difference_over_seeds(ik_xp, sk_xp, expected):
    scores = SeedScores(population(ik_xp, sk_xp))
    rows = family_claims(scores, "MLP", "ik", SK, budget=1_000_000)
    (claim, here, decided), zero, paper, gap = rows
    assert claim.startswith("IK beats SK in cross-play") and decided.startswith(f"{expected}; per layout ")
    assert "(3 v 3 seeds)" in here and f"cramped_room {np.mean(ik_xp):.2f} vs {np.mean(sk_xp):.2f}" in here
    # The SK teams' self-play on held-out levels: at most 0.1 in every resample, below 0.5.
    assert zero[2] == HOLDS and "0.03 [0.00, 0.07]" in zero[1]
    assert paper[2] == "1.0e+06 steps, not 2e9: not comparable" and "3.50 [3.00, 4.00] (3 seeds)" in paper[1]
    assert gap[2] == HOLDS  # SK's gap is 3, IK's 1, on every seed


def test_the_paper_budgets_claim_is_decided_by_the_interval_against_the_papers_figure():
    scores = SeedScores(seed_rows("gnn_ik", HELD, "xp", [9.5, 9.6, 9.8]))
    [(_, here, decided)] = family_claims(scores, "GNN", "gnn_ik", {}, budget=2_000_000_000)
    assert decided == HOLDS and "9.63 [9.50, 9.80] (3 seeds)" in here  # above 9, the paper's 10 less one
    scores = SeedScores(seed_rows("gnn_ik", HELD, "xp", [2.0, 9.5, 9.8]))
    assert family_claims(scores, "GNN", "gnn_ik", {}, budget=2_000_000_000)[0][2] == INCONCLUSIVE


def test_a_shared_teacher_and_beyond_the_teacher_are_paired_by_seed_and_set_against_the_cook():
    rows = [*seed_rows("ik", HELD, "xp", [4.0, 3.0, 5.0]), *seed_rows("ik", HELD, "cross", [3.5, 2.6, 4.4], "ewsn"),
            *seed_rows("ik", HELD, "sp", [4.2, 4.3, 4.4]), *seed_rows("scripted cook", HELD, "sp", [4.0])]
    scores = SeedScores(rows)
    # Unpaired, 3.0-5.0 against 2.6-4.4 overlap; seed by seed every IK seed loses 0.4 to 0.6 across.
    [(_, here, decided)] = shared_teacher(scores, "ik", "ewsn")
    assert decided == HOLDS and "4.00 against 3.50" in here
    [self_play, cross_play] = beyond_teacher(scores, "ik")
    assert self_play[2] == HOLDS and cross_play[2] == INCONCLUSIVE and "the cook 4.00" in self_play[1]


def stranger_pairs(condition, normalised_by_seed, names=("a", "b", "idle")):
    """Rows of strangers_pairs.csv: seed k's normalised score beside each stranger, in both seats; the last
    stranger never delivers with itself (normalised NaN)."""
    rows = []
    for k, scores in enumerate(normalised_by_seed):
        for name, score in zip(names, [*scores, np.nan]):
            for seat in (0, 1):
                rows.append({"team": f"{condition}/seed{k}", "condition": condition, "stranger": name,
                             "team_seat": seat, "grids": HELD, "deliveries": str(2 * score if name != "idle" else 1),
                             "normalised": str(score), "over_best_response": str(score / 2)})
    return rows


def test_beside_every_stranger_holds_only_where_it_holds_beside_each_and_leaves_out_one_that_never_cooks():
    scores = SeedScores([], stranger_pairs("zoo", [(1.5, 1.1), (1.6, 0.9), (1.7, 1.2)]))
    [(_, here, decided)] = beside_every_stranger(scores, "zoo", "normalised", 1.0, "claim")
    assert decided == INCONCLUSIVE  # above 1.0 beside a; beside b the seeds straddle 1.0
    assert here.startswith("holds on 1, inconclusive on 1 of 2 strangers (3 seeds)") and "idle" not in here
    scores = SeedScores([], stranger_pairs("zoo", [(1.5, 0.5), (1.6, 0.6), (1.7, 0.7)]))
    assert beside_every_stranger(scores, "zoo", "normalised", 1.0, "claim")[0][2] == DOES_NOT_HOLD
    scores = SeedScores([], stranger_pairs("zoo", [(1.5, 1.1), (1.6, 1.2), (1.7, 1.3)]))
    assert beside_every_stranger(scores, "zoo", "normalised", 1.0, "claim")[0][2] == HOLDS
    assert beside_every_stranger(scores, "zoo", "over_best_response", 0.9, "claim")[0][2] == DOES_NOT_HOLD


def test_the_claims_beside_strangers_compare_conditions_seed_by_seed():
    one = stranger_pairs("one", [(0.7, 0.8), (0.6, 0.7), (0.8, 0.9)])
    zoo = stranger_pairs("zoo", [(1.2, 1.1), (1.3, 1.2), (1.1, 1.4)])
    many = stranger_pairs("many", [(0.9, 0.8), (0.8, 0.9), (1.0, 1.0)])
    xp = [*seed_rows("one", HELD, "xp", [4.0, 4.1, 4.2]), *seed_rows("many", HELD, "xp", [3.6, 3.5, 3.7])]
    scores = SeedScores(xp, [*one, *zoo, *many])
    compared = {"one_teacher": "one", "diverse_teachers": "many", "zoo_partners": "zoo"}
    rows = {row[0]: (who, row) for who, _, row in stranger_claims(scores, {}, compared)}
    who, (_, here, decided) = rows["Diverse teachers lower the cross-play inflation of one teacher (XP between "
                                    "seeds minus play with strangers)"]
    assert who == "many" and decided == HOLDS  # one's seeds: XP 4 - about 1.5; many's: 3.6 - about 1.8
    who, (_, here, decided) = rows["Zoo partners in training raise play with strangers on held-out levels "
                                    "(normalised IQM)"]
    assert who == "zoo" and decided == HOLDS and "(3 v 3 seeds)" in here


def test_a_difference_of_conditions_with_seeds_that_all_agree_is_a_point():
    gap = difference(np.array([[2.0], [2.0]]), np.array([[1.0], [1.0], [1.0]]))
    assert (gap.value, gap.low, gap.high) == (1.0, 1.0, 1.0)
