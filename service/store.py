"""The durable store: SQLite in WAL mode, one writer, commits before anything is acknowledged.

What it holds (times are int64 epoch nanoseconds, UTC; rates Sm3/h; pressures bar a):

- ``wells``: every well the service knows, with when and how it was added, and when it
  was retired (``DELETE /wells/{well}``; null while in service).
- ``samples``: every accepted sensor sample with the prediction made for it (empty
  prediction columns while the well's model was not ready), and the prediction's
  interval where the method gives one (``q_total_std``, ``q_total_p05``, ``q_total_p95``,
  Sm3/h; null otherwise).
- ``measurements``: every accepted measurement (MPFM reading or well test) with its
  status: ``pending`` (waiting for its sensor sample), ``learned`` (with the order it was
  learned in, ``learn_seq``, the paired inputs and the prediction at that sample, so
  that a restart can re-learn it without the samples), ``unpaired`` (no sample within
  the tolerance), ``held`` (an instrument fault at its sample), ``review`` (held for the
  operator's review) or ``rejected`` (rejected on review); the last three never learned.
- ``checkpoints``: :meth:`vfm_core.learning.streaming.WellLearner.checkpoint` bytes (tensors
  and plain values, read back with ``weights_only``; never pickle), with the
  ``learn_seq`` they include and a JSON side-car (drift detector state).
- ``drift_events``: confirmed input drifts per well (the T^2 "operating point" notice).
- ``residual_alarms``: the start and end of each residual alarm per well and meter
  (created on opening any store, like the tables below; an older service ignores it).
- ``reviews``: the measurements held for review (a well test inconsistent with the model
  and with the MPFM near it, :class:`service.engine.alarms.WellTestReview`), with the
  evidence, the paired sample and the operator's decision (created on opening any store).
- ``parameter_history``: a well's physical parameters over time (``parameters``: JSON
  ``{name: {value, std, unit, low, high, at_bound}}``, SI units), with the data time of the
  measurement they follow (``time_ns``), the model version and name; written in the same
  transaction as the learning it follows, thinned to one row per
  ``store.parameters_every`` model updates (and one at each model change), at most
  ``store.parameters_kept`` rows per well (the oldest pruned).

Reads return typed rows (:class:`SampleRow`, :class:`LearnedRow`, :class:`CheckpointRow`,
...), filled by column name. Writes are typed operations, one small frozen dataclass per
statement (:class:`AddWell`, :class:`InsertSample`, :class:`MarkLearned`, ...) whose
fields are bound to the statement by name, so no caller depends on the order of a
table's columns. :meth:`Store.write` runs a list of them in one transaction under a lock
(group commit). Readers (the HTTP API, pairing look-ups) open their own connections:
WAL lets them read while the writer writes.

Schema versions (``meta.schema``): 1, the first; 2 adds the interval columns of
``samples`` and ``wells.retired_ns``. A version-1 store is migrated in place when the
service opens it (columns added, nothing rewritten); a store of a later version than this
code knows is refused with a sentence. 3 adds ``parameter_history`` (a table, nothing
rewritten).

Two tables came later without a new schema version, since they are created on opening
any store and change nothing that exists (an older service ignores them):

- ``model_versions``: the model a well ran before each model change or rollback, as a
  checkpoint (``blob``, the ``learn_seq`` it includes, the data time of the change, its
  specification ``[model, effects, method]`` as JSON and a note saying why it was
  replaced); the latest ``trial.keep_versions`` per well, for
  ``POST /wells/{well}/model/rollback``.
- ``trials``: each ended trial of a model change against its shadow (see
  :mod:`service.engine.trial`): its start and end (data time), both models, the outcome
  and the summary GET /wells/{well} shows (JSON).
- ``separator_readings``: every accepted reading of a separator's total (``q_total``,
  Sm3/h) with its status (``pending``: waiting for its wells' samples; ``learned``,
  ``allocated``: allocated, not learned from; ``unused``: not allocated, ``note`` says
  why), the sum of its wells' predictions (``predicted``) and the reconciliation residual
  (``residual`` = ``q_total`` - ``predicted``, Sm3/h); ``allocations``: per reading and
  member well its prediction ``q_pred``, allocated rate ``q_alloc`` and 90 % interval
  ``lo90``/``hi90`` (Sm3/h) and the sample it was made at. ``separator_states``: each
  separator's kept cross-covariances between its wells' parameters (``separators.cross``;
  ``joint``: float64 bytes of the [M D, M D] matrix, ``wells`` and the wells' model
  ``versions`` as JSON), replaced in the transaction that moves them, with the members'
  checkpoints. Written and read by :mod:`service.engine.separators`.
"""

from __future__ import annotations

import functools
import logging
import sqlite3
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any, ClassVar, NamedTuple, TypeVar

from vfm_core.errors import ConfigError

logger = logging.getLogger("vfm.service.store")

__all__ = [
    "Store",
    "INPUT_FIELDS",
    # rows read
    "SampleRow",
    "LearnedRow",
    "PendingRow",
    "ErrorRow",
    "CheckpointRow",
    "DriftEventRow",
    "ParameterRow",
    "ModelVersionRow",
    "TrialRow",
    "HistorySample",
    "HistoryMeasurement",
    # writes
    "Op",
    "AddWell",
    "InsertSample",
    "InsertMeasurement",
    "MarkLearned",
    "MarkUnpaired",
    "MarkHeld",
    "InsertReview",
    "MarkReview",
    "DecideReview",
    "MarkRejected",
    "ReviewRow",
    "InsertCheckpoint",
    "PruneCheckpoints",
    "InsertDriftEvent",
    "InsertResidualAlarm",
    "InsertParameters",
    "PruneParameters",
    "InsertModelVersion",
    "PruneModelVersions",
    "InsertTrial",
    "RetireWell",
    "DeleteWellRows",
    "purge_ops",
    "SCHEMA_VERSION",
]

