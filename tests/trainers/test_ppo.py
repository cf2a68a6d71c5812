import copy
import csv
import functools
import signal
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
import torch
from PIL import Image
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensordict import TensorDict
from tensordict.nn import TensorDictSequential
from tiny import TINY
from torchrl.envs.utils import set_exploration_type
from torchrl.modules import set_recurrent_mode

import trainers.ppo.collection
import trainers.ppo.loop
import trainers.ppo.step
import trainers.ppo.team
from jax_env import CLASSIC_LAYOUTS, EXPANDED_LAYOUTS
from jax_env.generator import GeneratorConfig
from torch_kitchen.cpu_kernels import BatchObservations
from torch_kitchen.keys import OBSERVATION
from torch_kitchen.models import make_actor_critic
from torch_kitchen.models.e3t_partner import MIXED, PartnerMixture, PartnerSeats
from trainers.algorithms import ALGORITHMS, E3T, IPPO, register_algorithm
from trainers.algorithms.base import standardize_advantage
from trainers.algorithms.e3t import EGO
from trainers.checkpoint import CheckpointError, load_checkpoint
from trainers.config import ConfigError, TrainConfig
from trainers.config.compose import load_config
from trainers.evaluation import load_team, report_trained_team
from trainers.evaluation import main as eval_main
from trainers.evaluation.figures import read_scalar
from trainers.ppo.advantages import compute_advantages
from trainers.ppo.collection import make_collector
from trainers.ppo.loop import train
from trainers.ppo.runtime import Learner, sharded_gradients
from trainers.ppo.step import team_gradients
from trainers.ppo.team import build_team, make_algorithm, make_env, make_loss, with_model_transforms
from trainers.train_command import main

MAIN_CONFIG = str(Path(__file__).resolve().parents[2] / "configs" / "main.yaml")
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
    """The main job's pipeline, tiny: the scripted cook distilled into the run's folder, self-play from it on
    generated kitchens, the final table on a held-out level and the classics."""
    overrides = [o for o in TINY if not o.startswith(("eval_episodes", "levels", "init_from"))]
    argv = [MAIN_CONFIG, *overrides, f"run_dir={tmp_path}", "total_steps=128", "eval_episodes=2", "eval_heldout=1",
            "distill.rounds=2", "distill.epochs=1"]
    assert main(argv) == 0
    run = tmp_path / "main" / "seed0"
    config = load_config(run / "config.yaml")
    assert (config.levels, config.init_from) == ("infinite", "scripted_cook")
    assert load_checkpoint(run / "distilled")["update"] == 2
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
    base_lr = load_config(run / "config.yaml").ppo.lr
    assert lr[0] == pytest.approx(base_lr) and lr[1] == pytest.approx(base_lr / 2)  # annealed linearly

    table = (run / "eval.md").read_text()
    layouts = list(EXPANDED_LAYOUTS)  # a team of generated kitchens: the classics beside held-out levels
    for group in [*layouts, "held-out (1)"]:
        assert f"| main | {group} |" in table
    assert "with the scripted cook |" in table  # a partner outside its training, in either seat
    with open(run / "pairs.csv") as handle:
        pairs = list(csv.DictReader(handle))
    own = [row for row in pairs if row["agent0"] == row["agent1"] == "main/seed0"]
    assert [(row["kind"], row["grid"], row["episodes"]) for row in own] == [
        ("SP", grid, "2") for grid in [*layouts, "heldout_000"]
    ]
    assert {(row["agent0"], row["agent1"]) for row in pairs if row["kind"] == "partner"} == {
        ("main/seed0", "scripted cook"), ("scripted cook", "main/seed0")}
    with Image.open(run / "team.gif") as gif:
        assert gif.n_frames > 1
    with Image.open(run / "learning_curve.png") as curve:
        assert curve.width > curve.height > 100
    steps, shaped = read_scalar(run, "charts/shaped_return")
    assert steps.tolist() == [64, 128] and shaped.tolist() == [v for _, v in read_metrics(run)["charts/shaped_return"]]
    printed = capsys.readouterr().out
    assert "gif:" in printed and "learning curve:" in printed


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
    trained = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["actor"]
    for name, tensor in team.actor_critic.actor.state_dict().items():
        assert torch.equal(tensor, trained[name]), name


