"""The zoo: diverse conventions drawn deterministically, strangers held out of training, teams trained beside zoo
cooks (zoo_ippo) and distilled from several teachers, each resumed bit for bit."""

import csv
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from scripted_cook import TWO_BOOTHS
from tensordict import TensorDict
from test_ppo import tiny_config
from tiny import infinite_observations, redraw_zoo

from jax_env import load_layout, save_layout
from jax_env.cook import floor_tables, walkable_floor
from jax_env.generator import heldout_grids
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.conventions import (
    STRANGER,
    TRAIN,
    ZOO_FILE,
    ZOO_HEADER,
    Convention,
    Zoo,
    ZooMember,
    fingerprints,
    generator_settings,
    load_zoo,
    save_zoo,
)
from torch_kitchen.partners.scripted_cook import ScriptedCook, stacked_conventions
from torch_kitchen.partners.zoo_seats import LEARNER, ZOO_COOK, ZooPartners, ZooSeats, seating
from torch_kitchen.partners.zoo_seats import cook_actions as zoo_cook_actions
from torch_kitchen.teams import RandomStream, TeamPolicy
from trainers.algorithms import ZooIPPO, check_algorithm
from trainers.checkpoint import LATEST, load_checkpoint
from trainers.evaluation import load_team
from trainers.evaluation import main as eval_main
from trainers.ppo.collection import make_collector
from trainers.ppo.distill import DATA, TEACHER_PROBS, distill
from trainers.ppo.distill import main as distill_main
from trainers.ppo.loop import train
from trainers.train_command import main as train_main
from trainers.zoo import (
    clash_rows,
    cross_play,
    draw_zoo,
    same_minus_cross,
    select_diverse,
    stranger_by_content,
    zoo_levels,
)
from trainers.zoo import main as zoo_main

ROOT = Path(__file__).resolve().parents[2]
TEACHERS = [Convention(name="west_first", move_order="WENS"), Convention(name="loader", role="loader"),
            Convention(name="onions", preferences={"onion_pickup": 0.6}, goal_temperature=0.5)]


@pytest.fixture()
def zoo_file(tmp_path):
    members = [ZooMember(c, TRAIN, 1.0, 1.0, {}) for c in TEACHERS]
    members.append(ZooMember(Convention(name="stranger", handover="avoid"), STRANGER, 1.0, 1.0, {}))
    return str(save_zoo(Zoo(0, 7, generator_settings(7), members), tmp_path / "zoo.yaml"))


def test_the_diverse_selection_takes_the_profiles_furthest_apart_first():
    profiles = np.array([[0.5, 0.5], [0.5, 0.52], [1.0, 0.0], [0.0, 1.0], [0.51, 0.5]])
    chosen = select_diverse(profiles, 3)
    assert set(chosen) == {2, 3} | {chosen[2]} and chosen[2] in (0, 1, 4)  # the two corners, then one of the middle


def test_conventions_clash_where_each_plays_better_with_itself_than_with_the_others():
    # A crafted pair that clashes: each delivers 4 with itself, 1 beside the other (either seat); and one that
    # does not (2 whoever sits beside whom).
    clashing = np.array([[4.0, 1.0], [1.0, 4.0]])
    np.testing.assert_allclose(same_minus_cross(clashing), [3.0, 3.0])
    [row] = clash_rows(clashing[..., None], ["held-out (1)"])
    assert (row["same"], row["cross"], row["difference"], row["clash"]) == (4.0, 1.0, 3.0, "holds")
    [row] = clash_rows(np.full((2, 2, 1), 2.0), ["held-out (1)"])
    assert row["difference"] == 0 and row["clash"] == "inconclusive"
    # Asymmetric seats count both ways: with the others means in either seat.
    np.testing.assert_allclose(same_minus_cross(np.array([[4.0, 2.0], [0.0, 3.0]])), [3.0, 2.0])