#: the six model inputs, in vfm_core.schema.INPUT_COLUMNS order
INPUT_FIELDS: tuple[str, ...] = ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS wells (
    well TEXT PRIMARY KEY, created_ns INTEGER NOT NULL, origin TEXT NOT NULL,
    retired_ns INTEGER
);
CREATE TABLE IF NOT EXISTS samples (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL,
    choke REAL NOT NULL, p_up REAL NOT NULL, p_down REAL NOT NULL, t_up REAL NOT NULL,
    eta_gas REAL NOT NULL, eta_oil REAL NOT NULL,
    received_ns INTEGER NOT NULL,
    q_total REAL, q_gas REAL, q_oil REAL, q_water REAL, version INTEGER,
    q_total_std REAL, q_total_p05 REAL, q_total_p95 REAL
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
CREATE TABLE IF NOT EXISTS residual_alarms (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL, source TEXT NOT NULL, kind TEXT NOT NULL,
    direction TEXT NOT NULL, statistic REAL, threshold REAL
);
CREATE UNIQUE INDEX IF NOT EXISTS residual_alarms_key ON residual_alarms (well, source, time_ns, kind);
CREATE TABLE IF NOT EXISTS parameter_history (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL, version INTEGER NOT NULL,
    model TEXT NOT NULL, parameters TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS parameter_history_time ON parameter_history (well, time_ns);
CREATE INDEX IF NOT EXISTS parameter_history_id ON parameter_history (well, id);
CREATE TABLE IF NOT EXISTS model_versions (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, version INTEGER NOT NULL, created_ns INTEGER NOT NULL,
    data_time_ns INTEGER, learn_seq INTEGER NOT NULL, model TEXT NOT NULL,
    method TEXT NOT NULL, spec TEXT NOT NULL, note TEXT NOT NULL, blob BLOB NOT NULL
);
CREATE INDEX IF NOT EXISTS model_versions_well ON model_versions (well, id);
CREATE TABLE IF NOT EXISTS trials (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, created_ns INTEGER NOT NULL, since_ns INTEGER NOT NULL,
    ended_ns INTEGER, model TEXT NOT NULL, shadow_model TEXT NOT NULL,
    outcome TEXT NOT NULL, summary TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS trials_well ON trials (well, id);
CREATE TABLE IF NOT EXISTS reviews (
    id INTEGER PRIMARY KEY,
    well TEXT NOT NULL, time_ns INTEGER NOT NULL, source TEXT NOT NULL, q_total REAL NOT NULL,
    predicted REAL NOT NULL, sd_log REAL NOT NULL, z REAL NOT NULL, mpfm REAL,
    reason TEXT NOT NULL, sample_time_ns INTEGER NOT NULL,
    choke REAL, p_up REAL, p_down REAL, t_up REAL, eta_gas REAL, eta_oil REAL,
    sample_predicted REAL, held_ns INTEGER NOT NULL, decision TEXT, decided_ns INTEGER
);
CREATE UNIQUE INDEX IF NOT EXISTS reviews_key ON reviews (well, source, time_ns);
CREATE TABLE IF NOT EXISTS separator_readings (
    id INTEGER PRIMARY KEY,
    separator TEXT NOT NULL, time_ns INTEGER NOT NULL, q_total REAL NOT NULL,
    received_ns INTEGER NOT NULL, via TEXT NOT NULL, status TEXT NOT NULL,
    predicted REAL, residual REAL, note TEXT
);
CREATE UNIQUE INDEX IF NOT EXISTS separator_readings_key ON separator_readings (separator, time_ns);
CREATE TABLE IF NOT EXISTS allocations (
    id INTEGER PRIMARY KEY,
    separator TEXT NOT NULL, time_ns INTEGER NOT NULL, well TEXT NOT NULL,
    sample_time_ns INTEGER, q_pred REAL NOT NULL, q_alloc REAL, lo90 REAL, hi90 REAL
);
CREATE UNIQUE INDEX IF NOT EXISTS allocations_key ON allocations (separator, time_ns, well);
CREATE TABLE IF NOT EXISTS separator_states (
    separator TEXT PRIMARY KEY, time_ns INTEGER NOT NULL, wells TEXT NOT NULL,
    versions TEXT NOT NULL, dim INTEGER NOT NULL, joint BLOB NOT NULL
);
"""

SCHEMA_VERSION = "3"

#: the statements that bring a store of the key's version to the next one
_MIGRATIONS: dict[str, list[str]] = {
    "1": [
        "ALTER TABLE samples ADD COLUMN q_total_std REAL",
        "ALTER TABLE samples ADD COLUMN q_total_p05 REAL",
        "ALTER TABLE samples ADD COLUMN q_total_p95 REAL",
        "ALTER TABLE wells ADD COLUMN retired_ns INTEGER",
    ],
    # the table and its indexes are created by the schema script on opening; named here
    # too so that the step says what it brings
    "2": [
        "CREATE TABLE IF NOT EXISTS parameter_history (id INTEGER PRIMARY KEY,"
        " well TEXT NOT NULL, time_ns INTEGER NOT NULL, version INTEGER NOT NULL,"
        " model TEXT NOT NULL, parameters TEXT NOT NULL)",
        "CREATE INDEX IF NOT EXISTS parameter_history_time ON parameter_history (well, time_ns)",
        "CREATE INDEX IF NOT EXISTS parameter_history_id ON parameter_history (well, id)",
    ],
}


# -- rows read --------------------------------------------------------------------------------
class SampleRow(NamedTuple):
    """A stored sensor sample as pairing needs it: its time, six inputs and the prediction made."""

    time_ns: int
    inputs: tuple[float, ...]  # INPUT_FIELDS order: fraction, bar a, bar a, degC, -, -
    predicted: float | None  # q_total predicted at this sample, Sm3/h (None: no model yet)


class LearnedRow(NamedTuple):
    """A learned measurement, in learning order, with the sample it was paired with."""

    learn_seq: int
    time_ns: int
    source: str
    q_total: float
    sample: SampleRow


class PendingRow(NamedTuple):
    """A measurement still waiting for its sensor sample."""

    time_ns: int
    source: str
    q_total: float
    via: str


class ErrorRow(NamedTuple):
    """The prediction made at a learned measurement's sample, and the measured rate (Sm3/h)."""

    predicted: float | None
    measured: float


class DriftEventRow(NamedTuple):
    time_ns: int
    statistic: float | None
    p_value: float | None
    action: str


class ParameterRow(NamedTuple):
    """A well's physical parameters after learning up to ``time_ns`` (data time, epoch ns)."""

    time_ns: int
    version: int
    model: str
    parameters: str  # JSON {name: {value, std, unit, low, high, at_bound}}, SI units


class HistorySample(NamedTuple):
    """A stored sample with the prediction made for it (None where the model was not ready)."""

    time_ns: int
    choke: float
    p_up: float
    p_down: float
    t_up: float
    eta_gas: float
    eta_oil: float
    received_ns: int
    q_total: float | None
    q_gas: float | None
    q_oil: float | None
    q_water: float | None
    version: int | None
    q_total_std: float | None = None
    q_total_p05: float | None = None
    q_total_p95: float | None = None


class HistoryMeasurement(NamedTuple):
    """A stored measurement with its status, its paired sample and the prediction there."""

    time_ns: int
    source: str
    q_total: float
    received_ns: int
    via: str
    status: str  # pending | learned | unpaired | held (an instrument fault at its sample)
    # | review (held for review: service.engine.alarms.WellTestReview) | rejected (on review)
    sample_time_ns: int | None
    predicted: float | None
    version_after: int | None


class ModelVersionRow(NamedTuple):
    """An earlier model of a well (``model_versions``); ``blob`` is empty when not asked for."""

    well: str
    version: int
    created_ns: int
    data_time_ns: int | None
    learn_seq: int
    model: str
    method: str
    spec: str  # JSON [model, effects, method]
    note: str
    blob: bytes


class TrialRow(NamedTuple):
    """An ended trial (``trials``); ``summary`` is its JSON view."""

    well: str
    created_ns: int
    since_ns: int
    ended_ns: int | None
    model: str
    shadow_model: str
    outcome: str
    summary: str


@dataclass(frozen=True)
class CheckpointRow:
    well: str
    version: int
    learn_seq: int
    model: str
    method: str
    blob: bytes
    extra: str  # JSON side-car: drift state, learned inputs, drift events, model changes, spec
    created_ns: int


# -- writes -----------------------------------------------------------------------------------
class Op:
    """One write statement; a subclass is a dataclass (frozen, but for the one made per
    sample) whose fields are its parameters."""

    __slots__ = ()
    SQL: ClassVar[str]

    def statement(self) -> str:
        """The SQL statement (its class's ``SQL``, unless the operation builds its own)."""
        return self.SQL

    def params(self) -> Mapping[str, Any] | Sequence[Any]:
        """The statement's parameters by name (or in order, for a statement with ``?``)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]


@dataclass(frozen=True, slots=True)
class AddWell(Op):
    well: str
    created_ns: int
    origin: str  # history | config/store | first sight

    SQL: ClassVar[str] = (
        "INSERT OR IGNORE INTO wells (well, created_ns, origin) VALUES (:well, :created_ns, :origin)"
    )


@dataclass(slots=True)  # not frozen: made once per sample, and a frozen one costs 6x to make
class InsertSample(Op):
    """An accepted sensor sample with the prediction made for it (rates None: not ready)."""

    well: str
    time_ns: int
    inputs: tuple[float, ...]  # INPUT_FIELDS order
    received_ns: int
    q_total: float | None
    q_gas: float | None
    q_oil: float | None
    q_water: float | None
    version: int | None
    #: the prediction's sd and 90 % interval, Sm3/h (None: the method gives none)
    q_total_std: float | None = None
    q_total_p05: float | None = None
    q_total_p95: float | None = None

    # positional parameters: the service writes one row per sample, and a tuple costs a
    # fraction of a dict of 17 names (to build and to bind)
    SQL: ClassVar[str] = (
        "INSERT OR IGNORE INTO samples (well, time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil,"
        " received_ns, q_total, q_gas, q_oil, q_water, version, q_total_std, q_total_p05,"
        " q_total_p95)"
        " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
    )

    def params(self) -> tuple[Any, ...]:
        if len(self.inputs) != len(INPUT_FIELDS):
            raise ValueError(
                f"A sample needs {len(INPUT_FIELDS)} inputs ({', '.join(INPUT_FIELDS)}); "
                f"got {len(self.inputs)}."
            )
        return (
            self.well,
            self.time_ns,
            *self.inputs,
            self.received_ns,
            self.q_total,
            self.q_gas,
            self.q_oil,
            self.q_water,
            self.version,
            self.q_total_std,
            self.q_total_p05,
            self.q_total_p95,
        )


@dataclass(frozen=True, slots=True)
class InsertMeasurement(Op):
    """An accepted measurement, pending until it is learned or found unpaired."""

    well: str
    time_ns: int
    source: str
    q_total: float
    received_ns: int
    via: str  # zenoh | http

    SQL: ClassVar[str] = (
        "INSERT OR IGNORE INTO measurements (well, time_ns, source, q_total, received_ns, via, status)"
        " VALUES (:well, :time_ns, :source, :q_total, :received_ns, :via, 'pending')"
    )


@dataclass(frozen=True, slots=True)
class MarkLearned(Op):
    """A measurement learned from: its place in the learning order and the paired sample."""

    well: str
    source: str
    time_ns: int
    learn_seq: int
    sample: SampleRow
    version_after: int

    SQL: ClassVar[str] = (
        "UPDATE measurements SET status = 'learned', learn_seq = :learn_seq,"
        " sample_time_ns = :sample_time_ns, choke = :choke, p_up = :p_up, p_down = :p_down,"
        " t_up = :t_up, eta_gas = :eta_gas, eta_oil = :eta_oil, predicted = :predicted,"
        " version_after = :version_after"
        " WHERE well = :well AND source = :source AND time_ns = :time_ns"
    )

    def params(self) -> Mapping[str, Any]:
        return {
            "well": self.well,
            "source": self.source,
            "time_ns": self.time_ns,
            "learn_seq": self.learn_seq,
            "sample_time_ns": self.sample.time_ns,
            **dict(zip(INPUT_FIELDS, self.sample.inputs, strict=True)),
            "predicted": self.sample.predicted,
            "version_after": self.version_after,
        }


@dataclass(frozen=True, slots=True)
class MarkUnpaired(Op):
    well: str
    source: str
    time_ns: int

    SQL: ClassVar[str] = (
        "UPDATE measurements SET status = 'unpaired'"
        " WHERE well = :well AND source = :source AND time_ns = :time_ns"
    )


@dataclass(frozen=True, slots=True)
class MarkHeld(Op):
    """A measurement not learned from: its sample's inputs had an instrument fault
    (:mod:`vfm_core.sensor_faults`). Stored with status ``held``."""

    well: str
    source: str
    time_ns: int

    SQL: ClassVar[str] = (
        "UPDATE measurements SET status = 'held'"
        " WHERE well = :well AND source = :source AND time_ns = :time_ns"
    )


class ReviewRow(NamedTuple):
    """A measurement held for review (``reviews``; :class:`service.engine.alarms.WellTestReview`):
    its rate and the model's prediction (Sm3/h), the predictive sd in log space, z, the
    median of the MPFM readings near it (Sm3/h; None: none), the reason (a sentence), the
    paired sample, when it was held (wall time, ns) and the operator's decision (None while
    open; accept | reject) with its wall time (ns)."""

    well: str
    time_ns: int
    source: str
    q_total: float
    predicted: float
    sd_log: float
    z: float
    mpfm: float | None
    reason: str
    sample: SampleRow
    held_ns: int
    decision: str | None = None
    decided_ns: int | None = None


@dataclass(frozen=True, slots=True)
class InsertReview(Op):
    """Hold a measurement for review: its ``reviews`` row (the measurement's status is set
    to ``review`` by the same op list, :class:`MarkReview`)."""

    row: ReviewRow

    SQL: ClassVar[str] = (
        "INSERT OR REPLACE INTO reviews (well, time_ns, source, q_total, predicted, sd_log, z,"
        " mpfm, reason, sample_time_ns, choke, p_up, p_down, t_up, eta_gas, eta_oil,"
        " sample_predicted, held_ns) VALUES (:well, :time_ns, :source, :q_total, :predicted,"
        " :sd_log, :z, :mpfm, :reason, :sample_time_ns, :choke, :p_up, :p_down, :t_up,"
        " :eta_gas, :eta_oil, :sample_predicted, :held_ns)"
    )

    def params(self) -> Mapping[str, Any]:
        r = self.row
        return {
            "well": r.well,
            "time_ns": r.time_ns,
            "source": r.source,
            "q_total": r.q_total,
            "predicted": r.predicted,
            "sd_log": r.sd_log,
            "z": r.z,
            "mpfm": r.mpfm,
            "reason": r.reason,
            "sample_time_ns": r.sample.time_ns,
            **dict(zip(INPUT_FIELDS, r.sample.inputs, strict=True)),
            "sample_predicted": r.sample.predicted,
            "held_ns": r.held_ns,
        }


@dataclass(frozen=True, slots=True)
class MarkReview(Op):
    """A measurement held for review, not learned from (status ``review``)."""

    well: str
    source: str
    time_ns: int

    SQL: ClassVar[str] = (
        "UPDATE measurements SET status = 'review'"
        " WHERE well = :well AND source = :source AND time_ns = :time_ns"
    )


@dataclass(frozen=True, slots=True)
class DecideReview(Op):
    """The operator's decision on a held measurement (``accept``: it is learned, its
    status set by :class:`MarkLearned`; ``reject``: status ``rejected``) at ``decided_ns``
    (wall time)."""

    well: str
    source: str
    time_ns: int
    decision: str  # accept | reject
    decided_ns: int

    SQL: ClassVar[str] = (
        "UPDATE reviews SET decision = :decision, decided_ns = :decided_ns"
        " WHERE well = :well AND source = :source AND time_ns = :time_ns"
    )


@dataclass(frozen=True, slots=True)
class MarkRejected(Op):
    """A held measurement the operator rejected: stored, never learned (status ``rejected``)."""

    well: str
    source: str
    time_ns: int

    SQL: ClassVar[str] = (
        "UPDATE measurements SET status = 'rejected'"
        " WHERE well = :well AND source = :source AND time_ns = :time_ns"
    )


@dataclass(frozen=True, slots=True)
class InsertCheckpoint(Op):
    well: str
    created_ns: int
    version: int
    learn_seq: int
    model: str
    method: str
    blob: bytes
    extra: str

    SQL: ClassVar[str] = (
        "INSERT INTO checkpoints (well, created_ns, version, learn_seq, model, method, blob, extra)"
        " VALUES (:well, :created_ns, :version, :learn_seq, :model, :method, :blob, :extra)"
    )


@dataclass(frozen=True, slots=True)
class PruneCheckpoints(Op):
    """Keep only the well's latest ``keep`` checkpoints."""

    well: str
    keep: int

    SQL: ClassVar[str] = (
        "DELETE FROM checkpoints WHERE well = :well AND id NOT IN"
        " (SELECT id FROM checkpoints WHERE well = :well ORDER BY id DESC LIMIT :keep)"
    )


@dataclass(frozen=True, slots=True)
class InsertDriftEvent(Op):
    well: str
    time_ns: int
    statistic: float
    p_value: float
    action: str  # recorded | retrained

    SQL: ClassVar[str] = (
        "INSERT OR IGNORE INTO drift_events (well, time_ns, statistic, p_value, action)"
        " VALUES (:well, :time_ns, :statistic, :p_value, :action)"
    )


@dataclass(frozen=True, slots=True)
class InsertResidualAlarm(Op):
    """A residual alarm began (``kind`` start) or ended (end) on a well's meter stream
    (:mod:`service.engine.residual_alarms`); ``time_ns`` is the data time."""

    well: str
    time_ns: int
    source: str
    kind: str  # start | end
    direction: str  # high: measured above the model | low
    statistic: float
    threshold: float

    SQL: ClassVar[str] = (
        "INSERT OR IGNORE INTO residual_alarms"
        " (well, time_ns, source, kind, direction, statistic, threshold)"
        " VALUES (:well, :time_ns, :source, :kind, :direction, :statistic, :threshold)"
    )


@dataclass(frozen=True, slots=True)
class InsertParameters(Op):
    """A well's physical parameters at a data time (see ``parameter_history``)."""

    well: str
    time_ns: int
    version: int
    model: str
    parameters: str  # JSON

    SQL: ClassVar[str] = (
        "INSERT INTO parameter_history (well, time_ns, version, model, parameters)"
        " VALUES (:well, :time_ns, :version, :model, :parameters)"
    )


@dataclass(frozen=True, slots=True)
class PruneParameters(Op):
    """Keep only the well's latest ``keep`` parameter rows."""

    well: str
    keep: int

    SQL: ClassVar[str] = (
        "DELETE FROM parameter_history WHERE well = :well AND id <="
        " (SELECT id FROM parameter_history WHERE well = :well ORDER BY id DESC"
        " LIMIT 1 OFFSET :keep)"
    )


@dataclass(frozen=True, slots=True)
class RetireWell(Op):
    """Mark a well retired: its data stay, the service no longer loads or serves it."""

    well: str
    retired_ns: int

    SQL: ClassVar[str] = "UPDATE wells SET retired_ns = :retired_ns WHERE well = :well"


#: the tables that hold a well's rows, as :class:`DeleteWellRows` may name them
_WELL_TABLES = (
    "samples",
    "measurements",
    "checkpoints",
    "drift_events",
    "residual_alarms",
    "parameter_history",
    "model_versions",
    "trials",
    "reviews",
    "wells",
)


@dataclass(frozen=True, slots=True)
class DeleteWellRows(Op):
    """Delete every row of a well from one of its tables (a purge)."""

    well: str
    table: str

    def __post_init__(self) -> None:
        if self.table not in _WELL_TABLES:
            raise ValueError(f"'{self.table}' is not a table of well rows")

    SQL: ClassVar[str] = "DELETE FROM <table> WHERE well = :well"

    def statement(self) -> str:
        return self.SQL.replace("<table>", self.table)  # a whitelisted table name

    def params(self) -> Mapping[str, Any]:
        return {"well": self.well}


def purge_ops(well: str) -> list[Op]:
    """The writes that remove every row of a well (samples, measurements, checkpoints, ...)."""
    return [DeleteWellRows(well=well, table=t) for t in _WELL_TABLES]


@dataclass(frozen=True, slots=True)
class InsertModelVersion(Op):
    """Keep the model a well ran until a model change or a rollback (``model_versions``)."""

    well: str
    version: int
    created_ns: int
    data_time_ns: int | None
    learn_seq: int
    model: str
    method: str
    spec: str
    note: str
    blob: bytes

    SQL: ClassVar[str] = (
        "INSERT INTO model_versions (well, version, created_ns, data_time_ns, learn_seq, model,"
        " method, spec, note, blob) VALUES (:well, :version, :created_ns, :data_time_ns,"
        " :learn_seq, :model, :method, :spec, :note, :blob)"
    )


@dataclass(frozen=True, slots=True)
class PruneModelVersions(Op):
    """Keep only the well's latest ``keep`` earlier model versions."""

    well: str
    keep: int

    SQL: ClassVar[str] = (
        "DELETE FROM model_versions WHERE well = :well AND id NOT IN"
        " (SELECT id FROM model_versions WHERE well = :well ORDER BY id DESC LIMIT :keep)"
    )


@dataclass(frozen=True, slots=True)
class InsertTrial(Op):
    """An ended trial of a model change against its shadow (``trials``)."""

    well: str
    created_ns: int
    since_ns: int
    ended_ns: int | None
    model: str
    shadow_model: str
    outcome: str
    summary: str  # JSON

    SQL: ClassVar[str] = (
        "INSERT INTO trials (well, created_ns, since_ns, ended_ns, model, shadow_model, outcome,"
        " summary) VALUES (:well, :created_ns, :since_ns, :ended_ns, :model, :shadow_model,"
        " :outcome, :summary)"
    )


# -- reading helpers --------------------------------------------------------------------------
_Row = TypeVar("_Row")

_SAMPLE_COLUMNS = "time_ns, " + ", ".join(INPUT_FIELDS) + ", q_total"


def _named(cursor: sqlite3.Cursor) -> Iterator[dict[str, Any]]:
    """The cursor's rows as column name -> value."""
    names = [d[0] for d in cursor.description]
    for values in cursor:
        yield dict(zip(names, values, strict=True))


def _fetch(cursor: sqlite3.Cursor, row: type[_Row]) -> list[_Row]:
    return [row(**named) for named in _named(cursor)]


def _sample_row(
    named: Mapping[str, Any], time: str = "time_ns", predicted: str = "q_total"
) -> SampleRow:
    """A :class:`SampleRow` from named columns (a sample's own, or a learned measurement's copy)."""
    return SampleRow(named[time], tuple(named[k] for k in INPUT_FIELDS), named[predicted])


#: rows of samples a multi-row statement inserts (17 values a row; SQLite allows 32,766)
_ROWS_PER_STATEMENT = 64


@functools.lru_cache(maxsize=8)
def _multi_row(rows: int) -> str:
    """The statement of :class:`InsertSample` for ``rows`` rows (each ignored on conflict
    alone, as one by one)."""
    head, values = InsertSample.SQL.split(" VALUES ")
    return f"{head} VALUES {', '.join([values] * rows)}"


def _insert_rows(con: sqlite3.Connection, rows: Sequence[Any]) -> int:
    """Insert sample rows in statements of :data:`_ROWS_PER_STATEMENT` rows and the rest in
    halving sizes (few distinct statements; one step of SQLite, and one release of the GIL,
    each); the number of rows written."""
    changed, i, n = 0, 0, len(rows)
    size = _ROWS_PER_STATEMENT
    while i < n:
        while size > n - i:
            size //= 2
        flat = [value for row in rows[i : i + size] for value in row]
        changed += con.execute(_multi_row(size), flat).rowcount
        i += size
    return changed


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
            self._migrate(str(row[0]))
        self._readers: list[sqlite3.Connection] = []
        #: called with the ops of every successful commit, on the writing thread (the
        #: engine's :class:`~service.engine.observe.Observer`); it must not block
        self.on_commit: Callable[[Sequence[Op]], None] | None = None

    def _migrate(self, version: str) -> None:
        """Bring an older store to :data:`SCHEMA_VERSION` in place, one version at a time."""
        if version not in _MIGRATIONS:
            raise ConfigError(
                f"The store {self.path} has schema version {version}, this service writes "
                f"version {SCHEMA_VERSION} and reads versions up to it; use a new store.path "
                "or a newer version of the service."
            )
        con = self._writer
        while version != SCHEMA_VERSION:
            steps = _MIGRATIONS.get(version)
            if steps is None:  # pragma: no cover - a gap in _MIGRATIONS
                raise ConfigError(f"No migration of the store from schema version {version}.")
            con.execute("BEGIN IMMEDIATE")
            try:
                for statement in steps:
                    con.execute(statement)
                version = str(int(version) + 1)
                con.execute("UPDATE meta SET value = ? WHERE key = 'schema'", (version,))
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise

    def _connect(self) -> sqlite3.Connection:
        con = sqlite3.connect(
            self.path, isolation_level=None, check_same_thread=False, timeout=30.0
        )
        con.execute("PRAGMA journal_mode=WAL")
        con.execute(f"PRAGMA synchronous={self.synchronous.upper()}")
        con.execute("PRAGMA busy_timeout=30000")
        return con

    # -- writing ------------------------------------------------------------------------
    def write(self, ops: Sequence[Op]) -> int:
        """Run the operations in one transaction, in order; the number of rows they changed.

        Consecutive operations of the same statement (a batch's samples) run together:
        samples as multi-row statements (:func:`_insert_rows`), others as one
        ``executemany``: the same rows, without a call per row."""
        if not ops:
            return 0
        changed = 0
        with self._lock:
            con = self._writer
            con.execute("BEGIN IMMEDIATE")
            try:
                i, n = 0, len(ops)
                while i < n:
                    statement = ops[i].statement()
                    j = i + 1
                    while (
                        j < n and type(ops[j]) is type(ops[i]) and ops[j].statement() == statement
                    ):
                        j += 1
                    if j - i == 1:
                        changed += con.execute(statement, ops[i].params()).rowcount
                    elif type(ops[i]) is InsertSample:
                        changed += _insert_rows(con, [op.params() for op in ops[i:j]])
                    else:
                        changed += con.executemany(
                            statement, [op.params() for op in ops[i:j]]
                        ).rowcount
                    i = j
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
        if self.on_commit is not None:
            try:
                self.on_commit(ops)
            except Exception as exc:  # pragma: no cover - what is committed stays committed
                logger.warning("The commit observer failed: %s", exc)
        return changed

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
        """The wells in service (not retired), in the order they were added."""
        with self.reader() as con:
            return [
                r[0]
                for r in con.execute(
                    "SELECT well FROM wells WHERE retired_ns IS NULL ORDER BY created_ns, well"
                )
            ]

    def retired_wells(self) -> dict[str, int]:
        """Retired wells (their data kept) -> when they were retired (epoch ns)."""
        with self.reader() as con:
            return {
                r[0]: int(r[1])
                for r in con.execute(
                    "SELECT well, retired_ns FROM wells WHERE retired_ns IS NOT NULL"
                )
            }

    def recent_rates(self, well: str, n: int) -> list[float]:
        """The q_total (Sm3/h) of the well's last ``n`` stored measurements, oldest first."""
        with self.reader() as con:
            rows = con.execute(
                "SELECT q_total FROM measurements WHERE well = ? AND status != 'unpaired'"
                " ORDER BY time_ns DESC LIMIT ?",
                (well, n),
            ).fetchall()
        return [float(r[0]) for r in rows[::-1]]

    def latest_checkpoint(self, well: str) -> CheckpointRow | None:
        with self.reader() as con:
            rows = _fetch(
                con.execute(
                    "SELECT well, version, learn_seq, model, method, blob, extra, created_ns"
                    " FROM checkpoints WHERE well = ? ORDER BY id DESC LIMIT 1",
                    (well,),
                ),
                CheckpointRow,
            )
        return rows[0] if rows else None

    def model_versions(self, well: str) -> list[ModelVersionRow]:
        """The well's kept earlier models, newest first, without their blobs."""
        with self.reader() as con:
            rows = con.execute(
                "SELECT well, version, created_ns, data_time_ns, learn_seq, model, method, spec,"
                " note FROM model_versions WHERE well = ? ORDER BY id DESC",
                (well,),
            ).fetchall()
        return [ModelVersionRow(*(*r, b"")) for r in rows]

    def model_version(self, well: str, version: int) -> ModelVersionRow | None:
        """One kept earlier model of the well, with its checkpoint; None if not kept."""
        with self.reader() as con:
            r = con.execute(
                "SELECT well, version, created_ns, data_time_ns, learn_seq, model, method, spec,"
                " note, blob FROM model_versions WHERE well = ? AND version = ?"
                " ORDER BY id DESC LIMIT 1",
                (well, version),
            ).fetchone()
        return ModelVersionRow(*r) if r is not None else None

    def trials(self, well: str, limit: int = 20) -> list[TrialRow]:
        """The well's ended trials, newest first."""
        with self.reader() as con:
            rows = con.execute(
                "SELECT well, created_ns, since_ns, ended_ns, model, shadow_model, outcome,"
                " summary FROM trials WHERE well = ? ORDER BY id DESC LIMIT ?",
                (well, limit),
            ).fetchall()
        return [TrialRow(*r) for r in rows]

    def learned_after(self, well: str, learn_seq: int) -> list[LearnedRow]:
        """Learned measurements after ``learn_seq``, in learning order, with their samples."""
        with self.reader() as con:
            cursor = con.execute(
                "SELECT learn_seq, time_ns, source, q_total, sample_time_ns, "
                + ", ".join(INPUT_FIELDS)
                + ", predicted FROM measurements"
                " WHERE well = ? AND status = 'learned' AND learn_seq > ? ORDER BY learn_seq",
                (well, learn_seq),
            )
            return [
                LearnedRow(
                    r["learn_seq"],
                    r["time_ns"],
                    r["source"],
                    r["q_total"],
                    _sample_row(r, time="sample_time_ns", predicted="predicted"),
                )
                for r in _named(cursor)
            ]

    def recent_errors(self, well: str, n: int, min_version: int | None = None) -> list[ErrorRow]:
        """The last ``n`` learned measurements, oldest first (only those learned at model
        version ``min_version`` or later, when given)."""
        with self.reader() as con:
            rows = _fetch(
                con.execute(
                    "SELECT predicted, q_total AS measured FROM measurements"
                    " WHERE well = ? AND status = 'learned'"
                    " AND version_after >= ? ORDER BY learn_seq DESC LIMIT ?",
                    (well, -1 if min_version is None else min_version, n),
                ),
                ErrorRow,
            )
        return rows[::-1]

    def pending(self, well: str) -> list[PendingRow]:
        """Measurements still waiting for a sample, in arrival order."""
        with self.reader() as con:
            return _fetch(
                con.execute(
                    "SELECT time_ns, source, q_total, via FROM measurements"
                    " WHERE well = ? AND status = 'pending' ORDER BY id",
                    (well,),
                ),
                PendingRow,
            )

    def recent_samples(self, well: str, n: int) -> list[SampleRow]:
        """The last ``n`` samples, oldest first."""
        with self.reader() as con:
            cursor = con.execute(
                f"SELECT {_SAMPLE_COLUMNS} FROM samples"  # noqa: S608 - constant columns
                " WHERE well = ? ORDER BY time_ns DESC LIMIT ?",
                (well, n),
            )
            rows = [_sample_row(r) for r in _named(cursor)]
        return rows[::-1]

    def latest_prediction(self, well: str) -> tuple[int, float, float | None, float | None] | None:
        """The well's latest stored prediction: time (ns), q_total and its 90 % interval's
        p05, p95 (Sm3/h; None for a method without one); None before any."""
        with self.reader() as con:
            row = con.execute(
                "SELECT time_ns, q_total, q_total_p05, q_total_p95 FROM samples"
                " WHERE well = ? AND q_total IS NOT NULL ORDER BY time_ns DESC LIMIT 1",
                (well,),
            ).fetchone()
        return None if row is None else (int(row[0]), float(row[1]), row[2], row[3])

    def nearest_sample(self, well: str, time_ns: int, tolerance_ns: int) -> SampleRow | None:
        """The stored sample nearest to ``time_ns`` within the tolerance, or None."""
        with self.reader() as con:
            before = [
                _sample_row(r)
                for r in _named(
                    con.execute(
                        f"SELECT {_SAMPLE_COLUMNS} FROM samples"  # noqa: S608
                        " WHERE well = ? AND time_ns <= ? AND time_ns >= ?"
                        " ORDER BY time_ns DESC LIMIT 1",
                        (well, time_ns, time_ns - tolerance_ns),
                    )
                )
            ]
            after = [
                _sample_row(r)
                for r in _named(
                    con.execute(
                        f"SELECT {_SAMPLE_COLUMNS} FROM samples"  # noqa: S608
                        " WHERE well = ? AND time_ns > ? AND time_ns <= ?"
                        " ORDER BY time_ns ASC LIMIT 1",
                        (well, time_ns, time_ns + tolerance_ns),
                    )
                )
            ]
        found = before + after
        return min(found, key=lambda r: abs(r.time_ns - time_ns)) if found else None

    def measurement_exists(self, well: str, source: str, time_ns: int) -> bool:
        with self.reader() as con:
            return (
                con.execute(
                    "SELECT 1 FROM measurements WHERE well = ? AND source = ? AND time_ns = ?",
                    (well, source, time_ns),
                ).fetchone()
                is not None
            )

    def drift_events(self, well: str, limit: int = 20) -> list[DriftEventRow]:
        with self.reader() as con:
            rows = _fetch(
                con.execute(
                    "SELECT time_ns, statistic, p_value, action FROM drift_events WHERE well = ?"
                    " ORDER BY time_ns DESC LIMIT ?",
                    (well, limit),
                ),
                DriftEventRow,
            )
        return rows[::-1]

    def history(
        self, well: str, start_ns: int, end_ns: int, limit: int
    ) -> tuple[list[HistorySample], list[HistoryMeasurement]]:
        """Samples (with predictions) and measurements of a well in [start, end), time order."""
        with self.reader() as con:
            samples = _fetch(
                con.execute(
                    "SELECT time_ns, " + ", ".join(INPUT_FIELDS) + ", received_ns,"
                    " q_total, q_gas, q_oil, q_water, version, q_total_std, q_total_p05,"
                    " q_total_p95 FROM samples"
                    " WHERE well = ? AND time_ns >= ? AND time_ns < ? ORDER BY time_ns LIMIT ?",
                    (well, start_ns, end_ns, limit),
                ),
                HistorySample,
            )
            measurements = _fetch(
                con.execute(
                    "SELECT time_ns, source, q_total, received_ns, via, status, sample_time_ns,"
                    " predicted, version_after FROM measurements"
                    " WHERE well = ? AND time_ns >= ? AND time_ns < ?"
                    " ORDER BY time_ns, source LIMIT ?",
                    (well, start_ns, end_ns, limit),
                ),
                HistoryMeasurement,
            )
        return samples, measurements

    def parameter_history(
        self, well: str, start_ns: int, end_ns: int, limit: int
    ) -> tuple[list[ParameterRow], bool]:
        """The well's latest ``limit`` parameter rows in [start, end), in time order, and
        whether more rows lay in the window (the older ones left out)."""
        with self.reader() as con:
            rows = _fetch(
                con.execute(
                    "SELECT time_ns, version, model, parameters FROM parameter_history"
                    " WHERE well = ? AND time_ns >= ? AND time_ns < ?"
                    " ORDER BY time_ns DESC, id DESC LIMIT ?",
                    (well, start_ns, end_ns, limit + 1),
                ),
                ParameterRow,
            )
        more = len(rows) > limit
        return rows[:limit][::-1], more

    def mpfm_near(self, well: str, time_ns: int, window_ns: int) -> list[tuple[int, float]]:
        """The well's MPFM readings within ``window_ns`` of ``time_ns``: (epoch ns, q_total
        in Sm3/h) each."""
        return self._near(
            "SELECT time_ns, q_total FROM measurements WHERE well = ? AND source = 'mpfm'"
            " AND time_ns >= ? AND time_ns <= ?",
            well,
            time_ns,
            window_ns,
        )

    def chokes_near(self, well: str, time_ns: int, window_ns: int) -> list[tuple[int, float]]:
        """The well's samples within ``window_ns`` of ``time_ns``, oldest first: (epoch ns,
        choke reading as a fraction open) each (one indexed range query)."""
        return self._near(
            "SELECT time_ns, choke FROM samples WHERE well = ? AND time_ns >= ? AND time_ns <= ?"
            " ORDER BY time_ns",
            well,
            time_ns,
            window_ns,
        )

    def _near(self, sql: str, well: str, time_ns: int, window_ns: int) -> list[tuple[int, float]]:
        """(epoch ns, value) rows of ``sql`` (constant, with the well and the window's two
        ends as its parameters) within ``window_ns`` of ``time_ns``."""
        with self.reader() as con:
            rows = con.execute(sql, (well, time_ns - window_ns, time_ns + window_ns)).fetchall()
        return [(int(r[0]), float(r[1])) for r in rows]

    def reviews(
        self, well: str, source: str | None = None, time_ns: int | None = None, limit: int = 100
    ) -> list[ReviewRow]:
        """The well's measurements held for review and not decided yet, oldest first (the
        latest ``limit``); with ``source`` and ``time_ns``, that one measurement's row
        whether decided or not (none: an empty list)."""
        one = source is not None and time_ns is not None
        where = "source = ? AND time_ns = ?" if one else "decision IS NULL"
        args: tuple[Any, ...] = (well, source, time_ns, 1) if one else (well, limit)
        with self.reader() as con:
            cursor = con.execute(
                "SELECT * FROM reviews WHERE well = ? AND "  # noqa: S608 - constant clauses
                + where
                + " ORDER BY time_ns DESC LIMIT ?",
                args,
            )
            rows = [
                ReviewRow(
                    r["well"],
                    r["time_ns"],
                    r["source"],
                    r["q_total"],
                    r["predicted"],
                    r["sd_log"],
                    r["z"],
                    r["mpfm"],
                    r["reason"],
                    _sample_row(r, time="sample_time_ns", predicted="sample_predicted"),
                    r["held_ns"],
                    r["decision"],
                    r["decided_ns"],
                )
                for r in _named(cursor)
            ]
        return rows[::-1]

    def latest_learned(self, well: str, source: str) -> int | None:
        """The time (epoch ns) of the well's latest learned measurement of ``source``."""
        with self.reader() as con:
            row = con.execute(
                "SELECT MAX(time_ns) FROM measurements WHERE well = ? AND source = ?"
                " AND status = 'learned'",
                (well, source),
            ).fetchone()
        return int(row[0]) if row is not None and row[0] is not None else None

    def latest_well_tests(self, well: str, n: int) -> list[tuple[int, float]]:
        """The time (epoch ns) and q_total (Sm3/h) of the well's last ``n`` stored well
        tests, oldest first."""
        with self.reader() as con:
            rows = con.execute(
                "SELECT time_ns, q_total FROM measurements WHERE well = ? AND source = 'well_test'"
                " AND status != 'unpaired' ORDER BY time_ns DESC LIMIT ?",
                (well, int(n)),
            ).fetchall()
        return [(int(t), float(q)) for t, q in reversed(rows)]

    def counts(self) -> dict[str, int]:
        with self.reader() as con:
            return {
                table: int(con.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])  # noqa: S608
                for table in (
                    "wells",
                    "samples",
                    "measurements",
                    "checkpoints",
                    "drift_events",
                    "parameter_history",
                )
            }
