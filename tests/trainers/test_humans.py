"""The 2019 human games' conversion, on games the tests write in the study's format from the scripted cook's play."""

import ast
import dataclasses
import io
import pickle
import subprocess
import tarfile

import jax
import numpy as np
import pytest
import torch

pandas = pytest.importorskip("pandas", reason="the human games need pandas: pip install .[humans]")

from jax_env import Overcooked, load_layout  # noqa: E402
from jax_env.human_games import (  # noqa: E402
    LAYOUTS,
    RECORDED_REWARD,
    SOURCE,
    TERRAIN,
    TRIALS,
    human_games,
    load_dataset,
    padded_game,
    write_dataset,
)
from jax_env.layouts import CLASSIC_LAYOUTS, POT, padded_layouts, padded_offset  # noqa: E402
from jax_env.state import DIR_VECTORS, DISH, ONION, PLATE, POT_EMPTY, POT_FULL  # noqa: E402
from torch_kitchen.models import make_actor_critic  # noqa: E402
from torch_kitchen.partners.scripted_cook import ScriptedCook  # noqa: E402
from trainers.checkpoint import load_checkpoint  # noqa: E402
from trainers.evaluation import load_team  # noqa: E402
from trainers.humans.command import main  # noqa: E402
from web_apps.play.game import Game, Partner, replay  # noqa: E402

SYMBOL = {kind: symbol for symbol, kind in TERRAIN.items() if symbol not in "12"}
NAMES = {ONION: "onion", PLATE: "dish", DISH: "soup"}
STUDY_NAME = {ours: theirs for theirs, ours in LAYOUTS.items()}


