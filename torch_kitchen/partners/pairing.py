"""Kitchens whose two seats are played by different teams: the policy of self-play and cross-play evaluation.

`SeatedPolicy(actors)` holds the actors of several teams. `seat(teams)` says, for every kitchen of the batch,
which team plays agent 0 and which plays agent 1 (long [B, 2]); a forward pass then runs each team's actor once
on the kitchens where it plays a seat and keeps, per seat, the logits of the team in that seat. Sampling
happens once, on those combined logits (`make_seated_actor` wraps it in a `ProbabilisticActor`), so the
kitchens' actions are drawn exactly as a team's own actor would draw them.

A team evaluates both agents of every kitchen it plays in and its output for the other seat is dropped: the
networks act on each agent's observation independently, so this costs compute (at most 2x) but never
changes what the seated agent does, and it keeps every architecture and parameter-sharing mode usable as is.

Recurrent state: a team's actor reads ("agents", "actor_h" | "actor_c") [*B, 2, 1, h]. Here seat s of kitchen b holds
the state of the team in that seat, under ("agents", "<name>_<h>") so that teams of different widths can meet;
`env_transforms()` gives the InitTracker and the primer that carry them, and the partner context
(`torch_kitchen.models.e3t_partner.PartnerContext`) when an E3T team plays. Every other entry a team's actor reads (its
observation, the partner context) is handed to it as the env wrote it.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import InitTracker, Transform
from torchrl.modules import ProbabilisticActor

from jax_env import NUM_ACTIONS
from torch_kitchen.keys import LOGITS, N_AGENTS, OBSERVATION
from torch_kitchen.models.acting import sampling_actor
from torch_kitchen.models.e3t_partner import PartnerContext
from torch_kitchen.models.partner_predictor import partner_context_length
from torch_kitchen.models.recurrence import agent_state_primer, recurrent_states


class SeatedPolicy(TensorDictModuleBase):
    """Logits ("agents", "logits") [B, 2, 6] of the teams seated in every kitchen (see the module docstring)."""

    def __init__(self, actors: list[TensorDictModuleBase]):
        super().__init__()
        self.actors = torch.nn.ModuleList(actors)
        # Per team: its state names -> the storage name (the state name suffixed with its width).
        self._storage: list[dict[str, str]] = []
        self._widths: dict[str, int] = {}  # storage name -> width
        self._inputs: list[list] = []  # per team: the entries its actor reads as they are
        for actor in actors:
            states = recurrent_states(actor)
            self._storage.append({name: f"{name}_{width}" for name, width in states.items()})
            self._widths.update({f"{name}_{width}": width for name, width in states.items()})
            own_states = {("agents", name) for name in states} | {"is_init"}
            self._inputs.append([key for key in actor.in_keys if key not in own_states])
        self.recurrent = bool(self._widths)
        contexts = {partner_context_length(actor) for actor in actors} - {0}
        if len(contexts) > 1:
            raise ValueError(f"teams read partner contexts of different lengths {sorted(contexts)}; one env "
                             "carries one context")
        self.context_length = contexts.pop() if contexts else 0
        state_keys = [("agents", name) for name in self._widths]
        inputs = list(dict.fromkeys(key for keys in self._inputs for key in keys))
        self.in_keys = inputs + (["is_init", *state_keys] if self.recurrent else [])
        self.out_keys = [LOGITS] + [("next", *key) for key in state_keys]
        # Per team: the kitchens it plays in, and per seat (where among them it plays that seat, those kitchens).
        self._rows: list[tuple[torch.Tensor, list[tuple[torch.Tensor, torch.Tensor]]]] = []
        self.seating: torch.Tensor | None = None  # long [B, 2]: the team of every seat, as `seat` was told

    def env_transforms(self) -> list[Transform]:
        """[InitTracker(), the primer of every stored state] if a team is recurrent, then the partner context if
        a team reads one."""
        transforms = [InitTracker(), agent_state_primer(self._widths)] if self.recurrent else []
        return transforms + ([PartnerContext(self.context_length)] if self.context_length else [])

    def seat(self, teams: torch.Tensor) -> SeatedPolicy:
        """Seats team teams[b, s] (an index into `actors`) as agent s of kitchen b, for the next forward passes."""
        if teams.ndim != 2 or teams.shape[1] != N_AGENTS:
            raise ValueError(f"teams must be [num_envs, {N_AGENTS}] team indices, got {list(teams.shape)}")
        if teams.numel() and not 0 <= int(teams.min()) <= int(teams.max()) < len(self.actors):
            raise ValueError(f"team indices must lie in [0, {len(self.actors)}), got {teams.unique().tolist()}")
        self.seating = teams
        self._rows = []
        for team in range(len(self.actors)):
            seated = teams == team  # [B, 2]
            rows = seated.any(-1).nonzero().squeeze(-1)
            # Per seat: where among `rows` the team plays it, and those kitchens. Found here, once per seating, so
            # that a step indexes by them and never waits to count a mask.
            places = [seated[rows, seat].nonzero().squeeze(-1) for seat in range(N_AGENTS)]
            self._rows.append((rows, [(place, rows[place]) for place in places]))
        self._num_envs = teams.shape[0]
        return self

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if not self._rows:
            raise RuntimeError("SeatedPolicy.seat(teams) must say who plays where before the first forward pass")
        observation = tensordict.get(OBSERVATION)
        if observation.shape[0] != self._num_envs:
            raise ValueError(f"seated for {self._num_envs} kitchens, got a batch of {observation.shape[0]}")
        logits = observation.new_zeros((*observation.shape[:2], NUM_ACTIONS), dtype=torch.float32)
        next_states = {name: torch.zeros_like(tensordict.get(("agents", name))) for name in self._widths}
        for actor, inputs, storage, (rows, seats) in zip(self.actors, self._inputs, self._storage, self._rows):
            if rows.numel() == 0:
                continue
            team_view = TensorDict({key: tensordict.get(key)[rows] for key in inputs}, batch_size=rows.shape)
            if storage:
                team_view.set("is_init", tensordict.get("is_init")[rows])
                for name, stored in storage.items():
                    team_view.set(("agents", name), tensordict.get(("agents", stored))[rows])
            team_view = actor(team_view)
            for seat, (place, kitchens) in enumerate(seats):
                logits[kitchens, seat] = team_view.get(LOGITS)[place, seat]
                for name, stored in storage.items():
                    next_states[stored][kitchens, seat] = team_view.get(("next", "agents", name))[place, seat]
        tensordict.set(LOGITS, logits)
        for name, state in next_states.items():
            tensordict.set(("next", "agents", name), state)
        return tensordict


def make_seated_actor(actors: list[TensorDictModuleBase]) -> ProbabilisticActor:
    """A `ProbabilisticActor` sampling ("agents", "action") from a `SeatedPolicy` over `actors` (`.module[0]`)."""
    return sampling_actor(SeatedPolicy(actors))
