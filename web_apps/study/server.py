"""The study's web server: a participant's visit as stages, each written to the database as it is done.

    GET  /?token=T&<participant_param>=ID   registers the platform's participant ID (or finds them again) and sends
                                            them on to their own page, /p/<key>?token=T
    GET  /p/<key>                           the page of the participant's current stage (a reload resumes there)
    GET  /api/p/<key>                       {"stage", "kind", "label", "stages", "position" of a game or its
                                            questions, "asks" of questions (each answer's allowed values),
                                            "code" once complete}
    POST /api/p/<key>/stages/<stage>        consent ({"consent": true}), instructions ({}), questions ({"answers":
                                            {item: 1..len(scale), "forced_choice": the chosen game's position}})
    WS   /ws/p/<key>/stages/<stage>         a practice or assigned game, played as in kitchen-play
                                            (`web_apps.play.server.play_game`); its end completes the stage
    GET  /operator?token=T&key=K            progress (and /api/progress: the same as JSON), behind the operator key

Every request needs the study's token (kitchen-play's own check, `web_apps.play.server.guard`). A stage posted
before its turn, a game for a stage not the participant's now, or a second game while one is playing (a second
tab; a reloaded tab's last game is waited for a moment, as it ends at its next tick) is refused with one line; an
answer posted again once its stage is done is stored once and answered {"already": true}. A game that does not
finish (a closed or reloaded tab, an idle player, a server stopped or killed) is kept as a cut attempt and the stage
is played again from the start, with the same kitchen and seed.
"""

from __future__ import annotations

import asyncio
import json
import logging
import secrets
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

from web_apps.play.game import Game, Partner, file_sha256
from web_apps.play.server import guard, play_game
from web_apps.study.assignment import COMPLETE, CONSENT, PLAYED, QUESTIONS, Stage, assign, stages_of
from web_apps.study.config import FORCED_CHOICE, StudyConfig, StudyError, kitchen_of, partner_key, study_partners
from web_apps.study.database import DATABASE, Refused, StillPlaying, StudyDatabase
from web_apps.study.pages import allowed_answers, progress_page, stage_page, without_id_page

try:
    from fastapi import FastAPI, HTTPException, Request, WebSocket
    from fastapi.responses import HTMLResponse, RedirectResponse, Response
    from pydantic import BaseModel

    class StageDone(BaseModel):
        """What a page posts to complete its stage."""

        consent: bool | None = None
        answers: dict[str, int] | None = None
except ImportError:  # the play extra
    FastAPI = None

RECORDS = "records"
# A reloaded tab asks for its game again before the server has seen the old page's socket close (its game ends at
# its next tick): a game asked for while another of the participant's plays waits this long for it to end.
LEFT_GAME_S = 2.0
MAX_ID = 128  # characters of a platform's participant id
log = logging.getLogger("kitchen-study")


class StudyGame(Game):
    """A kitchen-play game that tells the study how it ended (finished or cut) as its record closes: before the
    page sees its last state, so that a reload never finds the stage still to play."""

    def __init__(self, *args, on_end, **kwargs):
        self.on_end = on_end
        super().__init__(*args, **kwargs)

    def end(self, reason: str) -> None:
        if self.recorder is None:
            return
        path = self.recorder.path
        super().end(reason)
        self.on_end(self, reason, path)


def open_study(config: StudyConfig, token: str | None = None) -> tuple[StudyDatabase, str, str]:
    """The study's database (made, or opened again with every game cut by a stop marked), its participants' token
    (`token`, else the one it started with, else a new one) and its operator key. A StudyError if its folder holds
    a study of another config."""
    folder = config.folder
    database_path = folder / DATABASE
    if database_path.is_file():
        database = StudyDatabase(database_path)
        stored = database.meta("assignment")
        if stored is not None and stored != config.assignment_key():
            database.close()
            raise StudyError(f"{folder} holds a study started with another config (its conditions, kitchens, games "
                             "or questions differ): restore that config, or give this one another name or out_dir")
    else:
        folder.mkdir(parents=True, exist_ok=True)
        database = StudyDatabase(database_path)
    token = token or database.meta("token") or secrets.token_urlsafe(16)
    operator = database.meta("operator") or secrets.token_urlsafe(16)
    database.set_meta({"config": json.dumps(config.to_dict()), "assignment": config.assignment_key(), "token": token,
                       "operator": operator})
    if cut := database.cut_playing("the server stopped mid-game"):
        log.info("%d game(s) cut by the last stop are marked and will be played again", cut)
    return database, token, operator


def study_game(config: StudyConfig, kitchen: str, seed: int, partner: Partner, record: Path, steps: int,
               kind: type[Game] = Game, **extra) -> Game:
    """A game of the study's in `kitchen` beside `partner`, recorded into `record`: a participant's (`StudyGame`)
    and the warm-up's are built alike, so that the warm-up compiles what the participants' games run."""
    return kind(kitchen_of(kitchen, seed), partner, config.seat, record, seed=seed, max_steps=steps,
                tick_ms=config.tick_ms, mode=config.pace, device=config.device, **extra)


