import csv
from pathlib import Path

import pytest
import torch
from PIL import Image
from tensordict.nn import TensorDictSequential
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from torchrl.modules import set_recurrent_mode

from torch_kitchen.models import make_actor_critic
from trainers.checkpoint import load_checkpoint
from trainers.config import load_config
from trainers.evaluate import load_team
from torch_kitchen.partner import MIXED, PartnerMixture, PartnerSeats
from trainers.ippo import (EGO, compute_advantages, main, make_env, make_loss, normalize_ego_advantage, train,
                           with_model_transforms)
from trainers.rollout import make_collector

MAIN_CONFIG = str(Path(__file__).resolve().parents[2] / "configs" / "main.yaml")
# A few seconds per run: 4 kitchens x 16 steps per update, 16-step episodes, narrow networks.
TINY = [
    "num_envs=4",
    "rollout_steps=16",
    "max_steps=16",
    "hidden=16",
    "minibatches=2",
    "epochs=2",
    "threads=1",
    "progress=false",
    "eval_episodes=0",
    "levels=cramped_room_7x7",
]
TIMING = {"steps_per_second", "collect_seconds", "update_seconds"}


def tiny_config(tmp_path, *overrides, updates=2):
    return load_config(None, [*TINY, f"run_dir={tmp_path}", f"total_steps={updates * 64}", *overrides])


def read_metrics(run: Path) -> dict[str, list[tuple[float, float]]]:
    metrics = {}
    for path in sorted((run / "csv" / "scalars").rglob("*.csv")):
        if path.stem not in TIMING:
            with open(path) as handle:
                metrics[f"{path.parent.name}/{path.stem}"] = [tuple(map(float, row)) for row in csv.reader(handle)]
    return metrics


def test_the_entry_point_trains_checkpoints_logs_and_evaluates(tmp_path, capsys):
    overrides = [o for o in TINY if not o.startswith(("eval_episodes", "levels"))]
    argv = [MAIN_CONFIG, *overrides, f"run_dir={tmp_path}", "total_steps=128", "eval_episodes=2", "eval_heldout=1"]
    assert main(argv) == 0
    run = tmp_path / "main" / "seed0"
    assert load_config(run / "config.yaml").levels == "infinite"
    state = load_checkpoint(run)
    assert (state["update"], state["env_steps"]) == (2, 128)

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    expected = {"charts/episode_deliveries", "charts/episode_return", "charts/shaped_return", "charts/learning_rate",
                "charts/steps_per_second", "losses/policy", "losses/value", "losses/entropy", "losses/approx_kl",
                "losses/clip_fraction", "losses/explained_variance"}
    assert expected <= tags
    assert [event.step for event in events.Scalars("losses/policy")] == [64, 128]
    lr = [event.value for event in events.Scalars("charts/learning_rate")]
    assert lr[0] == pytest.approx(2.5e-4) and lr[1] == pytest.approx(1.25e-4)  # annealed linearly

    table = (run / "eval.md").read_text()
    layouts = ["cramped_room_7x7", "asymm_advantages_7x7", "coord_ring_7x7", "forced_coord_7x7", "counter_circuit_7x7"]
    for group in [*layouts, "held-out (1)"]:
        assert f"| main | {group} |" in table
    with open(run / "pairs.csv") as handle:
        pairs = list(csv.DictReader(handle))
    assert [(row["kind"], row["grid"], row["episodes"]) for row in pairs] == [
        ("SP", grid, "2") for grid in [*layouts, "heldout_000"]
    ]
    with Image.open(run / "team.gif") as gif:
        assert gif.n_frames > 1
    assert "gif:" in capsys.readouterr().out


@pytest.mark.parametrize("architecture, share_params, algorithm", [
    ("mlp", "false", "ippo"), ("mlp_lstm", "true", "ippo"), ("gnn", "true", "ippo"), ("gnn_lstm", "false", "ippo"),
    ("e3t_mlp", "true", "e3t"), ("e3t_gnn", "false", "e3t"),
])  # fmt: skip
def test_every_architecture_trains_and_reloads(tmp_path, architecture, share_params, algorithm):
    config = tiny_config(tmp_path, f"architecture={architecture}", f"share_params={share_params}",
                         f"algorithm={algorithm}")
    losses = []
    run = train(config, on_update=lambda update, metrics: losses.append(metrics["losses/value"]) and False)
    assert len(losses) == 2 and all(torch.isfinite(torch.tensor(losses)))
    team = load_team(run)
    trained = torch.load(run / "checkpoints" / "latest.pt", weights_only=False)["actor"]
    for name, tensor in team.actor_critic.actor.state_dict().items():
        assert torch.equal(tensor, trained[name]), name


