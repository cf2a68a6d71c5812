"""Self-play / cross-play evaluation: known counts from scripted cooks, pair selection, seeding, errors, outputs."""

import csv
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image
from scripted_cook import TWO_BOOTHS, save_scripted_team, scripted_team
from torchrl.envs.utils import ExplorationType, set_exploration_type

from jax_env import get_layout, parse_layout, save_layout
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic, model_identity
from trainers.checkpoint import CheckpointError, save_checkpoint
from trainers.config import ConfigError, EvalConfig, TrainConfig
from trainers.config.compose import load_config
from trainers.evaluation import (
    CROSS,
    HUMAN,
    PARTNER,
    SCRIPTED_CONDITION,
    SP,
    XP,
    evaluate,
    load_population,
    main,
    make_matchups,
    play,
)
from trainers.ppo.loop import train

# Agent 1's booth is complete; agent 0's has no plate pile, so agent 0 can never deliver here.
ONE_BOOTH = parse_layout("WPWPW\nW0O1B\nWXWXW", name="one_booth")
PACE = 7  # soups a scripted cook delivers alone in its booth in 256 steps
WORKING = {"scripted_cooks": (0, 1), "scripted_cook_seat0": (0,), "scripted_cook_seat1": (1,), "scripted_idle": ()}


@pytest.fixture()
def booth_files(tmp_path):
    return [save_layout(layout, str(tmp_path / f"{layout.name}.txt")) for layout in (TWO_BOOTHS, ONE_BOOTH)]


@pytest.mark.parametrize("layout, seats, expected", [
    (TWO_BOOTHS, (0, 1), 2 * PACE), (TWO_BOOTHS, (0,), PACE), (TWO_BOOTHS, (1,), PACE), (TWO_BOOTHS, (), 0),
    (ONE_BOOTH, (0, 1), PACE), (ONE_BOOTH, (0,), 0),
])  # fmt: skip
def test_a_scripted_cook_delivers_at_a_known_pace(layout, seats, expected):
    # Plain TorchRL rollouts, outside the evaluator: the ground truth the evaluator must reproduce.
    env = KitchenEnv(8, levels=layout, max_steps=256, seed=3)
    with set_exploration_type(ExplorationType.RANDOM):
        rollout = env.rollout(256, scripted_team(seats).actor)
    assert rollout["next", "deliveries"].sum(1).squeeze(-1).tolist() == [expected] * 8


def test_the_evaluator_reports_exactly_the_known_counts(tmp_path, booth_files):
    runs = {name: save_scripted_team(tmp_path / f"{name}.pt", name, seed=k) for k, name in enumerate(WORKING)}
    config = EvalConfig(
        conditions={"cooks": [runs["scripted_cooks"], runs["scripted_idle"]],
                    "halves": [runs["scripted_cook_seat0"], runs["scripted_cook_seat1"]]},
        cross=[["cooks", "halves"]], layouts=booth_files, heldout=0, rollouts=3,
        max_envs=10,  # 5 kitchens per grid per batch: several batches, the last one padded
        out_dir=str(tmp_path / "out"), progress=False, partner=False,
    ).check()  # fmt: skip
    out = evaluate(config)

    with open(out / "pairs.csv") as handle:
        pairs = list(csv.DictReader(handle))
    assert len(pairs) == (4 + 4 + 8) * 2
    for row in pairs:
        working0 = WORKING[_architecture(runs, row["agent0"])]
        working1 = WORKING[_architecture(runs, row["agent1"])]
        expected = PACE * (0 in working0) * (row["grid"] == "two_booths") + PACE * (1 in working1)
        assert (float(row["mean_deliveries"]), float(row["stderr"]), row["episodes"]) == (expected, 0.0, "3"), row
        kind = CROSS if row["condition0"] != row["condition1"] else SP if row["agent0"] == row["agent1"] else XP
        assert row["kind"] == kind

    with open(out / "summary.csv") as handle:
        summary = {(row["condition"], row["grids"]): row for row in csv.DictReader(handle)}
    cooks = summary["cooks", "two_booths"]  # SP: 14 (cooks) and 0 (idle); XP: 7 and 7
    assert [float(cooks[k]) for k in ("sp", "sp_stderr", "xp", "xp_stderr", "gap")] == pytest.approx([7, 7, 7, 0, 0])
    halves = summary["halves", "one_booth"]  # agent 0 idle here: SP 0 and 7, XP 7 (seat1 team in seat 1) and 0
    assert [float(halves[k]) for k in ("sp", "xp")] == [3.5, 3.5]
    assert int(summary["cooks x halves", "two_booths"]["xp_pairs"]) == 8
    assert "| cooks | two_booths | 7.00 ± 7.00 (2) | 7.00 ± 0.00 (2) | 0.00 |" in (out / "eval.md").read_text()

    # Per seed, the unit the claims' intervals resample: the working cook's pairs of each kind, in either seat.
    with open(out / "seeds.csv") as handle:
        seeds = {(row["team"], row["grids"], row["kind"], row["with"]): row for row in csv.DictReader(handle)}
    working = {key[2:]: float(row["deliveries"]) for key, row in seeds.items()
               if key[:2] == ("cooks/seed0", "two_booths")}
    assert working == {("sp", ""): 14, ("xp", ""): 7, ("cross", "halves"): 10.5}  # with halves: 7, 14, 14, 7
    assert int(seeds["cooks/seed0", "two_booths", "cross", "halves"]["pairs"]) == 4
    assert float(seeds["cooks/seed3", "two_booths", "sp", ""]["deliveries"]) == 0  # the idle cook with itself


