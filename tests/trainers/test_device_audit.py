"""The host's part of every loop, counted on the CPU (`device_audit`): each training loop (every collector,
the architecture families, networks per agent, E3T, the main job's), distillation, evaluation beside the scripted
cook and a human proxy, and behaviour cloning runs twice, the second run longer (8 steps per update or episode, or 2
minibatches), and the host reads and device-less tensors whose count grew are the loop's per-step (or
per-minibatch) ones. They are stated here, so a new one is a failing test naming its function."""

import pytest
import torch
from device_audit import DeviceAudit, per_step
from tiny import TINY

from torch_kitchen.graph import batched_edges
from torch_kitchen.keys import OBSERVATION
from torch_kitchen.symmetry import transform_observation
from trainers.config.compose import load_config
from trainers.ppo.distill import distill
from trainers.ppo.loop import train_teams
from trainers.ppo.team import team_configs

SHORT, LONG, UPDATES = 8, 16, 2
EXTRA_STEPS = (LONG - SHORT) * UPDATES
# Per step, on the CPU. The sparse first layer (sparse_linear.py) is the CPU's kernel (`accelerate_cpu`) and the
# actions go to JAX as NumPy there (`KitchenEnv._actions_to_jax`); on a GPU neither runs. Episode ends (16-step episodes
# here) are read once per step by the kitchen collector, and by the kitchens when some end.
CPU_KERNEL = {"nonzero at torch_kitchen/sparse_linear.py:flat_nonzero": 1.0}
CPU_KERNEL_MADE = {"zeros at torch_kitchen/sparse_linear.py:_row_offsets": 1.0}
ACTIONS_TO_JAX = {"numpy at torch_kitchen/env.py:KitchenEnv._actions_to_jax": 1.0}
EPISODE_ENDS = {"__bool__ at torch_kitchen/env.py:KitchenEnv._reset": 1 / 16}
LOOPS = {
    # name: (config, overrides, host reads per step, tensors made without a device per step)
    "xla": ("configs/ippo/mlp_ik.yaml", ["runtime.collector=xla"], {}, {}),
    "main job's IPPO (xla)": ("configs/main.yaml", ["runtime.collector=xla"], {}, {}),
    "kitchen": ("configs/ippo/mlp_ik.yaml", ["runtime.collector=kitchen"],
                {**CPU_KERNEL, **ACTIONS_TO_JAX, **EPISODE_ENDS, "__bool__ at torch_kitchen/rollout.py:advance": 0.25},
                CPU_KERNEL_MADE),
    "torchrl": ("configs/ippo/mlp_ik.yaml", ["runtime.collector=torchrl"],
                {**CPU_KERNEL, **ACTIONS_TO_JAX, **EPISODE_ENDS, "__bool__ at trainers/ppo/loop.py:train_loop": 0.25},
                CPU_KERNEL_MADE),
    "gnn (xla)": ("configs/ippo/gnn_ik.yaml", ["runtime.collector=xla"], {}, {}),
    "an SK LSTM, a network per agent (xla)": ("configs/ippo/mlp_lstm_sk_cramped_room.yaml", ["runtime.collector=xla"],
                                              {}, {}),
    "gnn (kitchen)": ("configs/ippo/gnn_ik.yaml", ["runtime.collector=kitchen"],
                      {**ACTIONS_TO_JAX, **EPISODE_ENDS, "__bool__ at torch_kitchen/rollout.py:advance": 0.25}, {}),
    # E3T's partner model has a sparse first layer of its own, and its partner draws are made on the CPU (their own
    # generator) at episode starts.
    "e3t": ("configs/e3t/mlp_ik.yaml", [],
            {"nonzero at torch_kitchen/sparse_linear.py:flat_nonzero": 2.0, **ACTIONS_TO_JAX,
             **EPISODE_ENDS, "__bool__ at torch_kitchen/models/e3t_partner.py:PartnerSeats._reset": 1 / 16,
             "__bool__ at torch_kitchen/rollout.py:transformed_rollout_into": 0.25},
            {"zeros at torch_kitchen/sparse_linear.py:_row_offsets": 2.0,
             "randint at torch_kitchen/models/e3t_partner.py:PartnerSeats._draw": 1 / 16}),
}

# Distillation, evaluation and behaviour cloning, run at SHORT and LONG steps (one episode ends in the longer run
# alone). The scripted cook, seated from torch, reads the floor plans on the host to key its table of distances, and
# hands the views, the tables and the plans to JAX as NumPy on the CPU (DLPack on a GPU).
SCRIPTED_COOK = {"numpy at torch_kitchen/partners/scripted_cook.py:FloorDistances.__call__": 1.0,
                 "numpy at torch_kitchen/partners/scripted_cook.py:ScriptedCook.forward.<locals>.to_jax": 3.0}
ONE_EPISODE_END = 1 / (LONG - SHORT)
DISTILL_READS = {**CPU_KERNEL, **ACTIONS_TO_JAX, **SCRIPTED_COOK,
                 "__bool__ at torch_kitchen/env.py:KitchenEnv._reset": ONE_EPISODE_END,
                 "__bool__ at torch_kitchen/rollout.py:advance": 0.5,
                 # the round's mean deliveries
                 "__float__ at trainers/ppo/distill.py:learn_round": ONE_EPISODE_END}
EVALUATION = {  # partner: (host reads, tensors made without a device) per step; the seated teams read nothing
    "scripted cook": ({**ACTIONS_TO_JAX, **SCRIPTED_COOK}, {}),
    "human proxy": (ACTIONS_TO_JAX, {}),
}


