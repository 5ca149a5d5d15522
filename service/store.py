"""The durable store: SQLite in WAL mode, one writer, commits before anything is acknowledged.

What it holds (times are int64 epoch nanoseconds, UTC; rates Sm3/h; pressures bar a):

- ``wells``: every well the service knows, with when and how it was added.
- ``samples``: every accepted sensor sample with the prediction made for it (empty
  prediction columns while the well's model was not ready).
- ``measurements``: every accepted measurement (MPFM reading or well test) with its
  status: ``pending`` (waiting for its sensor sample), ``learned`` (with the order it was
  learned in, ``learn_seq``, the paired inputs and the prediction at that sample, so
  that a restart can re-learn it without the samples), or ``unpaired`` (no sample within
  the tolerance).
- ``checkpoints``: :meth:`vfm_core.streaming.WellLearner.checkpoint` bytes (tensors
  and plain values, read back with ``weights_only``; never pickle), with the
  ``learn_seq`` they include and a JSON side-car (drift detector state).
- ``drift_events``: confirmed drifts per well.

Writes go through :meth:`Store.write`, a list of statements run in one transaction under
a lock (group commit). Readers (the HTTP API, pairing look-ups) open their own
connections: WAL lets them read while the writer writes.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vfm_core.errors import ConfigError

__all__ = ["Store", "Op", "CheckpointRow", "INPUT_FIELDS"]

#: the six model inputs, in vfm_core.schema.INPUT_COLUMNS order
INPUT_FIELDS: tuple[str, ...] = ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil")

Op = tuple[str, Sequence[Any]]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS wells (
    well TEXT PRIMARY KEY, created_ns INTEGER NOT NULL, origin TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS samples (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL,
    choke REAL NOT NULL, p_up REAL NOT NULL, p_down REAL NOT NULL, t_up REAL NOT NULL,
    eta_gas REAL NOT NULL, eta_oil REAL NOT NULL,
    received_ns INTEGER NOT NULL,
    q_total REAL, q_gas REAL, q_oil REAL, q_water REAL, version INTEGER
);
CREATE UNIQUE INDEX IF NOT EXISTS samples_well_time ON samples (well, time_ns);
CREATE TABLE IF NOT EXISTS measurements (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL, source TEXT NOT NULL,
    q_total REAL NOT NULL, received_ns INTEGER NOT NULL, via TEXT NOT NULL,
    status TEXT NOT NULL, learn_seq INTEGER, sample_time_ns INTEGER,
    choke REAL, p_up REAL, p_down REAL, t_up REAL, eta_gas REAL, eta_oil REAL,
    predicted REAL, version_after INTEGER
);
CREATE UNIQUE INDEX IF NOT EXISTS measurements_key ON measurements (well, source, time_ns);
CREATE INDEX IF NOT EXISTS measurements_seq ON measurements (well, learn_seq);
CREATE TABLE IF NOT EXISTS checkpoints (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, created_ns INTEGER NOT NULL, version INTEGER NOT NULL,
    learn_seq INTEGER NOT NULL, model TEXT NOT NULL, method TEXT NOT NULL,
    blob BLOB NOT NULL, extra TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS checkpoints_well ON checkpoints (well, id);
CREATE TABLE IF NOT EXISTS drift_events (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL, statistic REAL, p_value REAL, action TEXT NOT NULL
);
CREATE UNIQUE INDEX IF NOT EXISTS drift_events_key ON drift_events (well, time_ns);
"""

SCHEMA_VERSION = "1"

# statements the engine uses, by name, so that callers never build SQL
SQL: dict[str, str] = {
    "well": "INSERT OR IGNORE INTO wells (well, created_ns, origin) VALUES (?, ?, ?)",
    "sample": (
        "INSERT OR IGNORE INTO samples (well, time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil,"
        " received_ns, q_total, q_gas, q_oil, q_water, version)"
        " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
    ),
    "measurement": (
        "INSERT OR IGNORE INTO measurements (well, time_ns, source, q_total, received_ns, via, status)"
        " VALUES (?, ?, ?, ?, ?, ?, 'pending')"
    ),
    "learned": (
        "UPDATE measurements SET status = 'learned', learn_seq = ?, sample_time_ns = ?,"
        " choke = ?, p_up = ?, p_down = ?, t_up = ?, eta_gas = ?, eta_oil = ?,"
        " predicted = ?, version_after = ? WHERE well = ? AND source = ? AND time_ns = ?"
    ),
    "unpaired": "UPDATE measurements SET status = 'unpaired' WHERE well = ? AND source = ? AND time_ns = ?",
    "checkpoint": (
        "INSERT INTO checkpoints (well, created_ns, version, learn_seq, model, method, blob, extra)"
        " VALUES (?, ?, ?, ?, ?, ?, ?, ?)"
    ),
    "prune_checkpoints": (
        "DELETE FROM checkpoints WHERE well = ? AND id NOT IN"
        " (SELECT id FROM checkpoints WHERE well = ? ORDER BY id DESC LIMIT ?)"
    ),
    "drift": (
        "INSERT OR IGNORE INTO drift_events (well, time_ns, statistic, p_value, action) VALUES (?, ?, ?, ?, ?)"
    ),
}


