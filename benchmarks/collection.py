"""Where a collection step's time goes: microseconds per env step of each layer the trainer's collector runs.

Builds a team as `trainers.ppo.loop` does on a setting of `benchmarks/jax_ppo.py` and times, one after the other,
each over the same kitchens:

    JAX step           the env's jitted step alone (random actions, its outputs waited for)
    env.step           TorchRL's `EnvBase.step` of the `KitchenEnv`: the JAX step, DLPack both ways, the TensorDict
    acting policy      the team's policy on one step's observations (no gradients)
    collector step     a whole batch of TorchRL's `Collector`, per step: policy, `step_and_maybe_reset`, storage
    rollout step       a whole batch of the trainer's `KitchenCollector` (`torch_kitchen.rollout`), per step: the
                       same batch, written in place, the JAX step called directly
    xla rollout step   a whole batch of `XlaCollector` (`torch_kitchen.xla_rollout`, `runtime.collector=xla`), per
                       step: the kitchens and the team's network in one XLA program, the batch copied out once
    xla, dense first   the same with the networks' first layers as dense products over the observations (a GPU's
                       way) rather than from their cell tables (a CPU's, `torch_kitchen.xla_layers.cell_table`)

The difference between a whole step and "env.step" plus "acting policy" is TorchRL's bookkeeping around them
(`step_mdp`, resets, the collector's carrier and its stacked batch); for the rollout step, the difference from
"JAX step" plus "acting policy" is all that is neither the kitchens nor the network; the xla rollout step, less the
JAX step, is the network, the draws and the batch's copy together. Run it alone on the machine.

    python benchmarks/collection.py [--setting jaxmarl|ik] [--steps 2000] [--envs 192] [--device cuda] [key=value ...]
    python benchmarks/collection.py --setting ik architecture=ego_mlp hidden=128   # the main job's team

With `--envs 192` at the ik setting, the "JAX step" row is the floor of the paper's protocol (6 teams x 32 kitchens):
no trainer over this env collects a step faster.
"""

from __future__ import annotations

import argparse
import tempfile
from unittest import mock

import jax
import numpy as np
import torch
from timing import seconds_per_call

import torch_kitchen.xla_rollout as xla_rollout
from torch_kitchen.env import ProgramCache
from torch_kitchen.teams import TeamPolicy
from trainers.config.compose import load_config
from trainers.machine import machine_name
from trainers.ppo.collection import make_collector
from trainers.ppo.team import build_team, make_env, with_model_transforms


def main(argv=None) -> None:
    from jax_ppo import SETTINGS, setting_overrides  # with the test extra

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", choices=["jaxmarl", "ik"], default="jaxmarl")
    parser.add_argument("--steps", type=int, default=2000, help="calls per measurement")
    parser.add_argument("--envs", type=int, default=0, help="kitchens (default: the setting's)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("overrides", nargs="*", help="config overrides, key=value (e.g. architecture=ego_mlp)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    envs = [f"num_envs={args.envs}"] if args.envs else []
    config = load_config(None, [*setting_overrides(args.setting), *envs, "total_steps=1e6", "runtime.threads=1",
                                f"runtime.device={args.device}", *args.overrides])
    kitchen = make_env(config, seed=[config.seed])
    team = build_team(config, tempfile.mkdtemp(), kitchen, 0)
    env = with_model_transforms(kitchen, team.actor_critic)
    policy = TeamPolicy([team.policy], [team.stream], config.num_envs)

    rows = {}
    with torch.no_grad():
        tensordict = policy(env.reset())
        states, deliveries = kitchen.states, kitchen._deliveries
        # on the kitchens' JAX device already, so that the row times the step and no host-to-device copy
        actions = jax.device_put(np.random.default_rng(0).integers(0, 6, (config.num_envs, 2), dtype=np.int32),
                                 jax.tree_util.tree_leaves(states)[0].sharding)
        rows["JAX step"] = 1e6 * seconds_per_call(
            lambda: jax.block_until_ready(kitchen._programs.step(states, deliveries, actions)), args.steps, warmup=20)
        rows["env.step"] = 1e6 * seconds_per_call(lambda: env.step(tensordict), args.steps, warmup=20)
        rows["acting policy"] = 1e6 * seconds_per_call(lambda: policy(tensordict), args.steps, warmup=20)
    steps = SETTINGS[args.setting]["rollout_steps"]

    def collector_step(kind: str) -> float:
        collector = make_collector(env, policy, config.frames_per_batch, kind=kind)
        batches = iter(collector)
        next(batches)
        seconds = seconds_per_call(lambda: next(batches), max(1, args.steps // steps))
        collector.shutdown(close_env=False)
        return 1e6 * seconds / steps

    for row, kind in (("collector step", "torchrl"), ("rollout step", "kitchen"), ("xla rollout step", "xla")):
        rows[row] = collector_step(kind)
    with mock.patch.object(xla_rollout, "_chains_here", lambda _, chains: list(chains)), \
            mock.patch.object(xla_rollout, "_PROGRAMS", ProgramCache(kept=1)):  # programs of their own
        rows["xla, dense first"] = collector_step("xla")

    print(f"setting {args.setting}: {config.num_envs} kitchens, {config.architecture}, hidden {config.hidden}; "
          f"{args.device}, {machine_name()}, torch 1 thread")
    print(f"{'layer':<16s} {'us per env step':>16s}")
    for name, value in rows.items():
        print(f"{name:<16s} {value:16.1f}")
    rest = rows["collector step"] - rows["env.step"] - rows["acting policy"]
    print(f"{'(bookkeeping)':<16s} {rest:16.1f}   collector step - env.step - acting policy")
    rest = rows["rollout step"] - rows["JAX step"] - rows["acting policy"]
    print(f"{'(rollout rest)':<16s} {rest:16.1f}   rollout step - JAX step - acting policy")
    rest = rows["xla rollout step"] - rows["JAX step"]
    print(f"{'(xla rest)':<16s} {rest:16.1f}   xla rollout step - JAX step")


if __name__ == "__main__":
    main()
