"""A study as a config: its conditions (partners), kitchens, games, pace, texts and questions, checked in one pass.

    name: main_vs_scripted
    seed: 0
    conditions:                      # condition -> its partner
      team: runs/main/seed0          # a run directory or checkpoint (`{kitchen}`: one per kitchen, e.g. proxies)
      cook: scripted_cook            # the scripted cook; `convention:NAME`: a convention of the shipped zoo
    kitchens: [cramped_room_7x7, coord_ring_7x7]
    games_per_participant: 4         # a multiple of the number of conditions
    likert: {scale: [disagree, neutral, agree], items: {helpful: My partner was helpful.}}

Every other key has a default (`StudyConfig`). `load_study` refuses a config no study can run (an unknown key, a
partner that cannot be loaded or cannot play a kitchen's size, an unknown kitchen, a bad Likert scale...) with a
one-line `StudyError` before anything is written.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from jax_env import Layout
from torch_kitchen.partners.conventions import ZOO_FILE, ConventionError, load_zoo
from torch_kitchen.partners.scripted_cook import scripted_actor_critic
from trainers.checkpoint import CheckpointError
from web_apps.play.game import RANDOM, SCRIPTED, Partner, check_fits, load_partner
from web_apps.study.design import latin_square

SCRIPTED_COOK = "scripted_cook"  # the partner names a config gives for kitchen-play's own partners
RANDOM_AGENT = "random_agent"
CONVENTION = "convention:"
PACES = ("realtime", "turns")
TEXTS = ("consent", "instructions", "practice", "questions", "complete")
FORCED_CHOICE = "forced_choice"  # the answer key of the forced choice between the last two partners


class StudyError(ValueError):
    """A study config that cannot run, or a study folder that does not hold one; the message says why."""


@dataclass
class Likert:
    """The questions after each game: every item is answered on `scale` (its labels, lowest first)."""

    scale: list[str] = field(default_factory=lambda: ["strongly disagree", "disagree", "neutral", "agree",
                                                      "strongly agree"])
    items: dict[str, str] = field(default_factory=lambda: {
        "helpful": "My partner was helpful.",
        "predictable": "I understood what my partner would do.",
        "trust": "I would trust this partner in a real kitchen.",
    })  # fmt: skip


DEFAULT_TEXTS = {
    "consent": "This study asks you to cook in a small kitchen game with computer partners, then to answer a few "
               "questions about each. It takes about 15 minutes. Your moves and answers are stored with a random "
               "identifier, not your name. You may stop at any time.",
    "instructions": "Arrows or WASD move your cook (outlined in black), space or E picks up and puts down. A soup is "
                    "3 onions in a pot; once it has cooked, bring a plate to the pot, then the soup to the serving "
                    "counter. Deliver as many soups as you can together with your partner.",
    "practice": "A practice game first: it does not count.",
    "questions": "About the partner you just played with:",
    "complete": "Thank you: you have finished the study.",
}


# Keys added after studies were first run: at their defaults they leave a running study's assignment key as it was.
LATER_KEYS = ("link_params", "allow_without_id", "abandon_after")


@dataclass
class StudyConfig:
    """A study: who plays with whom, where, for how long, and what they are asked."""

    name: str
    conditions: dict[str, str]  # condition -> partner: a run dir or checkpoint, scripted_cook, convention:NAME
    kitchens: list[str]  # kitchen-play's kitchen names: layouts, heldout_000..099, level files
    seed: int = 0  # draws each participant's kitchens and games' seeds
    games_per_participant: int = 0  # 0: one game per condition; else a multiple of the number of conditions
    practice_games: int = 1
    practice_partner: str = SCRIPTED_COOK
    practice_kitchen: str = "cramped_room_7x7"
    seat: int = 0  # the participant's seat (0: red, 1: blue)
    pace: str = "realtime"  # or "turns": the kitchen steps when the participant acts
    tick_ms: int = 150  # milliseconds per step in real time (150: the 2019 human games)
    max_steps: int = 400  # steps per assigned game
    practice_steps: int = 200  # steps per practice game
    idle_s: float = 120.0  # a turns-paced game without an action for this long ends, and is played again
    participant_param: str = "participant"  # the query parameter of the platform's participant id in the link
    # Further parameters of the link stored beside the id when present (Prolific's study and session).
    link_params: list[str] = field(default_factory=lambda: ["STUDY_ID", "SESSION_ID"])
    allow_without_id: bool = False  # a lab run: a visit without the id is a new participant (else it is refused)
    # A participant neither finished nor active (a stage done, a game started or ended) for this many seconds has
    # abandoned the study: the next arrival may take its row of the design.
    abandon_after: float = 1800.0
    completion_code: str = "random"  # the code shown at the end: one for all, or "random" (one per participant)
    completion_url: str = ""  # where the last page links to, "{code}" replaced (e.g. the platform's return link)
    target_participants: int = 0  # shown on the operator page (0: none set); whole blocks of the design
    primary: list[str] = field(default_factory=list)  # the contrast the study asks first, [a, b]: a - b (default: the
    # first two conditions); the report gives it first, uncorrected, and Holm-corrects the other pairs
    accept_unbalanced: bool = False  # a target_participants that fills no whole number of blocks is then taken
    out_dir: str = ""  # the study's folder ("" : studies/<name>)
    device: str = "cpu"
    texts: dict[str, str] = field(default_factory=dict)  # consent, instructions, practice, questions, complete
    likert: Likert = field(default_factory=Likert)
    forced_choice: str = "Which of your last two partners would you rather cook with again?"  # "": not asked

    @property
    def primary_contrast(self) -> tuple[str, str]:
        """(a, b) of the primary contrast a - b: `primary`, or the first two conditions."""
        names = self.primary or list(self.conditions)[:2]
        return (names[0], names[1]) if len(names) > 1 else (names[0], names[0])

    @property
    def folder(self) -> Path:
        return Path(self.out_dir or f"studies/{self.name}")

    @property
    def games(self) -> int:
        return self.games_per_participant or len(self.conditions)

    @property
    def block_size(self) -> int:
        """Rows (participants) in one block of the design: the conditions' square's rows times the kitchens."""
        return len(latin_square(len(self.conditions))) * len(self.kitchens)

    def text(self, name: str) -> str:
        return self.texts.get(name, DEFAULT_TEXTS[name])

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def assignment_key(self) -> str:
        """What a running study's assignment, games and questions depend on (all but its texts and where it
        runs): a study restarted with another is refused."""
        defaults = StudyConfig(name="", conditions={}, kitchens=[]).to_dict()
        kept = {key: value for key, value in self.to_dict().items()
                if key not in ("texts", "out_dir", "device", "completion_url", "target_participants", "primary",
                               "accept_unbalanced")
                and not (key in LATER_KEYS and value == defaults[key])}  # a study of before them restarts
        return json.dumps(kept, sort_keys=True)


def config_from_dict(values: dict, where: str = "the study config") -> StudyConfig:
    """A `StudyConfig` of a mapping, its keys and types checked (not its partners and kitchens: `load_study`)."""
    if not isinstance(values, dict):
        raise StudyError(f"{where} is not a mapping of keys (see docs/study.md)")
    known = {f.name for f in dataclasses.fields(StudyConfig)}
    if unknown := sorted(set(values) - known):
        raise StudyError(f"{where}: unknown key {', '.join(map(repr, unknown))}; keys: {', '.join(sorted(known))}")
    if missing := [key for key in ("name", "conditions", "kitchens") if key not in values]:
        raise StudyError(f"{where}: missing {', '.join(missing)} (a study names its conditions and kitchens)")
    values = dict(values)
    likert = values.pop("likert", None)
    try:
        config = StudyConfig(**values, likert=likert_of(likert, where))
    except TypeError as error:
        raise StudyError(f"{where}: {error}") from None
    check_values(config, where)
    return config


def likert_of(values, where: str) -> Likert:
    if values is None:
        return Likert()
    if not isinstance(values, dict) or set(values) - {"scale", "items"}:
        raise StudyError(f"{where}: likert takes scale (a list of labels, lowest first) and items (key: statement)")
    likert = Likert(**values)
    scale = likert.scale
    if (not isinstance(scale, list) or not 2 <= len(scale) <= 11 or not all(isinstance(s, str) and s for s in scale)
            or len(set(scale)) != len(scale)):
        raise StudyError(f"{where}: likert scale must be 2 to 11 distinct labels, lowest first, got {scale!r}")
    items = likert.items
    if not isinstance(items, dict) or not all(isinstance(k, str) and k.isidentifier() and isinstance(v, str) and v
                                              for k, v in items.items()):
        raise StudyError(f"{where}: likert items must map a key (a name: letters, digits, _) to its statement")
    if FORCED_CHOICE in items:
        raise StudyError(f"{where}: likert item {FORCED_CHOICE!r} is the forced choice's key; name the item otherwise")
    return likert


def check_values(config: StudyConfig, where: str) -> None:
    def fail(message: str):
        raise StudyError(f"{where}: {message}")

    if not isinstance(config.name, str) or not config.name or "/" in config.name:
        fail(f"name must be a word for the study's folder, got {config.name!r}")
    if not isinstance(config.conditions, dict) or not config.conditions:
        fail("conditions must map each condition's name to its partner (a run directory, scripted_cook, ...)")
    if not all(isinstance(partner, str) and partner for partner in config.conditions.values()):
        fail("each condition's partner must be one string: a run directory, checkpoint, scripted_cook or "
             "convention:NAME")
    if not isinstance(config.kitchens, list) or not config.kitchens or not all(isinstance(k, str) for k in
                                                                               config.kitchens):
        fail("kitchens must be a list of kitchen names (e.g. [cramped_room_7x7, heldout_003])")
    for key in ("seed", "games_per_participant", "practice_games", "target_participants"):
        if not isinstance(getattr(config, key), int) or getattr(config, key) < 0:
            fail(f"{key} must be a whole number >= 0, got {getattr(config, key)!r}")
    for key in ("tick_ms", "max_steps", "practice_steps"):
        if not isinstance(getattr(config, key), int) or getattr(config, key) <= 0:
            fail(f"{key} must be a positive whole number, got {getattr(config, key)!r}")
    if not isinstance(config.abandon_after, int | float) or config.abandon_after <= 0:
        fail(f"abandon_after must be a positive number of seconds, got {config.abandon_after!r}")
    if not isinstance(config.idle_s, int | float) or config.idle_s <= 0:
        fail(f"idle_s must be a positive number of seconds, got {config.idle_s!r}")
    if config.games % len(config.conditions):
        fail(f"games_per_participant ({config.games}) must be a multiple of the {len(config.conditions)} conditions, "
             "so that every participant plays each as often")
    if config.seat not in (0, 1):
        fail(f"seat must be 0 or 1, got {config.seat!r}")
    if config.pace not in PACES:
        fail(f"pace must be one of {', '.join(PACES)}, got {config.pace!r}")
    if not isinstance(config.texts, dict) or (unknown := sorted(set(config.texts) - set(TEXTS))):
        fail(f"texts takes {', '.join(TEXTS)}" + (f", not {', '.join(map(repr, unknown))}"
                                                   if isinstance(config.texts, dict) else ""))
    if not all(isinstance(text, str) for text in config.texts.values()):
        fail("each of texts is one string (YAML's | keeps its paragraphs)")
    if not isinstance(config.completion_code, str) or not config.completion_code:
        fail("completion_code must be a code for the platform, or random")
    if not isinstance(config.participant_param, str) or not config.participant_param.isidentifier():
        fail(f"participant_param must be a query parameter's name, got {config.participant_param!r}")
    if not isinstance(config.forced_choice, str):
        fail("forced_choice must be its question, or empty to ask none")
    if not isinstance(config.link_params, list) or not all(isinstance(p, str) and p.isidentifier()
                                                           for p in config.link_params):
        fail(f"link_params must be a list of query parameters' names, got {config.link_params!r}")
    if not isinstance(config.allow_without_id, bool):
        fail(f"allow_without_id must be true or false, got {config.allow_without_id!r}")
    if config.primary and (not isinstance(config.primary, list) or len(config.primary) != 2
                           or len(set(config.primary)) != 2 or not set(config.primary) <= set(config.conditions)):
        fail(f"primary must name two of the conditions ({', '.join(config.conditions)}), got {config.primary!r}")
    check_balance(config, fail)


def check_balance(config: StudyConfig, fail) -> None:
    """Refuses a target of participants that fills no whole number of the design's blocks (its counts would not
    balance), naming the nearest targets that do, unless the config accepts an unbalanced design."""
    block = config.block_size
    target = config.target_participants
    if not isinstance(config.accept_unbalanced, bool):
        fail(f"accept_unbalanced must be true or false, got {config.accept_unbalanced!r}")
    if target and target % block and not config.accept_unbalanced:
        lower, upper = target // block * block, (target // block + 1) * block
        fail(f"target_participants={target} fills no whole number of the design's blocks of {block} participants "
             f"({len(config.conditions)} conditions' rows x {len(config.kitchens)} kitchens), so conditions, "
             f"kitchens and positions would not balance: take {' or '.join(map(str, filter(None, (lower, upper))))}, "
             "or set accept_unbalanced: true")


def partner_key(spec: str, kitchen: str) -> str:
    """The partner a condition's `spec` names in `kitchen`: one per run (a `{kitchen}` in its path resolved)."""
    return spec.replace("{kitchen}", kitchen)


