"""Self-play on the Infinite Kitchen with TorchRL: a `Collector` over `KitchenEnv`, GAE, `ClipPPOLoss`.

Read top to bottom: build the env and the networks, the loss and the optimizer, then for every batch of
`num_envs x rollout_steps` steps compute the rewards, the advantages and a few epochs of PPO, then log and
checkpoint. Two algorithms:

- IPPO: both agents are trained on their own transitions (independent PPO); with `share_params` they share one
  network.
- E3T (Yan et al., 2023): in every episode one agent, drawn per kitchen, is a mixed partner acting from
  (1 - eps) * pi + eps * uniform (`torch_kitchen.partner`); PPO trains on the other agent's (the ego's)
  transitions only, whose log-probabilities are those of the policy that acted. The actor carries a partner
  predictor, trained by cross-entropy on the partner's actual actions, whose prediction the policy reads.

    kitchen-train configs/ippo/mlp_ik.yaml seed=3 total_steps=1e6
    kitchen-train --resume runs/ippo_mlp_ik/seed3
"""

from __future__ import annotations

import argparse
import copy
import math
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torch.utils.tensorboard import SummaryWriter
from torchrl.envs import Transform
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value.functional import generalized_advantage_estimate
from torchrl.record.loggers import CSVLogger, TensorboardLogger
from tqdm import tqdm

from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.models import ActorCritic, make_actor_critic
from torch_kitchen.partner import MIXED, PartnerMixture, PartnerSeats
from trainers.checkpoint import LATEST, CheckpointError, check_identity, load_checkpoint, model_identity, save_checkpoint
from trainers.config import ConfigError, TrainConfig, load_config, save_config
from trainers.rollout import finished_episode_deliveries, make_collector

ACTION, LOG_PROB, VALUE = ("agents", "action"), ("agents", "action_log_prob"), ("agents", "state_value")
ADVANTAGE, VALUE_TARGET = ("agents", "advantage"), ("agents", "value_target")
EGO = ("agents", "ego")  # E3T: bool [B, T, 2], the transitions PPO learns from


class _TensorboardLogger(TensorboardLogger):
    """TorchRL's TensorBoard logger, purging the events a killed run wrote after its last checkpoint."""

    def __init__(self, exp_name: str, log_dir: str, purge_step: int | None = None):
        self._purge_step = purge_step
        super().__init__(exp_name=exp_name, log_dir=log_dir)

    def _create_experiment(self) -> SummaryWriter:
        return SummaryWriter(log_dir=str(Path(self.log_dir) / self.exp_name), purge_step=self._purge_step)


def make_env(config: TrainConfig, num_envs: int | None = None, levels=None, seed: int | None = None) -> KitchenEnv:
    """The `KitchenEnv` of a config (evaluation passes its own batch, levels and seed)."""
    return KitchenEnv(
        num_envs=num_envs or config.num_envs,
        levels=config.levels if levels is None else levels,
        max_steps=config.max_steps,
        device=config.device,
        seed=config.seed if seed is None else seed,
    )


def with_model_transforms(env: KitchenEnv, actor_critic: ActorCritic, *extra: Transform):
    """`env` plus the transforms the model needs (episode-start flags and recurrent state for LSTMs, the partner
    context for E3T models), then `extra` ones."""
    return with_transforms(env, [*actor_critic.env_transforms(), *extra])


def make_loss(config: TrainConfig, actor_critic: ActorCritic) -> ClipPPOLoss:
    """TorchRL's clipped PPO loss on the ("agents", ...) keys, with the protocol's coefficients.

    E3T: the loss counts the ego's transitions only (TorchRL's `loss_mask_key`), and the advantages arrive
    normalised over those (`normalize_ego_advantage`).
    """
    e3t = config.algorithm == "e3t"
    loss_module = ClipPPOLoss(
        actor_critic.ppo_actor or actor_critic.actor,
        actor_critic.critic,
        clip_epsilon=config.clip_epsilon,
        entropy_coeff=config.entropy_coef,
        critic_coeff=config.value_coef,
        loss_critic_type="l2",
        normalize_advantage=not e3t,  # per minibatch, pooled over kitchens, steps and agents
        normalize_advantage_exclude_dims=(-1,),  # only the trailing singleton: says "pooled" without a warning
        clip_value=True,
    )
    loss_module.set_keys(
        action=ACTION, sample_log_prob=LOG_PROB, value=VALUE, advantage=ADVANTAGE, value_target=VALUE_TARGET
    )
    if e3t:
        loss_module.loss_mask_key = EGO
    return loss_module


