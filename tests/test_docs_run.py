"""Every shell command of README.md and docs/*.md runs as written, page by page in the order the page gives, in a
fresh folder that holds a copy of configs/ (as a clone's root does), shrunk to a tiny size: the same arguments
with a few size overrides appended (`SHRINK`: a later `key=value` or option wins; a sweep's grid narrowed to the
first and last value of each key), in this process, the console scripts called as their entry points. A command
a page marks as refused (its comment begins "refused") must end in one line on stderr and exit status 2. What
cannot run here is named with its reason (`NOT_HERE`), and counted.

A page states what its commands presume with a hidden line, `<!-- docs-run: after COMMAND -->` (e.g. the main job
whose run the page evaluates): those commands run first, shrunk as well.
"""

import contextlib
import dataclasses
import glob
import importlib
import io
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch
from test_docs_commands import PAGES, ROOT, Code, code_of, entry_points, page_name
from tiny import script_module

SHELLS = ("bash", "sh", "shell", "console")
AFTER = re.compile(r"^<!--\s*docs-run:\s*after\s+(.+?)\s*-->$", re.MULTILINE)  # a line of its own
REFUSED = "refused"  # a comment that begins so marks a command meant to fail
# Appended to a command of that name (a later `key=value` or option wins): one update of 4 kitchens x 16 steps,
# 16-step episodes, narrow networks, one distillation round, 1-2 test levels, no progress bars; training and
# evaluation by the kitchens' collector, since a tiny run compiles longer inside XLA than it plays (6 s of a 16 s
# training run; that path has tests of its own: tests/torch_kitchen/test_xla_rollout.py, the stranger benchmark's).
TRAIN_SHRINK = ["num_envs=4", "rollout_steps=16", "max_steps=16", "hidden=16", "ppo.minibatches=2", "ppo.epochs=2",
                "total_steps=64", "runtime.threads=1", "progress=false", "eval_episodes=0", "distill.kitchens=4",
                "distill.rounds=1", "distill.epochs=1", "runtime.collector=kitchen"]
EVAL_SHRINK = ["rollouts=1", "heldout=1", "max_steps=16", "progress=false", "runtime.threads=1", "workers=1",
               "collector=kitchen"]
SHRINK = {
    "kitchen-train": TRAIN_SHRINK,
    "kitchen-distill": TRAIN_SHRINK,
    "kitchen-sweep": TRAIN_SHRINK,
    "kitchen-eval": EVAL_SHRINK,
    "kitchen-demo": ["--steps", "8"],
    "kitchen-levels sample": ["--n", "4"],
    # 12 candidates: seed 0's first draws with a stranger by content among them (the 11th).
    "kitchen-zoo draw": ["--candidates", "12", "--keep", "2", "--strangers", "1", "--levels", "2", "--min-cooked", "0",
                         "--table-heldout", "1", "--table-rollouts", "1", "--clash-heldout", "0", "--workers", "1",
                         "--max-steps", "16", "--out", "outputs/zoo"],
    "kitchen-zoo clash": ["--heldout", "0", "--max-steps", "2", "--out", "outputs/clash", "--conventions",
                          "cook_0_228", "cook_0_221", "cook_0_193"],  # three of the shipped zoo's
    "kitchen-study simulate": ["--participants", "2", "--parallel", "2", "--max-steps", "8"],
    "kitchen-study power": ["--studies", "4", "--sizes", "8", "16"],
    "scripts/reproduce.py": ["--teams", "1", "--rollouts", "1", "--heldout", "1", "--max-steps", "16", "--jobs", "1",
                             "--no-human-proxies", "--collector", "kitchen", *TRAIN_SHRINK],
}
# A strangers section beside the one stranger of the page's tiny zoo (kitchen-zoo draw, shrunk, writes it first):
# a best response and a learned stranger for it, not for the shipped zoo's 8.
SHRINK["scripts/reproduce.py configs/protocols/reduced.yaml --sections strangers"] = [
    *SHRINK["scripts/reproduce.py"], "--strangers", "outputs/zoo/zoo.yaml"]
# The paper's grid (36 conditions) in three of its corners: an IK condition with an SK one of its family, and the
# grid's last IK condition (tests/trainers/test_config.py loads every condition of every protocol).
SHRINK["scripts/reproduce.py configs/protocols/paper.yaml"] = [
    *SHRINK["scripts/reproduce.py"], "--conditions", "ippo_mlp_ik", "ippo_mlp_sk_cramped_room", "e3t_gnn_ik"]
