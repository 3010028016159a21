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

SCHEMA_VERSION = 1

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
    imported_from TEXT
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


def _blob(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f4").tobytes()


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
            version = int(self.db.execute("SELECT value FROM store_info WHERE key='schema_version'").fetchone()[0])
        except sqlite3.DatabaseError as exc:
            raise RatError(f"'{self.path}' is not a readable label store ({exc}); give a rat label store (.sqlite)") from exc
        if version != SCHEMA_VERSION:
            raise RatError(f"label store '{self.path}' has schema {version}; this rat reads {SCHEMA_VERSION}")

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> "LabelStore":
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

    def count(self, source: str | None = None) -> int:
        if source is None:
            return self.db.execute("SELECT COUNT(*) FROM labels").fetchone()[0]
        return self.db.execute("SELECT COUNT(*) FROM labels WHERE source=?", (source,)).fetchone()[0]

    def rounds(self, source: str) -> list[dict]:
        cur = self.db.execute("SELECT round, step, asked, answered, created_at FROM rounds WHERE source=? ORDER BY round",
                              (source,))
        return [dict(zip(("round", "step", "asked", "answered", "created_at"), r)) for r in cur]

    def sources(self) -> list[tuple[str, int]]:
        return self.db.execute("SELECT source, COUNT(*) FROM labels GROUP BY source ORDER BY source").fetchall()

    def read(self, source: str | None = None, ids: list[int] | None = None) -> LabelSet:
        """Labels in id order, optionally only those of one ``source`` or with given ``ids``."""
        query, args = "SELECT * FROM labels", []
        clauses = []
        if source is not None:
            clauses.append("source=?")
            args.append(source)
        if ids is not None:
            clauses.append(f"id IN ({','.join('?' * len(ids))})")
            args.extend(int(i) for i in ids)
        if clauses:
            query += " WHERE " + " AND ".join(clauses)
        cur = self.db.execute(query + " ORDER BY id", args)
        names = [d[0] for d in cur.description]
        arrays: list[list[np.ndarray]] = [[] for _ in range(6)]
        y, rows = [], []
        for values in cur:
            row = dict(zip(names, values))
            L, d, a = row["length"], row["obs_dim"], row["act_dim"]
            shapes = [(L, d), (L, a), (L,), (L, d), (L, a), (L,)]
            for k, (key, shape) in enumerate(zip(("obs0", "act0", "reward0", "obs1", "act1", "reward1"), shapes)):
                arrays[k].append(np.frombuffer(row.pop(key), dtype="<f4").reshape(shape))
            y.append(row["label"])
            row["labeller"] = json.loads(row["labeller"])
            rows.append(row)
        if not rows:
            return LabelSet(SegmentPairs(*(np.zeros((0,)) for _ in range(6))), np.zeros(0), [])
        return LabelSet(SegmentPairs(*(np.stack(a).astype(np.float32) for a in arrays)), np.asarray(y), rows)

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
                  *(_blob(a[0]) for a in pair.arrays()), row.get("imported_from"))
        sql = ("INSERT INTO labels (created_at, source, round, task, target, labeller, label, length, obs_dim, act_dim,"
               " obs0, act0, reward0, obs1, act1, reward1, imported_from) VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)")
        if in_transaction:
            self.db.execute(sql, values)
        else:
            with self._transaction():
                self.db.execute(sql, values)
