"""The partner side of E3T (Yan et al., 2023): a context of the partner's recent actions, and a mixed partner.

Three pieces, used by the PPO core (`trainers/ppo/loop.py`) when `algorithm: e3t`:

`PartnerContext(k)` (an env transform; every E3T model needs it, in training and evaluation) carries for each
agent i the last k (observation of agent i, action of agent 1 - i) pairs, oldest first:

    ("agents", "context_observation")  uint8 [B, 2, k, H, W, C]  zeros before the episode's first step
    ("agents", "context_action")       int64 [B, 2, k]           NO_ACTION before the episode's first step

The context read at step t holds steps t-k .. t-1 of the same episode and never step t: it is written after the
step, from the action the partner actually took, and emptied where an episode starts. The partner predictor of
`torch_kitchen.models` reads it to predict the partner's action at step t.

`PartnerSeats` (a training transform) draws, for every kitchen and every episode, which agent plays the mixed
partner: ("agents", "mixed") bool [B, 2], exactly one True per kitchen, constant over the episode.

`PartnerMixture(epsilon)` (a policy module, after the actor) makes the mixed agent act from
(1 - epsilon) * pi + epsilon * uniform, pi the actor's own policy or a slowly updated copy of it, and records
the log-probability of that mixture for it. The other agent, the ego, acts from pi alone, so its recorded
log-probability is exactly that of the policy that acted: PPO trains on the ego's transitions only.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Categorical, Composite
from torchrl.envs import Transform

from jax_env import NUM_ACTIONS
from torch_kitchen.keys import ACTION, CONTEXT_ACTION, CONTEXT_OBSERVATION, LOG_PROB, LOGITS, MIXED, OBSERVATION

NO_ACTION = NUM_ACTIONS  # the context's padding token: one more than the real actions


def _reset_rows(tensordict: TensorDictBase, batch_size: torch.Size, device) -> torch.Tensor:
    """bool [B] on `device`: the kitchens a reset starts anew (all of them without a "_reset" mask); the seats'
    draws live on the CPU, where their generator is, whatever the kitchens' device."""
    mask = tensordict.get("_reset", None) if tensordict is not None else None
    if mask is None:
        return torch.ones(batch_size, dtype=torch.bool, device=device)
    return mask.reshape(batch_size).to(device)


