import dataclasses
import json
from pathlib import Path

import pytest
import yaml
from tiny import script_module

from trainers.algorithms import check_algorithm
from trainers.config import PLANNER_START, ConfigError, EvalConfig, RuntimeConfig, TrainConfig
from trainers.config.compose import compose, load_config, sectioned
from trainers.ppo.runtime import minibatch_shards

CONFIG_DIR = Path(__file__).resolve().parents[2] / "configs"
# Defaults changed on purpose since data/config_values.json was recorded (flat keys, as the record has them): the
# distillation's fitting, 4 kitchens' steps a step at twice the rate (BENCHMARKS.md, "Distillation's rounds").
CHANGED_SINCE_RECORDED = {"distill_minibatch": 4, "distill_lr": 0.006}
RECORDED_FITTING = ["distill.minibatch=1", "distill.lr=0.003"]  # the recorded values, as overrides
# configs/eval: kitchen-eval's configs; configs/protocols: scripts/reproduce.py's (conditions, not one trainer config)
# configs/architecture, configs/runtime: config groups of one or two keys, chosen by the others (and below)
# configs/zoo: kitchen-zoo's file of conventions; configs/study: kitchen-study's (docs/study.md runs its check)
CONFIGS = sorted(path for path in CONFIG_DIR.rglob("*.yaml")
                 if path.parent.name not in ("eval", "protocols", "architecture", "runtime", "zoo", "study"))
EVAL_CONFIGS = sorted((CONFIG_DIR / "eval").glob("*.yaml"))
PROTOCOLS = sorted((CONFIG_DIR / "protocols").glob("*.yaml"))


def test_every_shipped_config_loads():
    assert len(CONFIGS) >= 39  # (4 IPPO + 2 E3T architectures) x (5 SK layouts + IK), the bases, the main job
    for path in CONFIGS:
        config = load_config(path)
        assert isinstance(config, TrainConfig), path
    assert EVAL_CONFIGS
    for path in EVAL_CONFIGS:
        config = load_config(path, schema=EvalConfig)
        if path.name == "runs.yaml":  # one's own runs, named on the command line
            assert not config.conditions and not config.cross and not config.gifs, path
            continue
        assert config.conditions and config.rollouts == 100 and config.heldout == 100, path
        # Every condition of the paper's evaluation names runs that the shipped training configs write.
        names = {load_config(train).name for train in CONFIGS}
        for condition, runs in config.conditions.items():
            assert condition in names and runs == f"runs/{condition}/seed*", (path, condition)


def test_every_shipped_config_resolves_to_the_values_recorded_before_configs_moved_to_omegaconf():
    # data/config_values.json: every config's values as the loader before OmegaConf resolved them (flat keys, before
    # `runtime` and `algorithm_config` had sections: `sectioned` puts them there, as for a saved run).
    recorded = json.loads((Path(__file__).parent / "data" / "config_values.json").read_text())
    root = CONFIG_DIR.parent
    assert set(recorded) == {str(path.relative_to(root)) for path in [*CONFIGS, *EVAL_CONFIGS]}
    for name, values in recorded.items():
        schema = EvalConfig if name.startswith("configs/eval/") else TrainConfig
        expected = sectioned({**values, **CHANGED_SINCE_RECORDED} if schema is TrainConfig else values, schema)
        if schema is TrainConfig:
            expected.setdefault("algorithm_config", {})
        assert dataclasses.asdict(load_config(root / name, schema=schema)) == expected, name
        if schema is TrainConfig:
            assert set(expected["runtime"]) == {field.name for field in dataclasses.fields(RuntimeConfig)}, name
            assert len(expected["algorithm_config"]) == (4 if values["algorithm"] == "e3t" else 0), name


