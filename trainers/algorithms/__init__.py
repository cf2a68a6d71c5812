"""The algorithms of the PPO core, by name: `algorithm: <name>` in a config picks one.

    ippo   independent PPO in self-play (`trainers.algorithms.ippo`)
    e3t    E3T's mixed partner and partner predictor (`trainers.algorithms.e3t`)
    anchored_ippo   IPPO kept near its starting policy by a KL penalty (`trainers.algorithms.anchored`)
    kickstarted_ippo   IPPO with the scripted cook as a teacher all through training (`trainers.algorithms.kickstarted`)
    zoo_ippo   IPPO where a share of the kitchens seat a zoo cook beside the learner (`trainers.algorithms.zoo_ippo`)

Add one by subclassing `Algorithm` (its docstring lists the hooks; its `Settings` dataclass holds its own settings)
and calling `register_algorithm(name, cls)` before the config is checked; `examples/` and docs/extending.md show how.
"""

from __future__ import annotations

import dataclasses

from trainers.algorithms.anchored import AnchoredIPPO
from trainers.algorithms.base import Algorithm
from trainers.algorithms.e3t import E3T
from trainers.algorithms.ippo import IPPO
from trainers.algorithms.kickstarted import KickstartedIPPO
from trainers.algorithms.zoo_ippo import ZooIPPO
from trainers.config import ConfigError, TrainConfig

ALGORITHMS: dict[str, type[Algorithm]] = {"ippo": IPPO, "e3t": E3T, "anchored_ippo": AnchoredIPPO,
                                       "kickstarted_ippo": KickstartedIPPO, "zoo_ippo": ZooIPPO}


def register_algorithm(name: str, algorithm: type[Algorithm]) -> None:
    """Makes `algorithm: name` train with `algorithm`; a name can be registered once."""
    if name in ALGORITHMS:
        raise ValueError(f"algorithm {name!r} is already registered")
    if not (isinstance(algorithm, type) and issubclass(algorithm, Algorithm)):
        raise TypeError(f"an algorithm must be a subclass of trainers.algorithms.Algorithm, got {algorithm!r}")
    ALGORITHMS[name] = algorithm


def check_algorithm(config: TrainConfig) -> TrainConfig:
    """Refuses, with one line (ConfigError), an algorithm that is not registered and settings its class cannot
    train with (`Algorithm.settings_of`, `Algorithm.check_config`): what every command that trains checks beside
    `config.check()`. Returns the config with the algorithm's settings spelled out (its defaults where a key was
    not given), as a run saves it."""
    if config.algorithm not in ALGORITHMS:
        raise ConfigError(f"algorithm must be one of {', '.join(ALGORITHMS)}, got {config.algorithm!r}")
    algorithm = ALGORITHMS[config.algorithm]
    settings = algorithm.settings_of(config)  # its own settings, checked
    algorithm.check_config(config)
    return dataclasses.replace(config, algorithm_config=dataclasses.asdict(settings))


def algorithm_settings() -> dict[str, type]:
    """Each registered algorithm's settings dataclass, by name, for those that have settings (for `--help`)."""
    return {name: algorithm.Settings for name, algorithm in ALGORITHMS.items()
            if dataclasses.fields(algorithm.Settings)}


__all__ = ["ALGORITHMS", "Algorithm", "AnchoredIPPO", "E3T", "IPPO", "KickstartedIPPO", "algorithm_settings",
           "check_algorithm", "register_algorithm", "ZooIPPO"]
