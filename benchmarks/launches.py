"""Kernel launches and host synchronisations per env step, per GAE and per PPO minibatch, counted on any device.

Counts what the trainer's device path dispatches (`benchmarks/op_audit.py`'s `OpAudit`; on a CPU the layers are held
to the products a GPU runs, `torch_kitchen.onednn_linear.device_path`): one batch of collection through TorchRL's
collector (divided by its steps), the advantages of that batch, and one PPO minibatch (loss, backward, clipping,
Adam step), for 1 team and for K teams in one batch, one after another and stacked (the "advantages" row at 8
steps; the last line compares GAE at the setting's rollout length against TorchRL's functional GAE). On a GPU
every launch costs a few microseconds of host time and every sync waits for the device, so these counts bound
the speed there.

    python benchmarks/launches.py [--setting protocol] [--teams 1 6] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import tempfile

import torch
from jax_ppo import SETTINGS, setting_overrides  # with the test extra
from op_audit import OpAudit

from torch_kitchen.env import team_rows
from torch_kitchen.onednn_linear import device_path
from torch_kitchen.teams import TeamPolicy
from trainers.config.compose import load_config
from trainers.machine import machine_name
from trainers.ppo.advantages import compute_advantages, shaping_weight_at
from trainers.ppo.collection import make_collector, select_kitchens
from trainers.ppo.loop import start_update
from trainers.ppo.runtime import Learner
from trainers.ppo.team import build_team, make_env, team_configs, with_model_transforms


def audit_training(setting: str, teams: int, device: str, steps: int = 8, stack: bool = False
                   ) -> dict[str, OpAudit]:
    """Audits of one collection batch of `steps` steps ("collection, per step" holds its counts / steps), the
    advantages of the first team's part of it, and one minibatch update, on the setting's shape with `teams` teams:
    the first team's, or with `stack` every team's as one (acting and learning stacked, as on a GPU)."""
    with tempfile.TemporaryDirectory() as run_dir:
        config = load_config(None, [*setting_overrides(setting), f"runtime.teams={teams}", f"rollout_steps={steps}",
                                    f"runtime.device={device}", f"run_dir={run_dir}", "progress=false"])
        configs = team_configs(config)
        lead = configs[0]
        kitchen = make_env(lead, num_envs=teams * lead.num_envs, seed=[c.seed for c in configs])
        built = [build_team(c, c.run_path, kitchen, index) for index, c in enumerate(configs)]
        env = with_model_transforms(kitchen, built[0].actor_critic)
        policy = TeamPolicy([team.policy for team in built], [team.stream for team in built], lead.num_envs,
                            stack=stack)
        frames = teams * lead.num_envs * steps
        collector = make_collector(env, policy, frames, 3 * frames)
        audits = {name: OpAudit() for name in ("collection, per step", "advantages", "minibatch")}
        with device_path():
            batches = iter(collector)
            next(batches)  # the first batch compiles the env and builds the collector's buffers
            with audits["collection, per step"]:
                batch = next(batches)
            team, team_batch = built[0], batch[: lead.num_envs]
            with audits["advantages"]:
                compute_advantages(team_batch, team.actor_critic.critic, lead, shaping_weight_at(lead, 0))
            team_batches = [batch[team_rows(index, lead.num_envs)] for index in range(teams)]
            orders = []
            for team, team_batch in zip(built, team_batches):
                with team.stream.active():
                    orders.append(start_update(team, team_batch)[0])
            if stack:  # every team's minibatch as one step
                step = Learner(lead, built).step

                def update(index: int) -> None:  # the first epoch's minibatch `index`
                    step(torch.stack([select_kitchens(team_batch, order[0][index])
                                      for team_batch, order in zip(team_batches, orders)]))
            else:  # the first team's minibatch
                step = Learner(lead, built[:1]).step

                def update(index: int) -> None:
                    minibatch = select_kitchens(team_batches[0], orders[0][0][index])
                    step(minibatch)
            update(0)  # the first builds the optimizer's state
            with audits["minibatch"]:
                update(1)
        collector.shutdown()
    audits["collection, per step"].per = steps
    return audits


def audit_advantages(num_envs: int, steps: int) -> tuple[OpAudit, OpAudit]:
    """Audits of TorchRL's functional GAE (a Python loop over time) and of ours (`trainers.ppo.advantages`) on one
    team's batch of `num_envs` kitchens x `steps` steps, episodes ending at the batch end."""
    from torchrl.objectives.value.functional import generalized_advantage_estimate

    from trainers.ppo.advantages import generalized_advantages

    value, next_value, reward = (torch.randn(num_envs, 2, steps, 1) for _ in range(3))
    done = torch.zeros(num_envs, 2, steps, 1, dtype=torch.bool)
    done[:, :, -1] = True
    audits = OpAudit(), OpAudit()
    for audit, gae in zip(audits, (generalized_advantage_estimate, generalized_advantages)):
        with audit:
            gae(0.99, 0.95, value, next_value, reward, done, done, time_dim=-2)
    return audits


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", choices=list(SETTINGS), default="protocol")
    parser.add_argument("--teams", type=int, nargs="+", default=[1, 6])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    print(f"device: {args.device}, {machine_name()}; setting {args.setting}, the device path")
    print(f"{'teams':>9s}  {'part':<21s} {'launches':>9s} {'syncs':>6s} {'host tensors':>13s}  syncing ops")
    for teams, stack in [(teams, stack) for teams in args.teams for stack in ([False, True] if teams > 1 else [False])]:
        for part, audit in audit_training(args.setting, teams, args.device, stack=stack).items():
            if stack and part == "advantages":
                continue  # the same as apart: a team's GAE
            if part == "minibatch":
                part = "minibatch, all teams" if stack else "minibatch, one team"
            per = getattr(audit, "per", 1)
            syncing = ", ".join(f"{name} x{count / per:g}" for name, count in sorted(audit.sync_ops().items()))
            label = f"{teams}{' stacked' if stack else ''}"
            print(f"{label:>9s}  {part:<21s} {audit.launches / per:9.0f} {audit.syncs / per:6.1f} "
                  f"{audit.host_tensors / per:13.1f}  {syncing or '-'}", flush=True)
    steps = SETTINGS[args.setting]["rollout_steps"]
    torchrl_gae, ours = audit_advantages(SETTINGS[args.setting]["num_envs"], steps)
    print(f"GAE over a team's {steps}-step batch: TorchRL's loop {torchrl_gae.launches} launches, "
          f"trainers.ppo.advantages {ours.launches}")


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
