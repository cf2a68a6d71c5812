"""The recurrent variants' memory: TorchRL's LSTMModule per agent or shared, its states carried under "agents"
([*B, 2, 1, h], zeroed where "is_init"), and the primer that gives the env those states.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import (
    TensorDictModuleBase,
)
from torch import nn
from torchrl.data import Composite, Unbounded
from torchrl.envs import TensorDictPrimer
from torchrl.modules import LSTMModule

from torch_kitchen.keys import (
    N_AGENTS,
)


def agent_state_primer(states: dict[str, int], n_agents: int = N_AGENTS) -> TensorDictPrimer:
    """Primer of the LSTM states ("agents", name) float32 [*B, n_agents, 1, size], zeros at every reset.

    states: name -> size. The specs sit in an "agents" Composite of shape [n_agents] so that, expanded to the
    env's batch size, they share the env's ("agents",) batch dims [*B, n_agents].
    """
    agents = Composite({name: Unbounded(shape=(n_agents, 1, size)) for name, size in states.items()},
                       shape=(n_agents,))
    return TensorDictPrimer(Composite(agents=agents), expand_specs=True)


class AgentLSTMModule(LSTMModule):
    """TorchRL's LSTMModule with states ("agents", name) [*B, n_agents, 1, hidden] in its primer.

    Run through `MultiAgentLSTM`, which moves the agent dim into the batch. The primer is what an env must carry,
    so `torchrl.modules.utils.get_primers_from_module` (and the collector's check) see the right shapes.
    """

    def __init__(self, *args, n_agents: int = N_AGENTS, **kwargs):
        super().__init__(*args, **kwargs)
        if any(len(key) != 2 or key[0] != "agents" for key in self.in_keys[1:3]):
            raise ValueError(f"AgentLSTMModule keeps its states under 'agents', got {self.in_keys[1:3]}")
        self.n_agents = n_agents

    def state_sizes(self) -> dict[str, int]:
        """Name under "agents" -> size of the two states (h, c)."""
        return {key[1]: self.lstm.hidden_size for key in self.in_keys[1:3]}

    def make_tensordict_primer(self) -> TensorDictPrimer:
        return agent_state_primer(self.state_sizes(), self.n_agents)


def recurrent_states(network: nn.Module) -> dict[str, int]:
    """Name under "agents" -> width of every LSTM state a network reads (empty if feed-forward)."""
    states = {}
    for module in network.modules():
        if isinstance(module, AgentLSTMModule):
            states.update(module.state_sizes())
    return states


class MultiAgentLSTM(TensorDictModuleBase):
    """LSTM over both agents: ("agents", "<net>_embedding") [*B, 2, h] -> ("agents", "<net>_memory") [*B, 2, h].

    Reads the state ("agents", "<net>_h" | "<net>_c") [*B, 2, 1, h] (zeros if absent) and "is_init" [*B, 1]. In
    step mode it writes the next state to ("next", "agents", "<net>_h" | "<net>_c"); in recurrent mode it leaves
    the stored next states as they are. LSTMModule takes time as the last batch dim, so the agent dim goes just
    before it, [B, T, 2] -> [B, 2, T]: shared, one LSTM runs both agents at once; separate, agent i's LSTM runs
    on agent i's slice.
    """

    def __init__(self, net: str, hidden: int, share_params: bool = True, n_agents: int = N_AGENTS):
        super().__init__()
        self.n_agents, self.share_params = n_agents, share_params
        embedding, memory = ("agents", f"{net}_embedding"), ("agents", f"{net}_memory")
        state_h, state_c = ("agents", f"{net}_h"), ("agents", f"{net}_c")
        self.in_keys = [embedding, state_h, state_c, "is_init"]
        self.out_keys = [memory, ("next", *state_h), ("next", *state_c)]
        self.lstms = nn.ModuleList(
            AgentLSTMModule(input_size=hidden, hidden_size=hidden, n_agents=n_agents, in_keys=list(self.in_keys),
                            out_keys=list(self.out_keys))
            for _ in range(1 if share_params else n_agents)
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if "is_init" not in tensordict:
            raise KeyError("recurrent models need 'is_init' [*B, 1]: append ActorCritic.env_transforms() "
                           "(InitTracker and the state primer) to the env")
        groups = [(0, self.n_agents)] if self.share_params else [(i, 1) for i in range(self.n_agents)]
        outputs = [self._run(lstm, tensordict, *group) for lstm, group in zip(self.lstms, groups)]
        agent_dim = tensordict.ndim
        if self.lstms[0].recurrent_mode:
            # Over a sequence LSTMModule returns next states that are zero but at the last step: keep the collected
            # ("next", ...) states rather than overwrite them with that padding.
            memory, *_ = zip(*outputs)
            tensordict.set(self.out_keys[0], torch.cat(memory, dim=agent_dim))
            return tensordict
        if ("next", "agents") not in tensordict.keys(include_nested=True):
            # Created with the agent dim, like the env's own ("next", "agents").
            tensordict.set(("next", "agents"), tensordict.get("agents").empty())
        for key, *values in zip(self.out_keys, *outputs):
            tensordict.set(key, torch.cat(values, dim=agent_dim))
        return tensordict

    def _run(self, lstm: LSTMModule, tensordict: TensorDictBase, first: int, count: int) -> list[torch.Tensor]:
        """Agents first .. first+count-1 through `lstm`: the out_keys' values, with the agent dim."""
        batch, ndim = tensordict.batch_size, tensordict.ndim
        fold = max(ndim - 1, 0)  # where the agent dim goes: just before time

        def to_lstm(value: torch.Tensor) -> torch.Tensor:
            return value.narrow(ndim, first, count).movedim(ndim, fold)

        is_init = to_lstm(tensordict.get("is_init").unsqueeze(ndim).expand(*batch, self.n_agents, 1))
        agents = {self.in_keys[0][1]: to_lstm(tensordict.get(self.in_keys[0]))}
        for key in self.in_keys[1:3]:
            state = tensordict.get(key, None)
            if state is not None:
                # LSTMModule zeroes the state at "is_init" only in step mode; in recurrent mode it trusts the
                # stored state at a sequence's start. Zeroing here makes a boundary inside a sequence safe too.
                state = to_lstm(state)
                agents[key[1]] = torch.where(is_init.unsqueeze(-1), torch.zeros_like(state), state)
        lstm_batch = is_init.shape[:-1]
        scratch = TensorDict({"agents": TensorDict(agents, batch_size=lstm_batch), "is_init": is_init},
                             batch_size=lstm_batch)
        scratch = lstm(scratch)
        return [scratch.get(key).movedim(fold, ndim) for key in self.out_keys]