@pytest.mark.parametrize("regime", ["ik", "sk_cramped_room", "sk_counter_circuit"])
def test_a_regime_chosen_on_the_command_line_replaces_the_files(regime):
    for algorithm, architecture in (("ippo", "gnn_lstm"), ("e3t", "mlp")):
        shipped = load_config(CONFIG_DIR / algorithm / f"{architecture}_{regime}.yaml", ["name=x"])
        for other in ("ik", "sk_coord_ring"):  # another condition of the family, its regime replaced
            chosen = load_config(CONFIG_DIR / algorithm / f"{architecture}_{other}.yaml",
                                 [f"regime={regime}", "name=x"])
            assert chosen == shipped, (algorithm, other)


def test_a_group_chosen_on_the_command_line_takes_the_files_choices_place_before_the_files_own_values():
    main = load_config(CONFIG_DIR / "main.yaml")
    assert (main.levels, main.hidden, main.share_params) == ("infinite", 128, True)  # the file's own width
    ik = load_config(CONFIG_DIR / "main.yaml", ["regime=ik"])  # the regime's hidden (256) gives way to the file's
    assert (ik.levels, ik.hidden, ik.share_params, ik.ppo.lr) == ("infinite", 128, True, main.ppo.lr)
    sk = load_config(CONFIG_DIR / "main.yaml", ["regime=sk_forced_coord"])
    assert (sk.levels, sk.hidden, sk.share_params, sk.init_from) == ("forced_coord_7x7", 128, False, main.init_from)
    assert load_config(CONFIG_DIR / "main.yaml", ["hidden=64", "regime=ik"]).hidden == 64
    with pytest.raises(ConfigError, match=r"^regime on the command line must be one of ik, sk_asymm_advantages, "
                                          r"sk_coord_ring, sk_counter_circuit, sk_cramped_room, sk_forced_coord, "
                                          r"got 'sk_nowhere'$"):
        load_config(CONFIG_DIR / "main.yaml", ["regime=sk_nowhere"])


def test_every_protocol_names_configs_that_load_with_its_overrides():
    assert len(PROTOCOLS) == 2
    for path in PROTOCOLS:
        protocol = yaml.safe_load(path.read_text())
        assert protocol["teams"] >= 3, path
        overrides = [o for o in protocol["overrides"] if not o.startswith("runtime.device=")]  # checked where it runs
        reproduce = script_module("reproduce")
        budgets = {}
        for name, entry in protocol["conditions"].items():
            train, own = reproduce.condition_entry(entry)
            config = load_config(CONFIG_DIR.parent / train, [*overrides, f"runtime.teams={protocol['teams']}", *own])
            assert config.name == name or own, (path, name)  # a shipped config under its own name, or one varied
            assert config.init_from != PLANNER_START or config.distill.rounds > 0, (path, name)
            budgets[name] = config.total_steps
        for section in reproduce.protocol_sections(protocol).values():  # one budget per section, which states it
            assert len({budgets[name] for name in section["conditions"]}) == 1, (path, section["title"])
        for family in protocol["families"].values():
            members = [family["ik"], *family["sk"]]
            # An SK condition per expanded layout, or none (a family compared on held-out levels alone)
            assert set(members) <= set(protocol["conditions"]) and len(family["sk"]) in (0, 5), path
        for pair in protocol.get("cross", []):
            assert len(pair) == 2 and set(pair) <= set(protocol["conditions"]), (path, pair)


def test_a_later_layer_replaces_a_mapping_rather_than_merging_into_it():
    paper = load_config(CONFIG_DIR / "eval" / "paper.yaml", schema=EvalConfig)
    assert len(paper.conditions) > 1
    mine = load_config(CONFIG_DIR / "eval" / "paper.yaml", ["conditions={mine: runs/mine/seed*}", "cross=[]"],
                       schema=EvalConfig)
    assert mine.conditions == {"mine": "runs/mine/seed*"}