def test_cross_play_seats_every_convention_beside_every_other_in_both_seats(tmp_path):
    booths = load_layout(save_layout(TWO_BOOTHS, str(tmp_path / "two_booths.txt")))
    deliveries, groups = cross_play(TEACHERS[:2], [booths], rollouts=1, seed=0, max_envs=8, workers=1,
                                    progress=False)
    assert deliveries.shape == (2, 2, 1) and groups == ["two_booths"]
    assert (deliveries == deliveries[0, 0, 0]).all() and deliveries[0, 0, 0] > 0  # each cooks in its own booth


def test_a_zoo_is_drawn_the_same_for_a_seed_on_its_training_levels():
    first, again = (draw_zoo(seed=5, candidates=6, keep=2, strangers=1, levels=4, min_cooked=0.5, max_steps=128,
                             progress=False) for _ in range(2))
    assert first == again and len(first.members) == 2
    assert len(first.strangers) == len(first.training) == 1 and first.strangers[0] not in first.training
    assert all(member.cooked >= 0.5 for member in first.members) and first.similarity["cooks"] >= 2
    # The split is by content: drawn again from the same seed with no strangers asked for, the first draw's stranger
    # is still no training convention (a quarter of all conventions can only ever be strangers).
    again_without = draw_zoo(seed=5, candidates=6, keep=2, strangers=0, levels=4, min_cooked=0.5, max_steps=128,
                             progress=False)
    assert all(stranger_by_content(c) for c in first.strangers) and len(again_without.training) == 2
    assert not fingerprints(first.strangers).keys() & fingerprints(again_without.training).keys()
    held_out = {grid.tobytes() for grid in np.asarray(heldout_grids())}
    assert not any(level.grid.tobytes() in held_out for level in zoo_levels(0, 64, 7))  # never a held-out grid


def test_the_shipped_zoo_holds_diverse_cooks_and_no_shipped_config_trains_with_a_stranger():
    zoo = load_zoo(ROOT / ZOO_FILE, kitchen_size=7)
    assert len(zoo.members) >= 24 and len(zoo.strangers) >= 8
    assert all(member.cooked >= 0.6 for member in zoo.members)
    assert zoo.similarity["kept"] < zoo.similarity["random"]
    # Held out by content: its strangers are strangers by their fingerprint, its training conventions are not.
    assert all(stranger_by_content(c) for c in zoo.strangers) and not any(map(stranger_by_content, zoo.training))
    names = {c.name for c in zoo.strangers}
    shipped = [p for p in (ROOT / "configs").rglob("*.yaml") if "zoo" not in p.parts and "eval" not in p.parts]
    shipped += list((ROOT / "benchmarks").rglob("*.yaml")) + list((ROOT / "examples").rglob("*.yaml"))
    assert len(shipped) > 40
    for path in shipped:
        text = path.read_text()
        if text.startswith(ZOO_HEADER):  # another zoo, whose names are its own (a stranger is one by its content)
            continue
        assert not [name for name in names if name in text], path


@pytest.mark.parametrize("overrides, words", [
    (["distill.teachers=[stranger]"], "'stranger' is a held-out stranger of the zoo"),
    (["distill.teachers=[nobody]"], "the zoo has no convention 'nobody'"),
    (["learned_stranger=true"], "learned_stranger distils from held-out strangers: name them in distill.teachers"),
    (["learned_stranger=true", "distill.teachers=[loader]"], "'loader' is a training convention of the zoo"),
    (["algorithm=zoo_ippo", "algorithm_config.zoo_conventions=[stranger]"], "'stranger' is a held-out stranger"),
    (["kitchen_size=9", "distill.teachers=[loader]"], "drawn for 7x7 kitchens, not 9x9"),
    (["algorithm=zoo_ippo", "algorithm_config.best_response_to=loader"], "'loader' is a training convention"),
    (["algorithm=zoo_ippo", "algorithm_config.best_response_to=stranger", "algorithm_config.zoo_conventions=[loader]"],
     "best_response_to trains beside one stranger alone"),
])  # fmt: skip
def test_a_training_config_that_names_a_stranger_or_an_unknown_cook_is_refused_in_one_line(
        tmp_path, zoo_file, capsys, overrides, words):
    assert train_main(["configs/ippo/mlp_ik.yaml", f"zoo={zoo_file}", f"run_dir={tmp_path}", *overrides]) == 2
    error = capsys.readouterr().err
    assert words in error and error.count("\n") == 1, error
    assert not list(tmp_path.glob("*/seed0"))


