"""A small study for the simulated participants of `web_apps.study.client` to run through, and its token."""

from __future__ import annotations

from pathlib import Path

import yaml

from torch_kitchen.models import make_actor_critic, model_identity
from trainers.checkpoint import save_checkpoint
from trainers.config import TrainConfig

TOKEN = "study-token"


def tiny_team(run: Path) -> Path:
    """A trained team's run directory (untrained networks of hidden 8) for 7x7 kitchens."""
    actor_critic = make_actor_critic("mlp", (7, 7, 26), 8, True)
    save_checkpoint(run / "checkpoints" / "latest.pt", {
        "config": TrainConfig(levels="cramped_room_7x7").to_dict(), "model": model_identity("mlp", (7, 7, 26), 8, True),
        "actor": actor_critic.actor.state_dict(), "critic": actor_critic.critic.state_dict(),
    })  # fmt: skip
    return run


def study_config(folder: Path, **overrides) -> Path:
    """A study of two conditions (a trained team, the scripted cook) on two kitchens, short turns-paced games."""
    values = {
        "name": "tiny", "seed": 3, "out_dir": str(folder / "study"),
        "conditions": {"team": str(tiny_team(folder / "runs" / "team" / "seed0")), "cook": "scripted_cook"},
        "kitchens": ["cramped_room_7x7", "coord_ring_7x7"], "games_per_participant": 2, "practice_games": 1,
        "pace": "turns", "max_steps": 5, "practice_steps": 3, "idle_s": 60, "completion_code": "random",
        "likert": {"scale": ["no", "rather no", "unsure", "rather yes", "yes"],
                   "items": {"helpful": "My partner was helpful.", "predictable": "I understood my partner."}},
    }  # fmt: skip
    values.update(overrides)
    path = folder / "study.yaml"
    path.write_text(yaml.safe_dump(values))
    return path
