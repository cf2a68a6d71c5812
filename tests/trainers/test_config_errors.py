"""Every bad config value is refused by `check()` (or the YAML reader) with one line that says what to change."""

import argparse
import dataclasses
from pathlib import Path

import jax
import pytest
import torch
from tiny import TINY

from jax_env import get_layout, save_layout
from trainers.algorithms import algorithm_settings, check_algorithm
from trainers.algorithms.e3t import E3TSettings
from trainers.config import ConfigError, DeviceConfig, EvalConfig, PPOConfig, RuntimeConfig, TrainConfig, check_device
from trainers.config.compose import config_help, load_config, save_config

# A 5x5 kitchen whose only pot is walled in: no team can ever cook. The same kitchen with the pot in reach.
WALLED_POT = "WWWWW\nOA  W\nB  AW\nWWXWW\nWPWWW\n"
OPEN_POT = "WWPWW\nOA  W\nB  AW\nWWXWW\nWWWWW\n"
RUNTIME_DEVICES = r"use runtime.device=cpu, runtime.device=cuda or runtime.device=cuda:<index>"
COUNTS = ("max_steps num_envs rollout_steps total_steps hidden ppo.epochs ppo.minibatches checkpoint_every "
          "runtime.threads runtime.teams distill.rounds distill.kitchens distill.epochs distill.minibatch").split()
NON_NEGATIVE = ("eval_episodes ppo.shaping_anneal_steps ppo.entropy_coef ppo.value_coef ppo.shaping_weight "
                "runtime.minibatch_shards runtime.parallel_teams").split()


