"""A planner-guided start: the scripted cook distilled into a team's torch networks by DAgger.

    kitchen-distill configs/ippo/ego_mlp_ik.yaml name=distill_ego_mlp_ik
    kitchen-train configs/ippo/ego_mlp_ik.yaml init_from=runs/distill_ego_mlp_ik/seed{seed}
    kitchen-train configs/ippo/ego_mlp_ik.yaml init_from=scripted_cook    # both: distils into RUN/distilled first

Round r rolls out the learner in `distill.kitchens` kitchens for `rollout_steps` steps, both seats, where each
seat takes the scripted cook's action instead of its own with probability `distill.teacher_decay ** r` (round 0:
the cook alone, behaviour cloning). With `runtime.collector=xla` (the default) the whole round, the learner's and the
cook's draws and the labels, is one XLA program (`torch_kitchen.xla_rollout`); else the cook plans step by step
(`GuidedPolicy`). Every visited state is labelled with the cook's action distribution and kept: the data of every
round, none dropped. Then the actor is fitted to the labels by cross-entropy (`distill.epochs` passes over every
round's data, or with `distill.replay` r > 0 over the newest round's kitchens and r times as many drawn from the
earlier rounds', a round's cost whatever the rounds before it; each minibatch under a random mirror image or quarter
turn of its kitchens with `distill.symmetries`), and the critic to the value targets of the round's own batch (GAE,
as PPO's), so that self-play starts with values for the policy it starts from.

Logged (TensorBoard, CSV), checkpointed after every round and resumed (`--resume RUN_DIR`) as training is. A
checkpoint holds the networks in the trainer's format: `kitchen-eval` and `kitchen-play` read it as a trained
team, and `init_from` starts IPPO from it. Any architecture distils (recurrent ones over whole sequences).
"""

from __future__ import annotations

import dataclasses
import fcntl
import hashlib
import itertools
import json
import shutil
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.modules import set_recurrent_mode
from tqdm import tqdm

from torch_kitchen.keys import LOGITS, OBSERVATION, VALUE, VALUE_TARGET
from torch_kitchen.models import ActorCritic, make_actor_critic, model_identity
from torch_kitchen.partners.conventions import fingerprints
from torch_kitchen.partners.guide import TEACHER_PROBS, GuidedPolicy
from torch_kitchen.partners.scripted_cook import ScriptedCook
from torch_kitchen.symmetry import symmetries_of, transform_action_probs, transform_observation
from trainers.algorithms import algorithm_settings, check_algorithm
from trainers.checkpoint import (
    LATEST,
    CheckpointError,
    capture_rng_states,
    load_checkpoint,
    restore_rng_states,
    save_checkpoint,
)
from trainers.config import PLANNER_START, RESUMABLE, ConfigError, TrainConfig
from trainers.config.compose import load_config, save_config, train_config_parser
from trainers.plugins import PluginError, add_plugin_option, import_plugins
from trainers.ppo.advantages import compute_advantages, shaping_weight_at
from trainers.ppo.collection import finished_episode_deliveries, make_collector, select_kitchens
from trainers.ppo.resume import load_to_resume, make_loggers, start_fresh
from trainers.ppo.team import (
    TeamKitchens,
    make_env,
    make_optimizer,
    place_networks,
    set_learning_rate,
    with_model_transforms,
)

DATA = "dagger"  # the run's folder of every round's labelled batch


def teacher_share(config: TrainConfig, round_: int) -> float:
    """The probability that a seat acts as the teacher in round `round_` (0-based): 1 in the first."""
    return config.distill.teacher_decay ** round_


def learning_rate(config: TrainConfig, round_: int) -> float:
    """The fitting rate of round `round_`: `distill.lr`, annealed linearly over the rounds."""
    return config.distill.lr * (1.0 - round_ / config.distill.rounds)