class PartnerContext(Transform):
    """Each agent's last k (own observation, partner action) pairs, emptied at episode starts (module docstring)."""

    def __init__(self, length: int = 5):
        super().__init__(in_keys=[OBSERVATION, ACTION], out_keys=[CONTEXT_OBSERVATION, CONTEXT_ACTION])
        if length < 1:
            raise ValueError(f"the partner context needs at least one step, got length={length}")
        self.length = length

    def _empty(self, observation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        batch = observation.shape[:-3]  # [B, 2]
        context_obs = observation.new_zeros((*batch, self.length, *observation.shape[-3:]))
        context_action = torch.full((*batch, self.length), NO_ACTION, dtype=torch.int64, device=observation.device)
        return context_obs, context_action

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        context_obs, context_action = self._empty(tensordict_reset.get(OBSERVATION))
        carried_obs = tensordict.get(CONTEXT_OBSERVATION, None) if tensordict is not None else None
        if carried_obs is not None:  # a partial reset: the other kitchens keep their context
            fresh = _reset_rows(tensordict, tensordict_reset.batch_size, context_obs.device)
            context_obs = torch.where(fresh.view(*fresh.shape, 1, 1, 1, 1, 1), context_obs, carried_obs)
            context_action = torch.where(fresh.view(*fresh.shape, 1, 1), context_action,
                                         tensordict.get(CONTEXT_ACTION))
        tensordict_reset.set(CONTEXT_OBSERVATION, context_obs)
        tensordict_reset.set(CONTEXT_ACTION, context_action)
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        # The pair of this step, (own observation at t, partner's action at t), joins the context read at t + 1.
        partner_action = tensordict.get(ACTION).flip(-1)  # [*B, 2]
        context_obs, observation = tensordict.get(CONTEXT_OBSERVATION), tensordict.get(OBSERVATION)
        context_obs = torch.cat([context_obs[..., 1:, :, :, :], observation.unsqueeze(-4)], dim=-4)
        context_action = torch.cat([tensordict.get(CONTEXT_ACTION)[..., 1:], partner_action.unsqueeze(-1)], dim=-1)
        next_tensordict.set(CONTEXT_OBSERVATION, context_obs)
        next_tensordict.set(CONTEXT_ACTION, context_action)
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        agents = observation_spec["agents"]
        obs = agents["observation"]
        batch = obs.shape[:-3]
        agents["context_observation"] = Bounded(
            0, 255, shape=(*batch, self.length, *obs.shape[-3:]), dtype=obs.dtype, device=obs.device
        )
        agents["context_action"] = Categorical(
            NO_ACTION + 1, shape=(*batch, self.length), dtype=torch.int64, device=obs.device
        )
        return observation_spec


class PartnerSeats(Transform):
    """Draws the mixed agent of every kitchen at each episode start: ("agents", "mixed") bool [B, 2].

    Its own generator (seeded) makes the draws reproducible; `state_dict()` holds it and the current seats, and after
    `load_state_dict` the next full reset hands those seats out again, as `KitchenEnv` does its kitchens. A subclass
    draws other seatings by overriding `key`, `_draw`, `_seating` and `_spec` (`torch_kitchen.partners.zoo_seats`).
    """

    key = MIXED

    def __init__(self, seed: int = 0):
        super().__init__(in_keys=[], out_keys=[self.key])
        self.generator = torch.Generator().manual_seed(seed)
        self._seats: torch.Tensor | None = None  # long [B]: each kitchen's draw (here: its mixed agent)
        self._restored = False

    @property
    def draws(self) -> torch.Tensor | None:
        """long [B]: each kitchen's current draw; a rollout that draws the seats elsewhere (inside XLA) sets it, so
        that checkpoints keep it."""
        return self._seats

    @draws.setter
    def draws(self, draws: torch.Tensor) -> None:
        self._seats = draws

    def _draw(self, count: int) -> torch.Tensor:
        return torch.randint(2, (count,), generator=self.generator)

    def _seating(self, device) -> torch.Tensor:
        """The entry [B, 2] of the current draws."""
        return torch.nn.functional.one_hot(self._seats, 2).bool().to(device)

    def _spec(self, agents: Composite):
        return Categorical(2, shape=agents.shape, dtype=torch.bool, device=agents.device)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch_size = tensordict_reset.batch_size
        fresh = _reset_rows(tensordict, batch_size, torch.device("cpu"))
        if self._restored and bool(fresh.all()):
            self._restored = False
        elif self._seats is None or bool(fresh.all()):
            self._seats = self._draw(batch_size.numel())
        else:
            self._seats = self._seats.clone()
            self._seats[fresh] = self._draw(int(fresh.sum()))
        tensordict_reset.set(self.key, self._seating(tensordict_reset.device))
        return tensordict_reset

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        next_tensordict.set(self.key, tensordict.get(self.key))
        return next_tensordict

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        agents = observation_spec["agents"]
        agents[self.key[-1]] = self._spec(agents)
        return observation_spec

    def get_extra_state(self) -> dict:
        return {"generator": self.generator.get_state(), "seats": self._seats}

    def set_extra_state(self, state: dict) -> None:
        # Back to the CPU, where the generator draws: a checkpoint may have been loaded onto a GPU.
        self.generator.set_state(state["generator"].cpu())
        self._seats = None if state["seats"] is None else state["seats"].cpu()
        self._restored = self._seats is not None


class PartnerMixture(TensorDictModuleBase):
    """The mixed agent acts from (1 - epsilon) * pi + epsilon * uniform (see the module docstring).

    Runs after the sampling actor, on ("agents", "action" | "logits" | "action_log_prob" | "mixed").
    `partner`: an actor whose logits define pi for the mixed agent (a slowly updated copy of the ego); by default
    the logits the actor just wrote, and the action it sampled stands where the mixture keeps pi.
    """

    def __init__(self, epsilon: float, partner: TensorDictModuleBase | None = None):
        super().__init__()
        if not 0.0 <= epsilon <= 1.0:
            raise ValueError(f"the partner's epsilon must lie in [0, 1], got {epsilon}")
        self.epsilon = epsilon
        self.partner = partner
        self.in_keys = [ACTION, LOGITS, LOG_PROB, MIXED] + (list(partner.in_keys) if partner is not None else [])
        self.out_keys = [ACTION, LOG_PROB]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action, mixed = tensordict.get(ACTION), tensordict.get(MIXED)
        if self.partner is None:
            partner_logits, partner_action = tensordict.get(LOGITS), action
        else:
            with torch.no_grad():
                partner_logits = self.partner(tensordict.select(*self.partner.in_keys, strict=False)).get(LOGITS)
            partner_action = torch.distributions.Categorical(logits=partner_logits, validate_args=False).sample()
        uniform = torch.rand(mixed.shape, device=mixed.device) < self.epsilon
        random_action = torch.randint_like(action, NUM_ACTIONS)
        partner_action = torch.where(uniform, random_action, partner_action)
        action = torch.where(mixed, partner_action, action)
        # log((1 - eps) * pi(a) + eps / |A|) of the action the mixed agent took.
        pi = torch.softmax(partner_logits, -1).gather(-1, action.unsqueeze(-1)).squeeze(-1)
        log_mixture = torch.log((1 - self.epsilon) * pi + self.epsilon / NUM_ACTIONS)
        tensordict.set(ACTION, action)
        tensordict.set(LOG_PROB, torch.where(mixed, log_mixture, tensordict.get(LOG_PROB)))
        return tensordict