@pytest.mark.parametrize(
    "override, message",
    [
        *[(f"{name}=0", rf"^{name} must be at least 1, got 0$") for name in COUNTS],
        *[(f"{name}=-1", rf"^{name} must be at least 0, got -1") for name in NON_NEGATIVE],
        ("ppo.lr=0", r"^ppo.lr must be greater than 0, got 0.0$"),
        ("ppo.adam_eps=-1e-5", r"^ppo.adam_eps must be greater than 0, got -1e-05$"),
        ("ppo.clip_epsilon=-1", r"^ppo.clip_epsilon must be greater than 0, got -1.0$"),
        ("ppo.max_grad_norm=0", r"^ppo.max_grad_norm must be greater than 0, got 0.0$"),
        ("ppo.gamma=5", r"^ppo.gamma must lie in \[0, 1\], got 5.0$"),
        ("ppo.gae_lambda=-3", r"^ppo.gae_lambda must lie in \[0, 1\], got -3.0$"),
        ("ppo.lr=nan", r"^ppo.lr must be a finite number, got nan$"),
        ("ppo.gamma=.inf", r"^ppo.gamma must be a finite number, got inf$"),
        ("seed=-1", r"^seed must be an integer in \[0, 4294967295\] .*, got -1$"),
        ("seed=4294967296", r"^seed must be an integer in \[0, 4294967295\] .*, got 4294967296$"),
        (f"seed={2**63}", rf"^seed must be an integer in \[0, 4294967295\] .*, got {2**63}$"),
        ("eval_heldout=200", r"^eval_heldout must be between 0 and 100 \(the held-out levels\), got 200$"),
        ("eval_heldout=-1", r"^eval_heldout must be between 0 and 100"),
        ("runtime.device=tpu", rf"^runtime.device=tpu is not a device: {RUNTIME_DEVICES}$"),
        ("runtime.device=garbage", rf"^runtime.device=garbage is not a device: {RUNTIME_DEVICES}$"),
        ("runtime.device=meta", rf"^runtime.device=meta is not supported: {RUNTIME_DEVICES}$"),
        ("runtime.device=cpu:1", rf"^runtime.device=cpu:1 is not supported: {RUNTIME_DEVICES}$"),
        ("threads=2", r"^unknown config key 'threads' in the command line \(did you mean 'runtime.threads'\?\)"),
        ("distill_rounds=2",
         r"^unknown config key 'distill_rounds' in the command line \(did you mean 'distill.rounds'\?\)"),
        ("lr=0.1", r"^unknown config key 'lr' in the command line \(did you mean 'ppo.lr'\?\)"),
        ("partner_epsilon=0.5", r"^unknown config key 'partner_epsilon' in the command line"),
        ("runtime.thread=2", r"^unknown config key 'runtime.thread' .*\(did you mean 'runtime.threads'\?\)"),
        ("runtime.threads=x", r"^runtime.threads in the command line must be int, got 'x'$"),
        ("runtime.compile_update=3", r"^runtime.compile_update in the command line must be bool, got 3$"),
        ("algorithm_config=3", r"^algorithm_config in the command line must be dict\[str, Any\], got 3$"),
        ("name=../..", r"^name='../..' must be a relative path inside run_dir, without '..'"),
        ("name=a/../../b", r"^name='a/../../b' must be a relative path inside run_dir"),
        ("name=/tmp/elsewhere", r"^name='/tmp/elsewhere' must be a relative path inside run_dir"),
        ("name=.", r"^name='.' must be a relative path inside run_dir"),
        ("name=''", r"^name='' must be a relative path inside run_dir"),
        ("levels=[infinite, cramped_room_7x7]", r"^levels=infinite stands alone: it cannot be one entry of a list"),
        ("levels=[]", r"^levels is empty"),
        ("distill.move_order=NSE", r"^distill.move_order must be a permutation of NSEW, got 'NSE'$"),
        ("runtime.minibatch_shards=3", r"^runtime.minibatch_shards \(3\) must divide the 8 kitchens of a minibatch"),
    ],
)
def test_bad_overrides_are_refused_before_any_work(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override])


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["algorithm=ppo"],
         r"^algorithm must be one of ippo, e3t, anchored_ippo, kickstarted_ippo, zoo_ippo, got 'ppo'$"),
        (["algorithm=e3t", "algorithm_config.partner_epsilon=1.5"],
         r"^algorithm_config.partner_epsilon must lie in \[0, 1\], got 1.5$"),
        (["algorithm=e3t", "algorithm_config.partner_copy_rate=-0.1"],
         r"^algorithm_config.partner_copy_rate must lie in \[0, 1\], got -0.1$"),
        (["algorithm=e3t", "algorithm_config.partner_policy=slow"],
         r"^algorithm_config.partner_policy must be one of ego, copy, got 'slow'$"),
        (["algorithm=e3t", "algorithm_config.predictor_coef=-1"],
         r"^algorithm_config.predictor_coef must be at least 0, got -1.0$"),
        (["algorithm=e3t", "algorithm_config.partner_epsilom=0.5"],
         r"^algorithm_config.partner_epsilom is not a setting of algorithm=e3t \(did you mean "
         r"algorithm_config.partner_epsilon\?\); its settings: partner_epsilon, partner_policy, "),
        (["algorithm=e3t", "algorithm_config.partner_epsilon=often"],
         r"^algorithm_config.partner_epsilon in the config must be float, got 'often'$"),
    ],
)
def test_an_algorithms_own_settings_are_refused_by_the_algorithm_before_any_work(overrides, message):
    config = load_config(None, overrides)  # the algorithm's keys are the algorithm's to check
    with pytest.raises(ConfigError, match=message):
        check_algorithm(config)
    if "algorithm=e3t" in overrides:  # not another algorithm's: refused by name
        key = overrides[1].partition("=")[0]
        setting = key.partition(".")[2]
        with pytest.raises(ConfigError, match=rf"^{key} is not a setting of algorithm=ippo, which has no settings of "
                                              "its own$"):
            check_algorithm(dataclasses.replace(config, algorithm="ippo",
                                                algorithm_config={setting: config.algorithm_config[setting]}))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"seed": "a"}, r"^seed must be int, got 'a'$"),
        ({"seed": 1.0}, r"^seed must be int, got 1.0$"),
        ({"seed": 2**64}, r"^seed must be an integer in \[0, 4294967295\]"),
        ({"num_envs": True}, r"^num_envs must be int, got True$"),
        ({"ppo": PPOConfig(lr="fast")}, r"^ppo.lr must be float, got 'fast'$"),
        ({"share_params": 1}, r"^share_params must be bool, got 1$"),
        ({"levels": ("a", "b")}, r"^levels must be str \| list\[str\], got \('a', 'b'\)$"),
        ({"levels": ["a", 3]}, r"^levels must be str \| list\[str\], got \['a', 3\]$"),
        ({"name": Path("run")}, r"^name must be str, got PosixPath\('run'\)$"),
        ({"runtime": RuntimeConfig(device=None)}, r"^runtime.device must be str, got None$"),
        ({"runtime": RuntimeConfig(threads=0)}, r"^runtime.threads must be at least 1, got 0$"),
        ({"ppo": PPOConfig(gamma=5)}, r"^ppo.gamma must lie in \[0, 1\], got 5$"),
        ({"ppo": PPOConfig(clip_epsilon=-1.0)}, r"^ppo.clip_epsilon must be greater than 0, got -1.0$"),
        ({"checkpoint_every": 0}, r"^checkpoint_every must be at least 1, got 0$"),
        ({"eval_heldout": 101}, r"^eval_heldout must be between 0 and 100"),
        ({"name": "../.."}, r"^name='../..' must be a relative path inside run_dir"),
    ],
)
def test_configs_built_in_python_are_checked_too(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        TrainConfig(**kwargs).check()


def test_values_at_the_edges_are_accepted():
    config = load_config(None, [
        "seed=4294967295", "eval_heldout=100", "ppo.gamma=1", "ppo.gae_lambda=0", "ppo.lr=1", "ppo.shaping_weight=0",
        "eval_episodes=0", "name=ablation/mlp", "runtime.device=cpu:0",
    ])  # fmt: skip
    assert (config.seed, config.ppo.lr, config.ppo.gamma) == (2**32 - 1, 1.0, 1.0)
    assert config.run_path == Path("runs/ablation/mlp/seed4294967295")
    assert TrainConfig().check() == TrainConfig() and EvalConfig().check() == EvalConfig()


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"rollouts": 0}, r"^rollouts must be at least 1, got 0$"),
        ({"max_steps": 0}, r"^max_steps must be at least 1, got 0$"),
        ({"max_envs": -5}, r"^max_envs must be at least 1, got -5$"),
        ({"workers": 0}, r"^workers must be at least 1, got 0$"),
        ({"runtime": DeviceConfig(threads=0)}, r"^runtime.threads must be at least 1, got 0$"),
        ({"heldout": 101}, r"^heldout must be between 0 and 100 \(the held-out levels\), got 101$"),
        ({"heldout": -1}, r"^heldout must be between 0 and 100"),
        ({"seed": -1}, r"^seed must be an integer in \[0, 4294967295\]"),
        ({"runtime": DeviceConfig(device="tpu")}, rf"^runtime.device=tpu is not a device: {RUNTIME_DEVICES}$"),
        ({"layouts": "cramped_room_7x7"}, r"^layouts must be list\[str\], got 'cramped_room_7x7'$"),
        ({"conditions": {"a": 3}}, r"^conditions must be dict\[str, str \| list\[str\]\], got \{'a': 3\}$"),
        ({"rollouts": "5"}, r"^rollouts must be int, got '5'$"),
        ({"layouts": [], "heldout": 0}, r"^nothing to evaluate on"),
        ({"cross": [["a", "b"]]}, r"^cross names the condition 'a', which is not among the conditions: \(none\)$"),
    ],
)
def test_bad_eval_configs_are_refused(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        EvalConfig(**kwargs).check()


@pytest.mark.parametrize(
    "override, message",
    [
        ("rollouts=0", r"^rollouts must be at least 1, got 0$"),
        ("runtime.threads=0", r"^runtime.threads must be at least 1, got 0$"),
        ("threads=2", r"^unknown config key 'threads' in the command line \(did you mean 'runtime.threads'\?\)"),
        ("max_envs=0", r"^max_envs must be at least 1, got 0$"),
        ("heldout=200", r"^heldout must be between 0 and 100"),
        ("seed=-1", r"^seed must be an integer in \[0, 4294967295\]"),
        ("runtime.device=tpu", rf"^runtime.device=tpu is not a device: {RUNTIME_DEVICES}$"),
        ("layouts=cramped_room_7x7", r"^layouts in the command line must be list\[str\], got 'cramped_room_7x7'$"),
    ],
)
def test_bad_eval_overrides_are_refused(override, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, [override], schema=EvalConfig)


def test_compiling_on_a_cpu_is_refused_where_no_cpp_compiler_is_on_the_path(monkeypatch):
    import trainers.config.schema

    for key in ("compile_update", "compile_policy"):
        load_config(None, [f"runtime.{key}=true"])  # this machine has one
    monkeypatch.setattr(trainers.config.schema.shutil, "which", lambda name: None)
    for key in ("compile_update", "compile_policy"):
        with pytest.raises(ConfigError, match=rf"^runtime\.{key}=true compiles CPU kernels with a C\+\+ compiler, "
                                              rf"and none of .+ is on the PATH: .* or set runtime\.{key}=false$"):
            load_config(None, [f"runtime.{key}=true"])
    load_config(None, [])  # eager runs need none


def test_cuda_is_refused_where_this_machine_has_no_such_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for device in ("cuda", "cuda:0"):
        message = rf"device={device}, but torch sees no CUDA GPU on this machine: use (runtime\.)?device=cpu$"
        with pytest.raises(ConfigError, match=rf"^runtime\.{message}"):
            load_config(None, [f"runtime.device={device}"])
        with pytest.raises(ConfigError, match=rf"^runtime\.{message}"):
            EvalConfig(runtime=DeviceConfig(device=device)).check()

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    with pytest.raises(ConfigError, match=r"^device=cuda:3, but torch sees 2 CUDA GPU\(s\) here: use cuda:0 to cuda:1"):
        check_device("cuda:3")

    def no_jax_gpu(backend=None):
        raise RuntimeError("Unknown backend gpu")

    monkeypatch.setattr(jax, "devices", no_jax_gpu)  # torch sees GPUs, but this JAX is a CPU build
    with pytest.raises(ConfigError, match=r"^device=cuda:1, but JAX sees 0 GPU\(s\) here .*or use device=cpu$"):
        check_device("cuda:1")
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["gpu0", "gpu1"])
    check_device("cuda:1")
    check_device("cuda")
    assert TrainConfig(runtime=RuntimeConfig(device="cuda:1")).check().runtime.device == "cuda:1"