def study_state(state, width: int) -> dict:
    """A state as the study's game logged it: pots as [onions, cook time] counting past 20, soups on plates."""
    grid, contents = np.asarray(state.grid), np.asarray(state.contents)
    objects = {}
    for y, x in zip(*np.nonzero((contents > 0) | (grid == POT))):  # a ready pot's status is 0
        if grid[y, x] == POT:
            status = int(contents[y, x])
            if status == POT_EMPTY:
                continue
            onions, cook_time = (POT_EMPTY - status, 0) if status > POT_FULL else (3, POT_FULL - status)
            cook_time += 4 if status == 0 else 0  # the client went on counting once a soup was ready
            objects[f"{x},{y}"] = {"name": "soup", "position": [int(x), int(y)], "state": ["onion", onions, cook_time]}
        else:
            objects[f"{x},{y}"] = {"name": NAMES[int(contents[y, x])], "position": [int(x), int(y)]}
    players = []
    for pos, facing, held in zip(np.asarray(state.agent_pos), np.asarray(state.agent_dir), np.asarray(state.agent_inv)):
        player = {"position": [int(pos % width), int(pos // width)], "orientation": list(DIR_VECTORS[int(facing)])}
        if held:
            player["held_object"] = {"name": NAMES[int(held)], "position": player["position"]}
        players.append(player)
    return {"players": players, "objects": objects, "order_list": ["onion"], "pot_explosion": False}


def study_action(action: int):
    return "INTERACT" if action == 5 else [0, 0] if action == 4 else list(DIR_VECTORS[action])


def scripted_game(layout_name: str, steps: int, worker: int, seed: int = 0) -> pandas.DataFrame:
    """`steps` steps of two scripted cooks (sampling) on a classic layout, as rows of the study's trials."""
    layout = load_layout(layout_name)
    kitchen = Overcooked(layout, max_steps=10_000)
    state = kitchen.initial_state(jax.random.PRNGKey(seed))
    cook, generator = ScriptedCook(), torch.Generator().manual_seed(seed)
    terrain_rows = str(["".join(SYMBOL[kind] for kind in row) for row in np.asarray(layout.grid)])
    rows = []
    for t in range(steps):
        observation = torch.from_numpy(np.array(kitchen.get_obs(state)))
        actions = torch.multinomial(cook(observation).softmax(-1), 1, generator=generator)[:, 0].tolist()
        after, reward, _, _ = kitchen.step_env(state, np.asarray(actions))
        rows.append({
            "layout_name": STUDY_NAME[layout_name], "workerid_num": worker, "run": "run-1", "round_num": 1.0,
            "cur_gameloop": float(t), "layout": terrain_rows,
            "state": str(study_state(state, layout.width)), "next_state": str(study_state(after, layout.width)),
            "joint_action": str([study_action(a) for a in actions]),
            "reward": float(reward[0]) / 20 * RECORDED_REWARD,
        })  # fmt: skip
        state = after
    return pandas.DataFrame(rows).sample(frac=1.0, random_state=seed)  # the study's rows are not in step order


@pytest.fixture(scope="module")
def trials():
    return pandas.concat([scripted_game("cramped_room", 150, worker=3), scripted_game("forced_coord", 40, worker=4)],
                         ignore_index=True)


def test_the_study_games_convert_and_every_step_replays_through_the_jax_env(trials, tmp_path):
    games = list(human_games(trials, "train"))
    assert [(g.layout, len(g)) for g in games] == [("cramped_room", 150), ("forced_coord", 40)]
    cramped = games[0]
    assert cramped.deliveries >= 1  # soups were cooked, plated, carried and served: every encoding crossed
    assert {PLATE, DISH} <= set(np.unique(cramped.agent_inv)) and (cramped.contents == 0).any()
    in_step_order = trials[trials.workerid_num == 3].sort_values("cur_gameloop")
    for t in (0, 7, 149):  # the study's actions, in its own notation, as action indices
        study = ast.literal_eval(in_step_order.joint_action.iloc[t])
        assert cramped.actions[t].tolist() == [
            5 if a == "INTERACT" else 4 if a == [0, 0] else DIR_VECTORS.index(tuple(a)) for a in study
        ]
    written = write_dataset(games, tmp_path)
    assert written == {("train", "cramped_room"): 150, ("train", "forced_coord"): 40}
    loaded = load_dataset(tmp_path, "train", "cramped_room")
    assert [g.name for g in loaded] == [cramped.name]
    for field in ("contents", "agent_pos", "agent_dir", "agent_inv", "actions", "delivered"):
        assert np.array_equal(getattr(loaded[0], field), getattr(cramped, field))


def test_a_game_drawn_inside_a_7x7_kitchen_replays_exactly_with_its_cells_shifted(trials):
    game = next(human_games(trials, "train"))
    padded = padded_game(game)  # checks every step's replay in the 7x7 kitchen
    assert padded.layout == "cramped_room_in_7x7" and padded.contents.shape == (150, 7, 7)
    classic, seven = load_layout("cramped_room"), load_layout("cramped_room_in_7x7")
    start = [(int(p % 5), int(p // 5)) for p in game.agent_pos[0]]
    assert [(int(p % 7), int(p // 7)) for p in padded.agent_pos[0]] == [(x + 1, y + 1) for x, y in start]
    assert np.array_equal(np.asarray(seven.grid)[1:5, 1:6], np.asarray(classic.grid))
    assert padded.deliveries == game.deliveries and np.array_equal(padded.actions, game.actions)
    with pytest.raises(ValueError, match="does not fit a 7x7 kitchen"):
        padded_game(dataclasses.replace(game, layout="counter_circuit"))


def test_a_game_drawn_inside_a_9x9_kitchen_replays_exactly_and_every_classic_layout_fits_one(trials):
    game = next(human_games(trials, "train"))
    nine = padded_game(game, 9)  # checks every step's replay in the 9x9 kitchen
    assert nine.layout == "cramped_room_in_9x9" and nine.contents.shape == (150, 9, 9)
    start = [(int(p % 5), int(p // 5)) for p in game.agent_pos[0]]
    assert [(int(p % 9), int(p // 9)) for p in nine.agent_pos[0]] == [(x + 2, y + 2) for x, y in start]
    assert nine.deliveries == game.deliveries and np.array_equal(nine.actions, game.actions)
    assert padded_layouts(9) == tuple(f"{layout}_in_9x9" for layout in CLASSIC_LAYOUTS)
    for layout in CLASSIC_LAYOUTS:  # walled in: the same kitchen, its cells shifted
        classic, drawn = load_layout(layout), load_layout(f"{layout}_in_9x9")
        (dx, dy), (height, width) = padded_offset(layout, 9), classic.shape
        assert drawn.shape == (9, 9)
        assert np.array_equal(np.asarray(drawn.grid)[dy:dy + height, dx:dx + width], np.asarray(classic.grid))


def test_a_step_that_does_not_replay_is_named_by_game_and_step(trials):
    broken = trials.copy()
    row = broken.index[(broken.workerid_num == 4) & (broken.cur_gameloop == 12.0)][0]
    actions = ast.literal_eval(broken.loc[row, "joint_action"])
    broken.loc[row, "joint_action"] = str([actions[0], "INTERACT" if actions[1] != "INTERACT" else [0, 0]])
    with pytest.raises(ValueError, match=r"forced_coord-worker4-run-1-round1: step 12 "):
        list(human_games(broken, "test"))


def study_archive(trials, cache):
    """The study's source distribution as pip would download it, holding `trials` (test split: worker 4's game)."""
    cache.mkdir(parents=True, exist_ok=True)
    name, version = SOURCE.split("==")
    with tarfile.open(cache / f"{name.replace('-', '_')}-{version}.tar.gz", "w:gz") as archive:
        for split, member in TRIALS.items():
            data = pickle.dumps(trials if split == "train" else trials[trials.workerid_num == 4])
            info = tarfile.TarInfo(f"{name}-{version}/{member}")
            info.size = len(data)
            archive.addfile(info, io.BytesIO(data))


def test_fetch_reads_the_source_distribution_and_writes_the_dataset(trials, tmp_path, capsys):
    cache = tmp_path / "cache"
    study_archive(trials, cache)
    assert main(["fetch", "--cache", str(cache), "--out", str(tmp_path / "humans")]) == 0
    out = capsys.readouterr().out
    assert "3 games, 230 of 230 recorded steps replayed exactly" in out
    assert "230 steps inside 7x7 kitchens and 230 steps inside 9x9 kitchens" in out
    assert sorted(p.name for p in (tmp_path / "humans").iterdir()) == sorted(
        f"{split}_{layout}{inside}.npz" for split, layout in
        [("test", "forced_coord"), ("train", "cramped_room"), ("train", "forced_coord")]
        for inside in ("", "_in_7x7", "_in_9x9"))


def test_a_failed_download_is_one_line(tmp_path, monkeypatch, capsys):
    def offline(command, **kwargs):
        return subprocess.CompletedProcess(command, 1, "", "ERROR: No matching distribution found\n")

    monkeypatch.setattr(subprocess, "run", offline)
    assert main(["fetch", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "humans")]) == 1
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "could not download overcooked-ai==1.1.0" in error
    assert not (tmp_path / "humans").exists()


def test_human_proxies_are_fitted_measured_and_saved_as_teams_that_play(trials, tmp_path, capsys):
    study_archive(trials, tmp_path / "cache")
    assert main(["fetch", "--cache", str(tmp_path / "cache"), "--out", str(tmp_path / "humans")]) == 0
    report = tmp_path / "proxies.md"
    assert main(["train", "--data", str(tmp_path / "humans"), "--runs", str(tmp_path / "runs"), "--layouts",
                 "forced_coord", "forced_coord_in_7x7", "forced_coord_in_9x9", "--hidden", "32", "--epochs", "40",
                 "--minibatch", "8",
                 "--episodes", "2", "--game-steps", "30", "--candidates", "2", "--fine-tune-below", "1e9",
                 "--fine-tune-steps", "1", "--report", str(report)]) == 0
    rows = [line.split("|")[1:-1] for line in report.read_text().splitlines() if line.startswith("| forced")]
    assert [row[0].strip() for row in rows] == ["forced_coord", "forced_coord_in_7x7", "forced_coord_in_9x9"]
    games = load_dataset(tmp_path / "humans", "test", "forced_coord")
    stays = np.mean(np.concatenate([g.actions for g in games]) == 4)
    for row in rows:
        accuracy, always_stay, moving, majority = (float(cell) for cell in row[2:6])
        assert always_stay == pytest.approx(stays, abs=1e-3)
        assert moving > majority  # the cooks' moves are a function of what they see: the proxy learned some
        assert float(row[7]) >= 0 and float(row[8]) == pytest.approx(np.mean([g.deliveries for g in games]))
        kept, tuned, (candidates, humans) = int(row[10]), row[11].strip(), row[12].split(" / ")
        fits, *tunes = candidates.split(";")
        assert kept in (0, 1) and len(fits.split()) == 2  # the kept fit of two, each fit's soups shown
        # The study's 40 steps of forced_coord deliver no soup: nothing to fine-tune toward (see below for a fine-tune).
        assert (tunes, tuned) == ([], "-")
        assert float(humans) == pytest.approx(np.mean([g.deliveries for g in load_dataset(tmp_path / "humans",
                                                                                           "train", "forced_coord")]))
    # Saved as trained teams: evaluation and kitchen-play load them like any run.
    team = load_team(tmp_path / "runs" / "bc_forced_coord_in_7x7" / "seed0")  # fitted on the train split
    assert team.obs_shape == (7, 7, 26) and team.config.levels == "forced_coord_in_7x7"
    inside_9x9 = load_team(tmp_path / "runs" / "bc_forced_coord_in_9x9" / "seed0")  # a partner for 9x9 teams
    assert inside_9x9.obs_shape == (9, 9, 26) and inside_9x9.config.levels == "forced_coord_in_9x9"
    assert team.config.seed == int(rows[1][10])  # the fit kept, in the run of the base seed
    game = Game(load_layout("forced_coord_in_7x7"), Partner(team.name, team.actor_critic, team.obs_shape), 0,
                tmp_path / "game.jsonl", max_steps=5)
    while not game.over:
        game.step(4)
    assert replay(tmp_path / "game.jsonl")["steps"] == 5
    # Fitted on the test split: the evaluations' human proxy, measured on the train split.
    assert main(["train", "--data", str(tmp_path / "humans"), "--runs", str(tmp_path / "runs"), "--layouts",
                 "forced_coord", "--hidden", "8", "--epochs", "1", "--episodes", "1", "--game-steps", "5",
                 "--fit-on", "test", "--fine-tune-steps", "0"]) == 0
    assert "fitted on the test split, measured on the train split" in capsys.readouterr().out
    assert load_team(tmp_path / "runs" / "human_proxy_forced_coord" / "seed0").config.levels == "forced_coord"
    # Settings no fit can use, and a layout without games, are one line.
    assert main(["train", "--data", str(tmp_path / "humans"), "--layouts", "forced_coord", "--candidates", "0"]) == 1
    assert "candidates must be at least 1, got 0" in capsys.readouterr().err
    assert main(["train", "--data", str(tmp_path / "humans"), "--layouts", "forced_coord", "--anchor-coef", "0"]) == 1
    assert "anchor_coef must be above 0, got 0.0" in capsys.readouterr().err
    assert main(["train", "--data", str(tmp_path / "humans"), "--layouts", "coord_ring"]) == 1
    assert "run `kitchen-humans fetch` first" in capsys.readouterr().err


def test_a_studys_own_kitchen_play_games_become_the_same_dataset_with_only_the_person_labelled(tmp_path, capsys):
    from trainers.humans.behaviour_cloning import NOT_HUMAN, human_batch
    from web_apps.play.game import SCRIPTED, load_partner

    keys = [1, 3, 5, 0, 2, 4, 5, 1]
    for seat in (0, 1):
        game = Game(load_layout("cramped_room"), load_partner(SCRIPTED), seat, tmp_path / f"seat{seat}.jsonl",
                    seed=seat, max_steps=len(keys))
        for key in keys:
            game.step(key)
    records = [str(tmp_path / "seat0.jsonl"), str(tmp_path / "seat1.jsonl")]
    assert main(["import", *records, "--out", str(tmp_path / "study"), "--split", "test"]) == 0
    assert "test_cramped_room.npz: 16 steps" in capsys.readouterr().out
    games = load_dataset(tmp_path / "study", "test", "cramped_room")
    assert [g.human_seats for g in games] == [(True, False), (False, True)]
    assert games[0].actions[:, 0].tolist() == keys and games[1].actions[:, 1].tolist() == keys
    labels = human_batch(games).get(("agents", "human_action"))
    assert labels[:8, 1].eq(NOT_HUMAN).all() and labels[8:, 0].eq(NOT_HUMAN).all()
    assert labels[:8, 0].tolist() == keys
    # Played on a kitchen that is no registered layout: refused in one line.
    header, *rest = (tmp_path / "seat0.jsonl").read_text().splitlines()
    other = tmp_path / "elsewhere.jsonl"
    other.write_text("\n".join([header.replace('"layout_name": "cramped_room"', '"layout_name": "heldout_007"'),
                                *rest]))
    assert main(["import", str(other), "--out", str(tmp_path / "x")]) == 1
    assert "not a registered layout" in capsys.readouterr().err


def test_the_proxy_kept_is_the_candidate_that_delivers_closest_to_the_humans(monkeypatch):
    import trainers.humans.behaviour_cloning as cloning

    soups = {3: 30.0, 4: 11.0, 5: 0.0, 6: 9.0}  # by seed; the humans delivered 10
    monkeypatch.setattr(cloning, "fit_proxy", lambda batch, settings: (f"proxy {settings.seed}", []))
    games = []
    monkeypatch.setattr(cloning, "deliveries_together",
                        lambda proxy, layout, steps, episodes, seed: games.append(seed) or soups[int(proxy[6:])])
    chosen = cloning.choose_proxy(None, "cramped_room", cloning.ProxySettings(seed=3, candidates=4), 100, 10.0, 8)
    # 11 is nearer 10 than 9 is by ratio (1.1 against 1/1.11); the most soups (30) or none (0) is not chosen.
    assert (chosen.actor_critic, chosen.seed, chosen.soups) == ("proxy 4", 4, soups)
    assert games == [cloning.SELECTION_GAMES + seed for seed in range(3, 7)]  # apart from the measured games
    assert cloning.humanlike_distance(10, 10) == 0 and cloning.humanlike_distance(0, 0) == 0


def test_a_proxy_that_delivers_far_less_than_the_humans_is_fine_tuned_until_it_delivers_about_as_much(monkeypatch,
                                                                                                       tmp_path):
    import trainers.evaluation.teams as teams
    import trainers.humans.behaviour_cloning as cloning

    # Soups by KL weight (the humans delivered 10): too few, too many, then about as many between the two.
    tuned_soups = {0.1: 4.0, 0.025: 14.0, 0.05: 9.5, 0.035: 11.0}
    runs, games = [], []
    monkeypatch.setattr(cloning, "save_proxy", lambda proxy, settings, layout, run: run)
    monkeypatch.setattr(cloning, "fine_tune", lambda start, layout, settings, coef, steps, seed, run_dir:
                        runs.append((start, coef, steps, seed, run_dir)) or coef)
    monkeypatch.setattr(teams, "load_team", lambda coef: type("Team", (), {"actor_critic": f"tuned {coef}"}))
    monkeypatch.setattr(cloning, "deliveries_together", lambda proxy, layout, steps, episodes, seed:
                        games.append(seed) or tuned_soups[float(proxy.removeprefix("tuned "))])
    settings = cloning.ProxySettings(fine_tunes=4)
    team = tmp_path / "bc_forced_coord" / "seed0"
    chosen = cloning.Chosen("cloned", 2, {2: 1.0})
    kept = cloning.fine_tuned(chosen, "forced_coord", settings, 1200, 10.0, 8, team)
    # 0.1 too strong, a quarter of it too weak, their geometric mean (0.05) within 10%: the search ends there.
    assert (kept.actor_critic, kept.seed, kept.anchor_coef) == ("tuned 0.05", 2, 0.05)
    assert kept.tuned == {0.1: 4.0, 0.025: 14.0, 0.05: 9.5}
    assert runs == [(team / "cloned", coef, 1200, 2, team / "anchored") for coef in (0.1, 0.025, 0.05)]
    assert games == [cloning.SELECTION_GAMES + 2] * 3  # the games the cloned proxy was chosen in
    assert cloning.next_anchor_coef({0.1: 20.0}, 10.0) == 0.4  # too many soups: a stronger anchor
    # Delivering half of what the humans did or more, or with fine-tuning off, the cloned proxy stays as it is.
    for near, steps in (({2: 5.0}, settings.fine_tune_steps), ({2: 1.0}, 0)):
        same = cloning.Chosen("cloned", 2, near)
        assert cloning.fine_tuned(same, "forced_coord", cloning.ProxySettings(fine_tune_steps=steps), 1200, 10.0, 8,
                                  team) is same
    # No fine-tune closer to the humans than the cloned proxy: it is kept, after `fine_tunes` tries.
    monkeypatch.setattr(cloning, "deliveries_together", lambda proxy, layout, steps, episodes, seed: 40.0)
    kept = cloning.fine_tuned(cloning.Chosen("cloned", 2, {2: 4.0}), "forced_coord", cloning.ProxySettings(), 1200,
                              10.0, 8, team)
    assert (kept.actor_critic, kept.anchor_coef, kept.tuned) == ("cloned", None, {0.1: 40.0, 0.4: 40.0, 1.6: 40.0})


def test_a_fine_tune_is_anchored_ippo_from_the_cloned_proxy_saved_beside_the_team(tmp_path):
    import trainers.humans.behaviour_cloning as cloning

    settings = cloning.ProxySettings(hidden=8, fine_tune_steps=1, fine_tunes=2)  # one update of each fine-tune
    proxy = make_actor_critic("ego_mlp", (*load_layout("cramped_room").shape, 26), 8)
    team = tmp_path / "bc_cramped_room" / "seed0"
    # Humans who delivered 5 soups in 20 steps: an untrained proxy's fine-tunes deliver fewer, so the second KL
    # weight is a quarter of the first.
    kept = cloning.fine_tuned(cloning.Chosen(proxy, 1, {1: 0.0}), "cramped_room", settings, 20, 5.0, 1, team)
    assert list(kept.tuned) == [0.1, 0.025] and kept.anchor_coef is None  # none closer than the cloned one
    for coef in ("0.1", "0.025"):
        tuned = load_team(team / "anchored" / f"anchor{coef}" / "seed1")
        config = tuned.config
        assert (config.algorithm, config.algorithm_config, config.init_from) == (
            "anchored_ippo", {"anchor_coef": float(coef)}, str(team / "cloned"))
        assert (config.levels, config.max_steps, config.ppo.lr, config.hidden) == ("cramped_room", 20, 1e-3, 8)
        assert load_checkpoint(team / "anchored" / f"anchor{coef}" / "seed1")["env_steps"] == 32 * 256
    assert load_team(team / "cloned").config.levels == "cramped_room"