def test_eval_config_values_are_checked():
    with pytest.raises(ConfigError, match=r"conditions in the command line must be dict\[str, str \| list\[str\]\]"):
        load_config(None, ["conditions=[a, b]"], schema=EvalConfig)
    with pytest.raises(ConfigError, match="heldout must be between 0 and 100"):
        load_config(None, ["heldout=101"], schema=EvalConfig)
    config = load_config(None, ["conditions={a: runs/a/seed*}", "rollouts=5"], schema=EvalConfig)
    assert (config.conditions, config.rollouts, config.heldout) == ({"a": "runs/a/seed*"}, 5, 100)


@pytest.mark.parametrize("architecture", ["mlp", "mlp_lstm", "gnn", "gnn_lstm"])
def test_regimes_follow_the_protocol(architecture):
    ik = load_config(CONFIG_DIR / f"ippo/{architecture}_ik.yaml")
    assert (ik.levels, ik.hidden, ik.share_params, ik.architecture) == ("infinite", 256, True, architecture)
    for layout in ["cramped_room", "asymm_advantages", "coord_ring", "forced_coord", "counter_circuit"]:
        sk = load_config(CONFIG_DIR / f"ippo/{architecture}_sk_{layout}.yaml")
        assert (sk.levels, sk.hidden, sk.share_params) == (f"{layout}_7x7", 128, False)
        assert sk.name == f"ippo_{architecture}_sk_{layout}"
    assert (ik.num_envs, ik.rollout_steps) == (32, 256)
    assert (ik.ppo.epochs, ik.ppo.minibatches, ik.ppo.shaping_weight) == (4, 4, 0.0)


@pytest.mark.parametrize("encoder", ["mlp", "gnn"])
def test_e3t_configs_follow_the_protocol_on_top_of_ippo(encoder):
    ik = load_config(CONFIG_DIR / f"e3t/{encoder}_ik.yaml")
    assert (ik.algorithm, ik.architecture, ik.levels, ik.hidden, ik.share_params) == (
        "e3t", f"e3t_{encoder}", "infinite", 256, True)
    settings = ik.algorithm_config
    assert (settings["partner_epsilon"], settings["partner_policy"]) == (0.3, "ego")
    assert (ik.num_envs, ik.rollout_steps) == (32, 256)
    for layout in ["cramped_room", "asymm_advantages", "coord_ring", "forced_coord", "counter_circuit"]:
        sk = load_config(CONFIG_DIR / f"e3t/{encoder}_sk_{layout}.yaml")
        assert (sk.algorithm, sk.levels, sk.hidden, sk.share_params) == ("e3t", f"{layout}_7x7", 128, False)
        assert sk.name == f"e3t_{encoder}_sk_{layout}"


def test_overrides_apply_on_top_of_the_file_and_are_typed():
    config = load_config(CONFIG_DIR / "ippo/mlp_ik.yaml", ["seed=3", "ppo.lr=1e-3", "total_steps=2e6", "levels=[a, b]"])
    assert (config.seed, config.ppo.lr, config.total_steps, config.levels) == (3, 1e-3, 2_000_000, ["a", "b"])
    assert config.run_path == Path("runs/ippo_mlp_ik/seed3")


def test_a_file_edited_between_two_loads_composes_anew(tmp_path):
    # Compositions are kept per process; an edit of the file, or of a file its defaults name, in the same tick of
    # the file system's clock and to the same size, is still read.
    (tmp_path / "mine.yaml").write_text("defaults: [base, _self_]\nlr: 0.1\n")
    (tmp_path / "base.yaml").write_text("hidden: 16\n")
    assert (load_config(tmp_path / "mine.yaml").ppo.lr, load_config(tmp_path / "mine.yaml").hidden) == (0.1, 16)
    (tmp_path / "mine.yaml").write_text("defaults: [base, _self_]\nlr: 0.2\n")
    (tmp_path / "base.yaml").write_text("hidden: 32\n")
    again = load_config(tmp_path / "mine.yaml")
    assert (again.ppo.lr, again.hidden) == (0.2, 32)
    first, second = compose(tmp_path / "mine.yaml"), compose(tmp_path / "mine.yaml")
    first["lr"] = 9.0  # each caller's own copy
    assert second["lr"] == 0.2 and compose(tmp_path / "mine.yaml")["lr"] == 0.2