@pytest.mark.parametrize(
    "text, message",
    [
        ("base: a.yaml\n", r"^base in .*bad\.yaml: list the file in the defaults instead, "
                            r"`defaults: \[a.yaml, _self_\]`"),
        ("5: 3\n", r"^the key 5 in .*bad\.yaml is not a config key \(keys are names\): valid keys: name, run_dir"),
        ("seed: 1\ntrue: 3\n", r"^the key True in .*bad\.yaml is not a config key"),
        ("seed: -4\n", r"^seed must be an integer in \[0, 4294967295\]"),
        ("gamma: 5\n", r"^ppo.gamma must lie in \[0, 1\], got 5.0$"),  # a file of before the ppo section
        ("runtime:\n  device: tpu\n", r"^runtime.device=tpu is not a device"),
        ("device: tpu\n", r"^runtime.device=tpu is not a device"),  # a file from before the section: read into it
        ("runtime: 4\n", r"^runtime in .*bad\.yaml must be a mapping of its keys \(device, threads, "),
        ("runtime:\n  speed: 2\n", r"^unknown config key 'runtime.speed' in .*bad\.yaml"),
        ("num_env: 8\n", r"^unknown config key 'num_env' in .*bad\.yaml \(did you mean 'num_envs'\?\)"),
        ("defaults: base.yaml\n", r"^.*bad\.yaml: Invalid defaults list in 'bad', defaults must be a list "
                                  r"\(got str\)$"),
        ("defaults: [layout: ik]\n", r"^the defaults of .*bad\.yaml name 'layout/ik', which is neither a config file "
                                     r"beside it nor a config group choice \(e.g. /algorithm: ippo, /regime: ik\)$"),
        ("defaults: [regime: sk_nowhere]\n", r"^regime in .*bad\.yaml must be one of ik, sk_asymm_advantages, .*, "
                                             r"got 'sk_nowhere'$"),
        ("defaults: [missing.yaml]\n", r"^the defaults of .*bad\.yaml name 'missing.yaml', which is neither a "),
    ],
)
def test_broken_yaml_files_name_the_file(tmp_path, text, message):
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(ConfigError, match=message):
        load_config(tmp_path / "bad.yaml")


