"""IPPO with zoo partners in the batch: in a share of its kitchens, one seat is a scripted cook of a convention from
the zoo's training split, the other the learner (population play on the Infinite Kitchen, the paper's future work).

Each episode of each kitchen draws whether a zoo cook plays, its seat and its convention (`ZooSeats`, with a
generator of its own that checkpoints keep, so a resumed run draws what an unstopped one would); the cook acts in
its seat (`ZooPartners`). PPO learns from the learner's transitions only (TorchRL's `loss_mask_key`), with the
advantages standardised over those. A held-out stranger named here is refused: strangers only evaluate, but for
`best_response_to`, which trains an evaluation instrument (ZSC-Eval's best response, for BR-Prox) beside one
stranger in every kitchen.
"""

from __future__ import annotations

from dataclasses import dataclass

from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Transform
from torchrl.objectives import ClipPPOLoss

from torch_kitchen.keys import AGENTS
from torch_kitchen.models import ActorCritic
from torch_kitchen.partners.conventions import Convention, ConventionError, load_zoo
from torch_kitchen.partners.zoo_seats import LEARNER, ZOO_COOK, ZooPartners, ZooSeats
from trainers.algorithms.base import Algorithm, standardize_advantage
from trainers.config import ConfigError, TrainConfig, option

LEARNS = (AGENTS, "learns")  # bool [B, T, 2]: the transitions PPO learns from (the learner's seats)


@dataclass
class ZooSettings:
    """The settings of `algorithm: zoo_ippo` (its `algorithm_config`)."""

    zoo_share: float = option(0.25, "the share of kitchens where one seat is a zoo cook, the other the learner")
    zoo_conventions: list[str] = option([], "the zoo's training conventions to draw from (empty: all of them)")
    best_response_to: str = option(
        "", "a held-out stranger of the zoo: train its best response, beside it in every kitchen (an evaluation "
            "instrument, `kitchen-eval best_responses`: never a team to evaluate)"
    )

    def check(self) -> None:
        if not 0.0 <= self.zoo_share <= 1.0:
            raise ConfigError(f"algorithm_config.zoo_share must lie in [0, 1], got {self.zoo_share}")
        if self.best_response_to and self.zoo_conventions:
            raise ConfigError("algorithm_config.best_response_to trains beside one stranger alone: leave "
                              "zoo_conventions empty")

    @property
    def share(self) -> float:
        """The share of kitchens with a zoo cook: all of them for a best response."""
        return 1.0 if self.best_response_to else self.zoo_share


def training_conventions(config: TrainConfig, settings: ZooSettings) -> list[Convention]:
    """The conventions a run draws its zoo cooks from: `zoo_conventions` of the training split of the run's zoo
    (`zoo`; all of them for an empty list), or the one stranger of `best_response_to`; a stranger named otherwise,
    an unknown name or a zoo of another kitchen size is a ConfigError in one line."""
    try:
        zoo = load_zoo(config.zoo, config.kitchen_size)
        if settings.best_response_to:
            return [zoo.convention(settings.best_response_to, splits=("stranger",))]
        names = settings.zoo_conventions
        return [zoo.convention(name, splits=("train",)) for name in names] if names else zoo.training
    except ConventionError as error:
        raise ConfigError(str(error)) from None


class ZooIPPO(Algorithm):
    Settings = ZooSettings
    shardable = False  # its loss averages over the learner's transitions, which shards split unevenly
    stackable = False  # each team draws its own seats

    @classmethod
    def check_config(cls, config: TrainConfig) -> None:
        super().check_config(config)
        training_conventions(config, cls.settings_of(config))

    def __init__(self, config: TrainConfig, actor_critic: ActorCritic):
        super().__init__(config, actor_critic)
        self.conventions = self.met_conventions(config)
        self.seats = ZooSeats(len(self.conventions), self.settings.share, config.seed)

    def env_transforms(self) -> list[Transform]:
        return [self.seats]

    @classmethod
    def met_conventions(cls, config: TrainConfig) -> list[Convention]:
        return training_conventions(config, cls.settings_of(config))

    def acting_modules(self) -> list[TensorDictModuleBase]:
        return [ZooPartners(self.conventions).to(self.config.runtime.device)]

    def configure_loss(self, loss: ClipPPOLoss) -> None:
        loss.loss_mask_key = LEARNS

    def process_batch(self, batch: TensorDictBase) -> None:
        batch.set(LEARNS, batch.get(ZOO_COOK) == LEARNER)

    def process_minibatch(self, minibatch: TensorDictBase) -> None:
        standardize_advantage(minibatch, where=minibatch.get(LEARNS))  # the cooks' transitions are not the policy's

    def state_dict(self) -> dict:
        return {"zoo_seats": self.seats.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.seats.load_state_dict(state["zoo_seats"])

