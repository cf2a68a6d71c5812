"""The paper's claims decided on an evaluation's numbers, seed by seed.

A claim compares aggregates over seeds (the teams of a condition, rliable's runs) on a set of tasks (a layout, the
held-out levels, a stranger): `SeedScores` reads the evaluation's per-seed tables (`seeds.csv`, and
`strangers_pairs.csv` where strangers were seated) into matrices [seeds, tasks]; each claim takes an aggregate, or a
difference of two conditions' aggregates, with its 95% stratified bootstrap interval (`trainers.evaluation.
intervals`), and reads "holds" only when the whole interval lies on the claimed side, "does not hold" when it lies
wholly on the other, and "inconclusive" otherwise. A row is (claim, what was measured, verdict).
"""

from __future__ import annotations

import csv
from collections import Counter
from pathlib import Path

import numpy as np

from trainers.evaluation.intervals import (
    DOES_NOT_HOLD,
    HOLDS,
    INCONCLUSIVE,
    Estimate,
    difference,
    interval,
    iqm,
    mean,
    verdict,
)
from trainers.evaluation.teams import HUMAN_PROXY_RUN, SCRIPTED_CONDITION

HELDOUT = "held-out"
PAPER_STEPS = 2e9  # env steps per team in the paper
# Deliveries in cross-play on held-out levels the paper reports for IK teams at 2e9 steps (Fig. 7), per family.
PAPER_HELDOUT_XP = {"MLP": 9, "GNN": 10}
SK_ZERO = 0.5  # "SK scores 0 on generated levels": below half a delivery per episode
BR_PROX_GOAL = 0.9  # as good a partner to a stranger as nine tenths of a team trained for it

Row = tuple[str, str, str]


class SeedScores:
    """Per-seed scores of an evaluation: `runs` and `matrix` for the pairs of the population (`seeds.csv`),
    `strangers` for the pairs with held-out strangers (`strangers_pairs.csv`). Seeds are ordered by team name, so
    two kinds of score of one condition line up seed by seed."""

    def __init__(self, seeds: list[dict], stranger_pairs: list[dict] = (), learned_pairs: list[dict] = ()):
        self._scores: dict[tuple[str, str, str, str], dict[str, float]] = {}
        for row in seeds:
            key = (row["condition"], row["grids"], row["kind"], row.get("with") or "")
            self._scores.setdefault(key, {})[row["team"]] = float(row["deliveries"])
        self._strangers: dict[tuple[str, str, str, bool], dict[str, dict[str, list[float]]]] = {}
        for learned, rows in ((False, stranger_pairs), (True, learned_pairs)):
            for row in rows:
                for key in ("deliveries", "normalised", "over_best_response"):
                    by_team = self._strangers.setdefault((row["condition"], row["grids"], key, learned), {})
                    by_team.setdefault(row["team"], {}).setdefault(row["stranger"], []).append(float(row[key]))

    @classmethod
    def read(cls, eval_dir: str | Path) -> SeedScores:
        eval_dir = Path(eval_dir)

        def rows(name: str) -> list[dict]:
            path = eval_dir / name
            if not path.is_file():
                return []
            with open(path) as handle:
                return list(csv.DictReader(handle))

        return cls(rows("seeds.csv"), rows("strangers_pairs.csv"), rows("learned_strangers_pairs.csv"))

    @property
    def heldout(self) -> str | None:
        """The held-out group's name, e.g. "held-out (100)"; None where the evaluation had none."""
        return next((grids for _, grids, *_ in [*self._scores, *self._strangers] if grids.startswith(HELDOUT)), None)

    def grids(self, condition: str, kind: str) -> list[str]:
        """The grid groups where `condition` has scores of `kind`."""
        return sorted({grids for name, grids, played, _ in self._scores if name == condition and played == kind})

    def runs(self, condition: str, grids: str, kind: str, partner: str = "") -> np.ndarray:
        """float [seeds]: each seed's mean deliveries in pairs of `kind` on `grids` (empty where not played)."""
        scores = self._scores.get((condition, grids, kind, partner), {})
        return np.array([scores[team] for team in sorted(scores)], dtype=np.float64)

    def matrix(self, tasks: list[tuple[str, str]], kind: str, partner: str = "") -> np.ndarray | None:
        """float [seeds, tasks]: a column per (condition, grids), each its condition's seeds; None where a task was
        not played or the tasks' conditions have different numbers of seeds."""
        columns = [self.runs(condition, grids, kind, partner) for condition, grids in tasks]
        if not columns or len({column.size for column in columns}) != 1 or columns[0].size == 0:
            return None
        return np.stack(columns, axis=1)

    def strangers(self, condition: str, grids: str, key: str = "deliveries", learned: bool = False
                  ) -> tuple[np.ndarray, list[str]] | None:
        """(float [seeds, strangers], the strangers' names): each seed's `key` beside each held-out stranger (the
        learned strangers with `learned`), both seats averaged, over the strangers where it is defined (the
        normalised score leaves out a stranger that never delivers with itself); None where no stranger sat beside
        the condition there."""
        by_team = self._strangers.get((condition, grids, key, learned))
        if not by_team:
            return None
        names = sorted({name for scores in by_team.values() for name in scores})
        table = np.array([[np.mean(by_team[team][name]) for name in names] for team in sorted(by_team)])
        kept = ~np.isnan(table).any(axis=0)
        if not kept.any():
            return None
        return table[:, kept], [name for name, keep in zip(names, kept) if keep]


