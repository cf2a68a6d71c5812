"""What the README and the docs/ pages name exists: every `kitchen-*` command is a console script of setup.cfg,
every `make` target and variable is the Makefile's, every path of the repository they name is there, every link
resolves (its #anchor a heading of the page), and every `key=value` given to `kitchen-train`, `kitchen-distill`,
`kitchen-sweep`, `kitchen-eval` or `scripts/reproduce.py` names a config key (`trainers.config`), a config group's
choice (`trainers.config.compose.GROUPS`) or a setting of the algorithm it trains (`trainers.algorithms`).

Commands are read from code: fenced blocks (a line, with its `\\` continuations, is a command line) and inline
code spans. A failure names the page, the line and what is unknown. Nothing trains; the pages are only read.
"""

import configparser
import dataclasses
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

from torch_kitchen.models import ARCHITECTURES, E3T_ARCHITECTURES
from trainers.algorithms import ALGORITHMS
from trainers.config import EvalConfig, TrainConfig, is_config_key
from trainers.config.compose import GROUPS, compose, group_choices

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
# The repository's own folders: a path that starts with one of them is checked to exist.
TOP_FOLDERS = ("jax_env", "torch_kitchen", "trainers", "scripts", "benchmarks", "examples", "configs", "tests", "docs")
PATH = re.compile(rf"(?<![\w./-])((?:{'|'.join(TOP_FOLDERS)})/[\w./-]*)")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
INLINE_CODE = re.compile(r"`([^`]+)`")
COMMAND_NAME = re.compile(r"(?<![\w-])kitchen-[a-z][a-z-]*")
# The commands whose key=value arguments are config overrides, with the schema they override.
SCHEMAS = {"kitchen-train": TrainConfig, "kitchen-distill": TrainConfig, "kitchen-sweep": TrainConfig,
           "scripts/reproduce.py": TrainConfig, "kitchen-eval": EvalConfig}
SEPARATORS = {";", "&&", "||", "|"}
GENERIC_OVERRIDE = "key=value"  # the form of an override in prose, not a key


@dataclass(frozen=True)
class Code:
    """A piece of code on a page: one command line of a fenced block or one inline span."""

    page: str
    line: int
    text: str
    language: str  # the fenced block's language ("bash", "python", ""), "inline" for a span


