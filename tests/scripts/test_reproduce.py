"""The reproduction command end to end at a tiny budget: it trains, evaluates, writes RESULTS.md, and resumes."""

from pathlib import Path

import pytest
import yaml
from scripted_cook import save_scripted_team
from tiny import redraw_zoo, script_module

from torch_kitchen.partners.conventions import (
    STRANGER,
    TRAIN,
    Convention,
    Zoo,
    ZooMember,
    generator_settings,
    save_zoo,
)
from trainers.config import ConfigError
from trainers.config.compose import load_config
from trainers.machine import code_version

ROOT = Path(__file__).resolve().parents[2]
reproduce = script_module("reproduce")

TINY = ["hidden=8", "num_envs=4", "rollout_steps=16", "max_steps=16", "total_steps=128", "ppo.epochs=1",
        "ppo.minibatches=2", "checkpoint_every=1", "eval_episodes=0", "progress=false", "loggers=[csv]",
        "runtime.collector=kitchen"]  # a tiny run compiles the XLA rollout for longer than it trains


@pytest.mark.slow
def test_the_protocol_trains_every_condition_evaluates_and_writes_the_report(tmp_path, monkeypatch, capsys):
    def scripted_proxy(out, settings):  # a stand-in for the human proxies (fetching and fitting: kitchen-humans' test)
        assert (settings.epochs, settings.candidates, settings.hidden) == (2, 1, 128)  # the protocol sizes them
        save_scripted_team(out / "runs" / "human_proxy_cramped_room_in_7x7" / "seed0" / "checkpoints" / "latest.pt",
                           "scripted_cooks", levels="cramped_room_in_7x7", shape=(7, 7))
        return out / "runs"

    monkeypatch.setattr(reproduce, "human_proxies", scripted_proxy)
    protocol = {
        "teams": 2, "overrides": TINY,
        "conditions": {"ik": str(ROOT / "configs/ippo/mlp_ik.yaml"),
                       "sk_cramped": str(ROOT / "configs/ippo/mlp_sk_cramped_room.yaml"),
                       "guided_sk": {"config": str(ROOT / "configs/ippo/mlp_ik.yaml"),
                                     "overrides": ["regime=sk_cramped_room", "hidden=4"]}},
        "families": {"MLP": {"ik": "ik", "sk": ["sk_cramped"]},
                     "MLP guided": {"ik": "ik", "sk": ["guided_sk"], "learner": "guided", "paper": "MLP"}},
        "cross": [["sk_cramped", "guided_sk"]],
        "evaluation": {"heldout": 1, "rollouts": 1, "max_steps": 16, "human_proxies": {"epochs": 2, "candidates": 1},
                       "collector": "kitchen"},  # a tiny evaluation compiles longer inside XLA than it plays
    }  # fmt: skip
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump(protocol))
    out, results = tmp_path / "out", tmp_path / "RESULTS.md"
    argv = [str(path), "--out", str(out), "--results", str(results)]
    assert reproduce.main([*argv, "--jobs", "2"]) == 0  # two conditions at a time, each in a process of its own
    (evaluated,) = out.glob("eval/*/eval_config.yaml")
    assert yaml.safe_load(evaluated.read_text())["collector"] == "kitchen"  # the protocol's evaluation settings

    for condition in ("ik", "sk_cramped", "guided_sk"):
        for seed in (0, 1):
            run = out / "runs" / condition / f"seed{seed}"
            assert (run / "checkpoints" / "latest.pt").is_file()
            assert load_config(run / "config.yaml").seed == seed
    guided = load_config(out / "runs" / "guided_sk" / "seed0" / "config.yaml")  # its own overrides, after TINY's
    assert (guided.levels, guided.hidden, guided.total_steps) == ("cramped_room_7x7", 4, 128)
    report = results.read_text()
    claim = "IK beats SK in cross-play on the 5 layouts (Fig. 3a) | IK - SK, mean over the 1 layouts: "
    assert f"| MLP | IPPO from scratch | {claim}" in report and f"| MLP guided | guided | {claim}" in report
    assert "(2 v 2 seeds); cramped_room " in report  # every verdict beside its interval and its seeds
    assert "- **guided_sk** adds `regime=sk_cramped_room hidden=4`." in report
    assert "| sk_cramped | guided_sk | cramped_room_7x7 |" in report  # the added pair beside its sides' own XP
    assert "SK scores 0 on generated levels" in report and "with the scripted cook" in report
    assert "| with the human proxy |" in report and "| ik | cramped_room_in_7x7 |" in report
    assert "128 env steps per team (2 updates of 4 kitchens x 16 steps), 2 teams" in report
    assert f"code at `{code_version()}`)" in report and code_version() != "unknown"  # the commit that ran it
    assert (tmp_path / "docs" / "results" / "all").is_dir() and "](docs/results/all/" in report
    summary = reproduce.read_summary(out / "eval" / "all" / "summary.csv")
    assert ("ik x sk_cramped", "cramped_room_7x7") in summary and ("guided_sk x ik", "cramped_room_7x7") in summary
    assert ("guided_sk x sk_cramped", "cramped_room_7x7") in summary  # a pair the protocol adds

    # Run again: every condition is trained already, so nothing trains and the checkpoints stay as they were;
    # without the human proxies where asked, which are then neither fetched nor fitted.
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("runs/*/seed*/checkpoints/latest.pt")}
    monkeypatch.setattr(reproduce, "human_proxies", lambda out, settings: pytest.fail("fetched the human proxies"))
    assert reproduce.main([*argv, "--no-human-proxies"]) == 0
    assert "| with the human proxy |" not in results.read_text()
    assert "ik reused (trained by an earlier run), sk_cramped reused" in results.read_text()  # said, not timed
    assert {p: p.stat().st_mtime_ns for p in out.glob("runs/*/seed*/checkpoints/latest.pt")} == stamps
    monkeypatch.setattr(reproduce, "human_proxies", scripted_proxy)
    # Run again with a setting changed: the runs trained with the old one are refused in one line, not reused,
    # before any condition trains.
    capsys.readouterr()
    with monkeypatch.context() as patched:
        patched.setattr(reproduce, "train_conditions", lambda *args: pytest.fail("trained before refusing"))
        assert reproduce.main([argv[0], "ppo.lr=0.1", "--jobs", "2", *argv[1:]]) == 2
    error = capsys.readouterr().err
    assert error.startswith("reproduce: error: guided_sk: ")  # the first condition refused names itself
    assert error.rstrip().endswith("or reproduce into another --out")
    assert "was trained with ppo.lr=0.00025, not ppo.lr=0.1: a resume keeps what the run learns" in error
    assert error.count("\n") == 1
    # A setting training itself refuses: refused as training would, naming the condition, before any trains.
    with monkeypatch.context() as patched:
        patched.setattr(reproduce, "train_conditions", lambda *args: pytest.fail("trained before refusing"))
        assert reproduce.main([argv[0], "ppo.lr=-1", *argv[1:]]) == 2
    error = capsys.readouterr().err
    assert error.startswith("reproduce: error: ") and ": ppo.lr must be greater than 0, got -1.0" in error
    assert error.split(": ")[2] in ("ik", "sk_cramped", "guided_sk") and error.count("\n") == 1

    # Part of the protocol: the conditions named, their family and the report saying what it left out.
    assert reproduce.main([*argv, "--conditions", "ik", "sk_cramped"]) == 0
    report = results.read_text()
    assert "- **Conditions:** 2 of the section's 3; not run here: guided_sk." in report
    assert f"| MLP | IPPO from scratch | {claim}" in report
    assert "| MLP guided | guided | IK beats SK" not in report  # its one SK condition left out: no SK claims
    assert report.count("guided_sk") == 1  # in the list of those left out only