def partner_of(spec: str, kitchen: str, device: str = "cpu") -> Partner:
    """The partner a condition names, for `kitchen` (a `{kitchen}` in a run's path is that kitchen's name); a
    StudyError says why one cannot be loaded."""
    if spec == SCRIPTED_COOK:
        return load_partner(SCRIPTED)
    if spec == RANDOM_AGENT:
        return load_partner(RANDOM)
    if spec.startswith(CONVENTION):
        name = spec.removeprefix(CONVENTION)
        try:
            convention = load_zoo(ZOO_FILE).convention(name, splits=("train", "stranger"))
        except ConventionError as error:
            raise StudyError(f"partner {spec!r}: {error}") from None
        return Partner(name, scripted_actor_critic(convention))
    path = partner_key(spec, kitchen)
    try:
        return load_partner(path, device)
    except CheckpointError as error:
        raise StudyError(f"partner {path!r}: {error}") from None


def kitchen_of(name: str, seed: int) -> Layout:
    """The layout of a kitchen name, as kitchen-play's lobby builds it; a StudyError names the choices."""
    from web_apps.play.server import make_kitchen  # the web server's module, imported only where games are made

    try:
        return make_kitchen(name, [name] if name.endswith((".txt", ".layout")) else [], seed)
    except (ValueError, OSError) as error:
        raise StudyError(str(error)) from None