@pytest.mark.parametrize("architecture, algorithm", [("mlp", "ippo"), ("mlp_lstm", "ippo"), ("e3t_mlp", "e3t")])
def test_a_crashed_run_resumes_from_its_checkpoint_with_the_same_metrics(tmp_path, architecture, algorithm):
    common = (f"architecture={architecture}", f"algorithm={algorithm}", "checkpoint_every=2", "shaping_weight=1",
              "shaping_anneal_steps=256", *(["partner_policy=copy"] if algorithm == "e3t" else []))
    whole = train(tiny_config(tmp_path / "whole", *common, updates=4))

    def crash_at_update_3(update, metrics):
        if update == 3:
            raise RuntimeError("killed")

    crashed_config = tiny_config(tmp_path / "crashed", *common, updates=4)
    with pytest.raises(RuntimeError, match="killed"):
        train(crashed_config, on_update=crash_at_update_3)
    assert load_checkpoint(crashed_config.run_path)["update"] == 2
    assert main(["--resume", str(crashed_config.run_path)]) == 0

    expected, resumed = read_metrics(whole), read_metrics(crashed_config.run_path)
    assert expected.keys() == resumed.keys() and "losses/policy" in expected
    for name in expected:
        assert [step for step, _ in resumed[name]] == [step for step, _ in expected[name]], name
        torch.testing.assert_close(torch.tensor(resumed[name]), torch.tensor(expected[name]), msg=name)
    final = load_checkpoint(crashed_config.run_path), load_checkpoint(whole)
    for name, tensor in final[1]["actor"].items():
        torch.testing.assert_close(final[0]["actor"][name], tensor)


def test_a_stop_request_checkpoints_the_finished_update(tmp_path):
    config = tiny_config(tmp_path, updates=5)
    train(config, on_update=lambda update, metrics: update == 2)
    assert load_checkpoint(config.run_path)["update"] == 2


def test_bad_runs_and_checkpoints_get_a_clear_message(tmp_path, capsys):
    config = tiny_config(tmp_path)
    run = train(config)

    assert main([MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "name=ippo_mlp_ik"]) == 2
    assert "already holds a trained run; resume it with `kitchen-train --resume" in capsys.readouterr().err

    assert main(["--resume", str(run), "architecture=gnn"]) == 2
    assert "holds another model (architecture: checkpoint 'mlp', expected 'gnn')" in capsys.readouterr().err

    assert main([MAIN_CONFIG, "lrr=0.1"]) == 2
    assert "unknown config key 'lrr' in the command line (did you mean 'lr'?)" in capsys.readouterr().err

    assert main([MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "algorithm=e3t"]) == 2
    assert "algorithm=e3t needs a model with a partner predictor, and 'mlp' has none" in capsys.readouterr().err
    assert main([MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "architecture=e3t_mlp"]) == 2
    assert "'e3t_mlp' carries E3T's partner predictor, which only algorithm=e3t trains" in capsys.readouterr().err
    assert main([MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "partner_policy=past"]) == 2
    assert "partner_policy must be one of ego, copy, got 'past'" in capsys.readouterr().err

    assert main([MAIN_CONFIG, "lrr=0.1"]) == 2
    assert "unknown config key 'lrr' in the command line (did you mean 'lr'?)" in capsys.readouterr().err

    checkpoint = run / "checkpoints" / "latest.pt"
    checkpoint.write_bytes(checkpoint.read_bytes()[:1000])
    assert main(["--resume", str(run)]) == 2
    assert "is not a readable checkpoint" in capsys.readouterr().err


@pytest.mark.parametrize("architecture", ["mlp", "gnn_lstm"])
def test_ppo_updates_lower_the_loss_on_a_fixed_batch(tmp_path, architecture):
    torch.manual_seed(0)
    config = tiny_config(tmp_path, f"architecture={architecture}", "shaping_weight=1")
    actor_critic = make_actor_critic(architecture, (7, 7, 26), hidden=16, share_params=True)
    env = with_model_transforms(make_env(config), actor_critic)
    frames = config.num_envs * config.max_steps
    collector = make_collector(env, TensorDictSequential(actor_critic.actor, actor_critic.critic), frames, frames)
    batch = next(iter(collector)).clone()
    collector.shutdown()
    compute_advantages(batch, actor_critic.critic, config, shaping_weight=1.0)
    loss_module = make_loss(config, actor_critic)
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=1e-3)

    def total_loss():
        with set_recurrent_mode(actor_critic.recurrent):
            losses = loss_module(batch)
        return losses["loss_objective"] + losses["loss_critic"] + losses["loss_entropy"]

    before = total_loss().item()
    for _ in range(5):
        optimizer.zero_grad()
        total_loss().backward()
        optimizer.step()
    assert total_loss().item() < before


