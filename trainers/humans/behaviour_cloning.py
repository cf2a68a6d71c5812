"""Human proxies: the project's torch policies behaviour-cloned from the 2019 human games, one per classic layout.

A proxy is fitted on one split's games (both seats, one shared network) by cross-entropy to the humans' actions,
and measured on the other: its accuracy against always-STAY, its accuracy on the humans' moves and
interactions (STAY labels left out) against their most frequent one, and the soups two copies of it deliver
together in games as long as the humans' against what the humans delivered. It is saved as a trained team
(`kitchen-humans train`: `runs/bc_<layout>/seed0` fitted on the train split, `runs/human_proxy_<layout>/seed0` on
the test split), so `kitchen-eval` and `kitchen-play` seat it like any other team.

`stay_weight` weighs the STAY labels in the loss: humans press no key on 49-72% of the 150 ms ticks, and a proxy
fitted to that waits where they would have moved (see `kitchen-humans train --help` and BENCHMARKS.md).

Fits of one layout with different seeds play very differently together (two proxies of the same games delivered
10.8 and 18.1 soups), so `candidates` proxies are fitted with seeds seed, seed + 1, ... and the one kept is the one
whose two copies deliver closest to what the humans of the fitted games delivered (`choose_proxy`): chosen on the
fitted split only, measured on the other.

Where cloning alone gets stuck (on forced_coord two cloned proxies deliver an eighth of the humans' soups: the cook
by the pots picks up a plate before any soup cooks, a state the humans almost never reached, and waits with it at
an empty pot), the kept proxy is fine-tuned in self-play by anchored IPPO, PPO with a KL penalty toward the cloned
policy (`trainers.algorithms.anchored`), with KL weights searched for until two copies deliver about what the
humans did, and the closest is kept (`fine_tuned`): the reward mends the stuck states, the penalty keeps the humans'
way of playing.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import jax
import numpy as np
import torch
from tensordict import TensorDict
from torchrl.envs.utils import ExplorationType, set_exploration_type

from jax_env import STAY, load_layout
from jax_env.human_games import HumanGame
from jax_env.observation import get_obs
from torch_kitchen.env import KitchenEnv
from torch_kitchen.keys import LOGITS, OBSERVATION
from torch_kitchen.models import ActorCritic, make_actor_critic, model_identity
from trainers.checkpoint import LATEST, save_checkpoint
from trainers.config import TrainConfig

HUMAN_ACTION = ("agents", "human_action")  # the label, kept apart from the actor's own sampled action
NOT_HUMAN = -1  # the label of a seat no person played (a kitchen-play game's partner): ignored
SELECTION_GAMES = 1000  # the seeds of the games candidates are chosen by start here, apart from the measured ones
ANCHOR_STEP = 4.0  # the factor between KL weights tried while the humans' soups are not yet between two of them
CLOSE_ENOUGH = 0.1  # a fine-tune this near the humans' soups (`humanlike_distance`, about 10%) ends the search


@dataclasses.dataclass(frozen=True)
class ProxySettings:
    """How a proxy is fitted: its network, the passes over the data, and the weight of the STAY labels."""

    architecture: str = "ego_mlp"
    hidden: int = 128
    epochs: int = 30
    lr: float = 1e-3
    minibatch: int = 256
    stay_weight: float = 0.1
    seed: int = 0
    candidates: int = 5  # fits with seeds seed, seed + 1, ...: the one that plays most like the humans is kept
    # Fine-tuning (`fine_tuned`) where two cloned proxies deliver less than `fine_tune_below` x the humans' soups:
    # anchored IPPO for `fine_tune_steps` steps (0: never) at most `fine_tunes` times, the first with KL weight
    # `anchor_coef`, the next ones' weights searched for (`next_anchor_coef`).
    fine_tune_below: float = 0.5
    fine_tune_steps: int = 2_097_152
    fine_tunes: int = 3
    anchor_coef: float = 0.1
    fine_tune_lr: float = 1e-3
    threads: int = 1  # torch threads
    device: str = "cpu"  # where the proxy is fitted, measured and plays (its checkpoint loads anywhere)

    def __post_init__(self):
        for name in ("hidden", "epochs", "minibatch", "candidates", "fine_tunes", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.fine_tune_steps < 0 or not self.fine_tune_below >= 0 or not self.fine_tune_lr > 0:
            raise ValueError("fine_tune_steps and fine_tune_below must be at least 0 and fine_tune_lr above 0, got "
                             f"{self.fine_tune_steps}, {self.fine_tune_below} and {self.fine_tune_lr}")
        if not self.anchor_coef > 0:
            raise ValueError(f"anchor_coef must be above 0, got {self.anchor_coef}")
        try:
            torch.device(self.device)
        except RuntimeError:
            raise ValueError(f"device must be a torch device such as cpu or cuda, got {self.device!r}") from None


def human_batch(games: list[HumanGame]) -> TensorDict:
    """Every step of `games` as a batch [N]: both seats' observations (uint8 [N, 2, H, W, 26], the time left
    counted to each game's own end) and the humans' actions (int64 [N, 2]; `NOT_HUMAN` where no person played)."""
    observations = [np.asarray(jax.vmap(lambda s, n=len(g): get_obs(s, n))(g.states())) for g in games]
    observation = torch.from_numpy(np.concatenate(observations))
    action = torch.from_numpy(np.concatenate([np.where(g.human_seats, g.actions, NOT_HUMAN) for g in games]))
    return TensorDict({OBSERVATION: observation, HUMAN_ACTION: action}, batch_size=[len(action)])


def proxy_device(actor_critic: ActorCritic) -> torch.device:
    """Where the proxy's networks are."""
    return next(actor_critic.actor.parameters()).device


