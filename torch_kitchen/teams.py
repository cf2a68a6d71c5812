"""Several independently trained teams in one batch of kitchens: each team acts, draws and resets as it would alone.

A `KitchenEnv` built with K seeds holds K teams of B/K kitchens, team k on rows k*B/K .. (k+1)*B/K - 1, each with
its own JAX key. The torch side keeps the teams apart with three pieces:

`RandomStream`   a team's own torch random stream (CPU, and its CUDA device), swapped in around the team's work,
                 so its weights, sampled actions and minibatch orders are those of a run of its own;
`TeamPolicy`     one TensorDict policy over the whole batch: team k's policy acts on team k's rows, in its stream;
`TeamTransform`  one env transform over the whole batch from one stateful transform per team (E3T's partner
                 seats, each drawing from its own generator), each on its team's rows.

Team k's networks see exactly the tensors, of exactly the shapes, that a run of its own would give them, so
the arithmetic is the same, bit for bit (`tests/trainers/test_teams.py`).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Composite
from torchrl.envs import Transform


def team_rows(team: int, team_size: int) -> slice:
    """The rows of team `team` in a batch of teams of `team_size` kitchens."""
    return slice(team * team_size, (team + 1) * team_size)


class RandomStream:
    """A torch random stream of its own, seeded like `torch.manual_seed(seed)`: `with stream.active():` makes it
    torch's global stream (CPU, and `device` if that is a GPU) and keeps where it got to for the next time."""

    def __init__(self, seed: int, device: str | torch.device = "cpu"):
        device = torch.device(device)
        self._cuda = device if device.type == "cuda" else None
        with torch.random.fork_rng(devices=[] if self._cuda is None else [self._cuda]):
            torch.manual_seed(seed)
            self._state = self._capture()

    def _capture(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        cuda = torch.cuda.get_rng_state(self._cuda) if self._cuda is not None else None
        return torch.get_rng_state(), cuda

    def _restore(self, state: tuple[torch.Tensor, torch.Tensor | None]) -> None:
        torch.set_rng_state(state[0])
        if self._cuda is not None:
            torch.cuda.set_rng_state(state[1], self._cuda)

    @contextlib.contextmanager
    def active(self) -> Iterator[None]:
        outer = self._capture()
        self._restore(self._state)
        try:
            yield
        finally:
            self._state = self._capture()
            self._restore(outer)


class TeamPolicy(TensorDictModuleBase):
    """Team k's `policies[k]` acts on team k's rows of the batch, drawing from `streams[k]` (see the module
    docstring). The policies read and write the same keys; one team's policy acts on the batch as it is."""

    def __init__(self, policies: Sequence[TensorDictModuleBase], streams: Sequence[RandomStream], team_size: int):
        super().__init__()
        if len(policies) != len(streams):
            raise ValueError(f"{len(policies)} policies and {len(streams)} random streams: give one of each per team")
        self.policies = torch.nn.ModuleList(policies)
        self.streams = list(streams)
        self.team_size = team_size
        self.in_keys = list(policies[0].in_keys)
        self.out_keys = list(policies[0].out_keys)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if len(self.policies) == 1:  # every step: spare one team the split and the copy back
            with self.streams[0].active():
                return self.policies[0](tensordict)
        acted = []
        for team, (policy, stream) in enumerate(zip(self.policies, self.streams)):
            with stream.active():
                acted.append(policy(tensordict[team_rows(team, self.team_size)]).select(*self.out_keys))
        return tensordict.update(torch.cat(acted))


class TeamTransform(Transform):
    """An env transform made of one transform per team, transform k on team k's rows (see the module docstring).
    The transforms write the same keys and specs; each keeps its own state."""

    def __init__(self, transforms: Sequence[Transform], team_size: int):
        first = transforms[0]
        super().__init__(in_keys=list(first.in_keys), out_keys=list(first.out_keys))
        self.transforms = torch.nn.ModuleList(transforms)
        self.team_size = team_size

    def _by_team(self, method: str, tensordict: TensorDictBase | None, out: TensorDictBase) -> TensorDictBase:
        """Calls every team's `transform.<method>(tensordict rows, out rows)` and writes their outputs into `out`."""
        parts = []
        for team, transform in enumerate(self.transforms):
            rows = team_rows(team, self.team_size)
            part = getattr(transform, method)(None if tensordict is None else tensordict[rows], out[rows])
            parts.append(part.select(*self.out_keys))
        return out.update(torch.cat(parts))

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return self._by_team("_reset", tensordict, tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._by_team("_step", tensordict, next_tensordict)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        return self.transforms[0].transform_observation_spec(observation_spec)
