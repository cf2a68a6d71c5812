"""Bring your own model: train a torch model of your own on `KitchenEnv` with plain TorchRL PPO.

No project trainer is involved: a `Collector` gathers rollouts, `ClipPPOLoss` with GAE computes the losses,
Adam steps, and a `TensorboardLogger` writes the curves. A model only has to honour the key contract:

    reads   ("agents", "observation")  uint8 [B, 2, H, W, 26]   (cast to float inside the model)
    actor   ("agents", "logits")       float [B, 2, 6]  ->  ("agents", "action") int64 [B, 2]
                                       and ("agents", "action_log_prob") [B, 2]
    critic  ("agents", "state_value")  float [B, 2, 1]

    python examples/train_custom_model.py --levels cramped_room_7x7 --total-steps 1000000
    tensorboard --logdir runs/custom_model
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, ValueEstimators
from torchrl.record.loggers import TensorboardLogger

from torch_kitchen.env import AgentDones, KitchenEnv


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--levels", nargs="+", default=["cramped_room_7x7"], help='layout(s), grid file(s) or "infinite"')
    p.add_argument("--envs", type=int, default=32, help="kitchens stepped together")
    p.add_argument("--rollout-steps", type=int, default=128, help="steps per kitchen per iteration")
    p.add_argument("--total-steps", type=int, default=1_000_000, help="kitchen steps over the whole run")
    p.add_argument("--max-steps", type=int, default=400, help="episode length")
    p.add_argument("--lr", type=float, default=3e-4)
    p.add_argument("--shaping-weight", type=float, default=1.0, help="weight of the shaped reward in the PPO reward")
    p.add_argument("--epochs", type=int, default=4, help="passes over each rollout")
    p.add_argument("--minibatches", type=int, default=4, help="minibatches per pass")
    p.add_argument("--log-dir", default="runs/custom_model")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help='"cpu" or "cuda[:i]" (the env runs JAX on the same device)')
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (leave a core to JAX)")
    return p.parse_args(argv)


# ---------------------------------------------------------------------------------------------- YOUR MODEL
class KitchenCNN(nn.Module):
    """A small CNN applied to each agent's view separately (parameters shared by both agents).

    uint8 [*, H, W, C] -> float32 [*, out_features]; the leading dims (batch, agents) are folded and restored.
    """

    def __init__(self, obs_shape: tuple[int, int, int], out_features: int, channels: int = 32, hidden: int = 128):
        super().__init__()
        self.obs_shape = tuple(obs_shape)
        height, width, in_channels = self.obs_shape
        self.net = nn.Sequential(
            nn.Conv2d(in_channels, channels, 3, padding=1), nn.ReLU(),
            nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(),
            nn.Flatten(),
            nn.Linear(channels * height * width, hidden), nn.ReLU(),
            nn.Linear(hidden, out_features),
        )

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        if tuple(observation.shape[-3:]) != self.obs_shape:
            raise ValueError(
                f"KitchenCNN expects observations [..., H, W, C] = [..., {self.obs_shape}], "
                f"got {tuple(observation.shape)}"
            )
        lead = observation.shape[:-3]
        x = observation.reshape(-1, *self.obs_shape).float().permute(0, 3, 1, 2)  # channels first for Conv2d
        return self.net(x).reshape(*lead, -1)


def make_actor_critic(env: KitchenEnv) -> tuple[ProbabilisticActor, TensorDictModule]:
    """The policy (logits -> Categorical over the 6 actions) and the per-agent critic, in the env's keys."""
    obs_shape = env.observation_spec["agents", "observation"].shape[-3:]
    num_actions = env.full_action_spec["agents", "action"].space.n
    observation = [("agents", "observation")]
    logits = TensorDictModule(KitchenCNN(obs_shape, num_actions), in_keys=observation, out_keys=[("agents", "logits")])
    actor = ProbabilisticActor(
        logits,
        in_keys={"logits": ("agents", "logits")},
        out_keys=[("agents", "action")],
        distribution_class=torch.distributions.Categorical,
        return_log_prob=True,
        log_prob_key=("agents", "action_log_prob"),
    )
    critic = TensorDictModule(KitchenCNN(obs_shape, 1), in_keys=observation, out_keys=[("agents", "state_value")])
    return actor.to(env.device), critic.to(env.device)


def make_loss_module(actor, critic) -> ClipPPOLoss:
    """ALGO LOGIC: PPO on the ("agents", ...) keys; each agent gets its own advantage from its own value (GAE)."""
    loss_module = ClipPPOLoss(
        actor, critic, clip_epsilon=0.2, entropy_coeff=0.01, critic_coeff=0.5,
        normalize_advantage=True, normalize_advantage_exclude_dims=(-2,),  # advantages [N, 2, 1]: per agent
    )
    loss_module.set_keys(
        action=("agents", "action"),
        sample_log_prob=("agents", "action_log_prob"),
        value=("agents", "state_value"),
        reward=("agents", "ppo_reward"),
        done=("agents", "done"),
        terminated=("agents", "terminated"),
        advantage=("agents", "advantage"),
        value_target=("agents", "value_target"),
    )
    loss_module.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    return loss_module