@pytest.mark.parametrize("architecture, algorithm", [("mlp", "ippo"), ("mlp_lstm", "ippo"), ("e3t_mlp", "e3t")])
@pytest.mark.bitwise
def test_a_crashed_run_resumes_from_its_checkpoint_with_the_same_metrics(tmp_path, architecture, algorithm):
    common = (f"architecture={architecture}", f"algorithm={algorithm}", "checkpoint_every=2", "ppo.shaping_weight=1",
              "ppo.shaping_anneal_steps=256", *(["algorithm_config.partner_policy=copy"] if algorithm == "e3t" else []))
    whole = train(tiny_config(tmp_path / "whole", *common, updates=4))

    def crash_at_update_3(update, metrics):
        if update == 3:
            raise RuntimeError("killed")

    crashed_config = tiny_config(tmp_path / "crashed", *common, updates=4)
    with pytest.raises(RuntimeError, match="killed"):
        train(crashed_config, on_update=crash_at_update_3)
    assert load_checkpoint(crashed_config.run_path)["update"] == 2
    assert main(["--resume", str(crashed_config.run_path), "runtime.threads=2"]) == 0  # under other run options
    assert load_config(crashed_config.run_path / "config.yaml").runtime.threads == 2
    identities = load_checkpoint(crashed_config.run_path)["config"], load_checkpoint(whole)["config"]
    assert "runtime" not in identities[0] and identities[0]["algorithm_config"] == identities[1]["algorithm_config"]
    assert {**identities[0], "run_dir": None} == {**identities[1], "run_dir": None}  # one run, whichever runtime

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

    # A resume that would change what the run learns is refused, its record kept; one that runs longer is not.
    saved = (run / "config.yaml").read_text()
    assert main(["--resume", str(run), "ppo.lr=0.1", "distill.epochs=16"]) == 2
    err = capsys.readouterr().err
    assert (f"{run} was trained with ppo.lr={config.ppo.lr!r}, distill.epochs=3, not ppo.lr=0.1, distill.epochs=16"
            in err)
    assert err.count("\n") == 1 and (run / "config.yaml").read_text() == saved

    assert main([MAIN_CONFIG, "lrr=0.1"]) == 2
    assert "unknown config key 'lrr' in the command line (did you mean 'ppo.lr'?)" in capsys.readouterr().err

    assert main([MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "algorithm=e3t"]) == 2
    assert "algorithm=e3t needs a model with a partner predictor, and 'ego_mlp' has none" in capsys.readouterr().err
    assert main([MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "architecture=e3t_mlp"]) == 2
    assert "'e3t_mlp' carries E3T's partner predictor, which only algorithm=e3t trains" in capsys.readouterr().err
    assert main([MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "algorithm=e3t", "architecture=e3t_mlp",
                 "algorithm_config.partner_policy=past"]) == 2
    assert "partner_policy must be one of ego, copy, got 'past'" in capsys.readouterr().err

    assert main([MAIN_CONFIG, "lrr=0.1"]) == 2
    assert "unknown config key 'lrr' in the command line (did you mean 'ppo.lr'?)" in capsys.readouterr().err

    checkpoint = run / "checkpoints" / "latest.pt"
    checkpoint.write_bytes(checkpoint.read_bytes()[:1000])
    assert main(["--resume", str(run)]) == 2
    assert "is not a readable checkpoint" in capsys.readouterr().err


@pytest.mark.parametrize("architecture", ["mlp", "gnn_lstm"])
def test_ppo_updates_lower_the_loss_on_a_fixed_batch(tmp_path, architecture):
    torch.manual_seed(0)
    config = tiny_config(tmp_path, f"architecture={architecture}", "ppo.shaping_weight=1")
    actor_critic = make_actor_critic(architecture, (7, 7, 26), hidden=16, share_params=True)
    env = with_model_transforms(make_env(config), actor_critic)
    frames = config.num_envs * config.max_steps
    collector = make_collector(env, TensorDictSequential(actor_critic.actor, actor_critic.critic), frames, frames)
    batch = next(iter(collector)).clone()
    collector.shutdown()
    compute_advantages(batch, actor_critic.critic, config, shaping_weight=1.0)
    loss_module = make_loss(config, actor_critic, make_algorithm(config, actor_critic))
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
    epsilon = E3T.settings_of(config).partner_epsilon
    policy = TensorDictSequential(actor_critic.actor, PartnerMixture(epsilon), actor_critic.critic)
    frames = config.num_envs * config.max_steps
    collector = make_collector(env, policy, frames, frames)
    batch = next(iter(collector)).clone()
    collector.shutdown()
    compute_advantages(batch, actor_critic.critic, config, shaping_weight=1.0)
    batch.set(EGO, ~batch.get(MIXED))
    return batch


