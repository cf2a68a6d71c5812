"""The sections of a training config, each a dataclass of its own keyed `section.key`: where a command runs
(`DeviceConfig`, an evaluation's whole `runtime`), a training run's run options (`RuntimeConfig`) and the planner-guided
start's distillation (`DistillConfig`, `kitchen-distill`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from trainers.config.schema import MAX_SEED, ConfigError, at_least, check_cpp_compiler, check_device, option

COLLECTORS = ("kitchen", "torchrl", "xla")  # runtime.collector: torch_kitchen.rollout's, TorchRL's, whole in XLA
TEACHER_MIXES = ("seed", "round")  # distill.teacher_mix: one teacher per seed, or one drawn per DAgger round


@dataclass
class DeviceConfig:
    """Where a command runs: the `runtime` section of every command (an evaluation's whole section)."""

    device: str = option("cpu", '"cpu" or "cuda[:i]"; the env and the networks share it')
    threads: int = option(1, "torch CPU threads (1 is fastest for small networks on a shared CPU)")

    @property
    def on_gpu(self) -> bool:
        """Whether `device` is a CUDA device (where stacked teams, CUDA graphs and capturable Adam apply)."""
        return torch.device(self.device).type == "cuda"


@dataclass
class RuntimeConfig(DeviceConfig):
    """The run options of a training run: how it uses the machine, not what it learns. A fixed seed learns the same
    under any of them (up to float rounding where a key says so, and on another device), so they are not part of a
    run's identity: a checkpoint leaves them out (`TrainConfig.identity`), and a run resumes under others."""

    teams: int = option(
        1, "train seeds seed .. seed+teams-1 at once, one batch of teams x num_envs kitchens; each team writes "
           "its own run directory, as a run of its own would"
    )
    parallel_teams: int = option(
        0, "teams whose PPO updates run at once (or a team's minibatch shards), each on a thread of its own with "
           "`threads` torch threads (0: as many as the CPU cores allow); the results are those of one at a time"
    )
    minibatch_shards: int = option(
        0, "split every PPO minibatch into this many equal parts by kitchen and average their gradients, computed "
           "at once on threads when one team learns (IPPO; equal to the minibatch's gradient up to float rounding); "
           "0: 2 on a CPU at hidden >= 128 where the kitchens split evenly, else 1"
    )
    compile_policy: bool = option(
        False, "torch.compile the acting policy: the same actions, faster collection after a one-off compilation "
               "(on a GPU, the teams' stacked networks replay as CUDA graphs)"
    )
    collector: str = option(
        "xla", '"xla": MLP, ego_mlp and GNN teams and their LSTMs (shared or per-agent networks) act inside the '
               'kitchens\' XLA program, a whole batch one call (torch_kitchen.xla_rollout; actions drawn by JAX), '
               'E3T as "kitchen"; "kitchen": the '
               'kitchens\' own in-place rollout (torch_kitchen.rollout); "torchrl": TorchRL\'s Collector; the last '
               'two collect the same batches bit for bit, the first at a fraction of the host\'s work per step'
    )
    compile_update: bool = option(
        False, "torch.compile each PPO minibatch step (loss, backward, clipping, Adam with the learning rate a tensor) "
               "as one function; on a GPU its graphs replay as CUDA graphs, on a CPU the sparse first layers stay "
               "sparse inside them (at hidden 64 a quarter off an update, after a one-off compilation of 8-25 s); "
               "equal to eager up to float rounding"
    )

    def check(self, seed: int, kitchens_per_minibatch: int) -> None:
        """Refuses run options no run can use, some of them with the run's shape: its first `seed` and the
        kitchens of its minibatches."""
        runtime = self
        at_least(runtime, ["threads", "teams"], 1, "runtime.")
        at_least(runtime, ["parallel_teams", "minibatch_shards"], 0, "runtime.")
        if seed + runtime.teams - 1 > MAX_SEED:
            raise ConfigError(f"runtime.teams={runtime.teams} from seed={seed} go past the largest seed, "
                              f"{MAX_SEED}")
        if runtime.compile_update and runtime.minibatch_shards > 1:
            raise ConfigError(f"runtime.compile_update compiles a whole minibatch's step: runtime.minibatch_shards="
                              f"{runtime.minibatch_shards} splits it; set runtime.minibatch_shards=1 (or 0)")
        if runtime.minibatch_shards > 1 and kitchens_per_minibatch % runtime.minibatch_shards:
            raise ConfigError(
                f"runtime.minibatch_shards ({runtime.minibatch_shards}) must divide the {kitchens_per_minibatch} "
                "kitchens of a minibatch (num_envs / minibatches): shards are equal parts"
            )
        if runtime.collector not in COLLECTORS:
            raise ConfigError(f"runtime.collector={runtime.collector!r}: choose one of {', '.join(COLLECTORS)}")
        check_device(runtime.device, "runtime.device")
        for key in ("compile_update", "compile_policy"):
            if getattr(runtime, key) and not runtime.on_gpu:
                check_cpp_compiler(f"runtime.{key}")


@dataclass
class PPOConfig:
    """The PPO core's settings (`trainers.ppo`): what every algorithm optimises with, whatever it adds."""

    lr: float = option(2.5e-4, "Adam's learning rate")
    anneal_lr: bool = option(True, "anneal the learning rate linearly to 0 over the run")
    adam_eps: float = option(1e-5, "Adam's epsilon")
    epochs: int = option(4, "passes over each batch")
    minibatches: int = option(4, "split over kitchens, so every minibatch holds whole sequences (for recurrent models)")
    gamma: float = option(0.99, "discount factor")
    gae_lambda: float = option(0.95, "lambda of the generalised advantage estimate")
    clip_epsilon: float = option(0.2, "PPO clip range, for the policy ratio and the value")
    entropy_coef: float = option(0.01, "weight of the entropy bonus in the loss")
    value_coef: float = option(0.5, "weight of the value loss")
    max_grad_norm: float = option(0.5, "gradients are clipped to this global norm")
    shaping_weight: float = option(0.0, "weight of the shaped reward added to the sparse one (0: sparse only)")
    shaping_anneal_steps: int = option(0, "anneal shaping_weight linearly to 0 over this many env steps (0: constant)")

    def check(self) -> None:
        at_least(self, ["epochs", "minibatches"], 1, "ppo.")
        at_least(self, ["entropy_coef", "value_coef", "shaping_weight", "shaping_anneal_steps"], 0, "ppo.")
        for name in ("lr", "adam_eps", "clip_epsilon", "max_grad_norm"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"ppo.{name} must be greater than 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"ppo.{name} must lie in [0, 1], got {getattr(self, name)}")


@dataclass
class DistillConfig:
    """The planner-guided start (`kitchen-distill`, and `init_from: scripted_cook`): the scripted cook, or conventions
    of the zoo, distilled into the team's networks by DAgger (`trainers.ppo.distill`)."""

    rounds: int = option(7, "DAgger rounds of distill.kitchens x rollout_steps steps each")
    kitchens: int = option(128, "kitchens rolled out at once in each round")
    teacher_decay: float = option(
        0.5, "a seat takes the scripted cook's action with probability teacher_decay**round (round 0: always)"
    )
    epochs: int = option(3, "fitting passes after each round")
    replay: float = option(
        0.0, "0: each fitting pass reads every round's data; r > 0: the newest round's kitchens and r times as many "
             "drawn at random from the earlier rounds' (all of them where they hold fewer), a round's cost whatever "
             "the rounds before it (fewer gradient steps: a worse start at the main job's budget, BENCHMARKS.md)"
    )
    minibatch: int = option(
        4, "kitchens' steps per fitting step: whole sequences for a recurrent learner, else as many steps drawn "
           "from every kitchen"
    )
    lr: float = option(6e-3, "Adam's rate, annealed linearly over the rounds")
    move_order: str = option(
        "NSEW", "the scripted cook's choice among equally short moves, the first in this order (a permutation of NSEW; "
                "cooks with other orders keep other conventions)"
    )
    symmetries: bool = option(True, "fit each minibatch under a random mirror image or quarter turn of its kitchens")
    teachers: list[str] = option(
        [], "conventions of the zoo's training split to learn from instead of the scripted cook (never a held-out "
            "stranger); empty: the scripted cook"
    )
    teacher_mix: str = option(
        "seed", 'with teachers: "seed" (seed k learns from teacher k mod n, one convention per seed) or "round" (each '
                "DAgger round from a teacher drawn by seed and round)"
    )

    def check(self) -> None:
        """Refuses values no distillation can use (the teachers' names are the zoo's to check)."""
        at_least(self, ["rounds", "kitchens", "epochs", "minibatch"], 1, "distill.")
        at_least(self, ["replay"], 0, "distill.")
        if sorted(self.move_order) != sorted("NSEW"):
            raise ConfigError(f"distill.move_order must be a permutation of NSEW, got {self.move_order!r}")
        if self.teacher_mix not in TEACHER_MIXES:
            raise ConfigError(f"distill.teacher_mix must be one of {', '.join(TEACHER_MIXES)}, got "
                              f"{self.teacher_mix!r}")
        if not self.lr > 0:
            raise ConfigError(f"distill.lr must be greater than 0, got {self.lr}")
        if not 0.0 <= self.teacher_decay <= 1.0:
            raise ConfigError(f"distill.teacher_decay must lie in [0, 1], got {self.teacher_decay}")
        if self.teachers and self.move_order != "NSEW":
            raise ConfigError("distill.move_order sets the scripted cook's moves; distill.teachers have their own "
                              "conventions: give one or the other")


# The PPO core's and distillation's keys as they were before they had sections, as saved runs and older files hold
# them: `lr` is now `ppo.lr`, `distill_rounds` is `distill.rounds`.
FLAT_KEYS = {**{field.name: ("ppo", field.name) for field in dataclasses.fields(PPOConfig)},
             **{f"distill_{field.name}": ("distill", field.name) for field in dataclasses.fields(DistillConfig)}}


def sectioned_keys(values: dict) -> dict:
    """`values` with the keys of before the `ppo` and `distill` sections (`lr`, `distill_rounds`) put in them."""
    if not any(key in values for key in FLAT_KEYS):
        return values
    values = dict(values)
    for key in [key for key in values if key in FLAT_KEYS]:
        section, name = FLAT_KEYS[key]
        values[section] = {name: values.pop(key), **(values.get(section) or {})}
    return values
