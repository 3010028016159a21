"""A durable label store: every preference label, with its two segments, who gave it and when.

Storage is SQLite in write-ahead-log mode with ``synchronous=FULL``:

- a label is *acknowledged* when :meth:`LabelStore.add` returns, which is after its transaction
  committed and was synced to disk; a process killed at any moment afterwards loses nothing,
  and one killed mid-write leaves the store as it was before that write (atomic commit);
- one file, in Python's standard library, readable by any SQLite tool, safe for concurrent
  readers (a dashboard, another run) while a run writes;
- label sets move between runs and methods as plain SQLite files (:meth:`export_to`,
  :meth:`import_from`), so SA-RL and PA-AD can learn from exactly the labels RAT used.

Segments are stored as little-endian float32 blobs with their shapes. Labels follow the one
convention of :mod:`rat.preferences.teacher`: ``label`` = P[σ¹ ≻ σ⁰].

Queries a person answers one at a time (:mod:`rat.labelling`) live in the same file: a run
*publishes* a round's queries, each answer is one transaction that logs it in ``answers`` (in
the order given; undo withdraws the latest) and, unless it is a skip, copies the query's segments
into ``labels``; the run *closes* the round when every query is answered. A query has at most
one answer (a unique key, so a repeated answer cannot be stored twice), and a closed round takes
no answers and no undos.
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from rat.errors import RatError
from rat.preferences.segments import SegmentPairs

SCHEMA_VERSION = 2
CHOICES = {"left": 0.0, "right": 1.0, "equal": 0.5, "skip": None}  #: a person's answers, as labels (skip: none)

_SCHEMA = """
CREATE TABLE IF NOT EXISTS store_info (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS labels (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    created_at  TEXT    NOT NULL,   -- ISO 8601, UTC
    source      TEXT    NOT NULL,   -- the run (or person) that asked
    round       INTEGER,            -- the query round of that run
    task        TEXT,
    target      TEXT,
    labeller    TEXT    NOT NULL,   -- JSON: {"type": "scripted", beta, gamma, ...} or {"type": "human", ...}
    label       REAL    NOT NULL,   -- P[second segment preferred]: 1, 0 or 0.5
    length      INTEGER NOT NULL,
    obs_dim     INTEGER NOT NULL,
    act_dim     INTEGER NOT NULL,
    obs0 BLOB NOT NULL, act0 BLOB NOT NULL, reward0 BLOB NOT NULL,
    obs1 BLOB NOT NULL, act1 BLOB NOT NULL, reward1 BLOB NOT NULL,
    imported_from TEXT,
    query_id    INTEGER,            -- the published query it answers (labels given one at a time)
    duration_s  REAL                -- how long the labeller took (people), seconds
);
CREATE TABLE IF NOT EXISTS rounds (
    source   TEXT    NOT NULL,
    round    INTEGER NOT NULL,
    step     INTEGER NOT NULL,      -- environment step of the round
    asked    INTEGER NOT NULL,      -- queries counted against the budget
    answered INTEGER NOT NULL,      -- labels obtained (a teacher may skip queries)
    created_at TEXT NOT NULL,
    PRIMARY KEY (source, round)
);
CREATE INDEX IF NOT EXISTS labels_by_source ON labels (source, round);
"""

# Schema 2: queries published for people, answered one at a time.
_QUERIES = """
CREATE TABLE IF NOT EXISTS queries (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    created_at  TEXT    NOT NULL,
    source      TEXT    NOT NULL,
    round       INTEGER NOT NULL,
    position    INTEGER NOT NULL,   -- index of the query in its round
    step        INTEGER NOT NULL,
    task        TEXT,
    target      TEXT,
    length      INTEGER NOT NULL,
    obs_dim     INTEGER NOT NULL,
    act_dim     INTEGER NOT NULL,
    obs0 BLOB NOT NULL, act0 BLOB NOT NULL, reward0 BLOB NOT NULL,
    obs1 BLOB NOT NULL, act1 BLOB NOT NULL, reward1 BLOB NOT NULL,
    physics     TEXT,               -- JSON shapes of the physics blobs below, when the run recorded them
    states0 BLOB, states1 BLOB,     -- float64 physics state of every step (rat.envs.physics), to film the
    scene0 BLOB, scene1 BLOB,       -- segments; and the scene of each segment's episode
    video0      TEXT,               -- file names, relative to the store's directory
    video1      TEXT,
    closed      INTEGER NOT NULL DEFAULT 0,
    UNIQUE (source, round, position)
);
CREATE TABLE IF NOT EXISTS answers (   -- every answer to a published query, in the order given
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    query_id    INTEGER NOT NULL UNIQUE,
    choice      TEXT    NOT NULL,   -- left, right, equal or skip (a label row holds the first three too)
    labeller    TEXT    NOT NULL,
    created_at  TEXT    NOT NULL,
    duration_s  REAL
);
CREATE UNIQUE INDEX IF NOT EXISTS labels_by_query ON labels (query_id);
"""


def _where(source: str | None, before_round: int | None, ids: list[int] | None = None) -> tuple[str, list]:
    """The WHERE clause (and its arguments) choosing labels of one ``source``, of rounds before ``before_round``
    (with the labels of no round, imported ones), with given ``ids``; empty when none is given."""
    clauses, args = [], []
    if source is not None:
        clauses.append("source=?")
        args.append(source)
    if before_round is not None:
        clauses.append("(round IS NULL OR round < ?)")
        args.append(int(before_round))
    if ids is not None:
        clauses.append(f"id IN ({','.join('?' * len(ids))})")
        args.extend(int(i) for i in ids)
    return (" WHERE " + " AND ".join(clauses) if clauses else ""), args


class AnswerError(RatError):
    """An answer the store refuses; ``status`` is the HTTP status that says why (404, 409, 422)."""

    def __init__(self, message: str, status: int):
        super().__init__(message)
        self.status = status


def _blob(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f4").tobytes()


def _segments(rows: list[dict]) -> SegmentPairs:
    """The segment pairs stored in rows of ``labels`` or ``queries`` (their blobs are popped from the rows)."""
    L, d, a = rows[0]["length"], rows[0]["obs_dim"], rows[0]["act_dim"]
    shapes = {"obs0": (L, d), "act0": (L, a), "reward0": (L,), "obs1": (L, d), "act1": (L, a), "reward1": (L,)}
    return SegmentPairs(*(np.stack([np.frombuffer(row.pop(key), dtype="<f4").reshape(shape) for row in rows])
                          .astype(np.float32) for key, shape in shapes.items()))


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


@dataclass
class LabelSet:
    """Labels read back from a store: the pairs, their labels, and one metadata row each."""

    pairs: SegmentPairs
    y: np.ndarray
    rows: list[dict]

    def __len__(self) -> int:
        return len(self.y)


class LabelStore:
    """A label store in one SQLite file (created if missing), or, with ``read_only``, an existing one
    opened without writing anything to it."""

    def __init__(self, path: str | Path, read_only: bool = False):
        self.path = Path(path)
        if read_only and not self.path.is_file():
            raise RatError(f"no label store at '{self.path}'; a run keeps its labels in <run>/labels.sqlite")
        try:
            if read_only:
                self.db = sqlite3.connect(f"{self.path.resolve().as_uri()}?mode=ro", uri=True, timeout=30,
                                          isolation_level=None)
                found = self.db.execute("SELECT name FROM sqlite_master WHERE type='table'").fetchall()
                if not {"store_info", "labels", "rounds"} <= {name for (name,) in found}:
                    self.db.close()
                    raise RatError(f"'{self.path}' is not a rat label store (it has no labels table); give the "
                                   "labels.sqlite of a rat run")
            else:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self.db = sqlite3.connect(self.path, timeout=30, isolation_level=None)
                self.db.execute("PRAGMA journal_mode=WAL")
                self.db.execute("PRAGMA synchronous=FULL")
                self.db.executescript(_SCHEMA)
                self.db.execute("INSERT OR IGNORE INTO store_info VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),))
                self._migrate()
                self.db.executescript(_QUERIES)
            version = int(self.db.execute("SELECT value FROM store_info WHERE key='schema_version'").fetchone()[0])
        except sqlite3.DatabaseError as exc:
            raise RatError(f"'{self.path}' is not a readable label store ({exc}); give a rat label store (.sqlite)") from exc
        if version > SCHEMA_VERSION:
            raise RatError(f"label store '{self.path}' has schema {version}; this rat reads up to {SCHEMA_VERSION} "
                           "(upgrade rat)")
        self.schema = version

    def _migrate(self) -> None:
        """Bring a schema-1 store (no query queue) to schema 2, in one transaction."""
        version = int(self.db.execute("SELECT value FROM store_info WHERE key='schema_version'").fetchone()[0])
        if version >= SCHEMA_VERSION:
            return
        with self._transaction():
            columns = {row[1] for row in self.db.execute("PRAGMA table_info(labels)")}
            for column, kind in (("query_id", "INTEGER"), ("duration_s", "REAL")):
                if column not in columns:
                    self.db.execute(f"ALTER TABLE labels ADD COLUMN {column} {kind}")
            self.db.execute("UPDATE store_info SET value=? WHERE key='schema_version'", (str(SCHEMA_VERSION),))

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> LabelStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # --- writing -------------------------------------------------------------------------------

    def add(self, pairs: SegmentPairs, y: np.ndarray, labeller: dict, source: str, round: int | None = None,
            task: str | None = None, target: str | None = None, step: int | None = None,
            asked: int | None = None) -> list[int]:
        """Store labelled pairs in one committed transaction; returns their ids once durable.

        With ``step`` and ``asked``, the query round is recorded in the same transaction, so a
        round is either wholly in the store (labels and accounting) or not at all.
        """
        length, obs_dim = pairs.obs0.shape[1:]
        act_dim = pairs.act0.shape[2]
        who, when = json.dumps(labeller, sort_keys=True), _now()
        rows = [(when, source, round, task, target, who, float(y[i]), length, obs_dim, act_dim,
                 *(_blob(a[i]) for a in pairs.arrays())) for i in range(len(y))]
        with self._transaction():
            first = self.db.execute("SELECT COALESCE(MAX(id), 0) FROM labels").fetchone()[0] + 1
            self.db.executemany(
                "INSERT INTO labels (created_at, source, round, task, target, labeller, label, length, obs_dim,"
                " act_dim, obs0, act0, reward0, obs1, act1, reward1) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)", rows)
            if step is not None and asked is not None:
                self.db.execute("INSERT INTO rounds VALUES (?,?,?,?,?,?)", (source, round, step, asked, len(rows), when))
        return list(range(first, first + len(rows)))

    def record_round(self, source: str, round: int, step: int, asked: int, answered: int) -> None:
        """Record a query round (the ground truth of budget accounting)."""
        with self._transaction():
            self.db.execute("INSERT OR REPLACE INTO rounds VALUES (?,?,?,?,?,?)",
                            (source, round, step, asked, answered, _now()))

    def _transaction(self):
        store = self

        class _Tx:
            def __enter__(self):
                store.db.execute("BEGIN IMMEDIATE")

            def __exit__(self, exc_type, *_):
                store.db.execute("ROLLBACK" if exc_type else "COMMIT")

        return _Tx()

    # --- reading -------------------------------------------------------------------------------

    def count(self, source: str | None = None, before_round: int | None = None) -> int:
        """How many labels (of one ``source``; of rounds before ``before_round``, as :meth:`read`)."""
        where, args = _where(source, before_round)
        return self.db.execute("SELECT COUNT(*) FROM labels" + where, args).fetchone()[0]

    def count_answered(self) -> int:
        """Labels given one at a time, as answers to published queries (a person's, or the teacher's after a timeout)."""
        return self.db.execute("SELECT COUNT(*) FROM labels WHERE query_id IS NOT NULL").fetchone()[0]

    def rounds(self, source: str) -> list[dict]:
        cur = self.db.execute("SELECT round, step, asked, answered, created_at FROM rounds WHERE source=? ORDER BY round",
                              (source,))
        return [dict(zip(("round", "step", "asked", "answered", "created_at"), r)) for r in cur]

    def sources(self) -> list[tuple[str, int]]:
        return self.db.execute("SELECT source, COUNT(*) FROM labels GROUP BY source ORDER BY source").fetchall()

    def read(self, source: str | None = None, ids: list[int] | None = None, before_round: int | None = None
             ) -> LabelSet:
        """Labels in id order, optionally only those of one ``source``, with given ``ids``, or of rounds before
        ``before_round`` (with the labels of no round, imported ones)."""
        where, args = _where(source, before_round, ids)
        rows = self._rows("SELECT * FROM labels" + where + " ORDER BY id", args)
        if not rows:
            return LabelSet(SegmentPairs(*(np.zeros((0,)) for _ in range(6))), np.zeros(0), [])
        pairs = _segments(rows)
        for row in rows:
            row["labeller"] = json.loads(row["labeller"])
        return LabelSet(pairs, np.asarray([row["label"] for row in rows]), rows)

    def _rows(self, sql: str, args=()) -> list[dict]:
        cur = self.db.execute(sql, args)
        names = [d[0] for d in cur.description]
        return [dict(zip(names, values)) for values in cur]

    # --- moving label sets between runs ------------------------------------------------------------

    def export_to(self, path: str | Path, source: str | None = None) -> int:
        """Write the labels (all, or one ``source``'s) to a new store file; returns how many."""
        path = Path(path)
        if path.exists():
            raise RatError(f"'{path}' already exists; export to a new file")
        with LabelStore(path) as out:
            labels = self.read(source)
            for row, i in zip(labels.rows, range(len(labels))):
                out._insert_row(row, labels.pairs.select([i]), labels.y[i])
            for src in ([source] if source else [s for s, _ in self.sources()]):
                for r in self.rounds(src):
                    out.record_round(src, r["round"], r["step"], r["asked"], r["answered"])
            return out.count()

    def import_from(self, path: str | Path, source: str | None = None) -> int:
        """Copy every label of another store into this one (new ids, provenance kept), with its query-round
        accounting; returns how many. With ``source``, everything is filed under that name."""
        with LabelStore(path, read_only=True) as other:
            labels = other.read()
            rounds = [(src, r) for src, _ in other.sources() for r in other.rounds(src)]
            with self._transaction():
                for i, row in enumerate(labels.rows):
                    row = dict(row)
                    row["imported_from"] = f"{path}#{row['id']}"
                    if source is not None:
                        row["source"] = source
                    self._insert_row(row, labels.pairs.select([i]), labels.y[i], in_transaction=True)
                for src, r in rounds:
                    self.db.execute("INSERT OR REPLACE INTO rounds VALUES (?,?,?,?,?,?)",
                                    (source or src, r["round"], r["step"], r["asked"], r["answered"], r["created_at"]))
            return len(labels)

    def _insert_row(self, row: dict, pair: SegmentPairs, y: float, in_transaction: bool = False) -> None:
        values = (row["created_at"], row["source"], row["round"], row["task"], row["target"],
                  json.dumps(row["labeller"], sort_keys=True), float(y), row["length"], row["obs_dim"], row["act_dim"],
                  *(_blob(a[0]) for a in pair.arrays()), row.get("imported_from"), row.get("duration_s"))
        sql = ("INSERT INTO labels (created_at, source, round, task, target, labeller, label, length, obs_dim, act_dim,"
               " obs0, act0, reward0, obs1, act1, reward1, imported_from, duration_s)"
               " VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)")
        if in_transaction:
            self.db.execute(sql, values)
        else:
            with self._transaction():
                self.db.execute(sql, values)

    # --- queries answered one at a time (people) ------------------------------------------------------

    def publish(self, pairs: SegmentPairs, source: str, round: int, step: int, task: str | None = None,
                target: str | None = None) -> list[int]:
        """Publish a round's queries (with their physics states, if ``pairs`` has them) for answering
        one at a time; returns their ids in order.

        Publishing a round that is already published (a run resumed while it waited) changes
        nothing and returns the ids it has.
        """
        existing = self.query_ids(source, round)
        if existing:
            return existing
        length, obs_dim = pairs.obs0.shape[1:]
        act_dim, when = pairs.act0.shape[2], _now()
        physics = pairs.physics
        shapes = json.dumps({"state": physics[0].shape[2], "scene": physics[2].shape[1]}) if physics else None

        def physics_blobs(i):
            return [np.ascontiguousarray(a[i], "<f8").tobytes() for a in physics] if physics else [None] * 4

        rows = [(when, source, round, i, step, task, target, length, obs_dim, act_dim,
                 *(_blob(a[i]) for a in pairs.arrays()), shapes, *physics_blobs(i)) for i in range(len(pairs))]
        with self._transaction():
            self.db.executemany(
                "INSERT INTO queries (created_at, source, round, position, step, task, target, length, obs_dim, act_dim,"
                " obs0, act0, reward0, obs1, act1, reward1, physics, states0, states1, scene0, scene1)"
                " VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)", rows)
        return self.query_ids(source, round)

    def query_pairs(self, ids: list[int]) -> SegmentPairs:
        """The segments of published queries, in the order of ``ids`` (with physics states if recorded)."""
        found = {row["id"]: row for row in self._rows(f"SELECT * FROM queries WHERE id IN ({','.join('?' * len(ids))})",
                                                      [int(i) for i in ids])}
        missing = [i for i in ids if i not in found]
        if missing:
            raise RatError(f"no published query {missing[0]} in '{self.path}'")
        rows = [found[i] for i in ids]
        pairs = _segments(rows)
        if rows[0]["physics"]:
            sizes, L = json.loads(rows[0]["physics"]), rows[0]["length"]
            shapes = {"states0": (L, sizes["state"]), "states1": (L, sizes["state"]), "scene0": (sizes["scene"],),
                      "scene1": (sizes["scene"],)}
            pairs.physics = tuple(np.stack([np.frombuffer(r[k], "<f8").reshape(shape) for r in rows])
                                  for k, shape in shapes.items())
        return pairs

    def set_videos(self, query_id: int, video0: str, video1: str) -> None:
        """Record the videos of a query (file names relative to the store's directory)."""
        with self._transaction():
            self.db.execute("UPDATE queries SET video0=?, video1=? WHERE id=?", (video0, video1, int(query_id)))

    def query_ids(self, source: str, round: int) -> list[int]:
        return [i for (i,) in self.db.execute("SELECT id FROM queries WHERE source=? AND round=? ORDER BY position",
                                               (source, round))]

    def queries(self, source: str | None = None, open_only: bool = True) -> list[dict]:
        """Published queries (no segments), oldest first, each with its answer if it has one:
        ``answer`` is left, right, equal, skip or None."""
        sql = ("SELECT q.id, q.source, q.round, q.position, q.step, q.task, q.target, q.video0, q.video1, q.closed,"
               " a.choice FROM queries q LEFT JOIN answers a ON a.query_id = q.id")
        clauses, args = [], []
        if source is not None:
            clauses.append("q.source=?")
            args.append(source)
        if open_only:
            clauses.append("q.closed=0")
        sql += (" WHERE " + " AND ".join(clauses) if clauses else "") + " ORDER BY q.id"
        out = []
        for *head, choice in self.db.execute(sql, args):
            row = dict(zip(("id", "source", "round", "position", "step", "task", "target", "video0", "video1",
                            "closed"), head))
            out.append(row | {"closed": bool(row["closed"]), "answer": choice})
        return out

    def answer(self, query_id: int, choice: str, labeller: dict, duration_s: float | None = None) -> int | None:
        """Store one answer to a published query, durably; returns the new label's id (None for a skip).

        Raises :class:`AnswerError` for an unknown query (404), a query already answered or in a
        closed round (409), or a choice or duration that is not one (422); nothing is stored then.
        """
        if choice not in CHOICES:
            raise AnswerError(f"unknown answer '{choice}'; use one of: {', '.join(CHOICES)}", 422)
        if duration_s is not None and not (isinstance(duration_s, (int, float)) and 0 <= duration_s < 1e6):
            raise AnswerError(f"duration must be a number of seconds >= 0, got {duration_s!r}", 422)
        who, when = json.dumps(labeller, sort_keys=True), _now()
        with self._transaction():
            found = self.db.execute("SELECT closed FROM queries WHERE id=?", (int(query_id),)).fetchone()
            if found is None:
                raise AnswerError(f"no query {query_id}", 404)
            if found[0]:
                raise AnswerError(f"query {query_id} is in a closed round; it takes no answers", 409)
            if self._answered(query_id):
                raise AnswerError(f"query {query_id} is already answered; undo it first to change the answer", 409)
            self.db.execute("INSERT INTO answers (query_id, choice, labeller, created_at, duration_s) VALUES (?,?,?,?,?)",
                            (int(query_id), choice, who, when, duration_s))
            if CHOICES[choice] is None:
                return None
            cur = self.db.execute(
                "INSERT INTO labels (created_at, source, round, task, target, labeller, label, length, obs_dim, act_dim,"
                " obs0, act0, reward0, obs1, act1, reward1, query_id, duration_s)"
                " SELECT ?, source, round, task, target, ?, ?, length, obs_dim, act_dim,"
                " obs0, act0, reward0, obs1, act1, reward1, id, ? FROM queries WHERE id=?",
                (when, who, CHOICES[choice], duration_s, int(query_id)))
            return cur.lastrowid

    def _answered(self, query_id: int) -> bool:
        return self.db.execute("SELECT 1 FROM answers WHERE query_id=?", (int(query_id),)).fetchone() is not None

    def undo(self, labeller_name: str) -> int | None:
        """Withdraw the latest answer that ``labeller_name`` gave to a query of an open round; returns
        that query's id (None if there is none to withdraw)."""
        with self._transaction():
            latest = self.db.execute(
                "SELECT a.id, a.query_id FROM answers a JOIN queries q ON q.id = a.query_id"
                " WHERE q.closed=0 AND json_extract(a.labeller, '$.name')=? ORDER BY a.id DESC LIMIT 1",
                (labeller_name,)).fetchone()
            if latest is None:
                return None
            answer_id, query_id = latest
            self.db.execute("DELETE FROM answers WHERE id=?", (answer_id,))
            self.db.execute("DELETE FROM labels WHERE query_id=?", (query_id,))
            return query_id

    def close_round(self, source: str, round: int, step: int) -> tuple[np.ndarray, np.ndarray]:
        """Close a published round and record it; returns the positions answered with a label and
        their labels (skips are left out)."""
        with self._transaction():
            self.db.execute("UPDATE queries SET closed=1 WHERE source=? AND round=?", (source, round))
            rows = self.db.execute("SELECT q.position, l.label FROM queries q JOIN labels l ON l.query_id = q.id"
                                   " WHERE q.source=? AND q.round=? ORDER BY q.position", (source, round)).fetchall()
            asked = self.db.execute("SELECT COUNT(*) FROM queries WHERE source=? AND round=?", (source, round)).fetchone()[0]
            self.db.execute("INSERT OR REPLACE INTO rounds VALUES (?,?,?,?,?,?)",
                            (source, round, step, asked, len(rows), _now()))
        return np.asarray([r[0] for r in rows], dtype=np.int64), np.asarray([r[1] for r in rows], dtype=np.float64)

    def video_path(self, query_id: int, side: int) -> Path | None:
        """The file of a query's video (side 0 or 1), or None: only names the store recorded, inside
        the store's own directory, are ever served."""
        if side not in (0, 1):
            return None
        row = self.db.execute(f"SELECT video{side} FROM queries WHERE id=?", (int(query_id),)).fetchone()
        if row is None or not row[0]:
            return None
        root = self.path.parent.resolve()
        path = (root / row[0]).resolve()
        return path if path.is_relative_to(root) and path.is_file() else None
