"""What an evaluation's config is (`kitchen-eval`): `EvalConfig`."""

from __future__ import annotations

from dataclasses import dataclass

from jax_env import EXPANDED_LAYOUTS
from jax_env.generator import NUM_HELDOUT_GENERATED
from jax_env.generator import SIZES as GENERATOR_SIZES
from trainers.config.schema import ConfigError, at_least, check_device, check_seed, check_types, option
from trainers.config.sections import DeviceConfig

EVAL_COLLECTORS = ("kitchen", "xla")  # EvalConfig.collector: torch at every step, or whole episodes in XLA


@dataclass
class EvalConfig:
    """The self-play / cross-play evaluation of populations of trained teams (`kitchen-eval`).

    Every ordered pair of teams within a condition plays (i == j: self-play, i != j: cross-play), and so does
    every pair across the conditions named in `cross`; each pair plays `rollouts` episodes on every test grid.
    """

    # --- who plays
    conditions: dict[str, str | list[str]] = option(
        {}, "condition name -> its teams' run dirs or globs", group="who plays"
    )
    cross: list[list[str]] = option([], "[[cond_a, cond_b], ...] to cross-play")
    partner: bool = option(True, "every team also plays with the scripted cook, a partner outside every population")
    human_proxies: str = option(
        "", "a folder of human proxies (`kitchen-humans train`: human_proxy_<layout>/seed0): every team also plays "
        "with the proxy of each test grid that has one, both seats (e.g. runs; empty: none)"
    )

    strangers: str = option(
        "", "a zoo file (`kitchen-zoo`; the shipped one: configs/zoo/zoo.yaml): every team also plays beside each of "
        "its held-out strangers, both seats, on every test grid, scored against two of the stranger (empty: none)"
    )
    best_responses: dict[str, str] = option(
        {}, "held-out stranger -> the run of its best response (kitchen-train algorithm=zoo_ippo "
            "algorithm_config.best_response_to=NAME): the teams are also scored over it (BR-Prox)"
    )
    learned_strangers: dict[str, str | list[str]] = option(
        {}, "name -> runs or globs of learned strangers (policies no evaluated team met: learned_stranger runs, "
            "whose snapshots each join, or teams trained apart), seated beside every team as the strangers are"
    )

    # --- where and how long
    layouts: list[str] = option(
        list(EXPANDED_LAYOUTS), "test grids: layout names or text-grid files", group="where and how long"
    )
    heldout: int = option(NUM_HELDOUT_GENERATED, "the first N of the 100 held-out generated levels")
    kitchen_size: int = option(7, "the side of the held-out generated levels: 7, or 9 for teams trained at 9x9")
    rollouts: int = option(100, "episodes per pair and grid, actions sampled")
    max_steps: int = option(256, "episode length")

    # --- execution
    max_envs: int = option(
        8192, "kitchens stepped together (pairs x rollouts x grids are cut into batches of this)", group="execution"
    )
    workers: int = option(1, "processes that play the batches at once, each on a core of its own (the same numbers "
                          "with any)")
    collector: str = option(
        "xla", 'how the pairs play: "xla" (a batch whose teams are all feed-forward networks or scripted cooks plays '
        'inside one XLA program, actions drawn by JAX; the others as "kitchen") or "kitchen" (torch acts at every '
        "step)")
    seed: int = option(0, "the same seed gives the same numbers")
    progress: bool = option(True, "a progress bar")
    runtime: DeviceConfig = option(DeviceConfig(), "where it runs: the same numbers on any threads", group="runtime")

    # --- outputs
    out_dir: str = option("results/eval", "the folder of the tables, figures and GIFs", group="outputs")
    gifs: list[str] = option([], '"cond/seed0+cond/seed1@grid": agent 0, agent 1, grid')
    heatmaps: list[str] = option([], "grids on which to draw the cells agents visit")

    def check(self) -> EvalConfig:
        """Refuses values no evaluation can use, before any work starts."""
        check_types(self)
        if self.kitchen_size not in GENERATOR_SIZES:
            raise ConfigError(f"kitchen_size must be one of {', '.join(map(str, GENERATOR_SIZES))}, got "
                              f"{self.kitchen_size}")
        check_seed(self.seed)
        at_least(self, ["rollouts", "max_steps", "max_envs", "workers"], 1)
        at_least(self.runtime, ["threads"], 1, "runtime.")
        if self.collector not in EVAL_COLLECTORS:
            raise ConfigError(f"collector={self.collector!r}: choose one of {', '.join(EVAL_COLLECTORS)}")
        if not 0 <= self.heldout <= NUM_HELDOUT_GENERATED:
            raise ConfigError(
                f"heldout must be between 0 and {NUM_HELDOUT_GENERATED} (the held-out levels), got {self.heldout}"
            )
        if not self.layouts and not self.heldout:
            raise ConfigError("nothing to evaluate on: give layouts or heldout > 0")
        for pair in self.cross:
            if len(pair) != 2:
                raise ConfigError(f"cross holds pairs of condition names, got {pair!r}")
            for name in pair:
                if name not in self.conditions:
                    raise ConfigError(
                        f"cross names the condition {name!r}, which is not among the conditions: "
                        f"{', '.join(self.conditions) or '(none)'}"
                    )
        check_device(self.runtime.device, "runtime.device")
        return self

