"""Checkpoints are data, not code: crafted files are refused unrun, writes hold plain values only, RNGs round trip."""

import pickle
import random
import re
import zipfile
from collections import OrderedDict

import numpy as np
import pytest
import torch
from tiny import TINY

from torch_kitchen.models import model_identity
from trainers.checkpoint import (
    FORMAT,
    CheckpointError,
    capture_rng_states,
    check_identity,
    load_checkpoint,
    restore_rng_states,
    save_checkpoint,
)
from trainers.config.compose import load_config, save_config

IDENTITY = model_identity("mlp", (7, 7, 26), 16, True)
REFUSED = "holds objects other than tensors and plain values .*: not an Infinite Kitchen checkpoint \\(refused"


class CreatesAFile:
    """Unpickling it opens (creates) `marker`: the smallest stand-in for a payload that runs code."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def craft(path, marker, zipped=True):
    """A file that looks like a checkpoint (format, model, weights) and runs code when unpickled."""
    torch.save({"format": FORMAT, "model": IDENTITY, "actor": {"weight": torch.zeros(2)}, "x": CreatesAFile(marker)},
               path, _use_new_zipfile_serialization=zipped)  # fmt: skip
    return path


@pytest.mark.parametrize("zipped", [True, False], ids=["zip", "legacy"])
def test_a_crafted_checkpoint_is_refused_before_it_runs(tmp_path, zipped):
    marker = tmp_path / "marker"
    crafted = craft(tmp_path / "crafted.pt", marker, zipped)
    with pytest.raises(CheckpointError, match=REFUSED) as refused:
        load_checkpoint(crafted)
    assert "\n" not in str(refused.value)
    assert not marker.exists()
    with open(crafted, "rb") as handle:  # the control: an unrestricted load does run it
        torch.load(handle, weights_only=False)
    assert marker.exists()


def test_a_bare_pickle_that_runs_code_is_refused(tmp_path):
    marker = tmp_path / "marker"
    crafted = tmp_path / "crafted.pt"
    crafted.write_bytes(pickle.dumps({"format": FORMAT, "model": {}, "x": CreatesAFile(marker)}, protocol=2))
    with pytest.raises(CheckpointError, match=REFUSED):
        load_checkpoint(crafted)
    assert not marker.exists()


def test_kitchen_eval_refuses_a_crafted_checkpoint(tmp_path, capsys):
    from trainers.evaluation import main

    marker = tmp_path / "marker"
    crafted = craft(tmp_path / "crafted.pt", marker)
    config = tmp_path / "eval.yaml"
    config.write_text(f"conditions:\n  c: {crafted}\nheldout: 1\nrollouts: 1\nout_dir: {tmp_path}/out\n")
    assert main([str(config)]) == 2
    assert "refused without running it" in capsys.readouterr().err
    assert not marker.exists()


def test_kitchen_train_resume_refuses_a_crafted_checkpoint(tmp_path, capsys):
    from trainers.train_command import main

    marker = tmp_path / "marker"
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    save_config(load_config(None, [*TINY, f"run_dir={tmp_path}"]), run / "config.yaml")
    craft(run / "checkpoints" / "latest.pt", marker)
    assert main(["--resume", str(run)]) == 2
    assert "refused without running it" in capsys.readouterr().err
    assert not marker.exists()


def test_damaged_and_foreign_files_are_refused(tmp_path):
    good = save_checkpoint(tmp_path / "good.pt", {"model": IDENTITY, "actor": {"weight": torch.randn(64, 64)}})
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(good.read_bytes()[:700])
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(bytes(range(256)) * 4)
    foreign_zip = tmp_path / "foreign.pt"
    with zipfile.ZipFile(foreign_zip, "w") as archive:
        archive.writestr("notes.txt", "not a checkpoint")
    for path in (truncated, foreign_zip):
        with pytest.raises(CheckpointError, match="is not a readable checkpoint .*truncated or corrupt") as refused:
            load_checkpoint(path)
        assert "\n" not in str(refused.value)
    text = tmp_path / "notes.pt"
    text.write_text("hello")
    for path in (empty, garbage, text):  # no file torch.save writes: said so, rather than how the reader failed
        with pytest.raises(CheckpointError, match="is not a checkpoint: not a file torch.save writes") as refused:
            load_checkpoint(path)
        assert "\n" not in str(refused.value) and "Error" not in str(refused.value)
    torch.save({"weight": torch.zeros(2)}, tmp_path / "weights.pt")  # torch's, but no checkpoint
    with pytest.raises(CheckpointError, match="not an Infinite Kitchen checkpoint \\(no format and model"):
        load_checkpoint(tmp_path / "weights.pt")
    with pytest.raises(CheckpointError, match="no checkpoint at .*give a checkpoint file or a run directory"):
        load_checkpoint(tmp_path / "missing.pt")


def test_format_1_checkpoints_are_refused_as_an_older_version(tmp_path):
    # Format 1 pickled numpy arrays (and the JAX kitchens) into the env's state: refused unrun, named as such.
    torch.save({"format": 1, "model": IDENTITY, "env": {"_extra_state": {"key": np.zeros(2, np.uint32)}}},
               tmp_path / "numpy.pt")  # fmt: skip
    # Scripted teams of format 1 held tensors only: they load, and their format is refused.
    torch.save({"format": 1, "model": IDENTITY, "actor": {}}, tmp_path / "plain.pt")
    for name in ("numpy.pt", "plain.pt"):
        with pytest.raises(CheckpointError, match="written by an older version .*format 1.*retrain, or load it with"):
            load_checkpoint(tmp_path / name)
    torch.save({"format": 3, "model": IDENTITY}, tmp_path / "newer.pt")
    with pytest.raises(CheckpointError, match="format 3, this version reads format 2"):
        load_checkpoint(tmp_path / "newer.pt")


def test_a_checkpoint_round_trips_through_the_weights_only_loader(tmp_path):
    module = torch.nn.Linear(3, 2)
    optimizer = torch.optim.Adam(module.parameters())
    module(torch.ones(1, 3)).sum().backward()
    optimizer.step()
    payload = {"config": {"levels": ["a", "b"], "lr": 3e-4, "shaping": (1.0, 0.5), "name": None},
               "model": IDENTITY, "actor": module.state_dict(), "optimizer": optimizer.state_dict(), "update": 3,
               "rng": capture_rng_states(), "shape": torch.Size([2, 3]), "dtype": torch.float32}  # fmt: skip
    path = save_checkpoint(tmp_path / "run" / "checkpoints" / "latest.pt", payload)
    assert not path.with_name("latest.pt.partial").exists()
    loaded = load_checkpoint(tmp_path / "run")  # a run directory: its latest checkpoint
    assert loaded["format"] == FORMAT and loaded["path"] == str(path)
    assert loaded["config"] == payload["config"] and loaded["update"] == 3 and loaded["shape"] == torch.Size([2, 3])
    for name, tensor in module.state_dict().items():
        torch.testing.assert_close(loaded["actor"][name], tensor, rtol=0, atol=0)
    torch.optim.Adam(torch.nn.Linear(3, 2).parameters()).load_state_dict(loaded["optimizer"])
    check_identity(loaded, IDENTITY)
    with pytest.raises(CheckpointError, match="hidden: checkpoint 16, expected 32; share_params: checkpoint True"):
        check_identity(loaded, model_identity("mlp", (7, 7, 26), 32, False))


@pytest.mark.parametrize("entry, named", [
    ({"env": {"_extra_state": {"key": np.zeros(2)}}}, "payload['env']['_extra_state']['key']: a numpy.ndarray"),
    ({"lr": np.float64(1e-3)}, "payload['lr']: a numpy.float64"),  # a float subclass, pickled under numpy's name
    ({"levels": [["a"], {"b"}]}, "payload['levels'][1]: a set"),
    ({"env": OrderedDict({1.5j: 0})}, "payload['env']: its key 1.5j is a complex"),
])  # fmt: skip
def test_save_refuses_what_the_loader_could_not_read(tmp_path, entry, named):
    target = tmp_path / "latest.pt"
    with pytest.raises(TypeError, match=re.escape(named)):
        save_checkpoint(target, {"model": IDENTITY, **entry})
    assert not target.exists() and not target.with_name("latest.pt.partial").exists()


def draws() -> tuple:
    return random.random(), random.gauss(0, 1), np.random.rand(3).tolist(), np.random.normal(), torch.rand(3).tolist()


def test_rng_states_round_trip_through_a_weights_only_file(tmp_path):
    random.seed(1), np.random.seed(2), torch.manual_seed(3)
    random.gauss(0, 1), np.random.normal()  # leave a cached Gaussian in both, part of their states
    save_checkpoint(tmp_path / "rng.pt", {"model": IDENTITY, "rng": capture_rng_states()})
    expected = draws()
    draws()
    restore_rng_states(torch.load(tmp_path / "rng.pt", weights_only=True)["rng"])
    assert draws() == expected
    restore_rng_states(load_checkpoint(tmp_path / "rng.pt")["rng"])
    assert draws() == expected


def test_rng_states_cover_cuda(monkeypatch):
    if not torch.cuda.is_initialized():
        assert capture_rng_states()["torch_cuda"] == []
    states = [torch.full((16,), 7, dtype=torch.uint8), torch.full((16,), 9, dtype=torch.uint8)]
    restored = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: states)
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", restored.extend)
    captured = capture_rng_states()
    assert [state.tolist() for state in captured["torch_cuda"]] == [state.tolist() for state in states]
    restore_rng_states(captured)  # two GPUs' states on a one-GPU machine: the first one's goes to it
    assert [state.tolist() for state in restored] == [states[0].tolist()]

    def no_cuda(_):
        raise AssertionError("no CUDA state may be set on a machine without CUDA")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", no_cuda)
    restore_rng_states(captured)


def test_a_trained_e3t_run_checkpoints_only_tensors_and_plain_values(tmp_path):
    from trainers.ppo.loop import train

    e3t = [*TINY, f"run_dir={tmp_path}", "algorithm=e3t", "architecture=e3t_mlp",
           "algorithm_config.partner_policy=copy"]
    run = train(load_config(None, [*e3t, "total_steps=64"]))
    saved = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)
    assert saved["format"] == FORMAT and saved["update"] == 1
    assert set(saved["env"]["_extra_state"]) == {"key", "states", "deliveries"}
    assert set(saved["rng"]) == {"python", "numpy", "torch", "torch_cuda"}
    # And the run resumes from it: kitchens, seats, networks and RNGs back in place.
    train(load_config(None, [*e3t, "total_steps=128"]), resume=True)
    assert load_checkpoint(run)["update"] == 2
