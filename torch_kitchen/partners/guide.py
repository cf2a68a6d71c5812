"""A teacher's guidance of a learner's rollout (DAgger's): each seat takes the teacher's action instead of its own
with a probability, and every visited state is labelled with the teacher's action distribution.

`GuidedPolicy` acts on TensorDicts (the kitchens' collector); `torch_kitchen.xla_rollout` runs the same guidance
inside the kitchens' XLA program, the teacher planning there with `jax_env.cook` (`trainers.ppo.distill` uses
either, as `runtime.collector` says).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from jax_env import NUM_ACTIONS
from torch_kitchen.keys import ACTION, OBSERVATION
from torch_kitchen.partners.scripted_cook import ScriptedCook

TEACHER_PROBS = ("agents", "teacher_probs")  # [..., 2, 6]: the teacher's action distribution in the visited state


class GuidedPolicy(TensorDictModuleBase):
    """The learner's acting policy (actor and critic), where each seat takes the `teacher`'s sampled action instead
    of its own with probability `teacher_share`; writes the teacher's action distribution (`TEACHER_PROBS`). The
    learner's log-probability stays that of its own draw."""

    def __init__(self, learner: TensorDictModuleBase, teacher: ScriptedCook, teacher_share: float = 1.0):
        super().__init__()
        self.learner, self.teacher = learner, teacher
        self.in_keys = list(learner.in_keys)
        self.out_keys = [*learner.out_keys, TEACHER_PROBS]
        self.teacher_share = teacher_share

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict = self.learner(tensordict)
        probs = torch.softmax(self.teacher(tensordict.get(OBSERVATION)), dim=-1)
        teacher_action = torch.multinomial(probs.reshape(-1, NUM_ACTIONS), 1).reshape(probs.shape[:-1])
        takes = torch.rand(teacher_action.shape, device=probs.device) < self.teacher_share
        tensordict.set(ACTION, torch.where(takes, teacher_action, tensordict.get(ACTION)))
        tensordict.set(TEACHER_PROBS, probs)
        return tensordict