def normalize_ego_advantage(minibatch: TensorDictBase) -> None:
    """E3T: standardises the advantages with the mean and deviation of the ego's transitions (IPPO's loss pools
    all of a minibatch's; here the mixed partner's would skew them)."""
    advantage, ego = minibatch.get(ADVANTAGE), minibatch.get(EGO).unsqueeze(-1)
    mean = advantage[ego].mean()
    std = advantage[ego].std(correction=0).clamp_min(1e-4) if ego.sum() > 1 else advantage.new_ones(())
    minibatch.set(ADVANTAGE, (advantage - mean) / std)


def partner_prediction_loss(predictor, minibatch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """E3T: cross-entropy of every agent's predicted partner action against the action the partner took at that
    step, and the accuracy of the most likely one, over whole kitchen sequences [mb, T]. The predictor reads
    only the context of earlier steps."""
    logits = predictor.sequence_logits(minibatch)  # [mb, T, 2, 6]
    partner_action = minibatch.get(ACTION).flip(-1)
    loss = torch.nn.functional.cross_entropy(logits.flatten(0, -2), partner_action.flatten())
    accuracy = (logits.argmax(-1) == partner_action).float().mean()
    return loss, accuracy.detach()


def compute_advantages(batch: TensorDictBase, critic, config: TrainConfig, shaping_weight: float) -> None:
    """Writes the training reward, GAE advantages and value targets into `batch` ([B, T], agents [B, T, 2]).

    Values come from the collection pass (the policy runs the critic), so recurrent critics see the hidden
    state they had while acting; only the step after the batch needs a new critic call. The time limit ends
    an episode as a terminal state, as in the paper's JaxMARL code: no bootstrap across it.
    """
    next_ = batch["next"]
    reward = next_["agents", "reward"] + shaping_weight * next_["agents", "shaped_reward"]
    next_["agents", "reward"] = reward  # the loss and the logs see the reward that was optimised
    done = next_["done"].unsqueeze(-2).expand_as(reward)  # [B, T, 1] -> [B, T, 2, 1]
    value = batch.get(VALUE)
    with torch.no_grad():
        after = critic(next_[:, -1].clone()).get(VALUE)
    next_value = torch.cat([value[:, 1:], after.unsqueeze(1)], dim=1)
    # The functional GAE wants time next to the feature dim: [B, 2, T, 1].
    advantage, target = generalized_advantage_estimate(
        config.gamma,
        config.gae_lambda,
        value.transpose(1, 2),
        next_value.transpose(1, 2),
        reward.transpose(1, 2),
        done.transpose(1, 2),
        done.transpose(1, 2),
        time_dim=-2,
    )
    batch.set(ADVANTAGE, advantage.transpose(1, 2))
    batch.set(VALUE_TARGET, target.transpose(1, 2))


def explained_variance(value: torch.Tensor, target: torch.Tensor) -> float:
    variance = target.var()
    return float("nan") if variance == 0 else float(1 - (target - value).var() / variance)


def shaping_weight_at(config: TrainConfig, env_steps: int) -> float:
    if config.shaping_anneal_steps <= 0:
        return config.shaping_weight
    return config.shaping_weight * max(0.0, 1.0 - env_steps / config.shaping_anneal_steps)


class _StopRequest:
    """First Ctrl-C (or SIGTERM): finish the current update, checkpoint, exit. Second Ctrl-C: stop now."""

    def __init__(self):
        self.requested = False
        self._previous = {}

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[sig] = signal.signal(sig, self._handle)
            except ValueError:  # not the main thread: leave signals alone
                pass
        return self

    def _handle(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        tqdm.write("stopping after this update (checkpoint first); press Ctrl-C again to stop at once")

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def train(
    config: TrainConfig,
    actor_critic: ActorCritic | None = None,
    resume: bool = False,
    on_update: Callable[[int, dict], bool | None] | None = None,
    run: Path | None = None,
) -> Path:
    """Trains a self-play team; returns the run directory (config.yaml, checkpoints/, tensorboard/, csv/).

    `actor_critic`: your own networks honouring the keys of `torch_kitchen.models` (default: built from
    `config.architecture`). `resume`: continue the run in `config.run_path` from its latest checkpoint.
    `on_update(update, metrics)`: called after every update; returning True stops the run after a checkpoint.
    `run`: the run directory (default `config.run_path`).
    """
    torch.set_num_threads(config.threads)
    torch.manual_seed(config.seed)
    run = Path(run) if run is not None else config.run_path
    checkpoint_path = run / "checkpoints" / LATEST
    if not resume and checkpoint_path.exists():
        raise ConfigError(
            f"{run} already holds a trained run; resume it with `kitchen-train --resume {run}`, or choose another "
            "name=, seed= or run_dir="
        )

    # ---------------------------------------------------------------- environment and networks
    kitchen = make_env(config)
    obs_shape = kitchen.kitchen.obs_shape
    if actor_critic is None:
        actor_critic = make_actor_critic(config.architecture, obs_shape, config.hidden, config.share_params)
    check_algorithm(config, actor_critic)
    identity = model_identity(config.architecture, obs_shape, config.hidden, config.share_params)
    actor, critic = actor_critic.actor.to(config.device), actor_critic.critic.to(config.device)
    predictor = actor_critic.predictor  # E3T's partner predictor, part of the actor
    e3t = config.algorithm == "e3t"
    # E3T: which agent is the mixed partner (per kitchen and episode), and the optional slow copy of the ego.
    seats = PartnerSeats(config.seed) if e3t else None
    copied = copy.deepcopy(actor).requires_grad_(False) if e3t and config.partner_policy == "copy" else None
    env = with_model_transforms(kitchen, actor_critic, *([seats] if e3t else []))
    acting = [actor, PartnerMixture(config.partner_epsilon, copied)] if e3t else [actor]
    policy = TensorDictSequential(*acting, critic)  # the critic runs while acting: its values feed GAE

    # ---------------------------------------------------------------- loss and optimizer
    loss_module = make_loss(config, actor_critic)
    parameters = [*loss_module.parameters(), *(predictor.parameters() if predictor is not None else [])]
    optimizer = torch.optim.Adam(parameters, lr=config.lr, eps=config.adam_eps)

    # ---------------------------------------------------------------- resume or start
    update, env_steps = 0, 0
    if resume:
        state = load_checkpoint(checkpoint_path, map_location=config.device)
        check_identity(state, identity)
        actor.load_state_dict(state["actor"])
        critic.load_state_dict(state["critic"])
        optimizer.load_state_dict(state["optimizer"])
        kitchen.load_state_dict(state["env"])  # the collector's first reset hands these kitchens out
        if seats is not None:
            seats.load_state_dict(state["partner_seats"])
        if copied is not None:
            copied.load_state_dict(state["partner_copy"])
        update, env_steps = state["update"], state["env_steps"]
    run.mkdir(parents=True, exist_ok=True)
    save_config(config, run / "config.yaml")
    purge = env_steps + 1 if resume else None
    loggers = [_TensorboardLogger("tensorboard", str(run), purge_step=purge), CSVLogger("csv", str(run))]
    if resume:
        _drop_csv_rows_after(run / "csv", env_steps)

    def checkpoint():
        save_checkpoint(
            checkpoint_path,
            {
                "config": config.to_dict(),
                "model": identity,
                "actor": actor.state_dict(),
                "critic": critic.state_dict(),
                "optimizer": optimizer.state_dict(),
                "update": update,
                "env_steps": env_steps,
                "torch_rng": torch.get_rng_state(),
                "env": kitchen.state_dict(),
                **({"partner_seats": seats.state_dict()} if seats is not None else {}),
                **({"partner_copy": copied.state_dict()} if copied is not None else {}),
            },
        )

    remaining = config.num_updates - update
    if remaining <= 0:
        print(f"{run}: already trained for {update} updates ({env_steps:,} steps); raise total_steps to go on")
        return run
    collector = make_collector(env, policy, config.frames_per_batch, remaining * config.frames_per_batch)
    if resume:  # after the collector, whose construction runs the policy once (and draws random actions)
        torch.set_rng_state(state["torch_rng"])
    bar = tqdm(
        total=config.num_updates * config.frames_per_batch,
        initial=env_steps,
        unit="step",
        unit_scale=True,
        disable=not config.progress,
        dynamic_ncols=True,
    )
    recent_deliveries = deque(maxlen=10 * config.num_envs)

    # ---------------------------------------------------------------- training loop
    with _StopRequest() as stop:
        started = time.perf_counter()
        for batch in collector:
            update += 1
            env_steps += batch.numel()
            collected = time.perf_counter()

            # --- learning rate and reward shaping for this update
            lr = config.lr * (1.0 - (update - 1) / config.num_updates) if config.anneal_lr else config.lr
            for group in optimizer.param_groups:
                group["lr"] = lr
            shaping = shaping_weight_at(config, env_steps)
            sparse_return = batch["next", "agents", "reward"].mean() * config.max_steps
            shaped_return = batch["next", "agents", "shaped_reward"].mean() * config.max_steps

            # --- advantages (GAE) over the whole batch
            compute_advantages(batch, critic, config, shaping)
            if e3t:
                batch.set(EGO, ~batch.get(MIXED))

            # --- PPO epochs over minibatches of whole kitchen sequences (E3T: plus the partner predictor)
            stats = []
            with set_recurrent_mode(actor_critic.recurrent):
                for _ in range(config.epochs):
                    for kitchens in torch.randperm(config.num_envs).chunk(config.minibatches):
                        minibatch = batch[kitchens.to(batch.device)]
                        if e3t:
                            normalize_ego_advantage(minibatch)
                        losses = loss_module(minibatch)
                        total = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
                        if predictor is not None:
                            prediction_loss, accuracy = partner_prediction_loss(predictor, minibatch)
                            total = total + config.predictor_coef * prediction_loss
                            losses.set("loss_partner_prediction", prediction_loss).set("partner_accuracy", accuracy)
                        optimizer.zero_grad()
                        total.backward()
                        grad_norm = torch.nn.utils.clip_grad_norm_(parameters, config.max_grad_norm)
                        optimizer.step()
                        stats.append(losses.detach().set("grad_norm", grad_norm.detach()))
            stats = torch.stack(stats).apply(lambda x: x.float().mean(), batch_size=[])
            if copied is not None:  # the slow copy follows the ego
                with torch.no_grad():
                    for slow, ego in zip(copied.parameters(), actor.parameters()):
                        slow.lerp_(ego, config.partner_copy_rate)

            # --- logging
            finished = finished_episode_deliveries(batch)
            recent_deliveries.extend(finished.tolist())
            now = time.perf_counter()
            metrics = {
                "charts/episode_deliveries": float(finished.mean()) if finished.numel() else float("nan"),
                "charts/episode_return": float(sparse_return),
                "charts/shaped_return": float(shaped_return),
                "charts/steps_per_second": batch.numel() / (now - started),
                "charts/collect_seconds": collected - started,
                "charts/update_seconds": now - collected,
                "charts/learning_rate": lr,
                "charts/shaping_weight": shaping,
                "losses/policy": float(stats["loss_objective"]),
                "losses/value": float(stats["loss_critic"]),
                "losses/entropy_loss": float(stats["loss_entropy"]),
                "losses/entropy": float(stats.get("entropy", float("nan"))),
                "losses/approx_kl": float(stats.get("kl_approx", float("nan"))),
                "losses/clip_fraction": float(stats.get("clip_fraction", float("nan"))),
                "losses/grad_norm": float(stats["grad_norm"]),
                "losses/explained_variance": explained_variance(batch.get(VALUE), batch.get(VALUE_TARGET)),
                "losses/partner_prediction": float(stats.get("loss_partner_prediction", float("nan"))),
                "charts/partner_accuracy": float(stats.get("partner_accuracy", float("nan"))),
            }
            for logger in loggers:
                for name, value in metrics.items():
                    if not math.isnan(value):
                        logger.log_scalar(name, value, step=env_steps)
            bar.update(batch.numel())
            recent = sum(recent_deliveries) / max(1, len(recent_deliveries))
            bar.set_postfix(deliveries=f"{recent:.2f}", sps=f"{metrics['charts/steps_per_second']:,.0f}")

            # --- checkpoint, and stop if asked
            asked = bool(on_update(update, metrics)) if on_update is not None else False
            last = update == config.num_updates or asked or stop.requested
            if last or update % config.checkpoint_every == 0:
                checkpoint()
            if last:
                break
            started = time.perf_counter()
    collector.shutdown()
    bar.close()
    return run


def check_algorithm(config: TrainConfig, actor_critic: ActorCritic) -> None:
    """E3T needs a model with a partner predictor (e3t_mlp, e3t_gnn); IPPO one without."""
    if config.algorithm == "e3t" and actor_critic.predictor is None:
        raise ConfigError(
            f"algorithm=e3t needs a model with a partner predictor, and {config.architecture!r} has none: use "
            "architecture=e3t_mlp or e3t_gnn (configs/e3t/)"
        )
    if config.algorithm != "e3t" and actor_critic.predictor is not None:
        raise ConfigError(
            f"{config.architecture!r} carries E3T's partner predictor, which only algorithm=e3t trains: set "
            "algorithm=e3t, or choose an architecture without it (mlp, gnn, ...)"
        )


def _drop_csv_rows_after(csv_dir: Path, env_steps: int) -> None:
    """Removes the CSV rows a killed run logged after its last checkpoint, so a resumed run does not repeat them."""
    for path in csv_dir.rglob("*.csv"):
        rows = [line for line in path.read_text().splitlines() if line and int(float(line.split(",")[0])) <= env_steps]
        path.write_text("".join(row + "\n" for row in rows))


# -------------------------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kitchen-train",
        description="Train a self-play team with IPPO or E3T (TorchRL) on Single or Infinite Kitchen levels.",
        epilog="Overrides: any config key as key=value, e.g. seed=3 levels=cramped_room_7x7 total_steps=2e6.",
    )
    parser.add_argument("config", nargs="?", help="a YAML config (configs/...); omit it with --resume")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    parser.add_argument("--resume", metavar="RUN_DIR", help="continue the run in RUN_DIR from its latest checkpoint")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.resume:
            # With --resume, the positional arguments are all overrides (e.g. total_steps=...).
            overrides = ([args.config] if args.config else []) + args.overrides
            saved = Path(args.resume) / "config.yaml"
            if not saved.is_file():
                raise ConfigError(f"{args.resume} is not a run directory (no config.yaml in it)")
            config = load_config(saved, overrides)
        else:
            if args.config is None:
                raise ConfigError("give a config file (e.g. configs/ippo/mlp_ik.yaml) or --resume RUN_DIR")
            if "=" in args.config:
                raise ConfigError(f"the first argument must be a config file, got the override {args.config!r}")
            config = load_config(args.config, args.overrides)
        run = train(config, resume=bool(args.resume), run=Path(args.resume) if args.resume else None)
        if config.eval_episodes > 0:
            from trainers.evaluate import report_trained_team

            report_trained_team(run)
    except (ConfigError, CheckpointError, ValueError) as error:
        print(f"kitchen-train: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("kitchen-train: stopped; resume from the last checkpoint with --resume", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