def test_a_condition_trained_beside_a_zoo_redrawn_since_is_refused_not_reused(tmp_path):
    cooks = [Convention(name="loader", role="loader"), Convention(name="server", role="server")]
    zoo = Zoo(0, 7, generator_settings(7), [ZooMember(cook, TRAIN, 1.0, 1.0, {}) for cook in cooks])
    zoo_file, runs, config = tmp_path / "zoo.yaml", tmp_path / "runs", str(ROOT / "configs/ippo/mlp_ik.yaml")
    save_zoo(zoo, zoo_file)
    overrides = [*TINY, "algorithm=zoo_ippo", f"zoo={zoo_file}", "algorithm_config.zoo_share=1.0"]
    reproduce.train_condition("beside_zoo", config, overrides, 1, runs)
    assert reproduce.trained_before("beside_zoo", config, overrides, 1, runs)
    # The same file drawn again with one cook changed: the team trained beside the old one is not reused as if
    # trained beside the new.
    redraw_zoo(zoo_file, "server", zoo_file)
    with pytest.raises(ConfigError, match=r"^beside_zoo: .*seed0 was not trained beside server as .*zoo\.yaml holds "
                                          r"them now .*, or reproduce into another --out$"):
        reproduce.trained_before("beside_zoo", config, overrides, 1, runs)