def test_every_team_also_plays_with_the_scripted_cook_in_both_seats(tmp_path, booth_files):
    runs = {name: save_scripted_team(tmp_path / f"{name}.pt", name, seed=k) for k, name in enumerate(WORKING)}
    config = EvalConfig(
        conditions={"cooks": [runs["scripted_cooks"], runs["scripted_idle"]]}, layouts=booth_files[:1], heldout=0,
        rollouts=2, out_dir=str(tmp_path / "out"), progress=False,
    ).check()  # fmt: skip
    out = evaluate(config)
    with open(out / "pairs.csv") as handle:
        pairs = {(row["agent0"], row["agent1"]): row for row in csv.DictReader(handle)}
    teams = ["cooks/seed0", "cooks/seed3"]
    partner = {key: row for key, row in pairs.items() if row["kind"] == PARTNER}
    assert set(partner) == {(team, SCRIPTED_CONDITION) for team in teams} | {(SCRIPTED_CONDITION, t) for t in teams}
    assert pairs[SCRIPTED_CONDITION, SCRIPTED_CONDITION]["kind"] == SP
    # Beside an idle team the scripted cook cooks alone in its booth; beside booth cooks both deliver.
    alone = float(pairs["cooks/seed3", SCRIPTED_CONDITION]["mean_deliveries"])
    assert 0 < alone < float(pairs["cooks/seed0", SCRIPTED_CONDITION]["mean_deliveries"])
    with open(out / "summary.csv") as handle:
        summary = {row["condition"]: row for row in csv.DictReader(handle)}
    assert int(summary["cooks"]["partner_pairs"]) == 4 and int(summary[SCRIPTED_CONDITION]["sp_pairs"]) == 1
    assert int(summary[SCRIPTED_CONDITION]["partner_pairs"]) == 0  # its row is its self-play, not its partners' play
    expected = sum(float(row["mean_deliveries"]) for row in partner.values()) / 4
    assert float(summary["cooks"]["partner"]) == pytest.approx(expected)
    assert "| SP - XP | with the scripted cook |" in (out / "eval.md").read_text()


def _architecture(runs, team_name):
    # Team names are "<condition>/seed<k>"; the scripted teams were saved with seed k = their index in WORKING.
    return list(WORKING)[int(team_name.rsplit("seed", 1)[1])]


def test_pairs_are_every_ordered_pair_within_a_condition_and_both_orders_across():
    class Fake:
        def __init__(self, condition):
            self.condition = condition

    population = {"a": [Fake("a"), Fake("a"), Fake("a")], "b": [Fake("b"), Fake("b")]}
    teams, matchups = make_matchups(population, cross=[["a", "b"]])
    assert len(teams) == 5
    sp = [(m.seat0, m.seat1) for m in matchups if m.kind == SP]
    xp = [(m.seat0, m.seat1) for m in matchups if m.kind == XP]
    cross = {(m.seat0, m.seat1) for m in matchups if m.kind == CROSS}
    assert sp == [(0, 0), (1, 1), (2, 2), (3, 3), (4, 4)]
    assert sorted(xp) == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0), (2, 1), (3, 4), (4, 3)]
    assert cross == {(a, b) for a in range(3) for b in (3, 4)} | {(b, a) for a in range(3) for b in (3, 4)}
    assert len(matchups) == 9 + 4 + 12