def test_a_file_beside_it_in_the_defaults_merges_under_the_files_own_values(tmp_path):
    (tmp_path / "base.yaml").write_text("seed: 1\nlr: 1e-3\n")
    (tmp_path / "run.yaml").write_text("defaults: [base.yaml]\nseed: 2\n")
    config = load_config(tmp_path / "run.yaml")
    assert (config.seed, config.ppo.lr) == (2, 1e-3)


def test_a_defaults_list_merges_files_then_group_choices_then_the_file(tmp_path):
    (tmp_path / "base.yaml").write_text("seed: 1\nlr: 1e-3\nhidden: 32\n")
    (tmp_path / "run.yaml").write_text("defaults: [base.yaml, regime: sk_coord_ring]\nseed: 2\n")
    config = load_config(tmp_path / "run.yaml")
    # base.yaml's hidden gives way to the regime's, which gives way to the file's own values.
    assert (config.seed, config.ppo.lr, config.hidden, config.levels) == (2, 1e-3, 128, "coord_ring_7x7")


def test_a_saved_config_loads_back_equal(tmp_path):
    config = load_config(None, ["seed=3", "levels=[cramped_room_7x7, coord_ring_7x7]", "name=ablation/mlp"])
    save_config(config, tmp_path / "config.yaml")
    assert load_config(tmp_path / "config.yaml") == config
    evaluation = EvalConfig(conditions={"a": "runs/a/seed*"}, heldout=3)
    save_config(evaluation, tmp_path / "eval.yaml")
    assert load_config(tmp_path / "eval.yaml", schema=EvalConfig) == evaluation


