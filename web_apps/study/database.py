"""A study's state in SQLite (the standard library's sqlite3, WAL journal, one transaction per event).

Tables (STUDY_DIR/study.sqlite):

    meta          key, value: the config the study started with (JSON), its token and operator key
    participants  number (by arrival, from 0), key (the secret in the participant's links), external_id (the
                  platform's id, unique), completion_code, started, finished
    slots         participant, practice (0/1), position, condition, kitchen, seed: the assignment
    stages        participant, stage (index into the visit's stages), kind, done: one row per stage done, in order
    answers       participant, stage, item, value: one row per answer (primary key: posted twice, stored once)
    games         id, participant, stage, attempt, practice, position, condition, kitchen, seed, seat, record (path
                  under STUDY_DIR), status (playing, finished, cut), reason, score, steps, sha256, started, ended

At most one game per participant is playing and at most one per stage is finished (unique indexes), so a second
tab cannot start a second game nor a game count twice; a game cut (a closed tab, an idle player, a server stopped
or killed) stays as a cut attempt and its stage is played again. Times are UTC, ISO 8601.
"""

from __future__ import annotations

import json
import math
import sqlite3
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from web_apps.study.assignment import COMPLETE, Slot

DATABASE = "study.sqlite"
PLAYING, FINISHED, CUT = "playing", "finished", "cut"
IN_PROGRESS, ABANDONED = "in progress", "abandoned"  # a participant's state, beside FINISHED
SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS participants (
    number INTEGER PRIMARY KEY, key TEXT NOT NULL UNIQUE, external_id TEXT UNIQUE, completion_code TEXT NOT NULL,
    started TEXT NOT NULL, finished TEXT, link TEXT, row INTEGER);
CREATE TABLE IF NOT EXISTS slots (
    participant INTEGER NOT NULL REFERENCES participants(number), practice INTEGER NOT NULL,
    position INTEGER NOT NULL, condition TEXT NOT NULL, kitchen TEXT NOT NULL, seed INTEGER NOT NULL,
    PRIMARY KEY (participant, practice, position));
CREATE TABLE IF NOT EXISTS stages (
    participant INTEGER NOT NULL REFERENCES participants(number), stage INTEGER NOT NULL, kind TEXT NOT NULL,
    done TEXT NOT NULL, PRIMARY KEY (participant, stage));
CREATE TABLE IF NOT EXISTS answers (
    participant INTEGER NOT NULL REFERENCES participants(number), stage INTEGER NOT NULL, item TEXT NOT NULL,
    value INTEGER NOT NULL, PRIMARY KEY (participant, stage, item));
CREATE TABLE IF NOT EXISTS games (
    id INTEGER PRIMARY KEY, participant INTEGER NOT NULL REFERENCES participants(number), stage INTEGER NOT NULL,
    attempt INTEGER NOT NULL, practice INTEGER NOT NULL, position INTEGER NOT NULL, condition TEXT NOT NULL,
    kitchen TEXT NOT NULL, seed INTEGER NOT NULL, seat INTEGER NOT NULL, record TEXT NOT NULL, status TEXT NOT NULL,
    reason TEXT, score INTEGER, steps INTEGER, sha256 TEXT, started TEXT NOT NULL, ended TEXT,
    UNIQUE (participant, stage, attempt));