# --------------------------------------------------------------------------------------------- wording
def seeds(*matrices: np.ndarray) -> str:
    """"3 seeds", or "3 v 3 seeds" for two conditions."""
    return " v ".join(str(matrix.shape[0]) for matrix in matrices) + " seeds"


def counted(verdicts: list[str], where: str) -> str:
    """"holds on 2, inconclusive on 3 of 5 layouts"."""
    count = Counter(verdicts)
    parts = [f"{kind} on {count[kind]}" for kind in (HOLDS, DOES_NOT_HOLD, INCONCLUSIVE) if count[kind]]
    return ", ".join(parts) + f" of {len(verdicts)} {where}"


def all_of(verdicts: list[str]) -> str:
    """A claim about every member: holds where it holds for each, does not hold where it fails for one."""
    return HOLDS if all(v == HOLDS for v in verdicts) else DOES_NOT_HOLD if DOES_NOT_HOLD in verdicts else INCONCLUSIVE


def layout_name(grids: str) -> str:
    return grids.removesuffix("_in_7x7").removesuffix("_7x7")


def per_task_differences(first: np.ndarray, second: np.ndarray, names: list[str], aggregate=mean
                         ) -> tuple[str, list[str]]:
    """("cramped_room 1.64 vs 1.24: +0.40 [...]", ...) per task, and each task's verdict of first > second."""
    parts, verdicts = [], []
    for t, name in enumerate(names):
        gap = difference(first[:, [t]], second[:, [t]], aggregate)
        verdicts.append(verdict(gap))
        parts.append(f"{name} {aggregate(first[:, [t]]):.2f} vs {aggregate(second[:, [t]]):.2f}: {signed(gap)}")
    return "; ".join(parts), verdicts


def signed(estimate: Estimate) -> str:
    return f"{estimate.value:+.2f} [{estimate.low:+.2f}, {estimate.high:+.2f}]"



# --------------------------------------------------------------------------------------------- the claims
def beats_across_layouts(scores: SeedScores, ik: str, sk: dict[str, str], kind: str, claim: str) -> list[Row]:
    """IK's `kind` against each layout's SK condition: the difference of means over the layouts (stratified per
    layout), with each layout's own difference and verdict."""
    first = scores.matrix([(ik, layout) for layout in sk], kind)
    second = scores.matrix([(condition, layout) for layout, condition in sk.items()], kind)
    if first is None or second is None:
        return []
    gap = difference(first, second)
    each, verdicts = per_task_differences(first, second, [layout_name(layout) for layout in sk])
    return [(claim, f"IK - SK, mean over the {len(sk)} layouts: {signed(gap)} ({seeds(first, second)}); {each}",
             f"{verdict(gap)}; per layout {counted(verdicts, 'layouts')}")]