GPU = "a GPU"
# What runs elsewhere or not at all here: (a pattern of the command line, why).
NOT_HERE = [
    (r"^make test\b", "the suite itself"),
    (r"^pip install", "installs from the package index"),
    (r"^tensorboard\b", "a server (TensorBoard's)"),
    (r"^kitchen-play (?!replay)", "a server (tests/web_apps/play drive it)"),
    (r"<\w+>", "names a file of the reader's"),
    (r"submitit_slurm|hydra/launcher=ray", "a cluster's launcher"),
    (r"runtime\.device=cuda|DEVICE=cuda|#.* on a GPU", GPU),
    (r"^kitchen-humans|human_proxies=runs|runs/bc_", "the 2019 human games, downloaded by kitchen-humans fetch"),
]
# `make main` as the Makefile's recipe runs it, once .venv is set up (the suite runs in it).
MAKE_MAIN = "kitchen-train configs/main.yaml runtime.device=cpu"


@dataclass
class Outcome:
    code: Code
    status: str  # "ran", "refused", "not here", "failed"
    detail: str = ""
    seconds: float = 0.0


def split_comment(text: str) -> tuple[str, str]:
    """A command line without and its trailing comment (after an unquoted #, '' when none)."""
    quote = None
    for index, char in enumerate(text):
        if quote:
            quote = None if char == quote else quote
        elif char in "'\"":
            quote = char
        elif char == "#" and (index == 0 or text[index - 1].isspace()):
            return text[:index].strip(), text[index + 1:].strip()
    return text.strip(), ""


def expand(arguments: list[str]) -> list[str]:
    """The shell's globbing: a pattern that matches files becomes them, one that matches none stays as written."""
    expanded = []
    for argument in arguments:
        matches = sorted(glob.glob(argument)) if any(char in argument for char in "*?") else []
        expanded.extend(matches or [argument])
    return expanded


def narrowed_grid(words: list[str]) -> list[str]:
    """A sweep's keys of more than two values narrowed to their first and last (a later value wins): docs/sweeps.md's
    paper grid in 4 points, not 24, each still a point of it."""
    narrowed = []
    for word in words[2:]:
        key, _, values = word.partition("=")
        values = values.split(",")
        if not key.startswith(("hydra", "-")) and len(values) > 2 and "(" not in word:
            narrowed.append(f"{key}={values[0]},{values[-1]}")
    return narrowed


def shrink_of(words: list[str]) -> list[str]:
    if "--resume" in words:
        return []  # a resumed run keeps its own (shrunk) config
    if words[0] in ("python", "python3"):
        words = words[1:]  # a script of scripts/, by its path
    # the longest start of the command that SHRINK names
    shrink = next((SHRINK[" ".join(words[:n])] for n in (4, 3, 2, 1) if " ".join(words[:n]) in SHRINK), [])
    if words[0] == "kitchen-sweep":
        shrink = [*shrink, *narrowed_grid(words)]
    return [*shrink, "hydra.launcher.n_jobs=1"] if "hydra/launcher=joblib" in words else shrink


def call(words: list[str]) -> tuple[int, str]:
    """Runs one command in this process: exit status and stderr."""
    targets = entry_points()
    if words[0] in targets:
        module, _, function = targets[words[0]].partition(":")
        main, argv = getattr(importlib.import_module(module), function), words[1:]
    elif words[0] in ("python", "python3") and words[1].startswith("scripts/"):
        main, argv = script_module(Path(words[1]).stem).main, words[2:]
    else:
        raise AssertionError(f"no way to run {words[0]!r} here: add it to NOT_HERE with the reason")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            status = main(argv)
        except SystemExit as stop:
            status = stop.code if isinstance(stop.code, int) else 1
    return status or 0, err.getvalue()


