"""The planner-guided start: DAgger from the scripted cook (`kitchen-distill`), then IPPO from it (`init_from`)."""

import dataclasses

import pytest
import torch
from tensordict import TensorDict
from test_ppo import MAIN_CONFIG, read_metrics, tiny_config
from tiny import TINY, redraw_zoo

import trainers.ppo.distill as distillation
from torch_kitchen.keys import VALUE_TARGET
from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.conventions import ZOO_FILE, load_zoo, save_zoo
from torch_kitchen.partners.scripted_cook import ScriptedCook
from trainers.checkpoint import load_checkpoint
from trainers.ppo.distill import DATA, TEACHER_PROBS, distill, distill_start, fit, main, minibatches, replayed
from trainers.ppo.loop import train
from trainers.train_command import main as train_main

ROUNDS = ["distill.rounds=3", "distill.epochs=1"]


def assert_labelled_by_the_cook(run, **tolerance):
    """Every kept state of the run's 3 rounds [4 kitchens, 16 steps], both seats, labelled with the cook's
    distribution as the cook outside gives it; returns the rounds."""
    rounds = [TensorDict.load_memmap(run / DATA / f"round{r}") for r in range(3)]
    for data in rounds:
        assert data.shape == (4, 16)
        observation = data["agents", "observation"]
        torch.testing.assert_close(data[TEACHER_PROBS], torch.softmax(ScriptedCook()(observation), -1), **tolerance)
    return rounds


def test_dagger_labels_every_visited_state_with_the_cooks_distribution_and_keeps_every_round(tmp_path):
    """The kitchens' collector labels with the cook's torch module, bit for bit (XLA's: the resume test below)."""
    run = distill(tiny_config(tmp_path, *ROUNDS))
    rounds = assert_labelled_by_the_cook(run, rtol=0, atol=0)
    assert not torch.equal(rounds[0]["agents", "observation"], rounds[1]["agents", "observation"])
    metrics = read_metrics(run)
    assert [share for _, share in metrics["distill/teacher_share"]] == [1.0, 0.5, 0.25]
    assert [steps for _, steps in metrics["distill/kitchen_steps"]] == [64, 128, 192]  # no round dropped
    assert all(0 <= agreement <= 1 for _, agreement in metrics["distill/agreement"])
    state = load_checkpoint(run)
    assert (state["update"], state["env_steps"]) == (3, 192)

    # Each pass fits the actor on every round's kitchens, or the newest round's and `replay` times as many of the
    # earlier rounds' (all of them at most), and the critic on the last round's batch, once: a feed-forward
    # learner's minibatches of one kitchen's worth of steps (16) drawn from every kitchen.
    for replay, kitchens in ((0, 3 * 4), (1, 4 + 4), (0.5, 4 + 2), (1e9, 3 * 4)):
        config = tiny_config(tmp_path, "distill.epochs=2", "distill.minibatch=1", f"distill.replay={replay}")
        actor_critic = make_actor_critic(config.architecture, (7, 7, 26), config.hidden, config.share_params)
        calls = {"actor": 0, "critic": 0}
        logits_body = actor_critic.actor.module[0]  # what the fitting runs of the actor: its logits, no action drawn
        for name, module in (("actor", logits_body), ("critic", actor_critic.critic)):
            module.register_forward_hook(lambda *_, name=name: calls.update({name: calls[name] + 1}))
        batch = rounds[2].select(("agents", "observation")).clone()
        batch[VALUE_TARGET] = torch.zeros(4, 16, 2, 1)
        optimizer = torch.optim.Adam([*actor_critic.actor.parameters(), *actor_critic.critic.parameters()])
        metrics = fit(actor_critic, optimizer, rounds, batch, config)
        assert calls == {"actor": 2 * kitchens, "critic": 2 * 4}, replay
        assert metrics["distill/value_error"] > 0