def test_every_team_also_plays_with_the_human_proxy_of_each_grid_that_has_one(tmp_path, booth_files):
    """A grid's human proxy is a team in `human_proxies`/human_proxy_<grid>/seed0 (here the scripted cook, whose
    pace is known); it plays beside every team on its own grid only, in both seats."""
    runs = {name: save_scripted_team(tmp_path / f"{name}.pt", name, seed=k) for k, name in enumerate(WORKING)}
    proxies = tmp_path / "proxies"
    save_scripted_team(proxies / "human_proxy_two_booths" / "seed0" / "checkpoints" / "latest.pt", "scripted_cooks",
                       levels=booth_files[0])
    config = EvalConfig(
        conditions={"halves": [runs["scripted_cook_seat0"], runs["scripted_cook_seat1"]]}, layouts=booth_files,
        heldout=0, rollouts=2, out_dir=str(tmp_path / "out"), progress=False, partner=False,
        human_proxies=str(proxies),
    ).check()  # fmt: skip
    out = evaluate(config)
    with open(out / "pairs.csv") as handle:
        human = [row for row in csv.DictReader(handle) if row["kind"] == HUMAN]
    assert {row["grid"] for row in human} == {"two_booths"} and len(human) == 4
    proxy = "scripted_cooks/seed0"  # a team's name: its config's (`kitchen-humans train`: human_proxy_<layout>)
    expected = {("halves/seed1", proxy): 14, (proxy, "halves/seed1"): 7, ("halves/seed2", proxy): 7,
                (proxy, "halves/seed2"): 14}  # a half cook works in its own seat only, the proxy in both
    assert {(row["agent0"], row["agent1"]): float(row["mean_deliveries"]) for row in human} == expected
    with open(out / "summary.csv") as handle:
        summary = {(row["condition"], row["grids"]): row for row in csv.DictReader(handle)}
    assert float(summary["halves", "two_booths"]["human"]) == 10.5
    assert int(summary["halves", "one_booth"]["human_pairs"]) == 0
    assert float(summary["scripted_cooks", "two_booths"]["sp"]) == 14  # the proxy with itself, on its grid
    assert ("scripted_cooks", "one_booth") not in summary  # and away from its grid: no row
    assert "| with the human proxy |" in (out / "eval.md").read_text()
    with pytest.raises(ConfigError, match="holds no human proxy of a test grid"):
        evaluate(EvalConfig(conditions={"halves": [runs["scripted_cook_seat0"]]}, layouts=booth_files[1:],
                            heldout=0, rollouts=1, out_dir=str(tmp_path / "out2"), progress=False,
                            human_proxies=str(proxies)).check())


def _save_model_team(path, architecture, seed, hidden=8, share_params=True):
    torch.manual_seed(seed)
    actor_critic = make_actor_critic(architecture, (7, 7, 26), hidden, share_params)
    config = TrainConfig(architecture=architecture, seed=seed, hidden=hidden, share_params=share_params)
    save_checkpoint(path, {
        "config": config.to_dict(), "model": model_identity(architecture, (7, 7, 26), hidden, share_params),
        "actor": actor_critic.actor.state_dict(), "critic": actor_critic.critic.state_dict(),
    })  # fmt: skip
    return str(path)


def test_the_same_seed_gives_the_same_numbers_with_recurrent_and_mixed_teams_and_any_workers(tmp_path):
    population = load_population({
        "lstm": [_save_model_team(tmp_path / "l0.pt", "mlp_lstm", 0, share_params=False),
                 _save_model_team(tmp_path / "l1.pt", "mlp_lstm", 1)],
        "gnn": [_save_model_team(tmp_path / "g0.pt", "gnn", 0, hidden=16)],
    })  # fmt: skip
    teams, matchups = make_matchups(population, cross=[["lstm", "gnn"]])
    grids = [get_layout("cramped_room_7x7"), get_layout("coord_ring_7x7")]

    def run(seed, workers=1):
        return play(teams, matchups, grids, rollouts=2, max_steps=32, max_envs=12, seed=seed, workers=workers)

    first, again, other = run(0), run(0, workers=2), run(1)  # the batches shared by two processes
    assert first.deliveries.shape == (len(matchups), 2, 2)
    np.testing.assert_array_equal(first.deliveries, again.deliveries)
    np.testing.assert_array_equal(first.visits, again.visits)
    assert not np.array_equal(first.visits, other.visits)
    # Every matchup, grid and seat: 2 rollouts x 32 steps spent somewhere on the floor.
    np.testing.assert_array_equal(first.visits.sum((-2, -1)), np.full((len(matchups), 2, 2), 64.0))