def ppo_epochs(loss_module: ClipPPOLoss, optimizer: torch.optim.Optimizer, data, epochs: int, minibatches: int
               ) -> list:
    """The batch flattened, then a few epochs of shuffled minibatches: PPO's clipped loss, the gradient clipped to
    norm 0.5, an Adam step. Returns each minibatch's losses."""
    flat, logs = data.reshape(-1), []
    for _ in range(epochs):
        for index in torch.randperm(flat.numel(), device=flat.device).chunk(minibatches):
            losses = loss_module(flat[index])
            loss = losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(loss_module.parameters(), max_norm=0.5)
            optimizer.step()
            logs.append(losses.detach())
    return logs


def log_iteration(logger: TensorboardLogger, losses, next_, shaped, frames: int, steps_per_second: float,
                  label: str) -> None:
    """An iteration's losses and deliveries to TensorBoard, and one line of them on the console."""
    done = next_["done"].squeeze(-1)
    scalars = {
        "losses/objective": losses["loss_objective"],
        "losses/critic": losses["loss_critic"],
        "losses/entropy": losses["entropy"],  # the policy's entropy (loss_entropy is -entropy_coeff x this)
        "losses/approx_kl": losses["kl_approx"],
        "losses/clipfrac": losses["clip_fraction"],
        "losses/explained_variance": losses["explained_variance"],
        "charts/shaped_reward": shaped.mean(),
        "charts/steps_per_second": steps_per_second,
    }
    if done.any():  # the episode's total is on its last step
        scalars["charts/episode_deliveries"] = next_["episode_deliveries"][done].mean()
    for name, value in scalars.items():
        logger.log_scalar(name, float(value), step=frames)
    deliveries = f"{float(scalars['charts/episode_deliveries']):.2f}" if done.any() else "-"
    print(
        f"{label}  steps {frames}  deliveries/episode {deliveries}  "
        f"objective {float(losses['loss_objective']):+.4f}  critic {float(losses['loss_critic']):.4f}  "
        f"entropy {float(losses['entropy']):.3f}  sps {steps_per_second:.0f}",
        flush=True,
    )


def main(argv: list[str] | None = None) -> dict:
    """Train, log to TensorBoard and print one line per iteration.

    Returns {"actor", "critic"} (the trained modules), "initial_params" ({"actor", "critic"}: TensorDicts of the
    parameters before training), "log_dir" (this run's TensorBoard folder) and "steps" (kitchen steps taken).
    """
    args = parse_args(argv)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    levels = args.levels[0] if len(args.levels) == 1 else args.levels
    env = KitchenEnv(num_envs=args.envs, levels=levels, max_steps=args.max_steps, device=args.device, seed=args.seed)
    env = env.append_transform(AgentDones())  # ("agents", "done" | "terminated") beside each agent's reward
    actor, critic = make_actor_critic(env)
    initial_params = {"actor": TensorDict.from_module(actor).clone(), "critic": TensorDict.from_module(critic).clone()}

    frames_per_batch = args.envs * args.rollout_steps
    iterations = max(1, args.total_steps // frames_per_batch)
    # A feed-forward policy needs no InitTracker: opt out of TorchRL 0.14's auto-registration (and its warning).
    collector = Collector(
        env, actor, frames_per_batch=frames_per_batch, total_frames=iterations * frames_per_batch,
        return_same_td=True, auto_register_policy_transforms=False,
    )

    loss_module = make_loss_module(actor, critic)
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=args.lr)
    run_name = f"{'+'.join(Path(level).stem for level in args.levels)}_seed{args.seed}_{time.strftime('%Y%m%d-%H%M%S')}"
    logger = TensorboardLogger(exp_name=run_name, log_dir=args.log_dir)

    frames, start = 0, time.perf_counter()
    for iteration, data in enumerate(collector, 1):  # data: [envs, rollout_steps]
        next_ = data["next"]
        # reward: the shared sparse reward plus each agent's weighted shaped reward, [B, T, 2, 1]
        shaped = next_["agents", "shaped_reward"]
        next_["agents", "ppo_reward"] = next_["agents", "reward"] + args.shaping_weight * shaped
        with torch.no_grad():
            loss_module.value_estimator(
                data, params=loss_module.critic_network_params, target_params=loss_module.target_critic_network_params
            )

        logs = ppo_epochs(loss_module, optimizer, data, args.epochs, args.minibatches)
        collector.update_policy_weights_()  # a no-op here (same process, same device); needed with remote workers

        frames += data.numel()
        log_iteration(logger, torch.stack(logs).apply(lambda x: x.float().mean(), batch_size=[]), next_, shaped,
                      frames, frames / (time.perf_counter() - start), f"iter {iteration}/{iterations}")

    collector.shutdown()
    logger.experiment.close()
    return {"actor": actor, "critic": critic, "initial_params": initial_params, "log_dir": logger.log_dir,
            "steps": frames}


if __name__ == "__main__":
    main()