def cross_entropy(logits: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """The mean over seats and steps of -sum(p * log q): logits [..., 6] of q, p the teacher's [..., 6]."""
    return -(probs * torch.log_softmax(logits, dim=-1)).sum(-1).mean()


def under_random_symmetry(data: TensorDictBase) -> TensorDictBase:
    """`data`'s observations and the teacher's labels under one random symmetry of the kitchen
    (`torch_kitchen.symmetry`): the same lesson in a mirrored kitchen."""
    observation = data.get(OBSERVATION)
    symmetry = int(torch.randint(symmetries_of(*observation.shape[-3:-1]), ()))
    mirrored = data.clone(False)
    mirrored.set(OBSERVATION, transform_observation(observation, symmetry))
    mirrored.set(TEACHER_PROBS, transform_action_probs(data.get(TEACHER_PROBS), symmetry))
    return mirrored


def minibatches(data: TensorDictBase, size: int, device: str | torch.device, sequences: bool
                ) -> list[TensorDictBase]:
    """`data` [K, T] (on `device`, the run's) in a random order, in minibatches of `size` kitchens' steps: with
    `sequences` (a recurrent learner's), whole sequences of `size` kitchens [size, T]; else `size` x T steps drawn
    from every kitchen and step [size * T]. A kitchen's steps in a row are much alike, so a feed-forward learner
    fits far more per step from steps drawn apart (BENCHMARKS.md, "Distillation's fitting")."""
    if not sequences:
        data, size = data.reshape(-1), size * data.shape[1]
    order = torch.randperm(data.shape[0], device=device)
    return [select_kitchens(data, rows) for rows in order.split(size)]


def replayed(rounds: Sequence[TensorDictBase], replay: float, device: str | torch.device) -> TensorDictBase:
    """What one fitting pass reads, on `device`: every one of the `rounds` [K, T] (`replay` 0), or the newest and
    `replay` x K kitchens drawn at random from the earlier ones (all of them where they hold fewer). Only the drawn
    kitchens are read from the memory-mapped files."""
    *earlier, newest = rounds
    sizes = torch.tensor([len(part) for part in earlier], dtype=torch.long)
    if replay == 0 or round(replay * len(newest)) >= sizes.sum():
        return torch.cat(list(rounds)).to(device)
    drawn = torch.randperm(int(sizes.sum()))[:round(replay * len(newest))].sort().values
    starts = torch.cumsum(sizes, 0) - sizes
    parts = [newest]
    for part, start, size in zip(earlier, starts.tolist(), sizes.tolist()):
        rows = drawn[(drawn >= start) & (drawn < start + size)] - start
        if len(rows):
            parts.append(select_kitchens(part, rows))
    return torch.cat([part.to(device) for part in parts])


def fit(actor_critic: ActorCritic, optimizer: torch.optim.Optimizer, rounds: Sequence[TensorDictBase],
        batch: TensorDictBase, config: TrainConfig) -> dict[str, float]:
    """`distill.epochs` passes of the actor's cross-entropy to the teacher over the `rounds`' data [K, T] (every
    round's, or with `distill.replay` the newest round's and a fresh draw of the earlier ones': `replayed`), each
    with one pass of the critic's squared error to the value targets of this round's `batch` [distill.kitchens, T]
    (in its first steps); returns their means and the actor's agreement with the teacher's most likely action."""
    size, device, sequences = config.distill.minibatch, config.runtime.device, actor_critic.recurrent
    parameters = [parameter for group in optimizer.param_groups for parameter in group["params"]]
    imitations, value_errors = [], []  # on the device, read once at the end
    every_round = replayed(rounds, 0, device) if config.distill.replay == 0 else None  # read once, not per pass
    with set_recurrent_mode(True):
        for _ in range(config.distill.epochs):
            data = every_round if every_round is not None else replayed(rounds, config.distill.replay, device)
            # One pass over the round's batch per pass over the data: the critic learns the current policy's values.
            pairs = itertools.zip_longest(minibatches(data, size, device, sequences),
                                          minibatches(batch, size, device, sequences))
            for own, current in pairs:
                if config.distill.symmetries:
                    own = under_random_symmetry(own)
                # The logits alone: no action drawn.
                logits = actor_critic.actor.get_dist_params(own.clone(False)).get(LOGITS)
                probs = own.get(TEACHER_PROBS)
                imitation = cross_entropy(logits, probs)
                loss = imitation
                if current is not None:
                    value = actor_critic.critic(current.clone(False)).get(VALUE)
                    value_error = (value - current.get(VALUE_TARGET)).pow(2).mean()
                    loss = loss + config.ppo.value_coef * value_error
                    value_errors.append(value_error.detach())
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(parameters, config.ppo.max_grad_norm)
                optimizer.step()
                agreement = (logits.argmax(-1) == probs.argmax(-1)).float().mean()
                imitations.append(torch.stack([imitation.detach(), agreement]))
    imitation, agreement = torch.stack(imitations).mean(0).tolist()
    value_error = torch.stack(value_errors).mean().item()
    return {"distill/cross_entropy": imitation, "distill/value_error": value_error, "distill/agreement": agreement}


def kept(batch: TensorDictBase, actor_critic: ActorCritic) -> TensorDictBase:
    """What a round keeps of its batch: what the actor reads and the teacher's labels (a copy: the collector
    reuses its buffers)."""
    keys = {*actor_critic.actor.in_keys, TEACHER_PROBS}
    return batch.select(*keys, strict=False).clone()


def round_path(run: Path, round_: int) -> Path:
    return run / DATA / f"round{round_}"


def load_rounds(run: Path, rounds: int) -> list[TensorDictBase]:
    """The labelled data of rounds 0 .. rounds - 1 (memory-mapped)."""
    missing = [r for r in range(rounds) if not round_path(run, r).exists()]
    if missing:
        raise CheckpointError(f"{run} lacks the data of round(s) {missing} in {run / DATA}: distil it again")
    return [TensorDict.load_memmap(round_path(run, r)) for r in range(rounds)]


def distill(config: TrainConfig, resume: bool = False, run: Path | None = None,
            on_round: Callable[[int, dict], bool | None] | None = None) -> Path:
    """Distils the scripted cook into `config.architecture` over `config.distill.rounds` rounds (see the module
    docstring); returns the run directory. `resume`: continue the run from its last round. `on_round(round,
    metrics)`: called after every round's checkpoint; returning True stops the run there. Raises ConfigError or
    CheckpointError before any work."""
    config = checked(config)
    run = Path(run or config.run_path)
    checkpoint = run / "checkpoints" / LATEST
    if not resume and checkpoint.exists():
        raise ConfigError(f"{run} already holds a run; resume it with `kitchen-distill --resume {run}`, or choose "
                          "another name=, seed= or run_dir=")
    torch.set_num_threads(config.runtime.threads)
    torch.manual_seed(config.seed)

    kitchen = make_env(config, num_envs=config.distill.kitchens)
    actor_critic, optimizer, parts, identity = learner_parts(config, kitchen)
    teacher = ScriptedCook(config.distill_teacher(0)).to(config.runtime.device)
    policy = GuidedPolicy(actor_critic.acting_policy(), teacher)

    done_rounds, env_steps, rng = rounds_done(config, run, parts, identity, resume)
    if done_rounds >= config.distill.rounds:
        print(f"{run}: already distilled for {done_rounds} rounds; raise distill.rounds to go on")
        return run
    data = load_rounds(run, done_rounds)
    run.mkdir(parents=True, exist_ok=True)
    save_config(config, run / "config.yaml")
    loggers = make_loggers(config, run, purge_step=env_steps + 1 if resume else None)

    collector = make_collector(with_model_transforms(kitchen, actor_critic), policy,
                               config.distill.kitchens * config.rollout_steps, kind=config.runtime.collector)
    if rng is not None:  # after the collector, whose construction runs the policy once
        restore_rng_states(rng)
    bar = tqdm(total=config.distill.rounds, initial=done_rounds, unit="round", disable=not config.progress,
               dynamic_ncols=True)
    try:
        batches = iter(collector)
        for round_ in range(done_rounds, config.distill.rounds):
            policy.teacher = ScriptedCook(config.distill_teacher(round_)).to(config.runtime.device)
            policy.teacher_share = teacher_share(config, round_)
            batch = next(batches)
            env_steps += batch.numel()
            metrics = learn_round(config, round_, batch, env_steps, data, actor_critic, optimizer, run)
            metrics["distill/teacher_share"] = policy.teacher_share
            for logger in loggers:
                logger.log_metrics(metrics, step=env_steps)
            save_round(config, checkpoint, parts, identity, round_ + 1, env_steps)
            bar.update(1)
            bar.set_postfix(agreement=f"{metrics['distill/agreement']:.2f}",
                            deliveries=f"{metrics.get('charts/episode_deliveries', float('nan')):.2f}")
            if on_round is not None and on_round(round_ + 1, metrics):
                break
    finally:
        collector.shutdown()
        bar.close()
        for logger in loggers:
            logger.close()
    return run


def learner_parts(config: TrainConfig, kitchen) -> tuple[ActorCritic, torch.optim.Optimizer, dict, dict]:
    """The learner's networks on the run's device, the trainer's Adam (its rate set at every round), what a
    checkpoint holds of them and of the kitchens, and the model's identity."""
    actor_critic = make_actor_critic(config.architecture, kitchen.obs_shape, config.hidden, config.share_params)
    place_networks(config, actor_critic, own_kernels=True)
    optimizer = make_optimizer(config, [*actor_critic.actor.parameters(), *actor_critic.critic.parameters()])
    identity = model_identity(config.architecture, kitchen.obs_shape, config.hidden, config.share_params)
    parts = {"actor": actor_critic.actor, "critic": actor_critic.critic, "optimizer": optimizer,
             "env": TeamKitchens(kitchen, 0)}
    return actor_critic, optimizer, parts, identity


def checked(config: TrainConfig) -> TrainConfig:
    """The config checked as a distillation's, before any work: one team, its levels loadable and solvable."""
    config = check_algorithm(config.check())
    config.check_run_location()
    if config.runtime.teams != 1:
        raise ConfigError("kitchen-distill distils one team; run it once per seed")
    for warning in config.check_levels():
        print(f"kitchen-distill: warning: {warning}", file=sys.stderr)
    return config


def rounds_done(config: TrainConfig, run: Path, parts: dict, identity: dict, resume: bool
                ) -> tuple[int, int, dict | None]:
    """(rounds done, env steps, random states): nothing for a fresh run (its folder's old logs removed); for a
    resumed one, its latest checkpoint loaded into `parts`, refused where its model or what it learns differs (more
    rounds may follow)."""
    if not resume:
        start_fresh(run)
        return 0, 0, None
    state = load_to_resume(run, run / "checkpoints" / LATEST, config, identity, (*RESUMABLE, "distill.rounds"))
    for name, part in parts.items():
        part.load_state_dict(state[name])
    return state["update"], state["env_steps"], state["rng"]


def save_round(config: TrainConfig, checkpoint: Path, parts: dict, identity: dict, rounds: int, env_steps: int
               ) -> None:
    """The checkpoint after `rounds` rounds, in the trainer's format, with the conventions the team met."""
    save_checkpoint(checkpoint, {
        "config": config.to_dict(), "model": identity, **{name: part.state_dict() for name, part in parts.items()},
        "algorithm": {}, "update": rounds, "env_steps": env_steps, "rng": capture_rng_states(),
        "met": fingerprints(config.distill_teacher(r) for r in range(rounds)),
    })  # fmt: skip


def learn_round(config: TrainConfig, round_: int, batch: TensorDictBase, env_steps: int, data: list,
                actor_critic: ActorCritic, optimizer: torch.optim.Optimizer, run: Path) -> dict[str, float]:
    """Round `round_` of distillation on its `batch` (the guided policy's, `env_steps` in all so far): the batch's
    value targets, its kept steps added to `data` (memory-mapped into the run's folder), and the networks fitted
    to the rounds' data (`fit`) at the round's learning rate. Returns the round's metrics."""
    deliveries = finished_episode_deliveries(batch)
    compute_advantages(batch, actor_critic.critic, config, shaping_weight_at(config, env_steps))
    data.append(kept(batch, actor_critic).memmap_(round_path(run, round_)))
    set_learning_rate(config, optimizer, learning_rate(config, round_))
    metrics = fit(actor_critic, optimizer, data,
                  batch.select(*actor_critic.critic.in_keys, VALUE_TARGET, strict=False), config)
    metrics["distill/kitchen_steps"] = sum(part.numel() for part in data)
    metrics["charts/learning_rate"] = learning_rate(config, round_)
    if len(deliveries):
        metrics["charts/episode_deliveries"] = float(deliveries.float().mean())
    return metrics


# Where the planner-guided starts are kept, under a run's run_dir, each in a folder named by `start_key`.
SHARED_STARTS = ".distilled"
# The settings distillation never reads: runs that differ in these alone start from the same distilled team.
NOT_DISTILLED = ("name", "run_dir", "algorithm", "algorithm_config", "total_steps", "init_from", "learned_stranger",
                 "checkpoint_every", "snapshots", "loggers", "progress", "eval_episodes", "eval_heldout", "gif")


def start_key(config: TrainConfig) -> str:
    """A name for the distillation `config` asks for: a hash of every setting but `NOT_DISTILLED`, with the zoo file
    read for what it holds (its teachers' fingerprints, where a teacher is named), so two runs share a start
    only where their distillations are the same, whichever file a teacher came from and however it was redrawn."""
    settings = {key: value for key, value in config.to_dict().items() if key not in NOT_DISTILLED}
    settings.pop("zoo")
    if config.distill.teachers:
        settings["teachers"] = sorted(fingerprints(config.distill_teacher(r) for r in range(config.distill.rounds)))
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def distill_start(config: TrainConfig, run: Path) -> Path:
    """The planner-guided start of a training run (`init_from: scripted_cook`) in `run`: distilled once per
    distillation's settings into `run_dir/.distilled/<start_key>` (runs that differ only in what they do after it,
    an algorithm or a budget, share it; two processes asking for one wait for each other), its rounds' data dropped
    once it is done, then copied into `run`."""
    shared = Path(config.run_dir) / SHARED_STARTS / start_key(config)
    shared.parent.mkdir(parents=True, exist_ok=True)
    with open(shared.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        checkpoint = shared / "checkpoints" / LATEST
        if checkpoint.exists() and load_checkpoint(checkpoint)["update"] >= config.distill.rounds:
            print(f"{run}: its start was distilled with the same settings in {shared}, reused (remove that folder to "
                  "distil it again)", file=sys.stderr)
        else:
            own = dataclasses.replace(config, init_from="")
            if (shared / "config.yaml").exists():  # begun by another run: carried on with its settings of what follows
                begun = load_config(shared / "config.yaml")
                own = dataclasses.replace(own, **{key: getattr(begun, key) for key in NOT_DISTILLED})
            distill(own, resume=checkpoint.exists(), run=shared)
        # Its rounds' data (hundreds of MB) only served a distillation stopped part way: more rounds are another key.
        shutil.rmtree(shared / DATA, ignore_errors=True)
    shutil.rmtree(run, ignore_errors=True)
    shutil.copytree(shared, run, ignore=shutil.ignore_patterns(DATA))
    save_config(dataclasses.replace(config, init_from=""), run / "config.yaml")  # the run's own name and settings
    return run


def distill_planner_starts(configs: Sequence[TrainConfig], runs: Sequence[Path]) -> None:
    """The planner-guided start of every team whose `init_from` asks for it, a step before its training: distilled
    into the team's run folder, or copied there from a distillation of the same settings (`distill_start`)."""
    for config, run in zip(configs, runs):
        if config.init_from == PLANNER_START:
            distill_start(config, config.init_path(run))


def main(argv: Sequence[str] | None = None) -> int:
    parser = train_config_parser("kitchen-distill", "Distil the scripted cook into a team's networks by DAgger over "
                                 "its kitchens (a planner-guided start for kitchen-train's init_from).",
                                 algorithm_settings())
    parser.add_argument("--resume", metavar="RUN_DIR", help="continue the run in RUN_DIR from its latest round")
    add_plugin_option(parser)
    args = parser.parse_intermixed_args(argv)  # overrides may follow --import MODULE
    try:
        import_plugins(args.plugins)
        if args.resume:
            overrides = [item for item in [args.config, *args.overrides] if item]
            saved = Path(args.resume) / "config.yaml"
            if not saved.is_file():
                raise ConfigError(f"{args.resume} is not a run directory (no config.yaml in it)")
            distill(load_config(saved, overrides), resume=True, run=Path(args.resume))
        else:
            if args.config is None:
                raise ConfigError("give a config file (e.g. configs/ippo/ego_mlp_ik.yaml) or --resume RUN_DIR")
            distill(load_config(args.config, args.overrides))
    except (ConfigError, CheckpointError, ValueError, PluginError) as error:
        print(f"kitchen-distill: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("kitchen-distill: stopped; continue from the last round with --resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