def test_a_file_where_the_run_directory_must_go_is_refused(tmp_path):
    (tmp_path / "x").write_text("not a folder")
    config = TrainConfig(run_dir=str(tmp_path / "x" / "y")).check()  # check() does not look at the disk
    with pytest.raises(ConfigError, match=rf"^run_dir={tmp_path}/x/y: {tmp_path}/x is a file, not a folder$"):
        config.check_run_location()
    with pytest.raises(ConfigError, match=rf"^run_dir={tmp_path}/x: {tmp_path}/x is a file, not a folder$"):
        TrainConfig(run_dir=str(tmp_path / "x")).check_run_location()

    runs = tmp_path / "runs"
    (runs / "ablation").mkdir(parents=True)
    (runs / "ablation" / "mlp").write_text("")
    with pytest.raises(ConfigError, match=rf"^name=ablation/mlp: {runs}/ablation/mlp is a file, not a folder"):
        TrainConfig(run_dir=str(runs), name="ablation/mlp").check_run_location()
    (runs / "ippo").mkdir()
    (runs / "ippo" / "seed0").write_text("")
    with pytest.raises(ConfigError, match=rf"^name=ippo: {runs}/ippo/seed0 is a file, not a folder"):
        TrainConfig(run_dir=str(runs), name="ippo").check_run_location()

    TrainConfig(run_dir=str(runs), name="ippo", seed=1).check_run_location()  # not made yet: fine
    (runs / "ippo" / "seed1").mkdir()
    TrainConfig(run_dir=str(runs), name="ippo", seed=1).check_run_location()  # already a folder (resume): fine


def test_unsolvable_levels_are_refused_unless_allowed(tmp_path):
    walled = tmp_path / "walled_pot.txt"
    walled.write_text(WALLED_POT)
    config = load_config(None, [f"levels={walled}"])  # loading the config does not read the level
    with pytest.raises(ConfigError, match=rf"^levels: {walled} is unsolvable, .*fix the layout, or pass "
                                          r"--allow-unsolvable to train on it anyway$"):  # fmt: skip
        config.check_levels()
    warnings = config.check_levels(allow_unsolvable=True)
    assert len(warnings) == 1 and str(walled) in warnings[0] and "unsolvable" in warnings[0]

    other = tmp_path / "walled_too.txt"
    other.write_text(WALLED_POT)
    solvable = tmp_path / "open_pot.txt"
    solvable.write_text(OPEN_POT)
    config = TrainConfig(levels=[str(walled), str(solvable), str(other)])
    with pytest.raises(ConfigError, match=rf"^levels: {walled}, {other} are unsolvable, .*to train on them anyway$"):
        config.check_levels()
    assert len(config.check_levels(allow_unsolvable=True)) == 2
    assert TrainConfig(levels=str(solvable)).check_levels() == []


@pytest.mark.parametrize(
    "levels",
    ["infinite", "heldout", "cramped_room_7x7", ["cramped_room_7x7", "forced_coord_7x7"], "saved"],
)
def test_solvable_and_generated_levels_pass(tmp_path, levels):
    if levels == "saved":  # a layout written by save_layout reads back as a level file
        levels = save_layout(get_layout("coord_ring_7x7"), str(tmp_path / "ring.txt"))
    assert TrainConfig(levels=levels).check().check_levels() == []