def proxy_logits(actor_critic: ActorCritic, batch: TensorDict) -> torch.Tensor:
    """The proxy's action logits [N, 2, 6] for the batch's observations (taken to the proxy's device)."""
    return actor_critic.actor(batch.select(OBSERVATION).to(proxy_device(actor_critic)).clone(False)).get(LOGITS)


def fit_proxy(train: TensorDict, settings: ProxySettings) -> tuple[ActorCritic, list[float]]:
    """A proxy fitted to `train` (a `human_batch`) on `settings.device`; returns it and the mean loss of each
    epoch. The loss is read once per epoch: nothing in a minibatch waits for the device."""
    torch.manual_seed(settings.seed)
    device = torch.device(settings.device)
    obs_shape = tuple(train.get(OBSERVATION).shape[-3:])
    actor_critic = make_actor_critic(settings.architecture, obs_shape, settings.hidden, share_params=True)
    actor_critic.actor.to(device)
    actor_critic.critic.to(device)
    train = train.to(device)
    # Fused: one kernel for every parameter, its step counts kept where they are, so that no step reads one.
    optimizer = torch.optim.Adam(actor_critic.actor.parameters(), lr=settings.lr, fused=True)
    weights = torch.ones(6, device=device)
    weights[STAY] = settings.stay_weight
    losses = []
    for _ in range(settings.epochs):
        total = torch.zeros((), device=device)
        order = torch.randperm(len(train), device=device)
        for rows in order.split(settings.minibatch):
            batch = train[rows]
            logits = proxy_logits(actor_critic, batch)
            loss = torch.nn.functional.cross_entropy(logits.reshape(-1, 6), batch.get(HUMAN_ACTION).reshape(-1),
                                                     weight=weights, ignore_index=NOT_HUMAN)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            total += loss.detach() * len(rows)
        losses.append(float(total) / len(train))
    actor_critic.actor.eval()
    return actor_critic, losses


@torch.no_grad()
def accuracy(actor_critic: ActorCritic, test: TensorDict, train: TensorDict) -> dict[str, float]:
    """On `test`: the proxy's most likely action against the humans' (all labels, and the moves and interactions
    alone, STAY excluded from both sides), with the baselines always-STAY and the train split's most frequent
    move or interaction."""
    test = test.to(proxy_device(actor_critic))
    human = test.get(HUMAN_ACTION) != NOT_HUMAN
    logits, labels = proxy_logits(actor_critic, test)[human], test.get(HUMAN_ACTION)[human]
    moving = labels != STAY
    no_stay = logits.clone()
    no_stay[..., STAY] = -torch.inf
    train_labels = train.get(HUMAN_ACTION)
    majority = int(torch.bincount(train_labels[(train_labels != STAY) & (train_labels != NOT_HUMAN)], minlength=6)
                   .argmax())
    return {
        "accuracy": float((logits.argmax(-1) == labels).float().mean()),
        "always_stay": float((labels == STAY).float().mean()),
        "moving_accuracy": float((no_stay.argmax(-1) == labels)[moving].float().mean()),
        "moving_majority": float((labels[moving] == majority).float().mean()),
    }


