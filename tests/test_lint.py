"""The code passes its own lint configuration (`pyproject.toml`, `make lint`)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing():
    result = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "."], cwd=ROOT, capture_output=True,
                            text=True)
    assert result.returncode == 0, result.stdout + result.stderr


def imported_modules(path: Path) -> set[str]:
    """The modules a file imports, those imported only for type checking too."""
    import ast

    modules = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            modules.add(node.module)
        elif isinstance(node, ast.Import):
            modules.update(alias.name for alias in node.names)
    return modules


def test_the_training_step_imports_run_one_way():
    """runtime -> step -> team: a team is built and placed below the options that step it."""
    order = ["trainers.ppo.runtime", "trainers.ppo.step", "trainers.ppo.team"]
    for index, module in enumerate(order):
        imported = imported_modules(ROOT / (module.replace(".", "/") + ".py"))
        above = [name for name in order[:index] if name in imported]
        assert not above, f"{module} imports {', '.join(above)}, which import it"
