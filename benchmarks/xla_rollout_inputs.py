"""How the XLA rollout's program takes its inputs from torch, on a GPU: microseconds per env step of `XlaCollector`
batches under each way, each in a process of its own (a failed program can leave the device unusable).

    copied             the default: weights, keys and the first carrier copied into XLA's own buffers
                       (`XlaCollector._to_jax`), the program's command buffers (XLA's CUDA graphs) on
    no command buffers the same, with XLA_FLAGS=--xla_gpu_enable_command_buffer= (every kernel launched by the host)
    shared             torch's memory handed over by DLPack alone: on an H200 (jax 0.11.2) the command buffers fail at a
                       later call, "Failed to set memcpy D2D node params: CUDA_ERROR_INVALID_VALUE"

    python benchmarks/xla_rollout_inputs.py [--envs 192] [--device cuda] [key=value ...]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

WAYS = {"copied": {}, "no command buffers": {"XLA_FLAGS": "--xla_gpu_enable_command_buffer="}, "shared": {}}


def time_batches(way: str, envs: int, device: str, overrides: list[str], batches: int = 4) -> str:
    """One way's line: us per env step over `batches` batches after two untimed ones, or the error."""
    import torch
    from jax_ppo import setting_overrides

    import torch_kitchen.xla_rollout as xla_rollout
    from torch_kitchen.teams import TeamPolicy
    from trainers.config.compose import load_config
    from trainers.ppo.collection import make_collector
    from trainers.ppo.team import build_team, make_env, with_model_transforms

    if way == "shared":
        xla_rollout.XlaCollector._to_jax = lambda self, tensor: xla_rollout.jax.device_put(
            xla_rollout.jax.dlpack.from_dlpack(tensor.detach().contiguous()), self.kitchen_env.jax_device)
    torch.set_num_threads(1)
    config = load_config(None, [*setting_overrides("ik"), f"num_envs={envs}", "total_steps=1e6", "runtime.threads=1",
                                f"runtime.device={device}", *overrides])
    kitchen = make_env(config, seed=[config.seed])
    team = build_team(config, tempfile.mkdtemp(), kitchen, 0)
    policy = TeamPolicy([team.policy], [team.stream], config.num_envs)
    collector = make_collector(with_model_transforms(kitchen, team.actor_critic), policy, config.frames_per_batch,
                               kind="xla")
    stream = iter(collector)
    try:
        for _ in range(2):
            next(stream)["next", "done"].any().item()
        started = time.perf_counter()
        for _ in range(batches):
            batch = next(stream)
        batch["next", "done"].any().item()
    except Exception as error:  # the measurement: which way fails, and how
        return f"{way:<20s} failed: {type(error).__name__}: {str(error).splitlines()[0][:200]}"
    per_step = (time.perf_counter() - started) / batches / config.rollout_steps
    return f"{way:<20s} {1e6 * per_step:10.0f} us per step of {envs} kitchens ({envs / per_step:,.0f} env steps/s)"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=192)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--way", choices=list(WAYS), help="time this way here (the driver runs each in its own)")
    parser.add_argument("overrides", nargs="*", help="config overrides, key=value (e.g. architecture=ego_mlp)")
    args = parser.parse_args(argv)
    if args.way:
        print(time_batches(args.way, args.envs, args.device, args.overrides), flush=True)
        return
    from trainers.machine import machine_name

    print(f"XlaCollector at the ik setting, {args.envs} kitchens, {' '.join(args.overrides) or 'mlp'}; "
          f"{args.device}, {machine_name()}")
    for way, variables in WAYS.items():
        done = subprocess.run([sys.executable, __file__, "--way", way, "--envs", str(args.envs), "--device",
                               args.device, *args.overrides], env={**os.environ, **variables}, capture_output=True,
                              text=True)
        lines = [line for line in done.stdout.splitlines() if line.startswith(way)]
        print(lines[-1] if lines else f"{way:<20s} exited {done.returncode}: {done.stderr.strip()[-200:]}", flush=True)


if __name__ == "__main__":
    main()