@torch.no_grad()
def play_together(actor_critic: ActorCritic, layout: str, steps: int, episodes: int = 8, seed: int = 0) -> TensorDict:
    """The rollout [episodes, steps] of `episodes` games of `steps` steps of two copies of the proxy (sampling)."""
    env = KitchenEnv(episodes, levels=layout, max_steps=steps, seed=seed, device=proxy_device(actor_critic))
    torch.manual_seed(seed)
    with set_exploration_type(ExplorationType.RANDOM):
        return env.rollout(steps, actor_critic.actor, break_when_any_done=False)


def deliveries_together(actor_critic: ActorCritic, layout: str, steps: int, episodes: int = 8,
                        seed: int = 0) -> float:
    """Mean soups delivered by two copies of the proxy (sampling) in `episodes` games of `steps` steps."""
    rollout = play_together(actor_critic, layout, steps, episodes, seed)
    return float(rollout.get(("next", "deliveries")).sum() / episodes)


def humanlike_distance(together: float, humans: float) -> float:
    """How far two proxies' soups are from the humans': |log ratio|, each count + 0.5 so that none is infinite."""
    return abs(math.log((together + 0.5) / (humans + 0.5)))


@dataclasses.dataclass(frozen=True)
class Chosen:
    """The proxy kept among the candidates: it, its seed, and each candidate's soups with a copy of itself in the
    fitted split's games (by seed); where it was fine-tuned (`fine_tuned`), the KL weight of the one kept (None: the
    cloned proxy) and each fine-tune's soups in the same games (by KL weight)."""

    actor_critic: ActorCritic
    seed: int
    soups: dict[int, float]
    anchor_coef: float | None = None
    tuned: dict[float, float] = dataclasses.field(default_factory=dict)


def choose_proxy(train: TensorDict, layout: str, settings: ProxySettings, steps: int, humans: float,
                 episodes: int) -> Chosen:
    """Fits `settings.candidates` proxies to `train` (seeds `settings.seed` on) and keeps the one whose two copies,
    in `episodes` games of `steps` steps on `layout`, deliver closest to `humans` (`humanlike_distance`; the
    earlier seed on a tie). Its games are drawn apart from those the proxy is measured with afterwards."""
    proxies, soups = {}, {}
    for seed in range(settings.seed, settings.seed + settings.candidates):
        proxies[seed], _ = fit_proxy(train, dataclasses.replace(settings, seed=seed))
        soups[seed] = deliveries_together(proxies[seed], layout, steps, episodes, seed=SELECTION_GAMES + seed)
    kept = min(soups, key=lambda seed: humanlike_distance(soups[seed], humans))  # the first of equals
    return Chosen(proxies[kept], kept, soups)


def fine_tune(start: Path, layout: str, settings: ProxySettings, coef: float, game_steps: int, seed: int,
              run_dir: Path) -> Path:
    """Anchored IPPO (`trainers.algorithms.anchored`) from the proxy saved at `start`: two copies in self-play on
    `layout`, in games of `game_steps` steps, for `settings.fine_tune_steps` steps at Adam's rate
    `settings.fine_tune_lr`, kept near the start by the KL weight `coef`. Returns the run
    (`run_dir/anchor<coef>/seed<seed>`)."""
    from trainers.config.compose import load_config
    from trainers.ppo.loop import train

    config = load_config(None, [
        f"levels={layout}", f"architecture={settings.architecture}", f"hidden={settings.hidden}", "share_params=true",
        "algorithm=anchored_ippo", f"algorithm_config.anchor_coef={coef}", f"init_from={start}",
        f"total_steps={settings.fine_tune_steps}", f"max_steps={game_steps}", f"ppo.lr={settings.fine_tune_lr}",
        f"seed={seed}", f"run_dir={run_dir}", f"name=anchor{coef:g}", "eval_episodes=0",
        f"runtime.threads={settings.threads}", f"runtime.device={settings.device}",
    ])  # fmt: skip
    return train(config)