def test_e3t_ppo_learns_from_the_ego_transitions_only(tmp_path):
    torch.manual_seed(0)
    config = tiny_config(tmp_path, "algorithm=e3t", "architecture=e3t_mlp", "algorithm_config.partner_epsilon=0.5")
    actor_critic = make_actor_critic("e3t_mlp", (7, 7, 26), hidden=16, share_params=True)
    batch = e3t_batch(config, actor_critic)
    assert (batch.get(EGO).sum(-1) == 1).all()
    loss_module = make_loss(config, actor_critic, make_algorithm(config, actor_critic))

    def losses(data):
        data = data.clone()
        standardize_advantage(data, where=data.get(EGO))
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
    argv = [config_file, *TINY, f"run_dir={tmp_path}", "hidden=16", "total_steps=192",
            "algorithm_config.partner_policy=copy",
            "algorithm_config.partner_copy_rate=0.5", "eval_episodes=1", "eval_heldout=1"]
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
        copy, start = state["algorithm"]["partner_copy"][name], initial[name]
        # After 3 updates at rate 0.5 the copy has moved 7/8 of the way: neither where it started nor the ego.
        if not torch.equal(ego, start):
            moved += 1
            assert not torch.equal(copy, ego) and not torch.equal(copy, start), name
    assert moved > 0
    assert "| e3t_mlp_ik | cramped_room_7x7 |" in (run / "eval.md").read_text()
    with Image.open(run / "team.gif") as gif:
        assert gif.n_frames > 1


# ------------------------------------------------------------------------------------- stops that tell the truth
def test_sigterm_stops_the_entry_point_with_143_after_a_checkpoint_and_no_evaluation(tmp_path):
    """The real command in a process of its own, stopped as a scheduler or `kill` would stop it."""
    argv = [sys.executable, "-m", "trainers.train_command", MAIN_CONFIG, *TINY, f"run_dir={tmp_path}",
            "total_steps=1e6", "checkpoint_every=1", "eval_episodes=2"]
    process = subprocess.Popen(argv, stderr=subprocess.PIPE, text=True, cwd=Path(__file__).resolve().parents[2])
    run = tmp_path / "main" / "seed0"
    deadline = time.monotonic() + 120
    while not (run / "checkpoints" / "latest.pt").exists() and time.monotonic() < deadline:
        time.sleep(0.2)
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 143, err
    assert "stopped by SIGTERM at update" in err and f"kitchen-train --resume {run}" in err
    assert 1 <= load_checkpoint(run)["update"] < 1e6 / 64
    assert not (run / "eval.md").exists()


def signal_at_update(monkeypatch, update, signum):
    """Makes the trainer receive `signum` while it computes the advantages of `update`."""
    real, calls = trainers.ppo.loop.compute_advantages, []

    def compute_advantages(*args, **kwargs):
        calls.append(None)
        if len(calls) == update:
            signal.raise_signal(signum)
        return real(*args, **kwargs)

    monkeypatch.setattr(trainers.ppo.loop, "compute_advantages", compute_advantages)


def test_ctrl_c_exits_130_after_checkpointing_the_update_and_evaluates_only_when_asked(tmp_path, monkeypatch, capsys):
    argv = [MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "total_steps=640", "checkpoint_every=100", "eval_episodes=1",
            "eval_heldout=0", "gif=false"]
    signal_at_update(monkeypatch, 2, signal.SIGINT)
    assert main(argv) == 130
    run = tmp_path / "main" / "seed0"
    assert "stopped by SIGINT at update 2 (128 of 640 env steps)" in capsys.readouterr().err
    assert load_checkpoint(run)["update"] == 2 and not (run / "eval.md").exists()

    signal_at_update(monkeypatch, 1, signal.SIGINT)
    assert main(["--resume", str(run), "--eval-on-stop"]) == 130
    assert load_checkpoint(run)["update"] == 3
    assert (run / "eval.md").read_text().startswith("Partly trained: 192 of 640 env steps")


