"""An architecture registered in a user's own module trains, evaluates and sweeps by name through `--import`."""

import sys
from pathlib import Path

import pytest
from tiny import TINY

from trainers.evaluation import main as eval_main
from trainers.plugins import PLUGINS_VARIABLE, import_plugins
from trainers.train_command import main as train_main

ROOT = Path(__file__).resolve().parents[2]
PLUGIN = '''
import functools
from torch_kitchen.models import build_builtin, register_architecture

CALLS = []

def narrow_mlp(obs_shape, hidden, share_params):
    CALLS.append(hidden)
    return build_builtin("mlp", obs_shape=obs_shape, hidden=hidden // 2, share_params=share_params)

register_architecture("{name}", narrow_mlp)
'''


@pytest.fixture()
def user_folder(tmp_path, monkeypatch):
    """A working directory holding the user's module; sys.path and the environment restored afterwards."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setenv(PLUGINS_VARIABLE, "")
    return tmp_path


def test_a_users_architecture_trains_and_evaluates_by_name(user_folder, capsys):
    (user_folder / "my_models.py").write_text(PLUGIN.format(name="plugin_narrow_mlp"))
    overrides = [*TINY, "architecture=plugin_narrow_mlp", "total_steps=64", f"run_dir={user_folder / 'runs'}",
                 "name=mine"]
    assert train_main(["--import", "my_models", str(ROOT / "configs" / "main.yaml"), *overrides]) == 0
    assert sys.modules["my_models"].CALLS  # the command built the user's network
    eval_config = user_folder / "eval.yaml"
    eval_config.write_text(f"conditions: {{mine: {user_folder / 'runs' / 'mine' / 'seed*'}}}\nlayouts: "
                           "[cramped_room_7x7]\nheldout: 0\nrollouts: 1\nmax_steps: 8\nprogress: false\n"
                           f"out_dir: {user_folder / 'eval'}\n")
    # Overrides may come before or after `--import MODULE`.
    assert eval_main([str(eval_config), "--import", "my_models", "rollouts=2"]) == 0
    assert "| mine | cramped_room_7x7 |" in (user_folder / "eval" / "eval.md").read_text()
    assert "(2 rollouts per pair and grid" in (user_folder / "eval" / "eval.md").read_text()
    # A sweep's job, in a process of its own, imports what the command was given: it is in the environment.
    assert import_plugins() == ["my_models"]


def test_a_module_that_cannot_be_imported_is_one_line(user_folder, capsys):
    (user_folder / "broken_models.py").write_text("raise RuntimeError('no GPU here')\n")
    assert train_main(["--import", "broken_models", "configs/main.yaml"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1
    assert "--import broken_models: cannot import 'broken_models' (RuntimeError: no GPU here)" in error
    assert train_main(["--import", "not_a_module_anywhere", "configs/main.yaml"]) == 2
    assert "ModuleNotFoundError" in capsys.readouterr().err