@pytest.mark.parametrize("kind", ["kitchen", "xla"])
def test_zoo_seats_draw_a_cook_per_kitchen_and_episode_and_the_cook_acts_in_its_seat(kind):
    seats = ZooSeats(conventions=3, share=0.5, seed=1)
    env = KitchenEnv(64, levels="infinite", max_steps=8, seed=0).append_transform(seats)
    td = env.reset()
    zoo_cook = td[ZOO_COOK]
    cooks = (zoo_cook != LEARNER).sum(-1)
    assert set(cooks.tolist()) == {0, 1} and 0.25 < cooks.float().mean() < 0.75  # at most one cook per kitchen
    assert set(zoo_cook[zoo_cook != LEARNER].tolist()) == {0, 1, 2}
    restored = ZooSeats(conventions=3, share=0.5, seed=7)
    restored.load_state_dict(seats.state_dict())
    assert torch.equal(restored._draw(64), seats._draw(64))  # a resume draws on as the run would have

    # Collected as training collects, by the kitchens' collector and inside XLA (the default): the cooks' seats take
    # their conventions' planned actions, the learner's its own; a seating lasts an episode and the next draws anew.
    actor_critic = make_actor_critic("mlp", (7, 7, 26), 16, True)
    policy = TeamPolicy([actor_critic.acting_policy(ZooPartners(TEACHERS))], [RandomStream(0)], team_size=64)
    collector = make_collector(env, policy, 64 * 12, kind=kind)
    assert type(collector).__name__ == {"kitchen": "KitchenCollector", "xla": "XlaCollector"}[kind]
    batch = next(iter(collector))
    zoo_cook, acted = batch[ZOO_COOK], batch["agents", "action"]
    assert torch.equal(zoo_cook[:, :8], zoo_cook[:, :1].expand(-1, 8, -1))  # one seating per episode
    assert not torch.equal(zoo_cook[:, 8], zoo_cook[:, 7]) and 0.25 < (zoo_cook[:, 8] >= 0).any(-1).float().mean()
    for index, convention in enumerate(TEACHERS[:2]):  # the deterministic ones
        logits = ScriptedCook(convention)(batch["agents", "observation"])
        seated = (zoo_cook == index) & ((logits == 0).sum(-1) == 1)
        assert seated.sum() > 20 and torch.equal(acted[seated], logits.argmax(-1)[seated])
    learner = zoo_cook == LEARNER
    own = torch.distributions.Categorical(logits=batch["agents", "logits"]).log_prob(acted)
    torch.testing.assert_close(own[learner], batch["agents", "action_log_prob"][learner])
    last = zoo_cook[:, -1]  # the seating the batch ends in, kept for a checkpoint as ZooSeats' draws
    assert torch.equal(seats.draws, torch.where((last >= 0).any(-1), 2 * last.amax(-1) + last.argmax(-1), LEARNER))