CREATE UNIQUE INDEX IF NOT EXISTS one_game_playing ON games (participant) WHERE status = 'playing';
CREATE UNIQUE INDEX IF NOT EXISTS one_game_counted ON games (participant, stage) WHERE status = 'finished';
"""


class Refused(Exception):
    """A request the study does not take now (a stage out of order, a second game at once); one line, said to
    the participant."""


class StillPlaying(Refused):
    """A game asked for while another of the participant's games is playing (a second tab, or a reloaded tab's
    game not ended yet)."""


def now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


class StudyDatabase:
    """The study's database; every method is one transaction, safe from any thread."""

    def __init__(self, path: str | Path, create: bool = True):
        self.path = Path(path)
        if not create and not self.path.is_file():
            raise FileNotFoundError(f"no study database at {self.path}")
        self._connection = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._connection.row_factory = sqlite3.Row
        self._lock = threading.RLock()
        with self._lock:
            self._connection.execute("PRAGMA journal_mode=WAL")
            self._connection.execute("PRAGMA synchronous=FULL")  # a transaction done is on disk
            self._connection.execute("PRAGMA foreign_keys=ON")
            if create:
                self._connection.executescript(SCHEMA)
                columns = {row["name"] for row in self._connection.execute("PRAGMA table_info(participants)")}
                if "link" not in columns:  # a study database of before the link's parameters were kept
                    self._connection.execute("ALTER TABLE participants ADD COLUMN link TEXT")
                if "row" not in columns:  # before rows were chosen by those who finish: the arrival's number
                    self._connection.execute("ALTER TABLE participants ADD COLUMN row INTEGER")
                    self._connection.execute("UPDATE participants SET row = number")

    def close(self) -> None:
        self._connection.close()

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        with self._lock:
            self._connection.execute("BEGIN IMMEDIATE")
            try:
                yield self._connection
            except BaseException:
                self._connection.execute("ROLLBACK")
                raise
            self._connection.execute("COMMIT")

    def rows(self, query: str, *arguments) -> list[sqlite3.Row]:
        with self._lock:
            return self._connection.execute(query, arguments).fetchall()

    # ------------------------------------------------------------------------------------------- the study
    def meta(self, key: str) -> str | None:
        found = self.rows("SELECT value FROM meta WHERE key = ?", key)
        return found[0]["value"] if found else None

    def set_meta(self, values: dict[str, str]) -> None:
        with self.transaction() as db:
            db.executemany("INSERT OR REPLACE INTO meta VALUES (?, ?)", values.items())

    def config(self) -> dict:
        """The config the study started with."""
        stored = self.meta("config")
        if stored is None:
            raise FileNotFoundError(f"{self.path} holds no study (no config stored)")
        return json.loads(stored)

    def cut_playing(self, reason: str) -> int:
        """Marks every game still playing (its server stopped or killed mid-game) as cut; returns how many."""
        with self.transaction() as db:
            return db.execute("UPDATE games SET status = ?, reason = ?, ended = ? WHERE status = ?",
                              (CUT, reason, now(), PLAYING)).rowcount

    # ----------------------------------------------------------------------------------------- participants
    def register(self, external_id: str | None, key: str, code: str, slots_of, link: dict[str, str] | None = None,
                 rows: int = 1, abandon_after: float = math.inf) -> sqlite3.Row:
        """The participant of `external_id` (the platform's id); if new, made with `key`, `code`, the link's other
        parameters (`link`, kept as JSON), the row of the design's block of `rows` with the fewest participants
        finished or in progress (active within `abandon_after` seconds; the lowest such row), and the slots
        `slots_of(number, row)` gives. Without an id, always a new one."""
        with self.transaction() as db:
            if external_id is not None:
                found = db.execute("SELECT * FROM participants WHERE external_id = ?", (external_id,)).fetchone()
                if found is not None:
                    return found
            number = db.execute("SELECT COUNT(*) FROM participants").fetchone()[0]
            taken = [0] * rows
            for holder in self._row_states(db, abandon_after):
                if holder["state"] != ABANDONED and holder["row"] < rows:
                    taken[holder["row"]] += 1
            row = min(range(rows), key=lambda index: (taken[index], index))
            db.execute("INSERT INTO participants (number, key, external_id, completion_code, started, link, row) "
                       "VALUES (?, ?, ?, ?, ?, ?, ?)", (number, key, external_id, code, now(),
                                                        json.dumps(link) if link else None, row))
            db.executemany("INSERT INTO slots VALUES (?, ?, ?, ?, ?, ?)",
                           [(number, int(s.practice), s.position, s.condition, s.kitchen, s.seed)
                            for s in slots_of(number, row)])
            return db.execute("SELECT * FROM participants WHERE number = ?", (number,)).fetchone()

    @staticmethod
    def _row_states(db, abandon_after: float) -> list[sqlite3.Row]:
        """Every participant's row and state: finished, in progress (active within `abandon_after` seconds: its
        start, a stage done, a game started or ended) or abandoned."""
        cutoff = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(time.time() - min(abandon_after, 1e10)))
        return db.execute(
            "SELECT number, row, CASE WHEN finished IS NOT NULL THEN ? WHEN MAX(started, "
            "COALESCE((SELECT MAX(done) FROM stages WHERE participant = number), ''), "
            "COALESCE((SELECT MAX(COALESCE(ended, started)) FROM games WHERE participant = number), '')) >= ? "
            "THEN ? ELSE ? END AS state FROM participants ORDER BY number",
            (FINISHED, cutoff, IN_PROGRESS, ABANDONED)).fetchall()

    def participant(self, key: str) -> sqlite3.Row | None:
        found = self.rows("SELECT * FROM participants WHERE key = ?", key)
        return found[0] if found else None

    def slots(self, number: int) -> list[Slot]:
        return [Slot(row["position"], bool(row["practice"]), row["condition"], row["kitchen"], row["seed"])
                for row in self.rows("SELECT * FROM slots WHERE participant = ? ORDER BY practice DESC, position",
                                     number)]

    def stage(self, number: int) -> int:
        """The participant's stage now: the index of the first stage not done."""
        return self.rows("SELECT COUNT(*) AS done FROM stages WHERE participant = ?", number)[0]["done"]

    def complete_stage(self, number: int, stage: int, kind: str, next_kind: str,
                       answers: dict[str, int] | None = None) -> bool:
        """Marks `stage` done with its `answers`, in one transaction; False (and nothing written) if it was done
        already; Refused if it is not the participant's stage now."""
        with self.transaction() as db:
            return self._complete(db, number, stage, kind, next_kind, answers)

    def _complete(self, db, number, stage, kind, next_kind, answers=None) -> bool:
        current = db.execute("SELECT COUNT(*) FROM stages WHERE participant = ?", (number,)).fetchone()[0]
        if stage < current:
            return False
        if stage > current:
            raise Refused(f"stage {stage} is not yours yet: you are at stage {current}")
        db.execute("INSERT INTO stages VALUES (?, ?, ?, ?)", (number, stage, kind, now()))
        db.executemany("INSERT OR IGNORE INTO answers VALUES (?, ?, ?, ?)",
                       [(number, stage, item, value) for item, value in (answers or {}).items()])
        if next_kind == COMPLETE:
            db.execute("UPDATE participants SET finished = ? WHERE number = ?", (now(), number))
        return True

    # ---------------------------------------------------------------------------------------------- games
    def start_game(self, number: int, stage: int, slot: Slot, seat: int, record_of) -> tuple[int, str]:
        """A new attempt at the game of `stage` (its id and record path, `record_of(attempt)`); Refused where the
        stage is not the participant's now, StillPlaying where another of their games is playing (a second tab)."""
        with self.transaction() as db:
            current = db.execute("SELECT COUNT(*) FROM stages WHERE participant = ?", (number,)).fetchone()[0]
            if stage != current:
                raise Refused(f"stage {stage} is not yours now: you are at stage {current}")
            if db.execute("SELECT 1 FROM games WHERE participant = ? AND status = ?", (number, PLAYING)).fetchone():
                raise StillPlaying("your game is already being played in another tab or window: go on there, or "
                                   "close it and reload this page")
            attempt = db.execute("SELECT COUNT(*) FROM games WHERE participant = ? AND stage = ?",
                                 (number, stage)).fetchone()[0]
            record = record_of(attempt)
            cursor = db.execute(
                "INSERT INTO games (participant, stage, attempt, practice, position, condition, kitchen, seed, seat, "
                "record, status, started) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (number, stage, attempt, int(slot.practice), slot.position, slot.condition, slot.kitchen, slot.seed,
                 seat, record, PLAYING, now()))
            return cursor.lastrowid, record

    def end_game(self, game: int, reason: str, score: int, steps: int, sha256: str | None, kind: str,
                 next_kind: str) -> None:
        """Ends a game: finished (its stage done in the same transaction) or cut (its stage to be played again)."""
        with self.transaction() as db:
            row = db.execute("SELECT * FROM games WHERE id = ?", (game,)).fetchone()
            if row is None or row["status"] != PLAYING:
                return  # marked cut by a restart meanwhile
            status = FINISHED if reason == "finished" else CUT
            db.execute("UPDATE games SET status = ?, reason = ?, score = ?, steps = ?, sha256 = ?, ended = ? "
                       "WHERE id = ?", (status, reason, score, steps, sha256, now(), game))
            if status == FINISHED:
                self._complete(db, row["participant"], row["stage"], kind, next_kind)

    # ------------------------------------------------------------------------------------------- progress
    def progress(self, abandon_after: float = math.inf) -> dict:
        """Participants started and finished, games finished per condition and kitchen, games cut, playing now, and
        the design's rows by their participants' states (finished, in progress, abandoned)."""
        def one(query: str) -> int:
            return self.rows(query)[0][0]

        def per(column: str) -> dict[str, int]:
            return {row[0]: row[1] for row in self.rows(
                f"SELECT {column}, COUNT(*) FROM games WHERE status = 'finished' AND practice = 0 GROUP BY {column} "
                f"ORDER BY {column}")}

        return {
            "started": one("SELECT COUNT(*) FROM participants"),
            "consented": one("SELECT COUNT(DISTINCT participant) FROM stages WHERE kind = 'consent'"),
            "finished": one("SELECT COUNT(*) FROM participants WHERE finished IS NOT NULL"),
            "games_finished": one("SELECT COUNT(*) FROM games WHERE status = 'finished' AND practice = 0"),
            "practice_finished": one("SELECT COUNT(*) FROM games WHERE status = 'finished' AND practice = 1"),
            "games_cut": one("SELECT COUNT(*) FROM games WHERE status = 'cut'"),
            "playing": one("SELECT COUNT(*) FROM games WHERE status = 'playing'"),
            "answers": one("SELECT COUNT(*) FROM answers"),
            "per_condition": per("condition"),
            "per_kitchen": per("kitchen"),
            "rows": self.row_counts(abandon_after),
        }  # fmt: skip

    def row_counts(self, abandon_after: float = math.inf) -> dict[int, dict[str, int]]:
        """Per row of the design, its participants finished, in progress and abandoned."""
        with self._lock:
            states = self._row_states(self._connection, abandon_after)
        counts: dict[int, dict[str, int]] = {}
        for holder in states:
            row = counts.setdefault(holder["row"], {FINISHED: 0, IN_PROGRESS: 0, ABANDONED: 0})
            row[holder["state"]] += 1
        return dict(sorted(counts.items()))