def family_claims(scores: SeedScores, family: str, ik: str, sk: dict[str, str], budget: int,
                  paper: str | None = None) -> list[Row]:
    """The paper's claims for one family (an IK condition, layout -> its SK condition) at this budget (env steps per
    team). A family without SK conditions has only its held-out claim; `paper`: the paper's family whose held-out
    figure applies (default: this one's name)."""
    heldout = scores.heldout
    rows = []
    if sk:
        rows += beats_across_layouts(scores, ik, sk, "xp", "IK beats SK in cross-play on the 5 layouts (Fig. 3a)")
        sk_sp = scores.matrix([(condition, heldout) for condition in sk.values()], "sp") if heldout else None
        if sk_sp is not None:
            estimate = interval(sk_sp, mean)
            rows.append((f"SK scores 0 on generated levels, even in self-play (Fig. 7): below {SK_ZERO}",
                         f"SK self-play on {heldout}, mean over the {len(sk)} SK conditions: {estimate} "
                         f"({seeds(sk_sp)} each)", verdict(estimate, SK_ZERO, above=False)))
    ik_xp = scores.matrix([(ik, heldout)], "xp") if heldout else None
    if ik_xp is not None and (paper or family) in PAPER_HELDOUT_XP:
        target = PAPER_HELDOUT_XP[paper or family]
        estimate = interval(ik_xp, mean)
        rows.append((f"IK reaches about {target} deliveries in cross-play on held-out levels at 2e9 steps (Fig. 7)",
                     f"IK cross-play on {heldout}: {estimate} ({seeds(ik_xp)})",
                     verdict(estimate, target - 1) if budget >= PAPER_STEPS
                     else f"{budget:.1e} steps, not 2e9: not comparable"))
    if sk:
        rows += smaller_gap(scores, ik, sk)
        rows += beats_across_layouts(scores, ik, sk, "partner", "IK plays with a partner outside its population "
                                     "better than SK: the scripted cook")
        rows += beside_human_proxies(scores, ik)
    return rows


def smaller_gap(scores: SeedScores, ik: str, sk: dict[str, str]) -> list[Row]:
    """The SP - XP gap of each seed, SK's against IK's over the layouts."""
    def gaps(tasks):
        sp, xp = scores.matrix(tasks, "sp"), scores.matrix(tasks, "xp")
        return None if sp is None or xp is None or sp.shape != xp.shape else sp - xp

    ik_gap = gaps([(ik, layout) for layout in sk])
    sk_gap = gaps([(condition, layout) for layout, condition in sk.items()])
    if ik_gap is None or sk_gap is None:
        return []
    gap = difference(sk_gap, ik_gap)
    return [("The SP - XP gap is smaller for IK (Fig. 3b)",
             f"SK's gap - IK's, mean over the {len(sk)} layouts: {signed(gap)} (IK {mean(ik_gap):.2f}, SK "
             f"{mean(sk_gap):.2f}; {seeds(ik_gap, sk_gap)})", verdict(gap))]


def beside_human_proxies(scores: SeedScores, ik: str) -> list[Row]:
    """IK beside each grid's human proxy against two proxies together, over the grids where proxies were seated."""
    grids = scores.grids(ik, "human")
    team = scores.matrix([(ik, g) for g in grids], "human") if grids else None
    proxies = scores.matrix([(HUMAN_PROXY_RUN.format(grid=g).split("/")[0], g) for g in grids], "sp")
    if team is None or proxies is None:
        return []
    gap = difference(team, proxies)
    return [("IK plays with a partner outside its population: beside a human proxy, above two proxies together",
             f"IK beside a proxy - two proxies, mean over {len(grids)} layouts: {signed(gap)} ({seeds(team)}); "
             + ", ".join(f"{layout_name(g)} {mean(team[:, [t]]):.2f} (two proxies {proxies[0, t]:.2f})"
                         for t, g in enumerate(grids)), verdict(gap))]