def audited_run(tmp_path, config: str, overrides: list[str], steps: int) -> DeviceAudit:
    config = load_config(config, [*TINY, f"rollout_steps={steps}", f"total_steps={4 * steps * UPDATES}",
                                  f"run_dir={tmp_path / str(steps)}", "loggers=[csv]", *overrides])
    # The GNN's edges are made once per number of graphs: each run makes its own, whichever the suite's earlier tests
    # left cached (a shape cached for one run and not the other counted as the longer run's per-step work).
    batched_edges.cache_clear()
    with DeviceAudit() as audit:
        train_teams(team_configs(config))
    return audit


@pytest.mark.parametrize("loop", LOOPS)
def test_each_loops_host_reads_and_device_less_tensors_per_step_are_the_stated_ones(tmp_path, loop):
    config, overrides, reads, made = LOOPS[loop]
    short, long = (audited_run(tmp_path, config, overrides, steps) for steps in (SHORT, LONG))
    assert per_step(short.host_reads, long.host_reads, EXTRA_STEPS) == pytest.approx(reads), long.report()
    assert per_step(short.factories, long.factories, EXTRA_STEPS) == pytest.approx(made), long.report()


def audited_distillation(tmp_path, steps: int) -> DeviceAudit:
    config = load_config("configs/main.yaml", [*TINY, f"rollout_steps={steps}", "distill.rounds=1",
                                               "distill.epochs=1", f"run_dir={tmp_path / str(steps)}",
                                               "loggers=[csv]"])
    with DeviceAudit() as audit:
        distill(config)
    return audit


def test_distillations_host_reads_and_device_less_tensors_per_step_are_the_stated_ones(tmp_path):
    # Each symmetry's gather indices are made once per process; both runs draw symmetries, so made here first, the
    # one-time cost falls on neither (whichever symmetries the suite's earlier tests drew).
    for symmetry in range(8):
        transform_observation(torch.zeros(1, 7, 7, 26, dtype=torch.uint8), symmetry)
    short, long = (audited_distillation(tmp_path, steps) for steps in (SHORT, LONG))
    assert per_step(short.host_reads, long.host_reads, LONG - SHORT) == pytest.approx(DISTILL_READS), long.report()
    assert per_step(short.factories, long.factories, LONG - SHORT) == pytest.approx(CPU_KERNEL_MADE), long.report()


def audited_evaluation(partner, steps: int) -> DeviceAudit:
    from torch_kitchen.models import make_actor_critic
    from trainers.config import TrainConfig
    from trainers.evaluation.pairs import evaluation_grids, make_matchups, play
    from trainers.evaluation.teams import Team

    torch.manual_seed(0)
    team = Team("ego/seed0", "ego", TrainConfig(architecture="ego_mlp", hidden=16),
                make_actor_critic("ego_mlp", (7, 7, 26), 16), (7, 7, 26), "(made here)")
    teams, matchups = make_matchups({"ego": [team]}, partner=partner)
    with DeviceAudit() as audit:
        play(teams, matchups, evaluation_grids(["cramped_room_7x7"], num_heldout=1), rollouts=1, max_steps=steps)
    return audit


def human_proxy_team():
    from torch_kitchen.models import make_actor_critic
    from trainers.config import TrainConfig
    from trainers.evaluation.teams import Team

    torch.manual_seed(1)
    return Team("human_proxy_cramped_room/seed0", "human_proxy_cramped_room", TrainConfig(architecture="ego_mlp"),
                make_actor_critic("ego_mlp", (7, 7, 26), 16), (7, 7, 26), "(made here)")


@pytest.mark.parametrize("partner", ["scripted cook", "human proxy"])
def test_evaluations_host_reads_and_device_less_tensors_per_step_are_the_stated_ones(partner):
    from trainers.evaluation.teams import scripted_cook_team

    seated = scripted_cook_team((7, 7, 26)) if partner == "scripted cook" else human_proxy_team()
    short, long = (audited_evaluation(seated, steps) for steps in (SHORT, LONG))
    reads, made = EVALUATION[partner]
    assert per_step(short.host_reads, long.host_reads, LONG - SHORT) == pytest.approx(reads), long.report()
    assert per_step(short.factories, long.factories, LONG - SHORT) == pytest.approx(made), long.report()


def audited_cloning(samples: int) -> DeviceAudit:
    from tensordict import TensorDict

    from trainers.humans.behaviour_cloning import HUMAN_ACTION, ProxySettings, fit_proxy

    generator = torch.Generator().manual_seed(0)  # made-up games: the fit's reads do not depend on what it sees
    observations = (torch.rand(samples, 2, 7, 7, 26, generator=generator) < 0.05).to(torch.uint8)
    labels = torch.randint(0, 6, (samples, 2), generator=generator)
    games = TensorDict({OBSERVATION: observations, HUMAN_ACTION: labels}, batch_size=[samples])
    with DeviceAudit() as audit:
        fit_proxy(games, ProxySettings(hidden=8, epochs=1, minibatch=8))
    return audit


def test_behaviour_clonings_minibatches_read_nothing_and_make_every_tensor_on_the_proxys_device():
    short, long = audited_cloning(16), audited_cloning(32)  # 2 and 4 minibatches
    assert per_step(short.host_reads, long.host_reads, 2) == {}, long.report()
    assert per_step(short.factories, long.factories, 2) == {}, long.report()


def test_the_audit_counts_host_reads_and_tensors_made_without_a_device_and_only_those():
    import torch

    with DeviceAudit() as audit:
        x = torch.zeros(3)
        torch.ones(2, device="cpu")
        x[x > 0].sum().item()
    assert set(audit.host_reads) == {"item at (outside the project)", "bool-index at (outside the project)"}
    assert sum(audit.factories.values()) == 1  # torch.zeros(3); ones was given its device