def test_a_stopped_condition_ends_the_command_with_one_line_and_the_signals_code(tmp_path, monkeypatch, capsys):
    def stopped(name, *args):
        raise reproduce.RunStopped(15, "stopped by SIGTERM at update 3 (384 of 1,024 env steps), checkpoint written")

    monkeypatch.setattr(reproduce, "train_condition", stopped)
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump({"teams": 1, "overrides": TINY, "families": {},
                                    "conditions": {"ik": str(ROOT / "configs/ippo/mlp_ik.yaml")}}))
    assert reproduce.main([str(path), "--out", str(tmp_path / "out"), "--results", str(tmp_path / "R.md")]) == 143
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "ik: stopped by SIGTERM" in error and "run the same command again" in error
    assert not (tmp_path / "R.md").exists()


def test_part_of_a_protocol_keeps_the_families_and_pairs_of_the_conditions_named():
    protocol = {"conditions": {"ik": "a.yaml", "sk_a": "b.yaml", "sk_b": "c.yaml", "guided": "d.yaml"},
                "families": {"MLP": {"ik": "ik", "sk": ["sk_a", "sk_b"]}, "guided": {"ik": "guided", "sk": ["sk_a"]}},
                "cross": [["guided", "sk_a"], ["ik", "sk_b"]]}
    selected, left_out = reproduce.select_conditions(protocol, ["sk_a", "ik"])
    assert list(selected["conditions"]) == ["ik", "sk_a"] and left_out == ["sk_b", "guided"]
    assert selected["families"] == {"MLP": {"ik": "ik", "sk": ["sk_a"]}} and selected["cross"] == []
    assert reproduce.select_conditions(protocol, None) == (protocol, [])


def test_a_condition_not_in_the_protocol_is_one_line_naming_the_ones_there(tmp_path, capsys):
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump({"teams": 1, "conditions": {"ik": "a.yaml"}, "families": {}}))
    with pytest.raises(SystemExit) as stopped:
        reproduce.main([str(path), "--conditions", "ik", "gnn_ik"])
    assert stopped.value.code == 2
    assert capsys.readouterr().err.strip().endswith("--conditions: gnn_ik not in the protocol, which has ik")
    # The human proxies' sizes in the protocol: an unknown one is refused before anything trains.
    path.write_text(yaml.safe_dump({"teams": 1, "conditions": {"ik": "a.yaml"}, "families": {},
                                    "evaluation": {"human_proxies": {"epoch": 1}}}))
    with pytest.raises(SystemExit):
        reproduce.main([str(path)])
    assert "evaluation.human_proxies: unknown settings epoch (the settings are anchor_coef, architecture" in \
        capsys.readouterr().err


def test_a_protocol_file_that_is_not_there_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit):
        reproduce.main([str(tmp_path / "nowhere.yaml")])
    assert capsys.readouterr().err.strip().endswith("nowhere.yaml: No such file or directory")


def test_a_section_written_again_keeps_the_others_as_they_were_and_the_claims_of_all(tmp_path):
    results = tmp_path / "RESULTS.md"

    def section(name, claim, body):
        return "\n".join([reproduce.SECTION_START.format(name), f"## {name}", "", reproduce.CLAIMS_START,
                          *reproduce.CLAIMS_HEADER, f"| {name} | learner | {claim} | 1.00 | holds |",
                          reproduce.CLAIMS_END, "", body, reproduce.SECTION_END.format(name)])

    reproduce.write_results(results, {"scratch": section("scratch", "A", "first run")}, ["scratch", "planner"])
    reproduce.write_results(results, {"planner": section("planner", "B", "second run")}, ["scratch", "planner"])
    reproduce.write_results(results, {"planner": section("planner", "C", "third run")}, ["scratch", "planner"])
    text = results.read_text()
    sections = reproduce.read_sections(text)
    assert sections == {"scratch": section("scratch", "A", "first run"),
                        "planner": section("planner", "C", "third run")}
    claims = text[text.index("## The paper's claims, here"):text.index(reproduce.SECTION_START.format("scratch"))]
    assert "| scratch | learner | A |" in claims and "| planner | learner | C |" in claims and "| B |" not in text