def shared_teacher(scores: SeedScores, ik: str, partner: str) -> list[Row]:
    """Each IK seed's cross-play with its own condition's seeds against its cross-play with `partner`'s (teams that
    imitated another teacher, or learned otherwise), on the held-out levels: what a shared teacher adds."""
    heldout = scores.heldout
    within = scores.runs(ik, heldout, "xp") if heldout else np.empty(0)
    across = scores.runs(ik, heldout, "cross", partner) if heldout else np.empty(0)
    if within.size == 0 or within.size != across.size:
        return []
    paired = interval((within - across)[:, None], mean)
    return [(f"Imitating one teacher inflates cross-play (IK x IK against IK x {partner})",
             f"{heldout}: {within.mean():.2f} against {across.mean():.2f}, paired by seed {signed(paired)} "
             f"({seeds(within[:, None])})", verdict(paired))]


def beyond_teacher(scores: SeedScores, ik: str) -> list[Row]:
    """IK's self-play and cross-play on the held-out levels against the scripted cook's own self-play there."""
    heldout = scores.heldout
    cook = scores.runs(SCRIPTED_CONDITION, heldout, "sp") if heldout else np.empty(0)
    rows = []
    for kind, name in (("sp", "self-play"), ("xp", "cross-play")):
        team = scores.matrix([(ik, heldout)], kind) if heldout else None
        if team is None or cook.size == 0:
            continue
        estimate = interval(team, mean)
        rows.append((f"A team beyond its teacher: IK's {name} above the scripted cook's own self-play on held-out "
                     "levels", f"{heldout}: IK {estimate} ({seeds(team)}); the cook {cook.mean():.2f}",
                     verdict(estimate, float(cook.mean()))))
    return rows


def beats_beside_strangers(scores: SeedScores, ik: str, sk: dict[str, str], learned: bool = False) -> list[Row]:
    """IK against SK beside the held-out strangers (the learned strangers with `learned`) on each layout: tasks are
    layout x stranger."""
    firsts, seconds = [], []
    for layout, condition in sk.items():
        first, second = scores.strangers(ik, layout, learned=learned), scores.strangers(condition, layout,
                                                                                       learned=learned)
        if first is None or second is None or first[1] != second[1]:
            return []
        firsts.append(first[0])
        seconds.append(second[0])
    if not firsts or len({m.shape[0] for m in firsts}) > 1 or len({m.shape[0] for m in seconds}) > 1:
        return []
    gap = difference(np.concatenate(firsts, axis=1), np.concatenate(seconds, axis=1))
    per_layout = [difference(a, b) for a, b in zip(firsts, seconds)]
    each = "; ".join(f"{layout_name(layout)} {mean(a):.2f} vs {mean(b):.2f}: {signed(g)}"
                     for layout, a, b, g in zip(sk, firsts, seconds, per_layout))
    kind = "learned strangers (policies)" if learned else "held-out strangers (scripted)"
    return [(f"IK beats SK beside {kind} on the 5 layouts (Fig. 3a, with partners no team saw)",
             f"IK - SK, mean over {len(sk)} layouts x {firsts[0].shape[1]} strangers: {signed(gap)} "
             f"({seeds(firsts[0], seconds[0])}); {each}",
             f"{verdict(gap)}; per layout {counted([verdict(g) for g in per_layout], 'layouts')}")]