def test_a_run_killed_before_its_first_checkpoint_starts_clean_when_run_again(tmp_path):
    argv = [MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "total_steps=192", "checkpoint_every=100", "eval_episodes=0"]
    config = load_config(argv[0], argv[1:])

    def killed_at_update_2(update, metrics):
        if update == 2:
            raise KeyboardInterrupt  # the process dies here: no checkpoint yet

    with pytest.raises(KeyboardInterrupt):
        train(config, on_update=killed_at_update_2)
    run = config.run_path
    assert not (run / "checkpoints" / "latest.pt").exists() and read_metrics(run)["losses/policy"]
    assert main(argv) == 0
    for name, rows in read_metrics(run).items():
        assert [step for step, _ in rows] == [64, 128, 192], name
    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    assert [event.step for event in events.Scalars("losses/policy")] == [64, 128, 192]


def test_a_nan_loss_stops_the_run_with_a_clear_error_and_the_last_good_weights(tmp_path, monkeypatch, capsys):
    real, calls = trainers.ppo.loop.compute_advantages, []

    def nan_advantages_at_update_2(batch, *args, **kwargs):
        real(batch, *args, **kwargs)
        calls.append(None)
        if len(calls) == 2:
            batch.set(("agents", "advantage"), torch.full_like(batch.get(("agents", "advantage")), float("nan")))

    saved = []  # every checkpoint's weights and optimizer state, as written
    real_save = trainers.ppo.team.save_checkpoint

    def keeping_a_copy(path, state):
        saved.append(copy.deepcopy({key: state[key] for key in ("actor", "critic", "optimizer")}))
        real_save(path, state)

    monkeypatch.setattr(trainers.ppo.loop, "compute_advantages", nan_advantages_at_update_2)
    monkeypatch.setattr(trainers.ppo.team, "save_checkpoint", keeping_a_copy)
    argv = [MAIN_CONFIG, *TINY, f"run_dir={tmp_path}", "total_steps=256", "checkpoint_every=1"]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "kitchen-train: error: losses/policy=nan at update 2 (128 env steps): training diverged" in err
    assert "Traceback" not in err
    state = load_checkpoint(tmp_path / "main" / "seed0")
    assert state["update"] == 2
    assert all(torch.isfinite(tensor).all() for tensor in state["actor"].values())
    # The whole update was undone: weights and Adam's moments are those checkpointed after update 1.
    after_update_1, at_divergence = saved
    for part in ("actor", "critic"):
        for key, tensor in after_update_1[part].items():
            assert torch.equal(at_divergence[part][key], tensor), (part, key)
    for moments, restored in zip(after_update_1["optimizer"]["state"].values(),
                                 at_divergence["optimizer"]["state"].values()):
        for key in moments:
            assert torch.equal(restored[key], moments[key]), key
    assert not (tmp_path / "main" / "seed0" / "eval.md").exists()


# ------------------------------------------------------------------------------------------ algorithms as parts
class CountingIPPO(IPPO):
    """IPPO plus a logged auxiliary term and a counter of updates that travels in checkpoints."""

    def __init__(self, config, actor_critic):
        super().__init__(config, actor_critic)
        self.updates = 0

    def auxiliary_losses(self, minibatch):
        value = minibatch.get(("agents", "state_value"))
        return {"loss_zero": 0.0 * value.mean(), "mean_value": value.mean().detach()}

    def after_update(self):
        self.updates += 1

    def state_dict(self):
        return {"updates": self.updates}

    def load_state_dict(self, state):
        self.updates = state["updates"]


def test_an_algorithm_added_by_registration_trains_logs_and_checkpoints(tmp_path, monkeypatch):
    monkeypatch.setitem(ALGORITHMS, "counting_ippo", CountingIPPO)
    config = tiny_config(tmp_path, "algorithm=counting_ippo", updates=3)
    run = train(config)
    metrics = read_metrics(run)
    assert [step for step, _ in metrics["losses/zero"]] == [64, 128, 192]
    assert [step for step, _ in metrics["charts/mean_value"]] == [64, 128, 192]
    assert "losses/partner_prediction" not in metrics  # metrics are logged only where they apply
    assert load_checkpoint(run)["algorithm"] == {"updates": 3}
    with pytest.raises(ValueError, match="already registered"):
        register_algorithm("ippo", CountingIPPO)