def study_partners(config: StudyConfig) -> dict[str, Partner]:
    """Every partner of the study, loaded once (`partner_key` -> Partner) and checked to fit each kitchen it plays:
    every condition's in every kitchen, the practice partner in its own (StudyError). The server's games share
    them: networks hold no state between steps (an LSTM's or E3T's lives in each game's env)."""
    pairs = [(f"condition {name!r}", spec, kitchen) for name, spec in config.conditions.items()
             for kitchen in config.kitchens]
    if config.practice_games:
        pairs.append(("the practice", config.practice_partner, config.practice_kitchen))
    layouts, partners = {}, {}
    for who, spec, kitchen in pairs:
        if kitchen not in layouts:
            layouts[kitchen] = kitchen_of(kitchen, config.seed)
        key = partner_key(spec, kitchen)
        try:
            if key not in partners:
                partners[key] = partner_of(spec, kitchen, config.device)
            check_fits(partners[key], layouts[kitchen])
        except (StudyError, ValueError) as error:
            raise StudyError(f"{who}: {error}") from None
    return partners


def load_study(path: str | Path, check: bool = True) -> StudyConfig:
    """The study of a YAML file, checked (with `check`, its partners loaded on its kitchens too)."""
    path = Path(path)
    if not path.is_file():
        raise StudyError(f"no study config at {path} (configs/study/example.yaml is one)")
    try:
        values = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as error:
        raise StudyError(f"{path} is not YAML ({str(error).splitlines()[0]})") from None
    config = config_from_dict(values, str(path))
    if check:
        try:
            study_partners(config)
        except StudyError as error:
            raise StudyError(f"{path}: {error}") from None
    return config