def test_the_claims_of_a_section_written_before_intervals_are_marked_as_decided_by_means(tmp_path):
    results = tmp_path / "RESULTS.md"
    old = "\n".join([reproduce.SECTION_START.format("scratch"), reproduce.CLAIMS_START,
                     "| family | learner | claim | here | at this budget |", "|---|---|---|---|---|",
                     "| MLP | IPPO | IK beats SK | 1.00 vs 0.50 | 3 of 5 layouts |", reproduce.CLAIMS_END,
                     reproduce.SECTION_END.format("scratch")])
    results.write_text(old)
    new = "\n".join([reproduce.SECTION_START.format("planner"), reproduce.CLAIMS_START, *reproduce.CLAIMS_HEADER,
                     "| MLP | planner | IK beats SK | +0.5 [0.1, 0.9] | holds |", reproduce.CLAIMS_END,
                     reproduce.SECTION_END.format("planner")])
    reproduce.write_results(results, {"planner": new}, ["scratch", "planner"])
    text = results.read_text()
    claims = text[text.index("## The paper's claims, here"):text.index(reproduce.SECTION_START.format("scratch"))]
    rows = [row for row in claims.splitlines() if row.startswith("| ")]
    assert rows == [reproduce.CLAIMS_HEADER[0],
                    f"| MLP | IPPO | IK beats SK | 1.00 vs 0.50 | 3 of 5 layouts{reproduce.BY_MEANS} |",
                    "| MLP | planner | IK beats SK | +0.5 [0.1, 0.9] | holds |"]
    assert reproduce.read_sections(text)["scratch"] == old  # the section itself is kept as it was written


def test_sections_name_their_conditions_and_an_unknown_one_is_one_line(tmp_path, capsys):
    protocol = {"conditions": {"ik": "a.yaml", "sk": "b.yaml", "guided": "c.yaml"},
                "sections": {"scratch": {"title": "S", "conditions": ["ik", "sk"]},
                             "planner": {"title": "P", "conditions": ["guided"]}}}
    assert reproduce.named_conditions(protocol, ["planner"], ["ik"]) == ["guided", "ik"]
    assert reproduce.named_conditions(protocol, None, None) is None
    assert list(reproduce.protocol_sections({"conditions": {"ik": "a.yaml"}})) == ["all"]
    path = tmp_path / "protocol.yaml"
    path.write_text(yaml.safe_dump({**protocol, "teams": 1, "families": {}}, sort_keys=False))
    with pytest.raises(SystemExit):
        reproduce.main([str(path), "--sections", "e3t"])
    assert capsys.readouterr().err.strip().endswith("--sections: e3t not in the protocol, which has scratch, planner")


def test_every_condition_of_the_reduced_protocol_is_in_one_section():
    protocol = yaml.safe_load((ROOT / "configs" / "protocols" / "reduced.yaml").read_text())
    placed = [name for section in protocol["sections"].values() for name in section["conditions"]]
    assert sorted(placed) == sorted(protocol["conditions"])


def test_a_distilled_sections_budget_is_set_beside_the_main_jobs():
    config = load_config(ROOT / "configs/ippo/ego_mlp_ik.yaml",
                         ["init_from=scripted_cook", "num_envs=32", "rollout_steps=256", "total_steps=393216"])
    line = reproduce.budget(config, teams=3)
    assert "393,216 env steps per team (48 updates of 32 kitchens x 256 steps)" in line
    assert "the main job, `configs/main.yaml`, trains 1,572,864 steps after 6 rounds of 3 passes, 4x this" in line
    main_jobs = load_config(ROOT / "configs/ippo/ego_mlp_ik.yaml", ["init_from=scripted_cook", "total_steps=1572864"])
    assert "trains 1,572,864 steps after 6 rounds of 3 passes, the same budget)" in reproduce.budget(main_jobs, teams=3)
    assert "main job" not in reproduce.budget(load_config(ROOT / "configs/ippo/mlp_ik.yaml"), teams=3)
    replayed = load_config(ROOT / "configs/ippo/ego_mlp_ik.yaml", ["init_from=scripted_cook", "distill.replay=1"])
    assert "3 passes over the newest round and 1x as many earlier kitchens after each" in reproduce.budget(replayed, 3)