def test_unknown_keys_are_refused_with_the_valid_ones(tmp_path):
    with pytest.raises(ConfigError, match=r"unknown config key 'lrr'.*did you mean 'ppo.lr'.*valid keys: name, "):
        load_config(None, ["lrr=0.1"])
    bad = tmp_path / "bad.yaml"
    bad.write_text("defaults: ['/ippo/mlp_ik@_global_', _self_]\nnum_env: 8\n")  # a shipped file, its keys on top
    with pytest.raises(ConfigError, match=r"unknown config key 'num_env' in .*bad.yaml.*did you mean 'num_envs'"):
        load_config(bad)


@pytest.mark.parametrize(
    "override, message",
    [
        ("share_params=3", "share_params in the command line must be bool"),
        ("ppo.lr=fast", "ppo.lr in the command line must be float"),
        ("num_envs=0", "num_envs must be at least 1"),
        ("num_envs=30", r"minibatches \(4\) must divide num_envs \(30\)"),
        ("seed", "must look like key=value"),
    ],
)
def test_bad_values_say_what_is_wrong(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


def test_broken_files_say_what_is_wrong(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        load_config(tmp_path / "missing.yaml")
    (tmp_path / "list.yaml").write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="must hold `key: value` lines"):
        load_config(tmp_path / "list.yaml")
    (tmp_path / "loop.yaml").write_text("defaults: [loop.yaml]\n")
    with pytest.raises(ConfigError, match=r"^the defaults of .*loop.yaml include one another in a loop$"):
        load_config(tmp_path / "loop.yaml")


def test_minibatch_shards_default_to_two_where_they_pay_and_never_for_e3t():
    def shards(*overrides):
        return minibatch_shards(load_config(None, list(overrides)))

    assert shards() == 2  # the paper's IK setting: hidden 256 on a CPU
    assert shards("hidden=128") == 2 and shards("hidden=64") == 1  # small networks: the loss's Python dominates
    assert shards("num_envs=4", "ppo.minibatches=4") == 1  # one kitchen per minibatch cannot be split
    assert shards("algorithm=e3t", "architecture=e3t_mlp") == 1  # its losses are means over the ego's transitions
    assert shards("hidden=64", "runtime.minibatch_shards=4") == 4  # asked for: as asked
    on_gpu = load_config(None)
    on_gpu.runtime.device = "cuda"  # set after the check, which looks for a GPU
    assert minibatch_shards(on_gpu) == 1  # no second pass on a GPU
    assert on_gpu.runtime.on_gpu and not load_config(None, ["runtime.device=cpu"]).runtime.on_gpu
    uneven = r"^algorithm=e3t averages its losses over some of a minibatch's transitions, which shards split unevenly"
    with pytest.raises(ConfigError, match=uneven + r": set runtime.minibatch_shards=1 \(got 2\)$"):
        check_algorithm(load_config(None, ["algorithm=e3t", "architecture=e3t_mlp", "runtime.minibatch_shards=2"]))


def test_a_run_saved_before_runtime_and_algorithm_config_had_sections_loads_into_them(tmp_path):
    recorded = json.loads((Path(__file__).parent / "data" / "config_values.json").read_text())
    e3t = {**recorded["configs/e3t/mlp_ik.yaml"], "threads": 2, "teams": 3, "partner_epsilon": 0.5}
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(e3t))  # a saved run's config.yaml, flat keys
    for config in (load_config(tmp_path / "config.yaml"), load_config(base=e3t)):  # or a checkpoint's config
        assert (config.runtime.threads, config.runtime.teams) == (2, 3)
        assert config.algorithm_config == {"partner_epsilon": 0.5, "partner_policy": "ego",
                                           "partner_copy_rate": 0.01, "predictor_coef": 1.0}
        assert check_algorithm(config) == config
    ippo = load_config(base=recorded["configs/ippo/mlp_ik.yaml"])  # E3T's keys, which IPPO ignored, are dropped
    assert ippo.algorithm_config == {} and check_algorithm(ippo).algorithm_config == {}
    assert ippo == load_config(CONFIG_DIR / "ippo" / "mlp_ik.yaml", RECORDED_FITTING)