@dataclass(frozen=True)
class CheckpointRow:
    well: str
    version: int
    learn_seq: int
    model: str
    method: str
    blob: bytes
    extra: str
    created_ns: int


class Store:
    """The service's SQLite file. Thread-safe: one locked writer, a reader per thread."""

    def __init__(self, path: str | Path, synchronous: str = "full") -> None:
        self.path = Path(path)
        if synchronous not in ("full", "normal"):
            raise ConfigError(f"store.synchronous must be 'full' or 'normal', not '{synchronous}'.")
        self.synchronous = synchronous
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._local = threading.local()
        try:
            self._writer = self._connect()
            self._writer.executescript(_SCHEMA)
            row = self._writer.execute("SELECT value FROM meta WHERE key = 'schema'").fetchone()
        except sqlite3.DatabaseError as exc:
            raise ConfigError(
                f"The store {self.path} cannot be opened as an SQLite database ({exc}); "
                "point store.path at a new file or at a store this service wrote."
            ) from None
        if row is None:
            self._writer.execute(
                "INSERT INTO meta (key, value) VALUES ('schema', ?)", (SCHEMA_VERSION,)
            )
        elif row[0] != SCHEMA_VERSION:
            raise ConfigError(
                f"The store {self.path} has schema version {row[0]}, this service writes "
                f"version {SCHEMA_VERSION}; use a new store.path."
            )
        self._readers: list[sqlite3.Connection] = []

    def _connect(self) -> sqlite3.Connection:
        con = sqlite3.connect(
            self.path, isolation_level=None, check_same_thread=False, timeout=30.0
        )
        con.execute("PRAGMA journal_mode=WAL")
        con.execute(f"PRAGMA synchronous={self.synchronous.upper()}")
        con.execute("PRAGMA busy_timeout=30000")
        return con

    # -- writing ------------------------------------------------------------------------
    def write(self, ops: Sequence[Op]) -> list[int]:
        """Run named statements (keys of ``SQL``) in one transaction; rowcounts per op."""
        if not ops:
            return []
        counts: list[int] = []
        with self._lock:
            con = self._writer
            con.execute("BEGIN IMMEDIATE")
            try:
                for name, params in ops:
                    counts.append(con.execute(SQL[name], params).rowcount)
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
        return counts

    def close(self) -> None:
        with self._lock:
            self._writer.close()
        for con in self._readers:
            try:
                con.close()
            except sqlite3.ProgrammingError:  # closed from another thread already
                pass

    # -- reading ------------------------------------------------------------------------
    @contextmanager
    def reader(self) -> Iterator[sqlite3.Connection]:
        """A read connection of this thread (reused)."""
        con = getattr(self._local, "con", None)
        if con is None:
            con = self._connect()
            self._local.con = con
            self._readers.append(con)
        yield con

    def wells(self) -> list[str]:
        with self.reader() as con:
            return [r[0] for r in con.execute("SELECT well FROM wells ORDER BY created_ns, well")]

    def latest_checkpoint(self, well: str) -> CheckpointRow | None:
        with self.reader() as con:
            row = con.execute(
                "SELECT well, version, learn_seq, model, method, blob, extra, created_ns FROM checkpoints"
                " WHERE well = ? ORDER BY id DESC LIMIT 1",
                (well,),
            ).fetchone()
        return CheckpointRow(*row) if row else None

    def learned_after(self, well: str, learn_seq: int) -> list[tuple[Any, ...]]:
        """Learned measurements after ``learn_seq``, in learning order:
        (learn_seq, time_ns, source, q_total, sample_time_ns, 6 inputs..., predicted)."""
        with self.reader() as con:
            return con.execute(
                "SELECT learn_seq, time_ns, source, q_total, sample_time_ns,"
                " choke, p_up, p_down, t_up, eta_gas, eta_oil, predicted FROM measurements"
                " WHERE well = ? AND status = 'learned' AND learn_seq > ? ORDER BY learn_seq",
                (well, learn_seq),
            ).fetchall()

    def recent_errors(
        self, well: str, n: int, min_version: int | None = None
    ) -> list[tuple[float, float]]:
        """(predicted, measured) of the last ``n`` learned measurements, oldest first
        (only those learned at model version ``min_version`` or later, when given)."""
        with self.reader() as con:
            rows = con.execute(
                "SELECT predicted, q_total FROM measurements WHERE well = ? AND status = 'learned'"
                " AND version_after >= ? ORDER BY learn_seq DESC LIMIT ?",
                (well, -1 if min_version is None else min_version, n),
            ).fetchall()
        return [(p, q) for p, q in reversed(rows)]

    def pending(self, well: str) -> list[tuple[int, str, float, str]]:
        """(time_ns, source, q_total, via) of measurements still waiting for a sample."""
        with self.reader() as con:
            return con.execute(
                "SELECT time_ns, source, q_total, via FROM measurements WHERE well = ? AND status = 'pending'"
                " ORDER BY id",
                (well,),
            ).fetchall()

    def recent_samples(self, well: str, n: int) -> list[tuple[Any, ...]]:
        """The last ``n`` samples, oldest first: (time_ns, 6 inputs..., q_total predicted)."""
        with self.reader() as con:
            rows = con.execute(
                "SELECT time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil, q_total FROM samples"
                " WHERE well = ? ORDER BY time_ns DESC LIMIT ?",
                (well, n),
            ).fetchall()
        return list(reversed(rows))

    def nearest_sample(self, well: str, time_ns: int, tolerance_ns: int) -> tuple[Any, ...] | None:
        """The stored sample nearest to ``time_ns`` within the tolerance, or None."""
        with self.reader() as con:
            before = con.execute(
                "SELECT time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil, q_total FROM samples"
                " WHERE well = ? AND time_ns <= ? AND time_ns >= ? ORDER BY time_ns DESC LIMIT 1",
                (well, time_ns, time_ns - tolerance_ns),
            ).fetchone()
            after = con.execute(
                "SELECT time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil, q_total FROM samples"
                " WHERE well = ? AND time_ns > ? AND time_ns <= ? ORDER BY time_ns ASC LIMIT 1",
                (well, time_ns, time_ns + tolerance_ns),
            ).fetchone()
        found = [r for r in (before, after) if r is not None]
        return min(found, key=lambda r: abs(r[0] - time_ns)) if found else None

    def measurement_exists(self, well: str, source: str, time_ns: int) -> bool:
        with self.reader() as con:
            return (
                con.execute(
                    "SELECT 1 FROM measurements WHERE well = ? AND source = ? AND time_ns = ?",
                    (well, source, time_ns),
                ).fetchone()
                is not None
            )

    def drift_events(self, well: str, limit: int = 20) -> list[tuple[int, float, float, str]]:
        with self.reader() as con:
            rows = con.execute(
                "SELECT time_ns, statistic, p_value, action FROM drift_events WHERE well = ?"
                " ORDER BY time_ns DESC LIMIT ?",
                (well, limit),
            ).fetchall()
        return list(reversed(rows))

    def history(
        self, well: str, start_ns: int, end_ns: int, limit: int
    ) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]]]:
        """Samples (with predictions) and measurements of a well in [start, end), time order."""
        with self.reader() as con:
            samples = con.execute(
                "SELECT time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil, received_ns,"
                " q_total, q_gas, q_oil, q_water, version FROM samples"
                " WHERE well = ? AND time_ns >= ? AND time_ns < ? ORDER BY time_ns LIMIT ?",
                (well, start_ns, end_ns, limit),
            ).fetchall()
            measurements = con.execute(
                "SELECT time_ns, source, q_total, received_ns, via, status, sample_time_ns, predicted,"
                " version_after FROM measurements"
                " WHERE well = ? AND time_ns >= ? AND time_ns < ? ORDER BY time_ns, source LIMIT ?",
                (well, start_ns, end_ns, limit),
            ).fetchall()
        return samples, measurements

    def counts(self) -> dict[str, int]:
        with self.reader() as con:
            return {
                table: int(con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])  # noqa: S608
                for table in ("wells", "samples", "measurements", "checkpoints", "drift_events")
            }