def warm_up(config: StudyConfig, partners: dict[str, Partner]) -> tuple[int, float]:
    """One step of a game with every partner in every kitchen a participant can meet, at its game's length, into a
    throwaway record: the kitchens' programs compiled and the partners' first passes run before the first participant
    comes, whose first state then waits for neither (3 to 5 s otherwise). -> (games played, seconds)."""
    games = {(partner_key(spec, kitchen), kitchen, config.max_steps)
             for spec in config.conditions.values() for kitchen in config.kitchens}
    if config.practice_games:
        games.add((partner_key(config.practice_partner, config.practice_kitchen), config.practice_kitchen,
                   config.practice_steps))
    start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="kitchen-study-warm-up-") as folder:
        for index, (partner, kitchen, steps) in enumerate(sorted(games)):
            game = study_game(config, kitchen, config.seed, partners[partner], Path(folder) / f"{index}.jsonl",
                              steps)
            game.step(0)
            game.end("warm-up")
    return len(games), time.monotonic() - start


def create_study_app(config: StudyConfig, database: StudyDatabase, token: str, operator: str,
                     hosts: list[str] | None = None, partners: dict[str, Partner] | None = None) -> FastAPI:
    """The study's web app over its open `database` (see the module docstring); `partners`: the study's, as
    `study_partners(config)` loaded them (loaded here if not given)."""
    if FastAPI is None:
        raise ImportError("kitchen-study needs the play extra: pip install .[play]")
    app = FastAPI(title="kitchen-study")
    admits = guard(app, hosts, token)
    # Loaded once: a game starting beside others then costs a kitchen, not a checkpoint read (the participants'
    # first games start together, and each load held the ticking games back).
    visits = Visits(config, database, partners if partners is not None else study_partners(config))

    @app.get("/")
    def entry(request: Request) -> Response:
        external_id = request.query_params.get(config.participant_param)
        if external_id is None and not config.allow_without_id:  # nothing registered: no row taken
            return HTMLResponse(without_id_page(config), status_code=400)
        link = {name: request.query_params[name] for name in config.link_params if name in request.query_params}
        for value in (external_id, *link.values()):
            if value is not None and not 0 < len(value) <= MAX_ID:
                raise HTTPException(400, f"the link's parameters must be 1 to {MAX_ID} characters")
        code = (secrets.token_hex(4).upper() if config.completion_code == "random" else config.completion_code)
        participant = database.register(external_id, secrets.token_urlsafe(12), code,
                                        lambda number, row: assign(config, number, row), link, config.block_size,
                                        config.abandon_after)
        return RedirectResponse(f"/p/{participant['key']}?token={quote(token, safe='')}", status_code=303)

    @app.get("/p/{key}", response_class=HTMLResponse)
    def page(key: str) -> str:
        participant, stage, stages = visits.at(key)
        return stage_page(config, stage, stages, key, token, participant["completion_code"])

    @app.get("/api/p/{key}")
    def where(key: str) -> dict:
        return visits.where(key)

    @app.post("/api/p/{key}/stages/{index}")
    def complete(key: str, index: int, done: StageDone) -> dict:
        return visits.complete(key, index, done)

    @app.websocket("/ws/p/{key}/stages/{index}")
    async def play(websocket: WebSocket, key: str, index: int) -> None:
        if not admits(websocket):
            await websocket.close(code=1008)  # policy violation, before accepting
            return
        await websocket.accept()
        try:
            game = await visits.start_when_free(key, index)
        except (Refused, StudyError) as refused:
            await websocket.send_json({"type": "error", "reason": str(refused)})
            await websocket.close()
            return
        await play_game(websocket, f"{key[:6]}/{index}", game, config.pace, config.tick_ms, config.idle_s)

    add_operator_pages(app, config, database, operator)
    return app


def add_operator_pages(app: FastAPI, config: StudyConfig, database: StudyDatabase, operator: str) -> None:
    """The operator's progress page and its numbers, for the holder of the operator key alone."""

    def operator_only(key: str | None) -> None:
        if key is None or not secrets.compare_digest(key.encode(), operator.encode()):
            raise HTTPException(403, "the operator's page needs &key=<the operator key printed when the study "
                                     "started>")

    @app.get("/operator", response_class=HTMLResponse)
    def operator_page(key: str | None = None) -> str:
        operator_only(key)
        return progress_page(config.name, database.progress(config.abandon_after), config.target_participants)

    @app.get("/api/progress")
    def progress(key: str | None = None) -> dict:
        operator_only(key)
        return database.progress(config.abandon_after)


