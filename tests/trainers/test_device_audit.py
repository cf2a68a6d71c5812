"""The host's part of every training loop, counted on the CPU (`trainers.device_audit`): each loop trains twice, the
second run 8 steps per update longer, and the host reads and device-less tensors whose count grew are the loop's
per-step (or per-episode) ones. They are stated here, so a new one is a failing test naming its function."""

import pytest
from tiny import TINY

from trainers.composer import load_config
from trainers.device_audit import DeviceAudit, per_step
from trainers.ppo import train_teams
from trainers.training_team import team_configs

SHORT, LONG, UPDATES = 8, 16, 2
EXTRA_STEPS = (LONG - SHORT) * UPDATES
# Per step, on the CPU. The sparse first layer (sparse_linear.py) is the CPU's kernel (`accelerate_cpu`) and the
# actions go to JAX as NumPy there (`KitchenEnv._actions_to_jax`); on a GPU neither runs. Episode ends (16-step episodes
# here) are read once per step by the kitchen collector, and by the kitchens when some end.
CPU_KERNEL = {"nonzero at torch_kitchen/sparse_linear.py:NonZeroEntries.__init__": 1.0}
CPU_KERNEL_MADE = {"zeros at torch_kitchen/sparse_linear.py:_row_offsets": 1.0}
ACTIONS_TO_JAX = {"numpy at torch_kitchen/env.py:KitchenEnv._actions_to_jax": 1.0}
EPISODE_ENDS = {"__bool__ at torch_kitchen/env.py:KitchenEnv._reset": 1 / 16}
LOOPS = {
    # name: (config, overrides, host reads per step, tensors made without a device per step)
    "xla": ("configs/ippo/mlp_ik.yaml", ["runtime.collector=xla"], {}, {}),
    "kitchen": ("configs/ippo/mlp_ik.yaml", ["runtime.collector=kitchen"],
                {**CPU_KERNEL, **ACTIONS_TO_JAX, **EPISODE_ENDS, "__bool__ at torch_kitchen/rollout.py:advance": 0.25},
                CPU_KERNEL_MADE),
    "torchrl": ("configs/ippo/mlp_ik.yaml", ["runtime.collector=torchrl"],
                {**CPU_KERNEL, **ACTIONS_TO_JAX, **EPISODE_ENDS, "__bool__ at trainers/ppo.py:train_teams": 0.25},
                CPU_KERNEL_MADE),
    "gnn": ("configs/ippo/gnn_ik.yaml", [],
            {**ACTIONS_TO_JAX, **EPISODE_ENDS, "__bool__ at torch_kitchen/rollout.py:advance": 0.25}, {}),
    # E3T's partner model has a sparse first layer of its own, and its partner draws are made on the CPU (their own
    # generator) at episode starts.
    "e3t": ("configs/e3t/mlp_ik.yaml", [],
            {"nonzero at torch_kitchen/sparse_linear.py:NonZeroEntries.__init__": 2.0, **ACTIONS_TO_JAX,
             **EPISODE_ENDS, "__bool__ at torch_kitchen/partner.py:PartnerSeats._reset": 1 / 16,
             "__bool__ at torch_kitchen/rollout.py:transformed_rollout_into": 0.25},
            {"zeros at torch_kitchen/sparse_linear.py:_row_offsets": 2.0,
             "randint at torch_kitchen/partner.py:PartnerSeats._draw": 1 / 16}),
}


def audited_run(tmp_path, config: str, overrides: list[str], steps: int) -> DeviceAudit:
    config = load_config(config, [*TINY, f"rollout_steps={steps}", f"total_steps={4 * steps * UPDATES}",
                                  f"run_dir={tmp_path / str(steps)}", "loggers=[csv]", *overrides])
    with DeviceAudit() as audit:
        train_teams(team_configs(config))
    return audit


@pytest.mark.parametrize("loop", LOOPS)
def test_each_loops_host_reads_and_device_less_tensors_per_step_are_the_stated_ones(tmp_path, loop):
    config, overrides, reads, made = LOOPS[loop]
    short, long = (audited_run(tmp_path, config, overrides, steps) for steps in (SHORT, LONG))
    assert per_step(short.host_reads, long.host_reads, EXTRA_STEPS) == pytest.approx(reads), long.report()
    assert per_step(short.factories, long.factories, EXTRA_STEPS) == pytest.approx(made), long.report()


def test_the_audit_counts_host_reads_and_tensors_made_without_a_device_and_only_those():
    import torch

    with DeviceAudit() as audit:
        x = torch.zeros(3)
        torch.ones(2, device="cpu")
        x[x > 0].sum().item()
    assert set(audit.host_reads) == {"item at (outside the project)", "bool-index at (outside the project)"}
    assert sum(audit.factories.values()) == 1  # torch.zeros(3); ones was given its device
