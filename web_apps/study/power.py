"""How many participants a study needs: power by simulation from a fitted model (`kitchen-study power STUDY_DIR`).

The study's games (its `analysis/games.csv`, `kitchen-study analyse` writes it; a real pilot's or a simulated one's)
fit the report's mixed model (`web_apps.study.inference`): the conditions' and kitchens' effects, the spread of the
participants' skill and of the games. Studies of N participants are then drawn from that model over the config's
design (`web_apps.study.assignment`: each participant a row of it, in arrival order) and analysed as the report
analyses them; the power at N is the share whose primary contrast is called at alpha (p below it), with a 95%
interval. Written into STUDY_DIR/analysis/: power.md (the table and the smallest N with 80% power) and power.png.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from web_apps.study.assignment import design_row
from web_apps.study.config import StudyConfig, StudyError
from web_apps.study.inference import Observation, fit_games, fit_mixed_model

SIZES = (8, 12, 16, 24, 32, 48, 64, 96, 128, 200)  # participants per simulated study
TARGET = 0.8  # the power a study is sized for


@dataclass(frozen=True)
class Model:
    """What a simulated game's deliveries are drawn from: the intercept, each condition's and kitchen's effect (the
    first of each at 0), the participants' skill spread and the games' spread."""

    intercept: float
    conditions: dict[str, float]
    kitchens: dict[str, float]
    participant_sd: float
    game_sd: float

    def draw(self, config: StudyConfig, participants: int, rng: np.random.Generator) -> list[Observation]:
        """A study of `participants` people over the config's design, each a row of it in arrival order."""
        observations = []
        for person in range(participants):
            skill = rng.normal(0.0, self.participant_sd)
            for position, (condition, kitchen) in enumerate(design_row(config, person)):
                mean = self.intercept + self.conditions[condition] + self.kitchens.get(kitchen, 0.0) + skill
                observations.append(Observation(person, condition, kitchen, position,
                                                float(mean + rng.normal(0.0, self.game_sd))))
        return observations


def fit_model(observations: list[Observation], config: StudyConfig) -> Model:
    """The model of a study's games: MixedLM with the conditions and kitchens as fixed effects, a random intercept
    per participant."""
    present = {observation.condition for observation in observations}
    kitchens = {observation.kitchen for observation in observations}
    result = fit_games(observations, [c for c in config.conditions if c in present],
                       [k for k in config.kitchens if k in kitchens], positions=False)
    if result is None:
        raise StudyError("the power needs a study with games of two participants at least, its conditions not "
                         "confounded with its kitchens: analyse a pilot first")
    effects = result.fe_params
    return Model(
        intercept=float(effects["Intercept"]),
        conditions={c: float(effects.get(f"C(condition)[T.{c}]", 0.0)) for c in config.conditions},
        kitchens={k: float(effects.get(f"C(kitchen)[T.{k}]", 0.0)) for k in config.kitchens},
        participant_sd=float(np.sqrt(max(result.cov_re.iloc[0, 0], 0.0))),
        game_sd=float(np.sqrt(result.scale)),
    )


def power_curve(model: Model, config: StudyConfig, sizes=SIZES, studies: int = 200, alpha: float = 0.05,
                seed: int = 0) -> dict[int, float]:
    """N -> the share of `studies` simulated studies of N participants whose primary contrast has p < alpha."""
    rng = np.random.default_rng(seed)
    primary = config.primary_contrast
    curve = {}
    for size in sizes:
        called = 0
        for _ in range(studies):
            contrasts = fit_mixed_model(model.draw(config, size, rng), list(config.conditions), primary)
            called += bool(contrasts) and contrasts[0].p < alpha
        curve[size] = called / studies
    return curve


def games_of(folder: Path) -> list[Observation]:
    """The counted games of a study's analysis (`analysis/games.csv`)."""
    path = folder / "analysis" / "games.csv"
    if not path.is_file():
        raise StudyError(f"{path} is missing: run `kitchen-study analyse {folder}` first")
    with open(path) as handle:
        return [Observation(int(row["participant"]), row["condition"], row["kitchen"], int(row["position"]),
                            float(row["deliveries"])) for row in csv.DictReader(handle)]


def write_power(config: StudyConfig, folder: Path, studies: int = 200, alpha: float = 0.05, sizes=SIZES
                ) -> tuple[Path, int | None]:
    """power.md and power.png in the study's analysis folder; returns power.md and the smallest N with `TARGET`
    power (None: none of `sizes`)."""
    model = fit_model(games_of(folder), config)
    curve = power_curve(model, config, sizes, studies, alpha)
    enough = next((size for size, power in curve.items() if power >= TARGET), None)
    first, second = config.primary_contrast
    half = {size: 1.96 * np.sqrt(power * (1 - power) / studies) for size, power in curve.items()}
    lines = [f"# Study {config.name}: how many participants", "",
             f"The model fitted to the study's counted games ({folder / 'analysis' / 'games.csv'}): {first} - "
             f"{second} {model.conditions[first] - model.conditions[second]:+.2f} deliveries per game, participants' "
             f"skill sd {model.participant_sd:.2f}, games' sd {model.game_sd:.2f}. Each size: {studies} studies drawn "
             f"from it over the config's design and analysed as the report does; power: the share whose primary "
             f"contrast has p < {alpha} (95% interval).", "",
             "| participants | power | 95% interval |", "|---:|---:|---|"]
    lines += [f"| {size} | {power:.2f} | [{max(0.0, power - half[size]):.2f}, {min(1.0, power + half[size]):.2f}] |"
              for size, power in curve.items()]
    lines += ["", f"The smallest N with {TARGET:.0%} power: "
              + (f"**{enough}**." if enough else f"more than {max(sizes)}."), "", "![power](power.png)", ""]
    out = folder / "analysis" / "power.md"
    out.write_text("\n".join(lines))
    plot_power(curve, half, out.with_suffix(".png"))
    return out, enough


def plot_power(curve: dict[int, float], half: dict[int, float], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(5.5, 3.4))
    sizes = list(curve)
    axes.errorbar(sizes, [curve[n] for n in sizes], yerr=[half[n] for n in sizes], marker="o", capsize=3)
    axes.axhline(TARGET, color="grey", linestyle="--", linewidth=1)
    axes.set_xscale("log")
    axes.set_xticks(sizes, [str(n) for n in sizes])
    axes.set_xlabel("participants")
    axes.set_ylabel("power of the primary contrast")
    axes.set_ylim(0, 1)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)