class Visits:
    """A participant's visit through the study's stages, over the study's `database`: where a participant is,
    completing a stage that is done by a post, and starting a stage's game beside its condition's partner."""

    def __init__(self, config: StudyConfig, database: StudyDatabase, partners: dict[str, Partner]):
        self.config, self.database, self.partners = config, database, partners

    def participant(self, key: str):
        participant = self.database.participant(key)
        if participant is None:
            raise HTTPException(404, "no such participant: open the study's link again")
        return participant

    def at(self, key: str) -> tuple[dict, Stage, list[Stage]]:
        """(participant, its current stage, all its stages)."""
        participant = self.participant(key)
        stages = stages_of(self.database.slots(participant["number"]))
        return participant, stages[min(self.database.stage(participant["number"]), len(stages) - 1)], stages

    def where(self, key: str) -> dict:
        participant, stage, stages = self.at(key)
        config = self.config
        return {"stage": stage.index, "kind": stage.kind, "label": stage.label, "stages": len(stages),
                **({"position": stage.slot.position} if stage.slot else {}),
                **({"asks": allowed_answers(config, stage)} if stage.kind == QUESTIONS else {}),
                **({"code": participant["completion_code"]} if stage.kind == COMPLETE else {})}

    def complete(self, key: str, index: int, done: StageDone) -> dict:
        """Stage `index` done by a post (consent, questions): stored once, refused out of turn or for a game."""
        participant = self.participant(key)
        number, stages = participant["number"], stages_of(self.database.slots(participant["number"]))
        current = self.database.stage(number)
        if not 0 <= index < len(stages):
            raise HTTPException(404, f"no stage {index}: the study has stages 0 to {len(stages) - 1}")
        if index < current:
            return {"already": True, "stage": current}  # a double post: stored once
        if index > current:
            raise HTTPException(409, f"stage {index} is not yours yet: you are at stage {current} "
                                     f"({stages[current].label})")
        stage = stages[index]
        answers = None
        if stage.kind == CONSENT and done.consent is not True:
            raise HTTPException(400, 'consent is given by posting {"consent": true}')
        if stage.kind in PLAYED:
            raise HTTPException(409, f"{stage.label} is done by playing it, not by a post")
        if stage.kind == COMPLETE:
            raise HTTPException(409, "the study is complete: nothing more to post")
        if stage.kind == QUESTIONS:
            answers = checked_answers(self.config, stage, done.answers)
        try:
            self.database.complete_stage(number, index, stage.kind, stages[index + 1].kind, answers)
        except Refused as refused:
            raise HTTPException(409, str(refused)) from None
        return {"stage": index + 1}

    async def start_when_free(self, key: str, index: int) -> StudyGame:
        """`start_game`, once the participant's game still playing (a reloaded tab's) has ended; StillPlaying if it
        goes on for `LEFT_GAME_S` plus a few ticks (a second tab)."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + LEFT_GAME_S + 3 * self.config.tick_ms / 1000
        while True:
            try:
                return await asyncio.to_thread(self.start_game, key, index)
            except StillPlaying:
                if loop.time() > deadline:
                    raise
                await asyncio.sleep(0.05)

    def start_game(self, key: str, index: int) -> StudyGame:
        """Stage `index`'s game (a new try of it), its end written to the database; Refused, or StudyError if it
        could not start."""
        config, database = self.config, self.database
        participant = database.participant(key)
        if participant is None:
            raise Refused("no such participant: open the study's link again")
        number, stages = participant["number"], stages_of(database.slots(participant["number"]))
        if not 0 <= index < len(stages) or stages[index].kind not in PLAYED:
            raise Refused(f"stage {index} is not a game")
        stage = stages[index]
        slot, after = stage.slot, stages[index + 1].kind
        game_id, record = database.start_game(number, index, slot, config.seat,
                                              lambda attempt: f"{RECORDS}/p{number:04d}-stage{index:02d}-"
                                                              f"try{attempt}.jsonl")

        def ended(game: Game, reason: str, path: Path) -> None:
            database.end_game(game_id, reason, game.score, game.t, file_sha256(path), stage.kind, after)
            log.info("participant %d %s ended (%s), score %d", number, stage.label, reason, game.score)

        try:
            partner = self.partners[partner_key(config.practice_partner if slot.practice
                                                else config.conditions[slot.condition], slot.kitchen)]
            return study_game(config, slot.kitchen, slot.seed, partner, config.folder / record,
                              config.practice_steps if slot.practice else config.max_steps, StudyGame, on_end=ended)
        except (StudyError, ValueError, OSError) as error:
            database.end_game(game_id, f"could not start: {error}", 0, 0, None, stage.kind, after)
            raise StudyError(f"the game could not start: {error}") from None


def checked_answers(config: StudyConfig, stage, answers: dict[str, int] | None) -> dict[str, int]:
    """The answers of a questions stage, each one of its allowed values (`allowed_answers`); an HTTPException (400)
    in one line otherwise."""
    allowed = allowed_answers(config, stage)
    answers = answers or {}
    if sorted(answers) != sorted(allowed):
        raise HTTPException(400, f"answer exactly {', '.join(allowed)}; got {', '.join(sorted(answers)) or 'none'}")
    for item, values in allowed.items():
        if answers[item] not in values:
            what = (f"the position of one of the last two games, {values[0]} or {values[1]}"
                    if item == FORCED_CHOICE else f"answered on {values[0]}..{values[-1]}")
            raise HTTPException(400, f"{item} is {what}; got {answers[item]}")
    return answers