def run_line(code: Code) -> Outcome:
    line, comment = split_comment(code.text)
    for pattern, why in NOT_HERE:
        if re.search(pattern, code.text) and not (why == GPU and torch.cuda.is_available()):
            return Outcome(code, "not here", why)
    words = shlex.split(line)
    if words[:2] == ["make", "main"]:
        words = shlex.split(MAKE_MAIN) + words[2:]
    words = words[:1] + expand(words[1:])
    start = time.perf_counter()
    status, err = call([*words, *shrink_of(words)])
    seconds = time.perf_counter() - start
    last = err.strip().splitlines()[-1] if err.strip() else ""
    if comment.startswith(REFUSED):
        lines = [line for line in err.splitlines() if line.strip() and "%|" not in line]
        ok = status == 2 and len(lines) == 1
        return Outcome(code, "refused" if ok else "failed",
                       last if ok else f"meant to be refused in one line, exit 2: got {status}, stderr {err[-400:]!r}",
                       seconds)
    return Outcome(code, "ran" if status == 0 else "failed", f"exit {status}: {last}" if status else "", seconds)


def page_commands(path: Path) -> list[Code]:
    return [code for code in code_of(page_name(path), path.read_text()) if code.language in SHELLS]


def run_page(path: Path, folder: Path) -> list[Outcome]:
    shutil.copytree(ROOT / "configs", folder / "configs")
    outcomes = []
    for before in AFTER.findall(path.read_text()):
        prerequisite = run_line(Code(page_name(path), 0, before, "bash"))
        assert prerequisite.status == "ran", f"{page_name(path)}: its prerequisite {before!r}: {prerequisite.detail}"
    for code in page_commands(path):
        outcomes.append(run_line(code))
    return outcomes


def test_make_main_stands_for_the_makefiles_recipe():
    recipe = MAKE_MAIN.replace("kitchen-train", "$(BIN)/kitchen-train").replace("=cpu", "=$(DEVICE)")
    assert recipe in (ROOT / "Makefile").read_text(), f"the Makefile's main target no longer runs {recipe}"
    assert split_comment("kitchen-eval 'a # b' x=1   # refused until # then") == ("kitchen-eval 'a # b' x=1",
                                                                                 "refused until # then")
    assert shrink_of(["kitchen-sweep", "c.yaml", "seed=0,1,2", "ppo.lr=1,2", "x=range(0,6)", "hydra.a=1,2,3"])[-1:] == [
        "seed=0,2"]


def tracked_changes() -> str:
    return subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT, capture_output=True,
                          text=True).stdout


def run_pages(folder: str, record: str) -> None:
    """Every page's commands, each page in a folder of its own under `folder`; the outcomes as JSON in `record`.
    Run in a process of its own, so that what a command leaves behind (logging set up, threads) stays there."""
    outcomes = []
    for index, path in enumerate(PAGES):
        page_folder = Path(folder) / f"page{index}"
        page_folder.mkdir()
        os.chdir(page_folder)
        outcomes += run_page(path, page_folder)
    Path(record).write_text(json.dumps([dataclasses.asdict(outcome) for outcome in outcomes]))


@pytest.mark.slow
def test_every_documented_command_runs_as_written(tmp_path, capsys):
    before = tracked_changes()
    record = tmp_path / "outcomes.json"
    child = subprocess.run(
        [sys.executable, "-c", f"import test_docs_run; test_docs_run.run_pages({str(tmp_path)!r}, {str(record)!r})"],
        cwd=tmp_path, capture_output=True, text=True,
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "tests")])})
    assert child.returncode == 0, child.stderr[-3000:]
    outcomes = [Outcome(Code(**outcome.pop("code")), **outcome) for outcome in json.loads(record.read_text())]
    counts = {status: sum(outcome.status == status for outcome in outcomes)
              for status in ("ran", "refused", "not here", "failed")}
    reasons = sorted({outcome.detail for outcome in outcomes if outcome.status == "not here"})
    with capsys.disabled():
        print(f"\ndocumented commands: {counts['ran']} ran as written (shrunk), {counts['refused']} refused as their "
              f"pages say, {counts['not here']} not run here ({'; '.join(reasons)}), {counts['failed']} failed")
        for outcome in sorted(outcomes, key=lambda outcome: -outcome.seconds)[:15]:
            print(f"{outcome.seconds:6.1f} s  {outcome.code.page}:{outcome.code.line}: {outcome.code.text[:90]}")
    failed = [f"{outcome.code.page}:{outcome.code.line}: {outcome.code.text}\n    {outcome.detail}"
              for outcome in outcomes if outcome.status == "failed"]
    assert not failed, "\n".join(failed)
    assert counts["ran"] >= 30, counts  # the pages' commands were found
    assert tracked_changes() == before, "a documented command wrote into the repository"