def test_a_fitting_pass_reads_the_newest_round_and_a_fresh_draw_of_the_earlier_ones():
    torch.manual_seed(0)
    rounds = [TensorDict({"x": torch.arange(r * 100, r * 100 + 4).reshape(4, 1)}, [4, 1]) for r in range(3)]
    passes = [replayed(rounds, 1.5, "cpu")["x"].flatten().tolist() for _ in range(20)]
    for kitchens in passes:
        assert kitchens[:4] == [200, 201, 202, 203] and len(kitchens) == 4 + 6  # the newest round, then 6 drawn
        assert len(set(kitchens)) == 10 and all(k // 100 in (0, 1) for k in kitchens[4:])  # earlier, none twice
    assert len({tuple(kitchens) for kitchens in passes}) > 1  # a fresh draw each pass
    assert {k for kitchens in passes for k in kitchens[4:]} == {0, 1, 2, 3, 100, 101, 102, 103}  # every one in time
    assert replayed(rounds[:1], 1.0, "cpu")["x"].flatten().tolist() == [0, 1, 2, 3]  # the first round alone
    everything = [0, 1, 2, 3, 100, 101, 102, 103, 200, 201, 202, 203]
    assert replayed(rounds, 0, "cpu")["x"].flatten().tolist() == everything  # replay 0: every round, in order


def test_a_feed_forward_learner_fits_steps_drawn_from_every_kitchen_and_a_recurrent_one_whole_sequences():
    torch.manual_seed(0)
    data = TensorDict({"x": torch.arange(6 * 4).reshape(6, 4)}, [6, 4])  # kitchen k's step t holds 4k + t
    steps = minibatches(data, 2, "cpu", sequences=False)
    assert [tuple(minibatch.shape) for minibatch in steps] == [(8,)] * 3  # two kitchens' worth of steps each
    assert sorted(torch.cat([minibatch["x"] for minibatch in steps]).tolist()) == list(range(24))  # each step once
    assert all(len({step // 4 for step in minibatch["x"].tolist()}) > 2 for minibatch in steps)  # drawn apart
    sequences = minibatches(data, 2, "cpu", sequences=True)
    assert [tuple(minibatch.shape) for minibatch in sequences] == [(2, 4)] * 3
    kitchens = torch.cat([minibatch["x"][:, 0] // 4 for minibatch in sequences])
    assert sorted(kitchens.tolist()) == list(range(6))
    for minibatch in sequences:  # whole kitchens, their steps in order
        assert torch.equal(minibatch["x"], minibatch["x"][:, :1] + torch.arange(4))


@pytest.mark.bitwise
def test_a_distillation_resumed_after_a_round_ends_as_one_run_straight_through(tmp_path, capsys):
    """Inside XLA (the default collector), whose draws come from torch's stream as the checkpoint left it, and whose
    labels are the cook's outside to float rounding (its sums fused otherwise)."""
    rounds = [*ROUNDS, "runtime.collector=xla"]
    straight = distill(tiny_config(tmp_path / "straight", *rounds))
    assert_labelled_by_the_cook(straight)
    stopped = distill(tiny_config(tmp_path / "stopped", *rounds), on_round=lambda round_, metrics: round_ == 2)
    assert load_checkpoint(stopped)["update"] == 2
    assert main(["--resume", str(stopped), "distill.lr=0.1"]) == 2  # another lesson: refused, nothing changed
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "was trained with distill.lr=0.006, not distill.lr=0.1" in error
    assert load_checkpoint(stopped)["update"] == 2
    assert main(["--resume", str(stopped)]) == 0
    for part in ("actor", "critic", "optimizer", "env"):
        torch.testing.assert_close(load_checkpoint(stopped)[part], load_checkpoint(straight)[part], rtol=0, atol=0)


def test_self_play_starts_from_the_distilled_team_and_resumes_without_it(tmp_path, capsys):
    distilled = distill(tiny_config(tmp_path, *ROUNDS, "name=distilled", "seed=1"))
    init_from = f"init_from={tmp_path}/distilled/seed{{seed}}"  # {seed}: each team its own
    # A rate so small that the first update leaves the weights where they started.
    run = train(tiny_config(tmp_path, init_from, "seed=1", "ppo.lr=1e-12", "ppo.anneal_lr=false", updates=1))
    scratch = train(tiny_config(tmp_path / "scratch", "seed=1", "ppo.lr=1e-12", "ppo.anneal_lr=false", updates=1))
    for part in ("actor", "critic"):
        weights = load_checkpoint(run)[part]
        torch.testing.assert_close(weights, load_checkpoint(distilled)[part], rtol=0, atol=1e-9)
        assert not all(torch.allclose(mine, theirs) for mine, theirs in
                       zip(weights.values(), load_checkpoint(scratch)[part].values()))

    other_model = [MAIN_CONFIG, *TINY, f"run_dir={tmp_path / 'other'}", init_from, "seed=1", "architecture=mlp",
                   "hidden=8"]
    assert train_main(other_model) == 2
    assert "holds another model (hidden: checkpoint 16, expected 8)" in capsys.readouterr().err

    (distilled / "checkpoints" / "latest.pt").unlink()  # a resumed run reads its own checkpoint only
    assert train_main(["--resume", str(run), "total_steps=128"]) == 0
    assert load_checkpoint(run)["update"] == 2


def test_a_run_from_the_scripted_cook_distils_its_start_into_its_own_folder_first(tmp_path):
    config = tiny_config(tmp_path, *ROUNDS, "init_from=scripted_cook", "ppo.lr=1e-12", "ppo.anneal_lr=false", updates=1)
    run = train(config)
    distilled = run / "distilled"
    assert load_checkpoint(distilled)["update"] == 3  # every round
    for part in ("actor", "critic"):
        torch.testing.assert_close(load_checkpoint(run)[part], load_checkpoint(distilled)[part], rtol=0, atol=1e-9)
    assert read_metrics(distilled)["distill/teacher_share"][0][1] == 1.0


def test_runs_whose_distillations_are_the_same_share_one_start(tmp_path, monkeypatch, capsys):
    """Two conditions that differ in what follows the distillation (an algorithm, a budget) distil once, and each
    run's folder holds the start bit for bit, without the rounds' data (dropped from the shared start once it is done);
    another seed distils its own."""
    rounds = []
    plain = distillation.learn_round
    monkeypatch.setattr(distillation, "learn_round", lambda *args: rounds.append(args[1]) or plain(*args))
    planned = {"ippo": ["name=ippo"], "zoo": ["name=zoo", "algorithm=zoo_ippo", "total_steps=512"],
               "seed1": ["name=seed1", "seed=1"]}
    configs = {name: tiny_config(tmp_path, *ROUNDS, "init_from=scripted_cook", *own) for name, own in planned.items()}
    starts = {name: distill_start(config, config.run_path / "distilled") for name, config in configs.items()}
    assert rounds == [0, 1, 2, 0, 1, 2]  # two distillations for three runs
    assert "its start was distilled with the same settings in" in capsys.readouterr().err  # said where it is reused
    assert distillation.start_key(configs["ippo"]) == distillation.start_key(configs["zoo"])
    assert distillation.start_key(configs["ippo"]) != distillation.start_key(configs["seed1"])
    for part in ("actor", "critic", "optimizer"):
        torch.testing.assert_close(load_checkpoint(starts["zoo"])[part], load_checkpoint(starts["ippo"])[part],
                                   rtol=0, atol=0)
    assert load_checkpoint(starts["zoo"])["met"] == load_checkpoint(starts["ippo"])["met"] != {}  # the cook met
    assert not (starts["zoo"] / DATA).exists() and load_checkpoint(starts["zoo"])["update"] == 3
    assert "name: zoo" in (starts["zoo"] / "config.yaml").read_text()
    assert len(list((tmp_path / distillation.SHARED_STARTS).glob("*/checkpoints"))) == 2
    assert not list((tmp_path / distillation.SHARED_STARTS).glob(f"*/{DATA}"))  # a finished start keeps no rounds
    # A teacher counts by what it is: the same zoo in another file is the same start, a teacher redrawn another.
    taught = tiny_config(tmp_path, *ROUNDS, "distill.teachers=[cook_0_193]", f"zoo={ZOO_FILE}")
    moved = save_zoo(load_zoo(ZOO_FILE), tmp_path / "moved.yaml")
    redrawn = redraw_zoo(ZOO_FILE, "cook_0_193", tmp_path / "redrawn.yaml")
    assert distillation.start_key(taught) == distillation.start_key(dataclasses.replace(taught, zoo=str(moved)))
    assert distillation.start_key(taught) != distillation.start_key(dataclasses.replace(taught, zoo=str(redrawn)))


@pytest.mark.parametrize("architecture", ["mlp_lstm", "gnn", "ego_mlp"])
def test_any_architecture_distils_and_its_team_plays_as_a_trained_one(tmp_path, architecture):
    """Recurrent models fit whole sequences; the checkpoint is a trained team's (`kitchen-eval`, `kitchen-play`)."""
    from trainers.evaluation import load_team

    run = distill(tiny_config(tmp_path, f"architecture={architecture}", "distill.rounds=2", "distill.epochs=1"))
    team = load_team(run)
    assert team.config.architecture == architecture
    assert len(read_metrics(run)["distill/cross_entropy"]) == 2