def page_name(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def code_of(name: str, text: str) -> list[Code]:
    """The fenced blocks' lines (with `\\` continuations joined) and the inline spans of a page's `text`."""
    pieces, prose, fence, pending = [], [], None, None
    for number, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fence = line.strip().removeprefix("```").strip() if fence is None else None
            prose.append("")
            continue
        if fence is None:
            prose.append(line)
            continue
        prose.append("")
        start, joined = pending or (number, "")
        joined += " " + line.strip().removesuffix("\\")
        pending = (start, joined) if line.rstrip().endswith("\\") else None
        if pending is None:
            pieces.append(Code(name, start, joined.strip(), fence))
    body = "\n".join(prose)
    for match in INLINE_CODE.finditer(body):
        pieces.append(Code(name, body.count("\n", 0, match.start()) + 1, " ".join(match.group(1).split()), "inline"))
    return pieces


def tokens_of(code: Code) -> list[str]:
    try:
        return shlex.split(code.text, comments=True)
    except ValueError:  # an unbalanced quote in prose-like code
        return code.text.split()


def commands_of(code: Code) -> list[tuple[str, list[str]]]:
    """The commands of a piece of shell code: (the command, e.g. kitchen-train, make or scripts/reproduce.py, its
    arguments up to the next command or separator). Python blocks hold no commands."""
    if code.language == "python":
        return []
    tokens, commands = tokens_of(code), []
    for index, token in enumerate(tokens):
        name = token.rsplit("/", 1)[-1] if "kitchen-" in token else token
        if COMMAND_NAME.fullmatch(name) or name == "make":
            command = name
        elif name in ("python", "python3") or token.endswith("/python"):
            if index + 1 >= len(tokens) or not tokens[index + 1].endswith(".py"):
                continue
            command, index = tokens[index + 1], index + 1
        else:
            continue
        arguments = []
        for argument in tokens[index + 1:]:
            if argument in SEPARATORS or argument.rstrip(";") != argument or COMMAND_NAME.fullmatch(argument):
                break
            arguments.append(argument)
        commands.append((command, arguments))
    return commands


def entry_points() -> dict[str, str]:
    """setup.cfg's console scripts: name -> "module:function"."""
    parser = configparser.ConfigParser()
    parser.read(ROOT / "setup.cfg")
    entries = parser.get("options.entry_points", "console_scripts", fallback="")
    return {name.strip(): target.strip() for name, _, target in
            (line.partition("=") for line in entries.splitlines() if "=" in line)}


def console_scripts() -> set[str]:
    return set(entry_points())


def makefile() -> tuple[set[str], set[str]]:
    """The Makefile's targets and variables."""
    text = (ROOT / "Makefile").read_text()
    targets = set(re.findall(r"^([A-Za-z][\w-]*)\s*:(?!=)", text, re.MULTILINE))
    variables = set(re.findall(r"^([A-Za-z_]\w*)\s*[?:+]?=", text, re.MULTILINE))
    return targets, variables


# ------------------------------------------------------------------------------------------ the checks
def command_problems(name: str, text: str) -> list[str]:
    """Every `kitchen-*` in code that is not a console script, every `make` target or variable the Makefile lacks."""
    scripts, (targets, variables), problems = console_scripts(), makefile(), []
    for code in code_of(name, text):
        for command in COMMAND_NAME.findall(code.text):
            if command not in scripts:
                problems.append(f"{code.page}:{code.line}: {command} is not a console script of setup.cfg "
                                f"({', '.join(sorted(scripts))})")
        for command, arguments in commands_of(code):
            if command != "make":
                continue
            for argument in arguments:
                if argument.startswith("-"):
                    continue
                variable, is_variable, _ = argument.partition("=")
                if is_variable and variable not in variables:
                    problems.append(f"{code.page}:{code.line}: make {argument}: the Makefile has no variable "
                                    f"{variable}")
                elif not is_variable and argument not in targets:
                    problems.append(f"{code.page}:{code.line}: make {argument}: the Makefile has no target "
                                    f"{argument} ({', '.join(sorted(targets))})")
    return problems


def path_problems(name: str, text: str) -> list[str]:
    """Every path under one of the repository's folders that is not there (globs and <placeholders> skipped)."""
    problems = []
    for number, line in enumerate(text.splitlines(), 1):
        for match in PATH.finditer(line):
            if line[match.end():match.end() + 1] in ("{", "<", "*", "[", "$"):
                continue
            path = match.group(1).rstrip(".")
            if not (ROOT / path).exists():
                problems.append(f"{name}:{number}: {path} does not exist")
    return problems


def slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set[str]:
    found, fenced = set(), False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced and re.match(r"#{1,6} ", line):
            found.add(slug(line.lstrip("#")))
    return found


def link_problems(path: Path, text: str) -> list[str]:
    """Every relative link (an image too) whose file is missing, or whose #anchor is no heading of its page."""
    problems, name = [], page_name(path)
    for number, line in enumerate(text.splitlines(), 1):
        for target in LINK.findall(line):
            if re.match(r"[a-z]+:", target):
                continue
            file, _, anchor = target.partition("#")
            linked = (path.parent / file).resolve() if file else path
            if not linked.exists():
                problems.append(f"{name}:{number}: the link {target} leads nowhere ({linked} does not exist)")
            elif anchor and anchor not in anchors(linked.read_text() if linked != path else text):
                problems.append(f"{name}:{number}: the link {target}: {file or name} has no heading #{anchor}")
    return problems


def algorithm_of(command: str, arguments: list[str]) -> list[str] | None:
    """The algorithms a command trains: those named by `algorithm=` (a sweep's, comma-separated), else its config
    file's; None when neither says (a resumed run)."""
    named = [argument.partition("=")[2] for argument in arguments if argument.startswith("algorithm=")]
    if named:
        return named[-1].split(",") if command == "kitchen-sweep" else [named[-1]]
    files = [argument for argument in arguments if argument.endswith(".yaml") and (ROOT / argument).is_file()]
    if files and command != "scripts/reproduce.py":
        return [compose(ROOT / files[0]).get("algorithm", TrainConfig.algorithm)]
    return None


def override_problems(name: str, text: str) -> list[str]:
    """Every `key=value` given to a command that reads a config whose key is no key of that config, no choice of a
    config group, or no setting of the algorithm the command trains (a module of `--import` may add the last)."""
    problems = []
    for code in code_of(name, text):
        for command, arguments in commands_of(code):
            schema = SCHEMAS.get(command)
            if schema is None:
                continue
            plugins = "--import" in arguments
            for argument in arguments:
                key, is_override, value = argument.partition("=")
                key = key.removeprefix("+")
                if argument.startswith("-") or not is_override or argument == GENERIC_OVERRIDE:
                    continue
                if command == "kitchen-sweep" and (key == "hydra" or key.startswith(("hydra.", "hydra/"))):
                    continue  # Hydra's own keys (launchers): Hydra checks them
                where = f"{code.page}:{code.line}: {command} {argument}"
                values = value.split(",") if command == "kitchen-sweep" else [value]
                problem = key_problem(schema, command, arguments, key, values, plugins)
                if problem:
                    problems.append(f"{where}: {problem}")
    return problems


def key_problem(schema: type, command: str, arguments: list[str], key: str, values: list[str],
                plugins: bool) -> str | None:
    """What is wrong with `key=values` for `command` (None: nothing)."""
    if key.startswith("algorithm_config."):
        if schema is not TrainConfig:
            return f"{schema.__name__} has no algorithm_config section"
        setting, trained = key.removeprefix("algorithm_config."), algorithm_of(command, arguments)
        candidates = trained or list(ALGORITHMS)
        settings = {algorithm: {field.name for field in dataclasses.fields(ALGORITHMS[algorithm].Settings)}
                    for algorithm in candidates if algorithm in ALGORITHMS}
        if plugins and len(settings) < len(candidates):
            return None  # an algorithm of an imported module: its settings are its own
        if trained is None:  # a resumed run: a setting of some registered algorithm
            found = any(setting in names for names in settings.values())
            return None if found else f"unknown algorithm setting {setting!r}: no registered algorithm has it"
        for algorithm in trained:
            if setting not in settings.get(algorithm, set()):
                return (f"unknown algorithm setting {setting!r} of {algorithm}: its settings are "
                        f"{', '.join(sorted(settings.get(algorithm, ()))) or '(none)'}")
        return None
    if key in GROUPS and not (schema is EvalConfig and key != "runtime"):
        choices = set(group_choices(key))
        if key == "algorithm":
            choices |= set(ALGORITHMS)
        if key == "architecture":
            choices |= {*ARCHITECTURES, *E3T_ARCHITECTURES}
        unknown = [value for value in values if value not in choices]
        if unknown and not (plugins and key in ("algorithm", "architecture")):
            return f"{key}={unknown[0]} is not one of {', '.join(sorted(choices))}"
        return None
    if not is_config_key(schema, key):
        return f"unknown config key {key!r} of {schema.__name__}"
    return None


# ------------------------------------------------------------------------------------------ the tests
def all_problems(check) -> list[str]:
    return [problem for path in PAGES for problem in check(page_name(path), path.read_text())]


def test_the_readme_links_every_page():
    readme = (ROOT / "README.md").read_text()
    assert len(PAGES) > 1, "docs/*.md: the manual's pages are missing"
    for path in PAGES[1:]:
        assert f"({page_name(path)})" in readme, f"README.md does not link {page_name(path)}"


def test_every_command_is_a_console_script_or_make_target():
    problems = all_problems(command_problems)
    assert not problems, "\n".join(problems)


def test_every_named_path_exists():
    problems = all_problems(path_problems)
    assert not problems, "\n".join(problems)


def test_every_link_resolves():
    problems = [problem for path in PAGES for problem in link_problems(path, path.read_text())]
    assert not problems, "\n".join(problems)


def test_every_override_names_a_config_key():
    problems = all_problems(override_problems)
    assert not problems, "\n".join(problems)


def test_the_checks_find_what_is_wrong():
    text = "\n".join([
        "Train:",
        "",
        "```bash",
        "kitchen-train configs/ippo/mlp_ik.yaml ppo.lr=1e-3 learning_rate=1e-3",
        "kitchen-sweep configs/ippo/mlp_ik.yaml regime=ik,sk_nowhere hydra/launcher=joblib \\",
        "    runtime.threads=2 runtime.thread=2",
        "kitchen-train configs/e3t/mlp_ik.yaml algorithm_config.partner_epsilon=0.5 algorithm_config.anchor_coef=1",
        "kitchen-eval configs/eval/paper.yaml rollouts=5 total_steps=5",
        "make main DEVICE=cuda && make everything",
        "```",
        "",
        "Or `kitchen-trian configs/ippo/mlp_ik.yaml` from `configs/ippo/nothing.yaml`, see [it](nowhere.md).",
    ])
    problems = override_problems("page.md", text)
    assert problems == [
        "page.md:4: kitchen-train learning_rate=1e-3: unknown config key 'learning_rate' of TrainConfig",
        "page.md:5: kitchen-sweep regime=ik,sk_nowhere: regime=sk_nowhere is not one of "
        f"{', '.join(sorted(group_choices('regime')))}",
        "page.md:5: kitchen-sweep runtime.thread=2: unknown config key 'runtime.thread' of TrainConfig",
        "page.md:7: kitchen-train algorithm_config.anchor_coef=1: unknown algorithm setting 'anchor_coef' of e3t: "
        "its settings are partner_copy_rate, partner_epsilon, partner_policy, predictor_coef",
        "page.md:8: kitchen-eval total_steps=5: unknown config key 'total_steps' of EvalConfig",
    ]
    commands = command_problems("page.md", text)
    assert len(commands) == 2
    assert commands[0].startswith("page.md:9: make everything: the Makefile has no target everything")
    assert commands[1].startswith("page.md:12: kitchen-trian is not a console script")
    assert path_problems("page.md", text) == ["page.md:12: configs/ippo/nothing.yaml does not exist"]
    page = ROOT / "docs" / "page.md"
    assert link_problems(page, text) == [
        f"docs/page.md:12: the link nowhere.md leads nowhere ({ROOT / 'docs' / 'nowhere.md'} does not exist)"]


def test_the_pages_small_python_snippets_run_as_written():
    """The JAX kitchen's snippet and the TorchRL-only training loop: whole programs a reader pastes (the pages'
    other snippets train at full size or read runs of one's own)."""
    for page, marker in [("docs/environment.md", "import jax, jax.numpy as jnp"),
                         ("docs/environment.md", "append_transform(AgentDones())")]:
        snippets = [code for code in re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)
                    if marker in code]
        assert len(snippets) == 1, page
        exec(compile(snippets[0], page, "exec"), {})  # a NameError or any failure fails the test