def test_a_strangers_section_trains_its_instruments_per_stranger_and_never_evaluates_them(tmp_path, monkeypatch):
    members = [ZooMember(Convention(name=name, role=role), STRANGER, 1.0, 1.0, {})
               for name, role in (("server", "server"), ("loader", "loader"))]
    zoo = str(save_zoo(Zoo(0, 7, generator_settings(7), members), tmp_path / "zoo.yaml"))
    protocol = reproduce.with_instruments({
        "conditions": {"ik": "a.yaml", "sk": "b.yaml", "other": "c.yaml"},
        "families": {"MLP": {"ik": "ik", "sk": []}},
        "sections": {"strangers": {"title": "S", "conditions": ["ik", "sk"], "strangers": zoo,
                                   "best_responses": {"config": "a.yaml", "overrides": [["hidden=8"], "ppo.lr=0.1"]},
                                   "learned_strangers": {"config": "a.yaml", "runs": ["other"]}},
                     "plain": {"title": "P", "conditions": ["other"]}}})
    swapped = reproduce.with_strangers(protocol, "other.yaml")["sections"]  # --strangers ZOO: only where seated
    assert swapped["strangers"]["strangers"] == "other.yaml" and "strangers" not in swapped["plain"]
    section = protocol["sections"]["strangers"]
    assert section["best_responses"] == {"server": "best_response_server", "loader": "best_response_loader"}
    assert section["learned_strangers"] == {"server": "learned_server", "loader": "learned_loader", "other": "other"}
    assert protocol["conditions"]["best_response_loader"] == {"config": "a.yaml", "overrides": [
        "hidden=8", "ppo.lr=0.1", "algorithm=zoo_ippo", "algorithm_config.best_response_to=loader", f"zoo={zoo}",
        "runtime.teams=1"]}
    assert protocol["conditions"]["learned_server"]["overrides"] == [
        "distill.teachers=[server]", "learned_stranger=true", "snapshots=3", f"zoo={zoo}", "runtime.teams=1"]
    # Trained with the section (one team each: a condition's own count comes after the protocol's), never
    # evaluated; a learned stranger trained by another section ("other") is reused where it was, never trained here.
    assert reproduce.named_conditions(protocol, ["strangers"], None) == [
        "ik", "sk", "best_response_server", "best_response_loader", "learned_server", "learned_loader"]
    assert reproduce.condition_overrides("br", ["runtime.teams=1"], 5, tmp_path)[:2] == ["runtime.teams=5",
                                                                                          "runtime.teams=1"]
    [section] = [s for s in reproduce.sections_run(protocol, protocol, {}) if s.name == "strangers"]
    assert section.evaluated == ["ik", "sk"] and section.best_responses["server"] == "best_response_server"
    for trained in ("learned_loader", "other"):
        (tmp_path / "runs" / trained / "seed0" / "checkpoints").mkdir(parents=True)
        (tmp_path / "runs" / trained / "seed0" / "checkpoints" / "latest.pt").touch()
    seen = {}
    monkeypatch.setattr(reproduce, "evaluate", lambda config: seen.setdefault("config", config))
    reproduce.evaluate_section(section, tmp_path, {"heldout": 1, "rollouts": 1}, "cpu", None, 1, 0)
    assert seen["config"].best_responses == {name: str(tmp_path / "runs" / f"best_response_{name}" / "seed0")
                                             for name in ("server", "loader")}
    # A protocol run from seed=5 trained each best response as seed5.
    assert reproduce.best_response_runs(section, tmp_path, 5)["loader"] == str(tmp_path / "best_response_loader" /
                                                                                "seed5")
    assert seen["config"].learned_strangers == {name: str(tmp_path / "runs" / condition / "seed*") for name, condition
                                                in (("loader", "learned_loader"), ("other", "other"))}
    assert set(seen["config"].conditions) == {"ik", "sk"}