def next_anchor_coef(tuned: dict[float, float], humans: float) -> float:
    """The next KL weight to fine-tune with, from the soups two copies delivered after each weight tried (`tuned`):
    a stronger anchor keeps a proxy nearer the cloned one, which delivers too few, so the next weight lies between
    the weakest that still delivered fewer than `humans` and the strongest that delivered more (their geometric
    mean), or `ANCHOR_STEP` times beyond the one side known; two significant digits."""
    too_strong = [coef for coef, soups in tuned.items() if soups < humans]
    too_weak = [coef for coef, soups in tuned.items() if soups >= humans]
    if too_strong and too_weak:
        coef = math.sqrt(min(too_strong) * max(too_weak))
    else:
        coef = min(too_strong) / ANCHOR_STEP if too_strong else max(too_weak) * ANCHOR_STEP
    return float(f"{coef:.2g}")


def fine_tuned(chosen: Chosen, layout: str, settings: ProxySettings, steps: int, humans: float, episodes: int,
               team: Path) -> Chosen:
    """`chosen` as it is where its two copies deliver at least `settings.fine_tune_below` x `humans` (or
    `fine_tune_steps` is 0). Else it is fine-tuned (`fine_tune`, from `team/cloned`, into `team/anchored`) with KL
    weight `settings.anchor_coef`, then with the weights `next_anchor_coef` finds, until two copies deliver within
    `CLOSE_ENOUGH` of `humans` or `settings.fine_tunes` were made; the one kept, of those and the cloned proxy, is
    the one whose two copies deliver closest to `humans` in the games `chosen` was measured in (the cloned one on a
    tie)."""
    cloned_soups = chosen.soups[chosen.seed]
    if not settings.fine_tune_steps or cloned_soups >= settings.fine_tune_below * humans:
        return chosen
    from trainers.evaluation.teams import load_team

    start = team / "cloned"
    save_proxy(chosen.actor_critic, dataclasses.replace(settings, seed=chosen.seed), layout, start)
    proxies, tuned = {}, {}
    coef = settings.anchor_coef
    for _ in range(settings.fine_tunes):
        run = fine_tune(start, layout, settings, coef, steps, chosen.seed, team / "anchored")
        proxies[coef] = load_team(run).actor_critic
        tuned[coef] = deliveries_together(proxies[coef], layout, steps, episodes, seed=SELECTION_GAMES + chosen.seed)
        if humanlike_distance(tuned[coef], humans) <= CLOSE_ENOUGH:
            break
        coef = next_anchor_coef(tuned, humans)
        if coef in tuned:  # no weight left between two tried
            break
    best = min(tuned, key=lambda coef: humanlike_distance(tuned[coef], humans))
    if humanlike_distance(tuned[best], humans) >= humanlike_distance(cloned_soups, humans):
        return dataclasses.replace(chosen, tuned=tuned)
    return dataclasses.replace(chosen, actor_critic=proxies[best], anchor_coef=best, tuned=tuned)


def save_proxy(actor_critic: ActorCritic, settings: ProxySettings, layout: str, run: Path) -> Path:
    """The proxy as a trained team's checkpoint in `run` (what `kitchen-eval` and `kitchen-play` load)."""
    obs_shape = list(load_layout(layout).shape) + [26]
    config = TrainConfig(name=run.parent.name, run_dir=str(run.parent.parent), levels=layout,
                         architecture=settings.architecture, hidden=settings.hidden, seed=settings.seed)
    return save_checkpoint(run / "checkpoints" / LATEST, {
        "config": config.to_dict(),
        "model": model_identity(settings.architecture, obs_shape, settings.hidden, True),
        "actor": actor_critic.actor.state_dict(), "critic": actor_critic.critic.state_dict(),
    })  # fmt: skip