def test_a_run_saved_before_ppo_and_distillation_had_sections_loads_into_them_and_resumes_key_by_key(tmp_path):
    recorded = json.loads((Path(__file__).parent / "data" / "config_values.json").read_text())
    flat = {**recorded["configs/main.yaml"], "distill_epochs": 16, "distill_teacher_mix": "round"}
    assert flat["distill_rounds"] == 6  # the recorded main job: distillation's keys at the top, as runs saved them
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(flat))
    for config in (load_config(tmp_path / "config.yaml"), load_config(base=flat)):
        assert (config.distill.rounds, config.distill.epochs, config.distill.teacher_mix) == (6, 16, "round")
        assert not any(key.startswith("distill_") for key in config.to_dict())
    # A checkpoint's config from before the section is compared key by key with today's: only what differs.
    today = load_config(CONFIG_DIR / "main.yaml", [*RECORDED_FITTING, "distill.epochs=8", "ppo.lr=0.1"])
    changed = today.changes_to_learning({**flat, "runtime": None})
    assert changed == {"distill.epochs": (16, 8), "distill.teacher_mix": ("round", "seed"), "ppo.lr": (flat["lr"], 0.1)}


def test_a_group_the_file_does_not_choose_is_added_and_the_runtime_group_fills_its_section(tmp_path):
    (tmp_path / "mine.yaml").write_text("hidden: 32\nlr: 0.01\n")  # a file of one's own, choosing no group
    mine = load_config(tmp_path / "mine.yaml", ["regime=sk_coord_ring", "algorithm=e3t", "architecture=e3t_mlp"])
    # Added as Hydra adds a group (`+regime=...`): after the file's own values, so the regime's width wins here,
    # as it would in a sweep of the same file; a group the file chooses would keep the file's values on top.
    assert (mine.levels, mine.hidden, mine.share_params, mine.ppo.lr) == ("coord_ring_7x7", 128, False, 2.5e-4)
    assert (mine.algorithm, mine.architecture, mine.algorithm_config["partner_epsilon"]) == ("e3t", "e3t_mlp", 0.3)
    assert compose(None, ["runtime=gpu"]) == {"runtime": {"device": "cuda", "threads": 1}}
    assert load_config(tmp_path / "mine.yaml", ["runtime=cpu", "runtime.threads=2"]).runtime.threads == 2
    twice = load_config(tmp_path / "mine.yaml", ["regime=ik", "architecture=mlp", "regime=sk_coord_ring",
                                                 "architecture=gnn"])  # the last choice, as for a key
    assert (twice.levels, twice.architecture) == ("coord_ring_7x7", "gnn")


def test_every_shipped_training_config_trains_a_whole_number_of_updates():
    """A run of any shipped config (and the paper's protocol) ends on an update's edge, with no warning."""
    root = Path(__file__).resolve().parents[2]
    paths = [*sorted((root / "configs" / "ippo").glob("*.yaml")), *sorted((root / "configs" / "e3t").glob("*.yaml")),
             root / "configs" / "main.yaml", root / "configs" / "main_9x9.yaml"]
    protocol = yaml.safe_load((root / "configs" / "protocols" / "paper.yaml").read_text())
    paper = [item for item in protocol["overrides"] if not item.startswith("runtime.")]  # a GPU's
    for path, overrides in [*((p, []) for p in paths), (paths[0], paper)]:
        config = load_config(path, overrides)
        assert config.total_steps % (config.num_envs * config.rollout_steps) == 0, (path, config.total_steps)