def test_help_lists_every_config_key_and_hyperparameters_reach_tensorboard(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    for name in TrainConfig.__dataclass_fields__:
        assert f"{name} " in text or f"{name}:" in text, name
    run = train(tiny_config(tmp_path))
    [hparams_dir] = [path for path in (run / "tensorboard").iterdir() if path.is_dir()]
    events = EventAccumulator(str(hparams_dir))
    events.Reload()
    assert events.PluginTagToContent("hparams")


@pytest.mark.slow
@pytest.mark.bitwise
def test_a_compiled_acting_policy_takes_the_same_actions_and_learns_the_same(tmp_path, monkeypatch):
    """torch.compile'd collection through the kitchen collector (the XLA one acts without torch): the same sampled
    actions (so the same returns), log-probabilities equal to float32 rounding (fused kernels), hence the same losses
    to 1e-5."""
    metrics, compiled_functions, compile = {}, [], torch.compile
    monkeypatch.setattr(torch, "compile", lambda function, **options: compiled_functions.append(function) or
                        compile(function, **options))
    for compiled in ("false", "true"):
        config = tiny_config(tmp_path / compiled, "ppo.shaping_weight=1", f"runtime.compile_policy={compiled}",
                             "runtime.collector=kitchen", updates=2)
        run = train(config)
        metrics[compiled] = read_metrics(run)
        assert [getattr(function, "__name__", "") for function in compiled_functions] == \
            (["act"] if compiled == "true" else []), "the acting pass was not the compiled one"
    assert metrics["false"].keys() == metrics["true"].keys()
    for name in ("charts/episode_return", "charts/shaped_return", "charts/episode_deliveries"):
        assert metrics["true"][name] == metrics["false"][name], name
    for name in metrics["false"]:
        torch.testing.assert_close(torch.tensor(metrics["true"][name]), torch.tensor(metrics["false"][name]),
                                   rtol=1e-4, atol=1e-5, msg=name)


def test_minibatches_are_the_rows_of_their_kitchens():
    batch = TensorDict({
        ("agents", "observation"): torch.randint(0, 3, (6, 4, 2, 7, 7, 26), dtype=torch.uint8),
        ("next", "agents", "reward"): torch.randn(6, 4, 2, 1),
        "done": torch.rand(6, 4, 1) < 0.5,
    }, batch_size=[6, 4])
    kitchens = torch.tensor([4, 0, 5])
    minibatch = trainers.ppo.collection.select_kitchens(batch, kitchens)
    assert minibatch.batch_size == (3, 4)
    assert (minibatch == batch[kitchens]).all()


def test_a_learners_minibatches_carry_only_what_the_losses_read_and_step_as_the_whole_batch_would(tmp_path):
    config = tiny_config(tmp_path, "ppo.shaping_weight=1", "ppo.lr=1e-3")
    team, batch = team_and_minibatch(config, tmp_path)
    kitchens = torch.arange(config.num_envs)
    [minibatch] = Learner(config, [team]).minibatches([batch], [[(kitchens,)]])
    keys = set(minibatch.keys(True, True))
    assert not any(key[0] == "next" for key in keys if isinstance(key, tuple)) and "done" not in keys
    assert ("agents", "logits") not in keys and ("agents", "advantage") in keys
    twin = build_team(config, tmp_path / "twin", make_env(config), 0)  # the same seed: the same weights
    assert all(torch.equal(ours, theirs) for ours, theirs in zip(team.parameters, twin.parameters))
    initial = [parameter.detach().clone() for parameter in team.parameters]
    with set_recurrent_mode(True):
        lean = Learner(config, [team]).step(minibatch)
        whole_minibatch = trainers.ppo.collection.select_kitchens(batch, kitchens)
        # Its first layers take their entries from the batch's, as the learner's minibatches do (the weight's
        # gradient then sums kitchen by kitchen in both).
        BatchObservations(batch.get(OBSERVATION)).hand_to(whole_minibatch.get(OBSERVATION), kitchens)
        whole = Learner(config, [twin]).step(whole_minibatch)
    assert all(torch.equal(lean[key], whole[key]) for key in whole)
    assert all(torch.equal(ours, theirs) for ours, theirs in zip(team.parameters, twin.parameters))
    assert not all(torch.equal(now, before) for now, before in zip(team.parameters, initial))


def team_and_minibatch(config, tmp_path):
    """A team built as the trainer builds it, and one batch it collected as one minibatch, advantages standardised."""
    kitchen = make_env(config)
    team = build_team(config, tmp_path / "run", kitchen, 0)
    frames = config.num_envs * config.max_steps
    collector = make_collector(with_model_transforms(kitchen, team.actor_critic), team.policy, frames, frames)
    minibatch = next(iter(collector)).clone()
    collector.shutdown()
    compute_advantages(minibatch, team.actor_critic.critic, config, shaping_weight=1.0)
    team.algorithm.process_minibatch(minibatch)
    return team, minibatch


@pytest.mark.parametrize("architecture", ["mlp", "gnn"])
@pytest.mark.bitwise
def test_a_ppo_step_moves_the_weights_bit_for_bit_as_backward_clipping_and_fused_adam_do(tmp_path, architecture):
    """The step written once for K teams (`ppo_step`, a team dim of 1 here) is what a team's step was before it:
    backward(), `clip_grad_norm_` and its fused Adam."""
    config = tiny_config(tmp_path, f"architecture={architecture}", "ppo.shaping_weight=1", "ppo.lr=1e-3",
                         "ppo.max_grad_norm=0.01")
    team, minibatch = team_and_minibatch(config, tmp_path)
    reference = copy.deepcopy(team.loss_module)
    parameters = list(reference.parameters())
    assert [p.shape for p in parameters] == [p.shape for p in team.parameters]
    optimizer = torch.optim.Adam(parameters, lr=config.ppo.lr, eps=config.ppo.adam_eps, fused=True)
    theirs = minibatch.clone()
    team.algorithm.process_minibatch(theirs)  # as the step does
    with set_recurrent_mode(True):
        trainers.ppo.step.total_loss(reference(theirs)).backward()
        losses = Learner(config, [team]).step(minibatch.clone())
    norm = torch.nn.utils.clip_grad_norm_(parameters, config.ppo.max_grad_norm)
    optimizer.step()
    assert losses["grad_norm"].shape == (1,) and torch.equal(losses["grad_norm"][0], norm) and norm > 0.01
    for ours, theirs in zip(team.parameters, parameters):
        assert torch.equal(ours.detach(), theirs.detach())
        assert ours.grad is None  # let go after the step


@pytest.mark.parametrize("overrides", [
    ["architecture=mlp"],  # the sparse first layer and the oneDNN layers
    ["architecture=mlp_lstm", "share_params=false"],  # recurrent sequences, one network per agent (vmapped)
    ["architecture=gnn"],
], ids=["mlp", "lstm-per-agent", "gnn"])
@pytest.mark.bitwise
def test_a_minibatch_in_shards_has_the_losses_and_gradient_of_the_whole_on_threads_or_not(tmp_path, overrides):
    config = tiny_config(tmp_path, *overrides, "ppo.shaping_weight=1")
    team, minibatch = team_and_minibatch(config, tmp_path)

    def gradients(gradients_of):
        # As `update_teams` does: the losses' own mode settings, interleaved on threads, then agree, and the
        # process's mode is left as it was.
        with set_recurrent_mode(True), set_exploration_type(team.loss_module.deterministic_sampling_mode):
            return gradients_of(minibatch.clone())

    whole_losses, whole = gradients(functools.partial(team_gradients, team))
    sequential_losses, sequential = gradients(sharded_gradients(team, 4, None))
    with ThreadPoolExecutor(4) as pool:
        threaded_losses, threaded = gradients(sharded_gradients(team, 4, pool))
    for name, value in whole_losses.items():
        if name.startswith("loss_") or name == "entropy":
            assert sequential_losses[name].shape == (1,)
            torch.testing.assert_close(sequential_losses[name], value, rtol=1e-5, atol=1e-6, msg=name)
    for shards, gradient in zip(sequential, whole):
        torch.testing.assert_close(shards, gradient, rtol=1e-4, atol=1e-6)
    for name in sequential_losses:  # on threads at once: the same numbers, bit for bit
        assert torch.equal(threaded_losses[name], sequential_losses[name]), name
    for shards, on_threads in zip(sequential, threaded):
        assert torch.equal(shards, on_threads)


def test_one_standardiser_pools_every_transition_or_those_asked_for_without_reading_the_host():
    advantage = torch.tensor([[[1.0], [5.0]], [[3.0], [100.0]], [[2.0], [-7.0]]])  # [T=3, 2 agents, 1]
    pooled = TensorDict({("agents", "advantage"): advantage.clone()}, [3])
    standardize_advantage(pooled)
    torch.testing.assert_close(pooled.get(("agents", "advantage")), (advantage - advantage.mean()) / advantage.std())
    ego = torch.tensor([[True, False], [True, False], [True, False]])  # the first agent's transitions only
    masked = TensorDict({("agents", "advantage"): advantage.clone()}, [3])
    standardize_advantage(masked, where=ego)
    first = advantage[:, 0]
    torch.testing.assert_close(masked.get(("agents", "advantage")), (advantage - first.mean()) / first.std())
    alone = TensorDict({("agents", "advantage"): advantage.clone()}, [3])
    standardize_advantage(alone, where=torch.tensor([[True, False], [False, False], [False, False]]))
    torch.testing.assert_close(alone.get(("agents", "advantage")), advantage - 1.0)  # one transition: scale 1


def test_a_team_trains_on_9x9_generated_kitchens_with_networks_built_for_them(tmp_path):
    """`kitchen_size=9`: the generator's 9x9 kitchens (a share of them 7x7 inside), the networks built for 9x9
    observations (the checkpoint says so), the kitchens' XLA rollout and the update as at 7x7; a 7x7 config cannot
    load the team, nor draw smaller kitchens. Its kitchens keep every continuous wall whole (`intact_walls`)."""
    config = tiny_config(tmp_path, "levels=infinite", "kitchen_size=9", "smaller_kitchens=0.5", "intact_walls=1")
    assert make_env(config).jax_env.generator == GeneratorConfig(size=9, p_smaller=0.5, p_wall_intact=1.0)
    run = train(config)
    state = load_checkpoint(run / "checkpoints" / "latest.pt")
    assert state["model"]["obs_shape"] == [9, 9, 26] and state["update"] == 2
    assert read_metrics(run)["losses/policy"]
    with pytest.raises(Exception, match="obs_shape"):
        train(tiny_config(tmp_path / "small", "levels=infinite", f"init_from={run}"))
    with pytest.raises(ConfigError, match="smaller_kitchens is a share in"):
        tiny_config(tmp_path / "small", "levels=infinite", "smaller_kitchens=0.5")
    with pytest.raises(ConfigError, match=r"^intact_walls is a probability in \[0, 1\], got 1.5$"):
        tiny_config(tmp_path / "small", "levels=infinite", "intact_walls=1.5")
    # Its table: the 9x9 held-out levels and the five classic layouts drawn inside 9x9.
    table = report_trained_team(run, episodes=1, num_heldout=2).read_text()
    for layout in CLASSIC_LAYOUTS:
        assert f"{layout}_in_9x9" in table
    assert "held-out (2)" in table


def test_networks_built_in_python_train_and_load_into_networks_of_ones_own_never_by_a_wrong_name(tmp_path, capsys):
    mine = make_actor_critic("mlp", (7, 7, 26), 8, True)  # narrower than the config's hidden=16
    run = train(tiny_config(tmp_path), actor_critic=mine)
    with pytest.raises(CheckpointError, match="built in Python .*load_team\\(RUN, actor_critic=") as refused:
        load_team(run)
    assert "\n" not in str(refused.value)
    team = load_team(run, actor_critic=make_actor_critic("mlp", (7, 7, 26), 8, True))
    for name, tensor in mine.actor.state_dict().items():
        assert torch.equal(team.actor_critic.actor.state_dict()[name], tensor), name
    assert eval_main(["configs/eval/runs.yaml", f"conditions={{mine: {run}}}", f"out_dir={tmp_path / 'eval'}"]) == 2
    error = capsys.readouterr().err
    assert "built in Python" in error and error.count("\n") == 1
    with pytest.raises(ConfigError, match="actor_critic must be a torch_kitchen.models.ActorCritic.*got a tuple"):
        train(tiny_config(tmp_path / "tuple"), actor_critic=(mine.actor, mine.critic))