def test_unusable_checkpoints_and_configs_are_refused_with_a_message(tmp_path, capsys):
    good = _save_model_team(tmp_path / "good.pt", "mlp", 0)
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(Path(good).read_bytes()[:500])
    with pytest.raises(CheckpointError, match="condition 'c': .*corrupt.pt is not a readable checkpoint"):
        load_population({"c": [good, str(corrupt)]})
    with pytest.raises(CheckpointError, match="no run matches 2 of the conditions' patterns: c .*nothing.*, d .*no") \
            as missing:  # every missing run named in one refusal
        load_population({"c": str(tmp_path / "nothing*"), "d": [good, str(tmp_path / "no*")]})
    assert "\n" not in str(missing.value)
    # The README's first evaluation: one's own runs named on the command line, no other condition needed.
    out = tmp_path / "quick"
    assert main(["configs/eval/runs.yaml", f"conditions={{c: {good}}}", "layouts=[cramped_room_7x7]", "heldout=1",
                 "rollouts=1", "max_steps=8", f"out_dir={out}", "progress=false"]) == 0
    assert "| c | cramped_room_7x7 |" in (out / "eval.md").read_text()
    save_checkpoint(tmp_path / "alien.pt", {"config": {}, "model": model_identity("alien", (7, 7, 26), 8, True),
                                            "actor": {}, "critic": {}})
    with pytest.raises(CheckpointError, match="'alien' model that cannot be built here"):
        load_population({"c": str(tmp_path / "alien.pt")})

    booths = save_scripted_team(tmp_path / "booth.pt", "scripted_idle")
    config = tmp_path / "eval.yaml"
    config.write_text(f"conditions:\n  c: {good}\n  d: {booths}\nheldout: 1\nrollouts: 1\nout_dir: {tmp_path}/o\n")
    assert main([str(config), "layouts=[]"]) == 2
    assert "built for 3x5 kitchens, the test grids are 7x7" in capsys.readouterr().err
    assert main([str(config), "rolouts=3"]) == 2
    assert "unknown config key 'rolouts' in the command line (did you mean 'rollouts'?)" in capsys.readouterr().err
    assert main([str(config), "cross=[[c, e]]"]) == 2
    assert "cross names the condition 'e'" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="gifs entry 'c/seed0@cramped_room_7x7' must look like"):
        evaluate(load_config(config, ["gifs=['c/seed0@cramped_room_7x7']", "conditions={c: " + good + "}"],
                             schema=EvalConfig))


def test_the_entry_point_writes_tables_figures_heatmaps_and_gifs(tmp_path):
    runs = [_save_model_team(tmp_path / f"t{seed}.pt", "mlp", seed) for seed in range(2)]
    out = tmp_path / "out"
    argv = [
        str(Path(__file__).resolve().parents[2] / "configs" / "eval" / "paper.yaml"),
        f"conditions={{mlp_ik: [{runs[0]}, {runs[1]}]}}", "cross=[]", "rollouts=1", "heldout=2", "max_steps=16",
        "layouts=[cramped_room_7x7, coord_ring_7x7]", f"out_dir={out}", "heatmaps=[coord_ring_7x7]",
        "gifs=['mlp_ik/seed0+mlp_ik/seed1@heldout_001']", "progress=false",
    ]  # fmt: skip
    assert main(argv) == 0
    for name in ["fig3a_xp_layouts.png", "fig3b_gap.png", "fig7_heldout.png", "fig8_per_layout.png",
                 "heatmap_coord_ring_7x7.png"]:
        with Image.open(out / name) as image:
            assert image.size[0] > 200 and image.size[1] > 200
    with Image.open(out / "mlp_ik-seed0+mlp_ik-seed1@heldout_001.gif") as gif:
        assert gif.n_frames > 1
    table = (out / "eval.md").read_text()
    assert "| mlp_ik | coord_ring_7x7 |" in table and "| mlp_ik | held-out (2) |" in table
    assert load_config(out / "eval_config.yaml", schema=EvalConfig).rollouts == 1


def test_e3t_teams_play_self_play_cross_play_and_beside_other_teams(tmp_path, booth_files):
    two_booths = booth_files[0]
    runs = []
    for seed in (0, 1):
        config = load_config(None, [
            "algorithm=e3t", "architecture=e3t_mlp", f"levels={two_booths}", "num_envs=4", "rollout_steps=16",
            "max_steps=16", "total_steps=64", "hidden=16", "ppo.minibatches=2", "ppo.epochs=1", "progress=false",
            "eval_episodes=0", f"run_dir={tmp_path / 'runs'}", f"seed={seed}",
        ])  # fmt: skip
        runs.append(str(train(config)))
    cook = save_scripted_team(tmp_path / "cook.pt", "scripted_cook_seat1", seed=0)
    config = EvalConfig(conditions={"e3t": runs, "cook": [cook]}, cross=[["e3t", "cook"]], layouts=[two_booths],
                        heldout=0, rollouts=2, max_envs=6, out_dir=str(tmp_path / "out"), progress=False).check()
    out = evaluate(config)

    with open(out / "pairs.csv") as handle:
        pairs = {(row["agent0"], row["agent1"]): row for row in csv.DictReader(handle)}
    e3t = ["e3t/seed0", "e3t/seed1"]
    assert {pairs[a, b]["kind"] for a in e3t for b in e3t} == {SP, XP}
    # In its own booth the scripted cook delivers at its pace whoever sits beside it (plus whatever E3T adds).
    for team in e3t:
        assert float(pairs[team, "cook/seed0"]["mean_deliveries"]) >= PACE
    summary = (out / "eval.md").read_text()
    assert "| e3t | two_booths |" in summary and "| cook x e3t | two_booths |" in summary