def test_levels_that_cannot_be_loaded_are_named(tmp_path):
    with pytest.raises(ConfigError, match=r"^levels: cannot load 'no_such_kitchen': unknown layout 'no_such_kitchen'"):
        TrainConfig(levels="no_such_kitchen").check_levels()
    missing = tmp_path / "missing.txt"
    with pytest.raises(ConfigError, match=rf"^levels: cannot load '{missing}': layout file .* does not exist$"):
        TrainConfig(levels=["cramped_room_7x7", str(missing)]).check_levels()
    ragged = tmp_path / "ragged.txt"
    ragged.write_text("WWWPW\nOA AW\nBWX\n")
    with pytest.raises(ConfigError, match=rf"^levels: cannot load '{ragged}': layout 'ragged': row 2 has 3 cells"):
        TrainConfig(levels=str(ragged)).check_levels()
    with pytest.raises(ConfigError, match=r"^levels must all have one size.*: cramped_room is 4x5, cramped_room_7"):
        TrainConfig(levels=["cramped_room", "cramped_room_7x7"]).check_levels()


def test_updates_round_up_and_say_so():
    config = TrainConfig(num_envs=8, rollout_steps=256, total_steps=1_000_000)
    assert config.num_updates == 489 and config.num_updates * config.frames_per_batch >= config.total_steps
    assert config.step_note() == (
        "total_steps=1,000,000 is not a multiple of the 2,048 steps of an update (num_envs x rollout_steps): "
        "training 489 updates = 1,001,472 steps"
    )
    exact = TrainConfig(num_envs=8, rollout_steps=256, total_steps=2048 * 3)
    assert (exact.num_updates, exact.step_note()) == (3, None)
    small = TrainConfig(num_envs=8, rollout_steps=256, total_steps=10)
    assert small.num_updates == 1 and "training 1 updates = 2,048 steps" in small.step_note()


def test_config_help_lists_every_key_with_type_default_and_meaning():
    for schema, prefix in ((TrainConfig, ""), (EvalConfig, ""), (RuntimeConfig, "runtime."), (E3TSettings, "")):
        text = config_help(TrainConfig, {"e3t": E3TSettings}) if schema is not EvalConfig else config_help(schema)
        prefix = "algorithm_config." if schema is E3TSettings else prefix
        for field in dataclasses.fields(schema):
            assert field.metadata["help"], field.name
            assert f"\n    {prefix}{field.name}: " in text, field.name
            assert f"\n        {field.metadata['help']}\n" in text + "\n", field.name
    text = config_help(TrainConfig, algorithm_settings())
    assert "    total_steps: int = 20000000\n        env steps over the run" in text
    assert "    levels: str | list[str] = infinite\n" in text and "    share_params: bool = true\n" in text
    assert "    runtime.threads: int = 1\n" in text and "    algorithm_config.partner_policy: str = ego\n" in text
    assert "    algorithm_config.anchor_coef: float = 0.1\n" in text
    assert "    algorithm_config.teacher_anneal_steps: int = 0\n" in text
    groups = [line.strip() for line in text.splitlines() if line.startswith("  ") and not line.startswith("   ")]
    assert groups == ["run:", "environment:", "model:", "PPO:",
                      "planner-guided start (kitchen-distill, then init_from):",
                      "logging, checkpoints, final evaluation:", "runtime:",
                      "algorithm_config (algorithm: e3t):", "algorithm_config (algorithm: anchored_ippo):",
                      "algorithm_config (algorithm: kickstarted_ippo):",
                      "algorithm_config (algorithm: zoo_ippo):"]  # fmt: skip
    assert "    layouts: list[str] = [cramped_room_7x7, " in config_help(EvalConfig)

    # As an epilog, argparse keeps its lines.
    parser = argparse.ArgumentParser(epilog=text, formatter_class=argparse.RawDescriptionHelpFormatter)
    assert text in parser.format_help()


def test_list_and_dict_defaults_are_not_shared():
    first, second = EvalConfig(), EvalConfig()
    first.layouts.append("extra")
    first.conditions["a"] = "runs/a"
    assert "extra" not in second.layouts and second.conditions == {}