def lower_inflation(scores: SeedScores, one: str, diverse: str) -> list[Row]:
    """Each seed's cross-play between seeds minus its play with strangers, on the held-out levels: one teacher's
    against diverse teachers'."""
    heldout = scores.heldout
    inflation = {}
    for condition in (one, diverse):
        xp, met = scores.runs(condition, heldout, "xp"), scores.strangers(condition, heldout)
        if met is None or xp.size != met[0].shape[0]:
            return []
        inflation[condition] = (xp - met[0].mean(axis=1))[:, None]
    gap = difference(inflation[one], inflation[diverse])
    return [("Diverse teachers lower the cross-play inflation of one teacher (XP between seeds minus play with "
             "strangers)", f"{heldout}: {one} {mean(inflation[one]):+.2f}, {diverse} {mean(inflation[diverse]):+.2f}; "
             f"one's - diverse's {signed(gap)} ({seeds(inflation[one], inflation[diverse])})", verdict(gap))]


def zoo_raises(scores: SeedScores, one: str, zoo: str) -> list[Row]:
    """The normalised score's IQM beside the strangers (tasks: the strangers that cook), zoo partners' against
    one teacher's, on the held-out levels."""
    heldout = scores.heldout
    first, second = scores.strangers(zoo, heldout, "normalised"), scores.strangers(one, heldout, "normalised")
    if first is None or second is None or first[1] != second[1]:
        return []
    gap = difference(first[0], second[0], iqm)
    return [("Zoo partners in training raise play with strangers on held-out levels (normalised IQM)",
             f"{zoo} {interval(first[0])} against {one}'s {interval(second[0])}; difference {signed(gap)} "
             f"({seeds(first[0], second[0])})", verdict(gap))]


def beside_every_stranger(scores: SeedScores, condition: str, key: str, threshold: float, claim: str) -> list[Row]:
    """Per stranger, the mean over seeds of `key` (normalised, or over the best response) against `threshold`; the
    claim holds beside every stranger only where it holds beside each."""
    heldout = scores.heldout
    met = scores.strangers(condition, heldout, key) if heldout else None
    if met is None:
        return []
    table, names = met
    estimates = [interval(table[:, [s]], mean) for s in range(len(names))]
    verdicts = [verdict(estimate, threshold) for estimate in estimates]
    return [(claim, f"{counted(verdicts, 'strangers')} ({seeds(table)}): "
             + ", ".join(f"{name} {estimate}" for name, estimate in zip(names, estimates)), all_of(verdicts))]


def stranger_claims(scores: SeedScores, families: dict, compared: dict) -> list[tuple[str, str, Row]]:
    """(condition or family, role, row) beside the held-out strangers: each family's IK against its SK teams; and,
    of the conditions `compared` names (one_teacher, diverse_teachers, zoo_partners), the cross-play a shared
    teacher adds over play with strangers, whether zoo partners raise play with strangers, and whether a condition
    is a better partner to every stranger than that stranger's own kind, and nine tenths of its best response."""
    rows = []
    for family, (ik, sk, learner, _) in families.items():
        if sk:
            rows += [(family, learner, row) for learned in (False, True)
                     for row in beats_beside_strangers(scores, ik, sk, learned)]
    if not scores.heldout:
        return rows
    role = {condition: f"compared as {key.replace('_', ' ')}" for key, condition in compared.items()}
    one, diverse, zoo = (compared.get(key) for key in ("one_teacher", "diverse_teachers", "zoo_partners"))
    if one and diverse:
        rows += [(diverse, role[diverse], row) for row in lower_inflation(scores, one, diverse)]
    if one and zoo:
        rows += [(zoo, role[zoo], row) for row in zoo_raises(scores, one, zoo)]
    for condition in dict.fromkeys(c for c in (one, diverse, zoo) if c):
        rows += [(condition, role[condition], row) for row in beside_every_stranger(
            scores, condition, "normalised", 1.0,
            "Beyond each stranger's own kind: normalised > 1.0 beside every stranger on held-out levels")]
        rows += [(condition, role[condition], row) for row in beside_every_stranger(
            scores, condition, "over_best_response", BR_PROX_GOAL,
            f"As good a partner as a best response: BR-Prox >= {BR_PROX_GOAL} beside every stranger on held-out "
            "levels (moonshot)")]
    return rows

