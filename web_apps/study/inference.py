"""A study's numbers by participant: a person's games are one person's, never as many independent people.

    participant_interval   a condition's mean deliveries (the mean of each participant's mean), with a 95% bootstrap
                           interval that resamples participants, each with all of its games
    fit_mixed_model        deliveries ~ condition + kitchen + position with a random intercept per participant
                           (statsmodels' MixedLM): each contrast between two conditions, its 95% interval and p-value
    holm                   Holm's step-down correction of several p-values
    sign_test              the forced choice: how often the first of a pair was chosen over the second, a two-sided
                           binomial test against one half

The questions each answers: is the primary contrast (the config's `primary`, a - b) different from zero, with the
kitchens and positions held apart (the mixed model's contrast, its interval and p); are the other pairs different
(the same model's contrasts, Holm-corrected); what does a condition deliver per participant (the bootstrap
interval); do people prefer one partner (the sign test).
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

CONFIDENCE = 0.95
RESAMPLES = 2000


@dataclass(frozen=True)
class Observation:
    """One counted game: who played it, beside which condition, on which kitchen, at which position, and its
    deliveries."""

    participant: int
    condition: str
    kitchen: str
    position: int
    deliveries: float


@dataclass(frozen=True)
class Contrast:
    """first - second in deliveries per game, with the kitchens, positions and participants held apart."""

    first: str
    second: str
    estimate: float
    low: float
    high: float
    p: float
    p_holm: float = float("nan")


def per_participant(observations: Sequence[Observation], condition: str) -> dict[int, float]:
    """Each participant's mean deliveries beside `condition` (those who played it)."""
    games: dict[int, list[float]] = {}
    for observation in observations:
        if observation.condition == condition:
            games.setdefault(observation.participant, []).append(observation.deliveries)
    return {participant: float(np.mean(values)) for participant, values in games.items()}


def participant_interval(observations: Sequence[Observation], condition: str, seed: int = 0
                         ) -> tuple[float, float, float, int]:
    """(mean, low, high, participants): the mean over participants of their mean deliveries beside `condition`,
    and its 95% percentile bootstrap interval over participants (each resampled with all its games there)."""
    means = np.asarray(list(per_participant(observations, condition).values()))
    if len(means) < 2:
        return (float(means.mean()) if len(means) else float("nan")), float("nan"), float("nan"), len(means)
    draws = np.random.default_rng(seed).integers(0, len(means), size=(RESAMPLES, len(means)))
    resampled = means[draws].mean(axis=1)
    tail = (1 - CONFIDENCE) / 2 * 100
    low, high = np.percentile(resampled, [tail, 100 - tail])
    return float(means.mean()), float(low), float(high), len(means)


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values, in the given order (NaN stays NaN)."""
    p = np.asarray(p_values, dtype=float)
    adjusted = np.full(len(p), np.nan)
    valid = np.flatnonzero(~np.isnan(p))
    order = valid[np.argsort(p[valid])]
    running = 0.0
    for rank, index in enumerate(order):
        running = max(running, min(1.0, (len(order) - rank) * p[index]))
        adjusted[index] = running
    return adjusted.tolist()


def fit_games(observations: Sequence[Observation], conditions: Sequence[str], kitchens: Sequence[str] | None = None,
              positions: bool = True):
    """statsmodels' MixedLM of deliveries on the condition (levels `conditions`, the first the reference), the
    kitchen (levels `kitchens`, else as found) and the position (with `positions`), each where it varies, with a
    random intercept per participant, fitted by REML; None where it cannot be fitted (fewer than two participants,
    or conditions confounded with kitchens or positions)."""
    import pandas as pd
    from statsmodels.regression.mixed_linear_model import MixedLM

    frame = pd.DataFrame([vars(observation) for observation in observations])
    if frame.empty or frame["participant"].nunique() < 2:
        return None
    frame["condition"] = pd.Categorical(frame["condition"], categories=list(conditions))
    if kitchens is not None:
        frame["kitchen"] = pd.Categorical(frame["kitchen"], categories=list(kitchens))
    terms = ["C(condition)"]
    if frame["kitchen"].nunique() > 1:
        terms.append("C(kitchen)")
    if positions and frame["position"].nunique() > 1:
        terms.append("C(position)")
    model = MixedLM.from_formula(f"deliveries ~ {' + '.join(terms)}", frame, groups=frame["participant"])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # convergence notes on tiny studies; the intervals say how sure it is
        try:
            return model.fit(reml=True)
        except (np.linalg.LinAlgError, ValueError):  # conditions confounded with kitchens or positions
            return None


def fit_mixed_model(observations: Sequence[Observation], conditions: Sequence[str],
                    primary: tuple[str, str]) -> list[Contrast]:
    """The mixed model of the module docstring, fitted by restricted maximum likelihood, as contrasts: the primary
    one first (not corrected), then every other pair of conditions, Holm-corrected among themselves. Empty where the
    model cannot be fitted (fewer than two participants, a single condition, or conditions confounded with kitchens
    or positions)."""
    reference = primary[1]
    present = {observation.condition for observation in observations}
    if len(present) < 2:
        return []
    levels = [reference, *(c for c in conditions if c != reference and c in present)]
    result = fit_games(observations, levels)
    if result is None:
        return []
    names = list(result.fe_params.index)

    def contrast(first: str, second: str) -> Contrast:
        vector = np.zeros(len(names))
        for condition, sign in ((first, 1.0), (second, -1.0)):
            if condition != reference:
                vector[names.index(f"C(condition)[T.{condition}]")] += sign
        test = result.t_test(vector.reshape(1, -1))
        low, high = np.asarray(test.conf_int(alpha=1 - CONFIDENCE)).ravel()
        return Contrast(first, second, float(np.asarray(test.effect).ravel()[0]), float(low), float(high),
                        float(np.asarray(test.pvalue).ravel()[0]))

    head = contrast(*primary)
    others = [contrast(a, b) for a, b in itertools.combinations(levels, 2) if {a, b} != set(primary)]
    adjusted = holm([other.p for other in others])
    return [head, *(Contrast(o.first, o.second, o.estimate, o.low, o.high, o.p, p) for o, p in zip(others, adjusted))]


def sign_test(chosen: int, not_chosen: int) -> float:
    """The two-sided binomial test's p-value that a choice between two partners is a coin's (NaN for none)."""
    total = chosen + not_chosen
    return float(stats.binomtest(chosen, total, 0.5).pvalue) if total else float("nan")