def test_cooks_planned_for_the_kitchens_they_play_in_act_as_cooks_planned_for_every_kitchen():
    observation = jnp.asarray(infinite_observations(16, seed=3).numpy())
    conventions = stacked_conventions(TEACHERS[:2])  # deterministic: the planned action with certainty
    learner = jnp.full((16, 2), 7, jnp.int32)  # no action: the learner's seats keep it
    key = jax.random.PRNGKey(0)
    cook_actions = jax.jit(zoo_cook_actions, static_argnames="kitchens_at_most")  # as the rollout compiles it
    for cooks in (5, 12):  # fewer kitchens with a cook than the 8 planned for, then more (every kitchen's plan)
        draws = jnp.where(jnp.arange(16) < cooks, jnp.arange(16) % 4, -1)  # conventions 0, 1 in seats 0, 1
        every = cook_actions(key, observation, learner, draws, conventions)
        tables = floor_tables(walkable_floor(observation[:, 0]))  # kept through an episode, as the rollout keeps them
        some = cook_actions(key, observation, learner, draws, conventions, kitchens_at_most=8, tables=tables)
        seated = np.asarray(seating(draws) >= 0)
        assert seated.sum() == cooks and np.array_equal(np.asarray(some), np.asarray(every))
        assert (np.asarray(every)[seated] < 6).all() and (np.asarray(every)[~seated] == 7).all()
        expected = torch.stack([ScriptedCook(TEACHERS[c])(torch.from_numpy(np.asarray(observation))).argmax(-1)
                                for c in range(2)])  # [convention, kitchen, seat]
        kitchens, seats = np.nonzero(seated)
        assert np.array_equal(np.asarray(every)[seated], expected[np.asarray(draws)[kitchens] // 2, kitchens, seats])


def test_a_best_response_trains_beside_its_stranger_in_every_kitchen(tmp_path, zoo_file):
    config = tiny_config(tmp_path, "algorithm=zoo_ippo", f"zoo={zoo_file}", "levels=infinite",
                         "algorithm_config.best_response_to=stranger", updates=1)
    algorithm = ZooIPPO(check_algorithm(config), make_actor_critic("mlp", (7, 7, 26), 16, True))
    assert [c.name for c in algorithm.conventions] == ["stranger"] and algorithm.seats.share == 1.0
    assert load_checkpoint(train(config))["config"]["algorithm_config"]["best_response_to"] == "stranger"


def test_zoo_ippo_learns_beside_zoo_cooks_and_resumes_bit_for_bit_beside_the_same_cooks(tmp_path, zoo_file, capsys):
    common = ("algorithm=zoo_ippo", f"zoo={zoo_file}", "algorithm_config.zoo_share=0.5", "checkpoint_every=1",
              "levels=infinite")
    whole = train(tiny_config(tmp_path / "whole", *common, updates=3))
    stopped_config = tiny_config(tmp_path / "stopped", *common, updates=3)
    train(stopped_config, on_update=lambda update, metrics: update == 2)
    # The zoo file redrawn under the same name since: a resume would train beside other cooks, so it is refused.
    before = Path(zoo_file).read_text()
    redraw_zoo(zoo_file, "loader", zoo_file)
    checkpoint = (stopped_config.run_path / "checkpoints" / LATEST).read_bytes()
    assert train_main(["--resume", str(stopped_config.run_path)]) == 2
    assert "was not trained beside loader as" in capsys.readouterr().err.strip().splitlines()[-1]
    assert (stopped_config.run_path / "checkpoints" / LATEST).read_bytes() == checkpoint  # nothing written
    Path(zoo_file).write_text(before)
    assert train_main(["--resume", str(stopped_config.run_path)]) == 0
    final, straight = load_checkpoint(stopped_config.run_path), load_checkpoint(whole)
    assert final["algorithm"]["zoo_seats"]  # the seats' generator and draws travel with the checkpoint
    assert final["met"] == fingerprints(TEACHERS)  # every training convention it met, kept through the resume
    for part in ("actor", "critic", "algorithm"):
        torch.testing.assert_close(final[part], straight[part], rtol=0, atol=0)


def test_distillation_from_several_teachers_labels_each_round_with_its_teacher_and_resumes_bit_for_bit(
        tmp_path, zoo_file):
    common = ("distill.rounds=3", "distill.epochs=1", f"zoo={zoo_file}", "distill.teacher_mix=round",
              "distill.teachers=[west_first,loader,onions]", "levels=infinite")
    straight_config = tiny_config(tmp_path / "straight", *common)
    straight = distill(straight_config)
    teachers = [straight_config.distill_teacher(r).name for r in range(3)]
    assert len(set(teachers)) > 1  # the draw of seed 0's rounds mixes teachers
    for round_, name in enumerate(teachers):
        data = TensorDict.load_memmap(straight / DATA / f"round{round_}")
        cook = ScriptedCook(next(c for c in TEACHERS if c.name == name))
        # The cook step by step, as the collector called it (XLA may round a batch of another shape otherwise).
        views = data["agents", "observation"]
        labels = torch.stack([cook(views[:, step]) for step in range(views.shape[1])], 1)
        torch.testing.assert_close(data[TEACHER_PROBS], torch.softmax(labels, -1), rtol=0, atol=0)
    stopped = distill(tiny_config(tmp_path / "stopped", *common), on_round=lambda round_, metrics: round_ == 2)
    assert distill_main(["--resume", str(stopped)]) == 0
    for part in ("actor", "critic", "optimizer", "env"):
        torch.testing.assert_close(load_checkpoint(stopped)[part], load_checkpoint(straight)[part], rtol=0, atol=0)
    assert load_checkpoint(straight)["met"] == fingerprints(straight_config.distill_teacher(r) for r in range(3))
    per_seed = [tiny_config(tmp_path, f"zoo={zoo_file}", "distill.teachers=[west_first,loader]", f"seed={seed}")
                for seed in range(3)]
    assert [config.distill_teacher(2).name for config in per_seed] == ["west_first", "loader", "west_first"]


def test_a_team_is_never_scored_beside_a_convention_it_met_whatever_zoo_file_or_name_it_has(tmp_path, zoo_file,
                                                                                           capsys):
    # The loader trains beside a team in zoo_ippo; a second team starts from that one (init_from) and inherits it.
    met = train(tiny_config(tmp_path / "met", "algorithm=zoo_ippo", f"zoo={zoo_file}", "levels=infinite",
                            "algorithm_config.zoo_conventions=[loader]", updates=1))
    child = train(tiny_config(tmp_path / "child", f"init_from={met}", "levels=infinite", updates=1))
    assert load_checkpoint(child)["met"] == fingerprints([TEACHERS[1]])
    # A second zoo file draws the same convention under another name, as a held-out stranger.
    renamed = Convention(**{**TEACHERS[1].as_dict(), "name": "cook_9_001"})
    assert renamed.fingerprint == TEACHERS[1].fingerprint != Convention(role="loader", noise=0.1).fingerprint
    other = save_zoo(Zoo(9, 7, generator_settings(7), [ZooMember(renamed, STRANGER, 1.0, 1.0, {})]),
                     tmp_path / "other.yaml")
    out = tmp_path / "eval"
    code = eval_main(["configs/eval/paper.yaml", f"conditions={{child: {child}}}", "heldout=0",
                      "layouts=[cramped_room_7x7]", f"strangers={other}", f"out_dir={out}", "progress=false",
                      "cross=[]", "gifs=[]"])
    error = capsys.readouterr().err
    assert code == 2 and error.count("\n") == 1, error
    assert "child/seed0 trained with the convention 'loader', which the stranger 'cook_9_001' of " in error
    assert not out.exists()  # nothing written


def test_a_learned_stranger_distils_a_stranger_keeps_fcp_snapshots_and_sits_only_beside_teams(tmp_path, zoo_file,
                                                                                              capsys):
    # Distilled from a held-out stranger, then IPPO, its checkpoint kept at a third, two thirds and the end.
    stranger = train(tiny_config(tmp_path / "learned", f"zoo={zoo_file}", "init_from=scripted_cook",
                                 "distill.rounds=1", "distill.epochs=1", "distill.teachers=[stranger]",
                                 "learned_stranger=true", "snapshots=3", "name=learned", updates=4))
    snapshots = sorted((stranger / "checkpoints").glob("snapshot_*.pt"))
    assert [load_checkpoint(path)["update"] for path in snapshots] == [2, 3, 4]  # 4 updates: ceil(4k/3)
    assert load_checkpoint(stranger)["met"] == fingerprints([Convention(name="stranger", handover="avoid")])
    team = train(tiny_config(tmp_path / "team", "name=team", updates=1))
    out = tmp_path / "eval"
    common = ["configs/eval/paper.yaml", "layouts=[cramped_room_7x7]", "heldout=0", "rollouts=1", "max_steps=16",
              "partner=false", "progress=false", "cross=[]", "gifs=[]", "heatmaps=[]"]
    assert eval_main([*common, f"conditions={{team: {team}}}", f"learned_strangers={{learned: {stranger}}}",
                      f"out_dir={out}"]) == 0
    with open(out / "learned_strangers_pairs.csv") as handle:
        met = {row["stranger"] for row in csv.DictReader(handle)}
    assert met == {"learned/seed0@1of3", "learned/seed0@2of3", "learned/seed0@3of3"}
    assert "With the learned strangers (3: learned/seed0@1of3" in (out / "eval.md").read_text()
    # Never a team to evaluate; nor seated beside a team that learned from the convention it learned from.
    twin = train(tiny_config(tmp_path / "twin", f"zoo={zoo_file}", "algorithm=zoo_ippo", "levels=infinite",
                             "algorithm_config.best_response_to=stranger", "name=twin", updates=1))
    for conditions, words in [(f"{{learned: {stranger}}}", "learned/seed0 is a learned stranger"),
                              (f"{{twin: {twin}}}", "twin/seed0 trained with the convention 'stranger', which the "
                                                    "stranger 'learned/seed0@1of3' of learned_strangers")]:
        assert eval_main([*common, f"conditions={conditions}", f"learned_strangers={{learned: {stranger}}}",
                          f"out_dir={tmp_path / 'refused'}"]) == 2
        error = capsys.readouterr().err
        assert words in error and error.count("\n") == 1, error
        assert not (tmp_path / "refused").exists()


def test_a_cook_of_the_zoo_is_saved_and_loaded_as_a_team_with_its_convention(tmp_path, zoo_file, capsys):
    assert zoo_main(["save", "loader", "stranger", "--zoo", zoo_file, "--run-dir", str(tmp_path)]) == 0
    assert "wrote" in capsys.readouterr().out
    team = load_team(tmp_path / "loader" / "seed0")
    assert team.fully_trained and team.name == "loader/seed0"
    observation = KitchenEnv(8, levels="heldout", seed=2).reset()["agents", "observation"]
    logits = team.actor_critic.actor(TensorDict({("agents", "observation"): observation}, [8]))["agents", "logits"]
    assert torch.equal(logits, ScriptedCook(TEACHERS[1])(observation))
    assert not torch.equal(logits, ScriptedCook()(observation))  # the loader, not the scripted cook
    assert zoo_main(["save", "nobody", "--zoo", zoo_file, "--run-dir", str(tmp_path)]) == 2
    error = capsys.readouterr().err
    assert "no convention 'nobody'" in error and error.count("\n") == 1


def test_a_clash_of_named_conventions_plays_those_alone_and_an_unknown_name_is_refused_in_one_line(
        tmp_path, zoo_file, capsys):
    out = tmp_path / "clash"
    assert zoo_main(["clash", zoo_file, "--conventions", "stranger", "loader", "--heldout", "0", "--max-steps", "4",
                     "--out", str(out)]) == 0
    pairs = {(row["seat0"], row["seat1"]) for row in csv.DictReader((out / "clash.csv").open())}
    assert pairs == {(a, b) for a in ("stranger", "loader") for b in ("stranger", "loader")}
    capsys.readouterr()
    for names, words in [(["loader", "nobody"], "no nobody in"), (["loader", "loader"], "two or more of")]:
        assert zoo_main(["clash", zoo_file, "--conventions", *names, "--out", str(tmp_path / "refused")]) == 2
        error = capsys.readouterr().err
        assert words in error and "loader" in error and error.count("\n") == 1
    assert not (tmp_path / "refused").exists()