# --------------------------------------------------------------------------- through the command line, as measured
TINY_RUN = [*TINY, "total_steps=64"]


def cli_cases(tmp_path: Path) -> list[tuple[list[str], str]]:
    """(arguments after the config file, the error's start) for every bad value found by trying the CLI."""
    (tmp_path / "a_file").write_text("")
    walled = tmp_path / "walled_pot.txt"
    walled.write_text(WALLED_POT)
    cases = [
        (["checkpoint_every=0"], "checkpoint_every must be at least 1"),
        (["runtime.device=tpu"], "runtime.device=tpu is not a device"),
        (["runtime.threads=0"], "runtime.threads must be at least 1"),
        (["threads=2"], "unknown config key 'threads' in the command line (did you mean 'runtime.threads'?)"),
        ([f"seed={2**63}"], "seed must be an integer in [0, 4294967295]"),
        (["ppo.gamma=5"], "ppo.gamma must lie in [0, 1]"),
        (["ppo.gae_lambda=-3"], "ppo.gae_lambda must lie in [0, 1]"),
        (["ppo.clip_epsilon=-1"], "ppo.clip_epsilon must be greater than 0"),
        (["eval_heldout=200"], "eval_heldout must be between 0 and 100"),
        (["name=../.."], "name='../..' must be a relative path inside run_dir"),
        ([f"run_dir={tmp_path / 'a_file' / 'runs'}"], f"run_dir={tmp_path / 'a_file' / 'runs'}: "),
        ([f"levels={walled}"], f"levels: {walled} is unsolvable"),
        (["loggers=[tensorboard, notebook]"], "loggers holds 'notebook'"),
        (["algorithm=mappo"], "algorithm must be one of ippo, e3t"),
    ]
    if not torch.cuda.is_available():
        cases.append((["runtime.device=cuda"],
                      "runtime.device=cuda, but torch sees no CUDA GPU on this machine: use runtime.device=cpu"))
    return cases


def test_every_bad_value_gets_one_line_and_exit_2_before_any_work(tmp_path, capsys):
    from trainers.train_command import main

    runs = tmp_path / "runs"
    for arguments, start in cli_cases(tmp_path):
        argv = [str(Path(__file__).resolve().parents[2] / "configs" / "main.yaml"), *TINY_RUN, f"run_dir={runs}",
                *arguments]
        assert main(argv) == 2, arguments
        err = capsys.readouterr().err
        assert err.startswith(f"kitchen-train: error: {start}") and err.count("\n") == 1, (arguments, err)
        assert not runs.exists(), arguments  # refused before anything was written


@pytest.mark.parametrize("text, start", [("base: 5\n", "base"), ("5: 3\n", "5")])
def test_bad_yaml_files_get_one_line_and_exit_2(tmp_path, capsys, text, start):
    from trainers.train_command import main

    path = tmp_path / "bad.yaml"
    path.write_text(text)
    assert main([str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("kitchen-train: error: ") and str(path) in err and err.count("\n") == 1, err


def test_an_unsolvable_level_trains_with_allow_unsolvable_and_a_warning(tmp_path, capsys):
    from trainers.train_command import main

    walled = tmp_path / "walled_pot.txt"
    walled.write_text(WALLED_POT)
    argv = [str(Path(__file__).resolve().parents[2] / "configs" / "main.yaml"), *TINY_RUN, f"run_dir={tmp_path}",
            f"levels={walled}", "--allow-unsolvable"]
    assert main(argv) == 0
    assert f"kitchen-train: warning: level {walled} is unsolvable" in capsys.readouterr().err
    assert (tmp_path / "main" / "seed0" / "checkpoints" / "latest.pt").exists()


def test_an_evaluation_takes_its_device_and_threads_in_the_runtime_section_as_training_does(tmp_path):
    (tmp_path / "old.yaml").write_text("device: cpu\nthreads: 2\nrollouts: 3\n")  # a file from before the section
    config = load_config(tmp_path / "old.yaml", ["runtime.device=cpu"], schema=EvalConfig)
    assert (config.runtime, config.rollouts) == (DeviceConfig(device="cpu", threads=2), 3)
    assert "runtime.threads" in config_help(EvalConfig) and "runtime.teams" not in config_help(EvalConfig)