def e3t_batch(config, actor_critic):
    """One collected E3T batch with its advantages, as the trainer sees it before the PPO epochs."""
    env = with_model_transforms(make_env(config), actor_critic, PartnerSeats(config.seed))
    policy = TensorDictSequential(actor_critic.actor, PartnerMixture(config.partner_epsilon), actor_critic.critic)
    frames = config.num_envs * config.max_steps
    collector = make_collector(env, policy, frames, frames)
    batch = next(iter(collector)).clone()
    collector.shutdown()
    compute_advantages(batch, actor_critic.critic, config, shaping_weight=1.0)
    batch.set(EGO, ~batch.get(MIXED))
    return batch


def test_e3t_ppo_learns_from_the_ego_transitions_only(tmp_path):
    torch.manual_seed(0)
    config = tiny_config(tmp_path, "algorithm=e3t", "architecture=e3t_mlp", "partner_epsilon=0.5")
    actor_critic = make_actor_critic("e3t_mlp", (7, 7, 26), hidden=16, share_params=True)
    batch = e3t_batch(config, actor_critic)
    assert (batch.get(EGO).sum(-1) == 1).all()
    loss_module = make_loss(config, actor_critic)

    def losses(data):
        data = data.clone()
        normalize_ego_advantage(data)
        return loss_module(data).select("loss_objective", "loss_critic", "loss_entropy").detach()

    before = losses(batch)
    # The mixed partner's transitions, scrambled: nothing changes.
    scrambled = batch.clone()
    partner = ~batch.get(EGO)
    for key in [("agents", "advantage"), ("agents", "value_target"), ("agents", "action_log_prob")]:
        scrambled.set(key, torch.where(partner.reshape(*partner.shape, *[1] * (batch.get(key).ndim - 3)),
                                       torch.randn_like(batch.get(key)) * 100, batch.get(key)))
    scrambled.set(("agents", "action"), torch.where(partner, (batch.get(("agents", "action")) + 1) % 6,
                                                    batch.get(("agents", "action"))))
    for name, value in losses(scrambled).items():
        torch.testing.assert_close(value, before[name], msg=name)
    # One ego transition changed: the policy loss moves.
    nudged = batch.clone()
    b, t = 0, 0
    ego_seat = int(batch.get(EGO)[b, t].long().argmax())
    nudged["agents", "action_log_prob"][b, t, ego_seat] -= 1.0
    assert not torch.allclose(losses(nudged)["loss_objective"], before["loss_objective"])


def test_e3t_through_the_entry_point_teaches_the_predictor_keeps_a_slow_copy_and_evaluates(tmp_path):
    config_file = str(Path(__file__).resolve().parents[2] / "configs" / "e3t" / "mlp_ik.yaml")
    argv = [config_file, *TINY, f"run_dir={tmp_path}", "hidden=16", "total_steps=192", "partner_policy=copy",
            "partner_copy_rate=0.5", "eval_episodes=1", "eval_heldout=1"]
    assert main(argv) == 0
    run = tmp_path / "e3t_mlp_ik" / "seed0"
    metrics = read_metrics(run)
    assert [step for step, _ in metrics["charts/partner_accuracy"]] == [64, 128, 192]
    assert all(0 <= accuracy <= 1 for _, accuracy in metrics["charts/partner_accuracy"])
    assert all(loss > 0 for _, loss in metrics["losses/partner_prediction"])
    state = load_checkpoint(run)
    torch.manual_seed(0)  # the initial weights, as train() built them
    initial = make_actor_critic("e3t_mlp", (7, 7, 26), hidden=16).actor.state_dict()
    moved = 0
    for name, ego in state["actor"].items():
        copy, start = state["partner_copy"][name], initial[name]
        # After 3 updates at rate 0.5 the copy has moved 7/8 of the way: neither where it started nor the ego.
        if not torch.equal(ego, start):
            moved += 1
            assert not torch.equal(copy, ego) and not torch.equal(copy, start), name
    assert moved > 0
    assert "| e3t_mlp_ik | cramped_room_7x7 |" in (run / "eval.md").read_text()
    with Image.open(run / "team.gif") as gif:
        assert gif.n_frames > 1
