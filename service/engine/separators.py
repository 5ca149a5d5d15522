"""Separator readings in the service: intake, waiting for the wells' samples, the joint
update, the allocation, what is stored and published (``docs/guide/separator.md``).

A separator (or export meter) measures the total of the wells that flow into it
(``separators.members``). A reading arrives on ``<prefix>/<separator>/measurements/separator``
(``{time, q_total}``, Sm3/h) or ``POST /separators/{name}/measurements``; the intake checks it
as it checks a measurement (:func:`parse_reading`, then the time and rate checks; an unknown
separator is refused as ``unknown separator``) and queues a :class:`SeparatorItem` at the
separator's worker. Every well of a separator is routed to that same worker
(:meth:`service.config.SeparatorSettings.route`), so the joint update reads and writes all
its wells' learners there, with no lock across workers.

**Which sample of each well counts** follows :mod:`vfm_core.separator_format`, as offline:
a reading at t measures the sum of its wells' rates at t; each well contributes its
prediction at its latest sample at or before t if that sample is at most
``separators.sample_window_s`` old (6 h), else (no sample, an older one, or a closed choke)
it counts as shut in and contributes 0. So a reading waits (status ``pending``) until every
member well has a sample at or after t, at most ``inputs.pending_timeout_s`` of wall time (a
shut-in well that sends nothing holds it that long), and at most ``inputs.pending_max``
readings wait per separator (the oldest is then settled with the samples there are).

**The joint update** (:class:`Separators`): the learning steps of the batch are run first
(a well test before the reading is learned before it), then the members' one-well ``bayes``
filters are seen as one filter (:class:`vfm_core.separator.WellFilters`) and
:class:`vfm_core.separator.SeparatorLearner` allocates the reading and makes the joint
update, exactly as ``vfm evaluate`` does.

**Cross-covariances** (``separators.cross``, default true, as ``run_separator``): each
separator's joint covariance between its wells' parameters is kept here, on its worker
(:class:`_Cross`), updated at every joint update and carried at every measurement a
member learns through its one-well filter (:class:`service.engine.learning.JointLearning`:
:meth:`Separators.before_learn` takes the well's covariance grown to the measurement,
:meth:`Separators.carry` hands the step to
:meth:`vfm_core.separator.SeparatorLearner.carry_well_tests`, which moves the partners).
Such a member's step is therefore never deferred to the end of the worker batch, and the
samples taken before it are predicted first. A member whose model was replaced, retired,
reset by its filter or moved otherwise (a retrain on a drift: its version is not the one
last seen here) shares nothing any more: its rows start at zero. A member without a model
yet is not touched by a carry (its first measurement starts it at its start variance).
``cross = false`` keeps none (block-diagonal: each member's own filter state holds all
there is).

**Restart.** Every step that moves the joint state (a reading learned, a carried step)
writes, in its own transaction, a checkpoint of every member whose model moved and the
separator's joint state (``separator_states``, :class:`SaveJoint`, with the members'
model versions). So the store always holds them together: a restart restores the members
and the joint state as they were after the last such step; what a member learned after
it without a carry (nothing to carry: it shares nothing yet) is re-learned from the store
as usual, and a member whose restored version is not the one the joint state was kept
with (a model rebuilt) has its rows dropped.
Wells with another method (``ol``, ``pbl``) do not learn from the total (their fit is a
per-well objective; see :func:`vfm_core.separator.check_method`): a reading with such a
well flowing is stored with the sum of the wells' predictions and the residual, not
allocated (status ``unused``, counted as the event ``separator readings unused``).

**Output**, once the batch is committed: the allocation on ``<prefix>/<separator>/allocation``
(:func:`allocation_message`), the reading's row in ``separator_readings`` with its status,
the sum of the predictions and the reconciliation residual (measured total minus that
sum), and a row per member well in ``allocations``; ``GET /separators/{name}``
(:meth:`Separators.view`) reads them back.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from dataclasses import dataclass
from datetime import UTC
from typing import Any, ClassVar

import numpy as np
import pandas as pd
import torch

from service.config import Settings
from service.engine.checkpoints import Checkpoints
from service.engine.items import Batch, MeasurementItem, refuse
from service.engine.learning import Learning
from service.engine.state import Sample, WellState
from service.errors import Duplicate, InvalidRequest
from service.inputs import Counters, Limits, parse_measurement
from service.store import INPUT_FIELDS, Op, Store
from vfm_core.data import DTYPE
from vfm_core.data import Batch as DataBatch
from vfm_core.errors import ConfigError
from vfm_core.learning.method import NEVER
from vfm_core.learning.streaming.samples import one_sample
from vfm_core.messages import Measurement
from vfm_core.separator import (
    Allocation,
    SeparatorLearner,
    WellFilters,
    WellTestMark,
    check_method,
)
from vfm_core.separator_format import SEPARATOR_SOURCE
from vfm_core.timeutil import iso, to_ns

__all__ = [
    "SeparatorItem",
    "Separators",
    "parse_reading",
    "is_separator_key",
    "reading_key",
    "allocation_key",
    "allocation_message",
    "submit_item",
    "InsertReading",
    "SettleReading",
    "InsertAllocation",
    "SaveJoint",
]

logger = logging.getLogger("vfm.service.engine")

_READING_TAIL = f"/measurements/{SEPARATOR_SOURCE}"
#: reading times kept per separator for the duplicate check (the store has them all)
_SEEN = 1024
_ALLOCATION_TAIL = "/allocation"
#: the readings' statuses in the store
STATUSES = ("pending", "learned", "allocated", "unused")


def reading_key(prefix: str, separator: str) -> str:
    """The key a separator's readings arrive on."""
    return f"{prefix}/{separator}{_READING_TAIL}"


def allocation_key(prefix: str, separator: str) -> str:
    """The key a separator's allocations are published on."""
    return f"{prefix}/{separator}{_ALLOCATION_TAIL}"


def is_separator_key(key: str) -> bool:
    """Whether ``key`` is a separator's reading or allocation (cheap: on every message)."""
    return key.endswith(_READING_TAIL) or key.endswith(_ALLOCATION_TAIL)


@dataclass(slots=True)
class SeparatorItem(MeasurementItem):
    """A separator's reading, checked, queued in its separator's FIFO: ``well`` is the
    separator's name, ``measurement`` its time and total (Sm3/h), ``source`` ``separator``."""


def parse_reading(
    settings: Settings, key: str, payload: bytes, limits: Limits, received_ns: int
) -> SeparatorItem | None:
    """The reading on ``key`` (None: an allocation, another instance's output), or the
    refusal: an unknown separator, or a payload that fails a measurement's checks (not
    finite, negative, missing, ...). The time and rate are checked by the intake."""
    rest = key[len(settings.prefix) + 1 :] if key.startswith(settings.prefix + "/") else ""
    name, _, tail = rest.partition("/")
    if "/" + tail == _ALLOCATION_TAIL:
        return None
    if not name or "/" + tail != _READING_TAIL:
        raise InvalidRequest(
            f"The key {key[:120]!r} is not {settings.prefix}/<separator>{_READING_TAIL}.",
            "unparseable key",
        )
    known = settings.separators.members
    if name not in known:
        listed = ", ".join(sorted(known)[:10]) or "none"
        raise InvalidRequest(
            f"The separator {name[:128]!r} is not one of separators.members ({listed}); its "
            "reading was not taken in. Map its wells to it in the configuration.",
            "unknown separator",
        )
    measurement = parse_measurement(payload, limits)
    return SeparatorItem(name, measurement, SEPARATOR_SOURCE, received_ns)


# -- the store's rows ----------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class InsertReading(Op):
    """An accepted separator reading, pending until its wells' samples are in."""

    separator: str
    time_ns: int
    q_total: float
    received_ns: int
    via: str

    SQL: ClassVar[str] = (
        "INSERT OR IGNORE INTO separator_readings (separator, time_ns, q_total, received_ns,"
        " via, status) VALUES (:separator, :time_ns, :q_total, :received_ns, :via, 'pending')"
    )


@dataclass(frozen=True, slots=True)
class SettleReading(Op):
    """What became of a reading: its status, the sum of its wells' predictions and the
    reconciliation residual (Sm3/h; None when no well had a prediction), and why."""

    separator: str
    time_ns: int
    status: str
    predicted: float | None
    residual: float | None
    note: str

    SQL: ClassVar[str] = (
        "UPDATE separator_readings SET status = :status, predicted = :predicted,"
        " residual = :residual, note = :note WHERE separator = :separator AND time_ns = :time_ns"
    )


@dataclass(frozen=True, slots=True)
class InsertAllocation(Op):
    """One member well's part of a reading (Sm3/h; ``q_alloc`` etc. None: not allocated)."""

    separator: str
    time_ns: int
    well: str
    sample_time_ns: int | None
    q_pred: float
    q_alloc: float | None
    lo90: float | None
    hi90: float | None

    SQL: ClassVar[str] = (
        "INSERT OR REPLACE INTO allocations (separator, time_ns, well, sample_time_ns, q_pred,"
        " q_alloc, lo90, hi90) VALUES (:separator, :time_ns, :well, :sample_time_ns, :q_pred,"
        " :q_alloc, :lo90, :hi90)"
    )


@dataclass(frozen=True, slots=True)
class SaveJoint(Op):
    """A separator's kept cross-covariances (``joint``: float64 bytes of the [M D, M D]
    matrix), its wells and their models' versions (JSON), as of ``time_ns`` (data time)."""

    separator: str
    time_ns: int
    wells: str
    versions: str
    dim: int
    joint: bytes

    SQL: ClassVar[str] = (
        "INSERT OR REPLACE INTO separator_states (separator, time_ns, wells, versions, dim,"
        " joint) VALUES (:separator, :time_ns, :wells, :versions, :dim, :joint)"
    )


@dataclass
class _Cross:
    """A separator's kept cross-covariances: its joint wells in order, each one's filter
    (the learner's method object: a replaced model is noticed; None when restored from
    the store) and its model's version when last seen here (a model moved otherwise, e.g.
    retrained on a drift or rebuilt at a restart, is noticed), the joint covariance
    [M D, M D] and D."""

    wells: list[str]
    filters: list[object | None]
    versions: list[int]
    joint: torch.Tensor
    dim: int

    def keeps(self, well: str, st: WellState) -> bool:
        """Whether ``well``'s rows still hold for its model now (the same model)."""
        if well not in self.wells:
            return False
        k = self.wells.index(well)
        f = self.filters[k]
        same = f is None or f is st.learner.method
        return same and self.versions[k] == st.learner.version

    def carried_over(self, wells: list[str], keep: list[bool], dim: int) -> torch.Tensor:
        """The joint covariance for ``wells`` (D = ``dim``): the blocks between wells it
        keeps (``keep``), zero elsewhere (a new or replaced well shares nothing yet)."""
        if wells == self.wells and all(keep) and dim == self.dim:
            return self.joint
        new = torch.zeros(len(wells) * dim, len(wells) * dim, dtype=DTYPE)
        if dim != self.dim:
            return new
        pos = [(k, self.wells.index(w)) for k, w in enumerate(wells) if keep[k]]
        for a, oa in pos:
            for c, oc in pos:
                new[a * dim : (a + 1) * dim, c * dim : (c + 1) * dim] = self.joint[
                    oa * dim : (oa + 1) * dim, oc * dim : (oc + 1) * dim
                ]
        return new


@dataclass
class _CarryMark:
    """A member's learning step about to be carried to its partners (``cross``)."""

    sep: str
    learner: SeparatorLearner
    mark: WellTestMark


@dataclass
class _Waiting:
    """A stored reading waiting for its wells' samples."""

    time_ns: int
    q_total: float
    since: float  # time.monotonic() when it started waiting
    future: Future[Any] | None = None


@dataclass
class _Member:
    """A member well at a reading: its state (None: not served yet), the sample that
    counts (None: shut in) and whether it flows."""

    well: str
    st: WellState | None
    sample: Sample | None

    @property
    def flowing(self) -> bool:
        return self.sample is not None and self.sample.inputs[0] > 0.0

    @property
    def predicted(self) -> float:
        """The well's model's rate at its sample now (Sm3/h; 0 when shut in or without a
        model), as a well test would measure it; a model that needs features the sample
        does not hold, or a field-wide one, gives the prediction stored with the sample."""
        if self.sample is None or not self.flowing or self.st is None:
            return 0.0
        learner = self.st.learner
        if learner.model.extra_columns or learner.shares_model or not learner.ready:
            return float(self.sample.predicted or 0.0)
        x = torch.tensor(self.sample.inputs, dtype=DTYPE)
        batch = one_sample(x, 0.0, self.sample.time_ns, True, torch.zeros(0, dtype=DTYPE), ())
        with torch.no_grad():
            return float(learner.method.predict(batch).mean[0, 0])

    @property
    def state(self) -> WellState:
        """The well's state (of a member known to flow, or of a joint one)."""
        assert self.st is not None
        return self.st


def allocation_message(
    separator: str,
    time_ns: int,
    measured: float,
    members: list[dict[str, Any]],
    status: str,
    note: str,
) -> dict[str, Any]:
    """The allocation of one reading as published and as ``GET /separators/{name}`` shows
    it: rates in Sm3/h (``units``); ``predicted`` is the sum of the wells' predictions and
    ``residual`` = ``q_total`` - ``predicted`` (the reconciliation residual)."""
    predicted = sum(m["q_pred"] for m in members) if members else None
    residual = None if predicted is None else measured - predicted
    return {
        "separator": separator,
        "time": iso(time_ns),
        "q_total": measured,
        "predicted": predicted,
        "residual": residual,
        "residual_ratio": None if not measured or residual is None else residual / measured,
        "status": status,
        "note": note,
        "units": "Sm3/h",
        "wells": members,
    }


class Separators:
    """The separators of the engine: readings waiting, settled, allocated, learned from;
    see the module docstring. Every method but :meth:`view` and :meth:`overview` runs on
    the separator's worker."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        counters: Counters,
        learning: Learning,
        checkpoints: Checkpoints,
        wells: Mapping[str, WellState],
        publish_key: Callable[[str, bytes], None] | None,
        worker_of: Callable[[str], int],
    ) -> None:
        cfg = settings.separators
        self.settings = settings
        self.members = {sep: list(ws) for sep, ws in cfg.members.items()}
        self.separator_of = {w: sep for sep, ws in self.members.items() for w in ws}
        self.noise = cfg.noise
        self.learn = cfg.learn
        self.cross = cfg.cross
        self.window_ns = int(cfg.sample_window_s * 1e9)
        self.timeout_s = settings.inputs.pending_timeout_s
        self.pending_max = settings.inputs.pending_max
        self.store = store
        self.counters = counters
        self.learning = learning
        self.checkpoints = checkpoints
        self.wells = wells
        self.publish_key = publish_key
        self.worker = {sep: worker_of(sep) for sep in self.members}
        #: the readings waiting per separator, in time order (the worker's own)
        self.waiting: dict[str, list[_Waiting]] = {sep: [] for sep in self.members}
        #: the times of each separator's latest readings taken (the duplicate check before
        #: they are committed; older ones are looked up in the store)
        self._seen: dict[str, deque[int]] = {sep: deque(maxlen=_SEEN) for sep in self.members}
        #: the latest allocation published per separator (read by HTTP threads)
        self._latest: dict[str, dict[str, Any]] = {}
        self._lock = threading.Lock()
        #: each separator's kept cross-covariances (``cross``; the worker's own)
        self._cross: dict[str, _Cross] = {}
        #: the carry starts once the wells are loaded (re-learning at start carries nothing)
        self._loaded = False
        if self.cross:
            learning.joint = self

    def load(self) -> None:
        """After a restart: the readings still pending wait again, and the kept
        cross-covariances come back (each checked against its wells' model versions when
        first used)."""
        self._load_joint()
        self._loaded = True
        now = time.monotonic()
        with self.store.reader() as con:
            rows = con.execute(
                "SELECT separator, time_ns, q_total FROM separator_readings"
                " WHERE status = 'pending' ORDER BY separator, time_ns"
            ).fetchall()
        for sep, t, q in rows:
            if sep in self.waiting:
                self.waiting[sep].append(_Waiting(int(t), float(q), now))

    def _load_joint(self) -> None:
        """The kept cross-covariances of the store (``separator_states``)."""
        if not self.cross:
            return
        with self.store.reader() as con:
            rows = con.execute(
                "SELECT separator, wells, versions, dim, joint FROM separator_states"
            ).fetchall()
        for sep, wells, versions, dim, blob in rows:
            if sep not in self.members:
                continue
            names, n = json.loads(wells), len(json.loads(wells)) * int(dim)
            values = np.frombuffer(blob, dtype="<f8")
            if values.size != n * n:
                logger.warning(
                    "The kept cross-covariances of %s are unusable; they start over.", sep
                )
                continue
            joint = torch.from_numpy(values.reshape(n, n).copy())
            self._cross[sep] = _Cross(names, [None] * len(names), json.loads(versions), joint, dim)

    def joint_state(self, sep: str) -> tuple[list[str], torch.Tensor] | None:
        """The wells and the kept joint covariance [M D, M D] of ``sep`` as the next joint
        step would use it (the rows of a well whose model is not the one they were kept
        with are dropped); None: none kept. For a caller on the separator's worker or
        while the service is idle (tests, tools)."""
        if sep not in self._cross:
            return None
        try:
            self._cross_learner(sep, self._joint_states(sep))
        except ConfigError:
            pass
        cross = self._cross[sep]
        return list(cross.wells), cross.joint.clone()

    # -- the carry of a member's learning step (service.engine.learning.JointLearning) --------
    def moves_others(self, well: str) -> bool:
        """Whether ``well``'s learning step may move its partners (``cross``)."""
        sep = self.separator_of.get(well)
        return self.cross and sep is not None and len(self.members[sep]) > 1

    def partner_may_learn(self, well: str, sample_wells: Mapping[str, bool]) -> bool:
        """Whether a partner of ``well`` has a sample in the batch at which it may learn
        (``sample_wells`` False: a measurement waits for it), which would move ``well``."""
        sep = self.separator_of.get(well)
        if not self.cross or sep is None:
            return False
        return any(sample_wells.get(p) is False for p in self.members[sep] if p != well)

    def before_learn(self, st: WellState, time_ns: int) -> _CarryMark | None:
        """Before ``st`` learns a measurement at ``time_ns``: what the carry needs (see
        :meth:`vfm_core.separator.SeparatorLearner.before_well_tests`)."""
        sep = self.separator_of.get(st.well)
        if not self._loaded or sep is None or not self.cross:
            return None
        joint = self._joint_states(sep)
        wells = [w for w, _ in joint]
        if st.well not in wells or len(wells) < 2:
            return None
        try:
            learner = self._cross_learner(sep, joint)
        except ConfigError:
            return None
        live = torch.zeros(len(wells), dtype=torch.bool)
        live[wells.index(st.well)] = True
        t = torch.full((len(wells),), NEVER, dtype=torch.int64)
        t[live] = time_ns
        mark = learner.before_well_tests(live & learner.filt.model.ready, t)
        return None if mark is None else _CarryMark(sep, learner, mark)

    def carry(self, mark: object) -> bool:
        """After the step: carry it to the partners; whether the joint state changed."""
        assert isinstance(mark, _CarryMark)
        touched = bool(mark.learner.carry_well_tests(mark.mark))
        if touched:
            self._cross[mark.sep].joint = mark.learner.joint(mark.sep)
        self._note_versions(mark.sep)
        return touched

    def carried(self, st: WellState, ops: list[Op], time_ns: int) -> None:
        """The partners moved: a new version each, a checkpoint of every joint member and
        the joint state, in the step's transaction (a restart finds them together)."""
        sep = self.separator_of[st.well]
        joint = self._joint_states(sep)
        for _, other in joint:
            if other is not st and other.learner.ready:
                other.learner.renumber(other.learner.version + 1)
        self._note_versions(sep)
        self._keep(sep, joint, ops, time_ns)

    def _note_versions(self, sep: str) -> None:
        """The joint wells' model versions now (moved here, by a step or a carry)."""
        cross = self._cross.get(sep)
        if cross is not None:
            cross.versions = [
                member.learner.version if (member := self.wells.get(w)) else -1 for w in cross.wells
            ]

    def _joint_states(self, sep: str) -> list[tuple[str, WellState]]:
        """The members that learn from the total together (bayes), in order."""
        out = []
        for well in self.members[sep]:
            st = self.wells.get(well)
            if st is not None and check_method(st.learner.method.text) is None:
                out.append((well, st))
        return out

    def _cross_learner(self, sep: str, joint: list[tuple[str, WellState]]) -> SeparatorLearner:
        """A :class:`SeparatorLearner` over the joint wells' filters holding the kept
        cross-covariances (those of a replaced or new well start at zero)."""
        wells = [w for w, _ in joint]
        filters = [st.learner.method for _, st in joint]
        learner = SeparatorLearner(
            WellFilters(wells, filters), {sep: wells}, noise=self.noise, cross=True
        )
        fresh = learner.joint(sep)
        dim = fresh.shape[0] // len(wells)
        old = self._cross.get(sep)
        if old is not None:
            learner.set_joint(
                sep, old.carried_over(wells, [old.keeps(w, s) for w, s in joint], dim)
            )
        versions = [st.learner.version for _, st in joint]
        self._cross[sep] = _Cross(wells, list(filters), versions, learner.joint(sep), dim)
        return learner

    def _keep(
        self, sep: str, joint: list[tuple[str, WellState]], ops: list[Op], time_ns: int
    ) -> None:
        """Checkpoints of the joint members whose model moved since their last one, and
        the separator's joint state (:class:`SaveJoint`)."""
        for _, st in joint:
            if st.learner.ready and st.checkpoint_version != st.learner.version:
                ops.extend(self.checkpoints.ops(st))
                self.checkpoints.changed(st, ops, time_ns)
        cross = self._cross.get(sep)
        if cross is None:
            return
        ops.append(
            SaveJoint(
                sep,
                time_ns,
                json.dumps(cross.wells),
                json.dumps(cross.versions),
                cross.dim,
                cross.joint.numpy().astype("<f8").tobytes(),
            )
        )

    def waits_on(self, well: str) -> bool:
        """Whether a reading of ``well``'s separator waits (the worker then predicts the
        well's samples one call at a time, so that a sample after the reading is
        predicted after the reading's update)."""
        sep = self.separator_of.get(well)
        return sep is not None and bool(self.waiting[sep])

    # -- in ----------------------------------------------------------------------------------
    def on_item(self, item: SeparatorItem, b: Batch) -> None:
        """A reading: refuse a duplicate, store it, then settle it (or let it wait)."""
        sep, t = item.well, to_ns(item.measurement.time)
        q = float(item.measurement.q_total)
        if t in self._seen[sep] or self._stored(sep, t):
            duplicate = Duplicate(
                f"The reading of the separator {sep} at {iso(t)} arrived before; it is "
                "stored once.",
                "duplicate",
            )
            refuse(self.counters, duplicate, sep, b, item.future)
            return
        b.ops.append(InsertReading(sep, t, q, item.received_ns, item.via))
        self._seen[sep].append(t)
        self.counters.accept("separator_readings")
        waiting = self.waiting[sep]
        waiting.append(_Waiting(t, q, time.monotonic(), item.future))
        waiting.sort(key=lambda w: w.time_ns)
        if len(waiting) > self.pending_max:
            self.counters.event("pending forced")
            self._settle(sep, waiting.pop(0), b)
        self.settle(sep, b)
        for w in waiting:  # still waiting: a caller is answered now
            if w.future is not None:
                b.answer(w.future, self._pending_answer(sep, w))
                w.future = None

    def on_sample(self, well: str, b: Batch) -> None:
        """A sample of ``well`` was stored: settle its separator's readings now complete."""
        sep = self.separator_of.get(well)
        if sep is not None and self.waiting[sep]:
            self.settle(sep, b)

    def before_sample(self, well: str, time_ns: int, b: Batch) -> None:
        """A sample of ``well`` at ``time_ns`` comes (before it is predicted): its
        separator's readings before it are settled first, with the samples there are, when
        the data have passed them: the sample lies more than ``sample_window_s`` after the
        reading, or every member well still without a sample at the reading has been silent
        for longer than the window before it (it counts as shut in either way, as offline;
        a member that sent within the window is waited for)."""
        sep = self.separator_of.get(well)
        if sep is None:
            return
        waiting = self.waiting[sep]
        while waiting and waiting[0].time_ns < time_ns:
            t = waiting[0].time_ns
            if t >= time_ns - self.window_ns and not self._only_silent_lack(sep, t):
                return
            self._settle(sep, waiting.pop(0), b)

    def _only_silent_lack(self, sep: str, t: int) -> bool:
        """Whether every member without a sample at or after ``t`` has none within the
        window before it either (none at all, or its latest is older)."""
        for well in self.members[sep]:
            st = self.wells.get(well)
            last = None if st is None else st.last_time_ns
            if last is not None and t - self.window_ns <= last < t:
                return False
        return True

    def expire(self, worker: int, b: Batch, now: float) -> None:
        """Settle the readings of this worker's separators that waited longer than
        ``inputs.pending_timeout_s``, with the samples there are."""
        for sep, waiting in self.waiting.items():
            if self.worker[sep] != worker:
                continue
            while waiting and now - waiting[0].since > self.timeout_s:
                self._settle(sep, waiting.pop(0), b)
            self.settle(sep, b)

    def settle(self, sep: str, b: Batch) -> None:
        """Settle the readings of ``sep`` whose every member well has a sample at or after
        their time, oldest first (a later one waits for an earlier one)."""
        waiting = self.waiting[sep]
        while waiting and self._complete(sep, waiting[0].time_ns):
            self._settle(sep, waiting.pop(0), b)

    def _complete(self, sep: str, t: int) -> bool:
        for well in self.members[sep]:
            st = self.wells.get(well)
            if st is None or st.last_time_ns is None or st.last_time_ns < t:
                return False
        return True

    def _stored(self, sep: str, t: int) -> bool:
        with self.store.reader() as con:
            row = con.execute(
                "SELECT 1 FROM separator_readings WHERE separator = ? AND time_ns = ?", (sep, t)
            ).fetchone()
        return row is not None

    # -- settling ----------------------------------------------------------------------------
    def _settle(self, sep: str, w: _Waiting, b: Batch) -> None:
        """Allocate a reading and learn from it (see the module docstring); store the
        outcome, and publish it once the batch is committed."""
        members = [
            _Member(well, self.wells.get(well), self._sample(self.wells.get(well), w.time_ns))
            for well in self.members[sep]
        ]
        if b.learn_wells & {m.well for m in members}:
            self.learning.run_deferred(b)  # what was learned before the reading comes first
        try:
            status, note, rows = self._allocate(sep, w, members, b)
        except Exception as exc:  # one reading must not stop the worker
            logger.exception("The reading of %s at %s failed: %s", sep, iso(w.time_ns), exc)
            self.counters.event("internal errors")
            status, note, rows = "unused", f"The reading could not be allocated: {exc}.", []
        message = allocation_message(sep, w.time_ns, w.q_total, rows, status, note)
        b.ops.append(
            SettleReading(sep, w.time_ns, status, message["predicted"], message["residual"], note)
        )
        for r in rows:
            b.ops.append(
                InsertAllocation(
                    sep,
                    w.time_ns,
                    r["well"],
                    int(pd.Timestamp(r["sample_time"]).value) if r["sample_time"] else None,
                    r["q_pred"],
                    r["q_alloc"],
                    r["lo90"],
                    r["hi90"],
                )
            )
        self.counters.event(f"separator readings {status}")
        self._after_commit(sep, message, b)
        b.answer(w.future, message)

    def _after_commit(self, sep: str, message: dict[str, Any], b: Batch) -> None:
        """Publish the allocation and show it as the latest once the batch is committed:
        a future the worker answers after the commit (with the error, if it failed)."""
        done: Future[Any] = Future()

        def publish(f: Future[Any]) -> None:
            if f.exception() is not None:
                return
            with self._lock:
                self._latest[sep] = message
            if self.publish_key is None:
                return
            try:
                self.publish_key(
                    allocation_key(self.settings.prefix, sep), json.dumps(message).encode()
                )
                self.counters.event("allocations published")
            except Exception as exc:  # pragma: no cover - session closed under us
                self.counters.event("publish errors")
                logger.warning("Publishing the allocation of %s failed: %s", sep, exc)

        done.add_done_callback(publish)
        b.answer(done, None)

    def _sample(self, st: WellState | None, t: int) -> Sample | None:
        """The well's latest sample at or before ``t`` within the window (None: shut in)."""
        if st is None:
            return None
        found: Sample | None = None
        if st.recent and st.recent[0].time_ns <= t:
            for s in reversed(st.recent):
                if s.time_ns <= t:
                    found = s
                    break
        else:
            with self.store.reader() as con:
                row = con.execute(
                    "SELECT time_ns, " + ", ".join(INPUT_FIELDS) + ", q_total FROM samples"
                    " WHERE well = ? AND time_ns <= ? ORDER BY time_ns DESC LIMIT 1",
                    (st.well, t),
                ).fetchone()
            if row is not None:
                found = Sample(int(row[0]), tuple(float(v) for v in row[1:7]), row[7])
        if found is None or t - found.time_ns > self.window_ns:
            return None
        return found

    def _allocate(
        self, sep: str, w: _Waiting, members: list[_Member], b: Batch
    ) -> tuple[str, str, list[dict[str, Any]]]:
        """The reading's status, a sentence, and a row per member well."""
        flowing = [m for m in members if m.flowing]
        if not flowing:
            return "unused", "No member well flows at the reading (all shut in).", []
        if w.q_total <= 0:
            rows = [self._row(m, m.predicted) for m in members]
            return "unused", "A zero total with flowing wells is not allocated.", rows
        problem = self._not_joint(flowing)
        if problem is not None:
            return "unused", problem, [self._row(m, m.predicted) for m in members]
        return self._joint(sep, w, members, b)

    def _not_joint(self, flowing: list[_Member]) -> str | None:
        """Why the flowing wells cannot learn from the total together (None: they can)."""
        for m in flowing:
            st = m.state  # a flowing well has a sample, so a state
            problem = check_method(st.learner.method.text)
            if problem is not None:
                return f"{m.well}: {problem}"
            if not st.learner.ready:
                return f"{m.well} has no model yet (no measurement so far); not allocated."
            if st.learner.model.extra_columns or st.learner.shares_model:
                return f"{m.well}'s model ({st.learner.name}) does not learn from a total."
        return None

    def _joint(
        self, sep: str, w: _Waiting, members: list[_Member], b: Batch
    ) -> tuple[str, str, list[dict[str, Any]]]:
        """The allocation and joint update over the members with a ``bayes`` learner (a
        shut-in well of another method is listed with 0)."""
        joint = [
            m
            for m in members
            if m.st is not None and check_method(m.st.learner.method.text) is None
        ]
        others = [m for m in members if m not in joint]
        try:
            learner = self._reading_learner(sep, joint)
        except ConfigError as exc:
            return "unused", str(exc), [self._row(m, m.predicted) for m in members]
        one, live = _one_sample_each(joint)
        versions = [m.state.learner.version for m in joint]
        alloc = learner.allocate_and_learn(
            sep, one, live, w.q_total, pd.Timestamp(w.time_ns, tz=UTC), learn=self.learn
        )
        if self.cross and alloc is not None and alloc.learned:
            self._cross[sep].joint = learner.joint(sep)
        if alloc is None:
            rows = [self._row(m, 0.0) for m in members]
            return "unused", "A flowing well has no model yet; the reading is not allocated.", rows
        # the others are shut in (a flowing one would have stopped the joint update)
        rows = [self._row(m, 0.0, shut=True) for m in others] + _allocated_rows(joint, alloc)
        rows.sort(key=lambda r: self.members[sep].index(r["well"]))
        if not alloc.learned:
            why = (
                "the total lies beyond the gate of its predictive distribution (6 sd)"
                if self.learn
                else "separators.learn is false"
            )
            return "allocated", f"Allocated, not learned from: {why}.", rows
        self._updated(sep, joint, versions, w.time_ns, b)
        return "learned", "Allocated and learned from (joint update of the wells).", rows

    def _reading_learner(self, sep: str, joint: list[_Member]) -> SeparatorLearner:
        """The joint update's learner over the joint wells' filters: with the kept
        cross-covariances (``cross``), or block-diagonal."""
        if self.cross:
            return self._cross_learner(sep, [(m.well, m.state) for m in joint])
        filters = WellFilters([m.well for m in joint], [m.state.learner.method for m in joint])
        return SeparatorLearner(
            filters, {sep: [m.well for m in joint]}, noise=self.noise, cross=False
        )

    def _updated(
        self, sep: str, joint: list[_Member], versions: list[int], time_ns: int, b: Batch
    ) -> None:
        """The wells' models moved (the flowing ones; with ``cross`` every member with a
        model, through the cross-covariances): a new version each, and a checkpoint of
        each (and the joint state) in the reading's transaction (the state after the
        reading survives a restart; what comes after is re-learned from the store)."""
        for m, before in zip(joint, versions, strict=True):
            if m.flowing or (self.cross and m.state.learner.ready):
                m.state.learner.renumber(before + 1)
        if self.cross:
            self._note_versions(sep)
            self._keep(sep, [(m.well, m.state) for m in joint], b.ops, time_ns)
            return
        for m in joint:
            if m.flowing:
                b.ops.extend(self.checkpoints.ops(m.state))
                self.checkpoints.changed(m.state, b.ops, time_ns)

    @staticmethod
    def _row(m: _Member, q_pred: float | None, shut: bool = False) -> dict[str, Any]:
        """A member's row without a joint allocation (``shut``: allocated 0, shut in)."""
        zero = 0.0 if shut else None
        return {
            "well": m.well,
            "sample_time": iso(m.sample.time_ns) if m.sample is not None else None,
            "flowing": m.flowing,
            "q_pred": float(q_pred or 0.0),
            "q_alloc": zero,
            "lo90": zero,
            "hi90": zero,
        }

    def _pending_answer(self, sep: str, w: _Waiting) -> dict[str, Any]:
        missing = [
            well
            for well in self.members[sep]
            if (st := self.wells.get(well)) is None
            or st.last_time_ns is None
            or st.last_time_ns < w.time_ns
        ]
        return allocation_message(
            sep,
            w.time_ns,
            w.q_total,
            [],
            "pending",
            f"Stored. It waits for the samples at or after {iso(w.time_ns)} of "
            f"{', '.join(missing)} (at most inputs.pending_timeout_s).",
        )

    # -- what HTTP reads ---------------------------------------------------------------------
    def view(self, sep: str, recent: int = 50) -> dict[str, Any]:
        """The separator's wells, its latest settled reading with its allocation and the
        reconciliation residual, its last ``recent`` readings and counts by status."""
        with self.store.reader() as con:
            rows = con.execute(
                "SELECT time_ns, q_total, status, predicted, residual, note"
                " FROM separator_readings WHERE separator = ? AND status != 'pending'"
                " ORDER BY time_ns DESC LIMIT ?",
                (sep, max(1, recent)),
            ).fetchall()
            counts = dict(
                con.execute(
                    "SELECT status, COUNT(*) FROM separator_readings WHERE separator = ?"
                    " GROUP BY status",
                    (sep,),
                ).fetchall()
            )
            latest = None
            if rows:
                t, q, status, _, _, note = rows[0]
                parts = con.execute(
                    "SELECT well, sample_time_ns, q_pred, q_alloc, lo90, hi90 FROM allocations"
                    " WHERE separator = ? AND time_ns = ?",
                    (sep, t),
                ).fetchall()
                members = [
                    {
                        "well": well,
                        "sample_time": iso(st) if st is not None else None,
                        "flowing": st is not None and q_pred > 0,
                        "q_pred": q_pred,
                        "q_alloc": qa,
                        "lo90": lo,
                        "hi90": hi,
                    }
                    for well, st, q_pred, qa, lo, hi in parts
                ]
                members.sort(key=lambda r: self.members[sep].index(r["well"]))
                latest = allocation_message(sep, int(t), float(q), members, status, note or "")
        return {
            "separator": sep,
            "wells": list(self.members[sep]),
            "noise": self.noise,
            "units": "Sm3/h",
            "latest": latest,
            "readings": {s: int(counts.get(s, 0)) for s in STATUSES},
            "waiting": len(self.waiting[sep]),
            "recent": [
                {
                    "time": iso(int(t)),
                    "q_total": q,
                    "predicted": p,
                    "residual": r,
                    "status": s,
                }
                for t, q, s, p, r, _ in reversed(rows)
            ],
        }

    def overview(self) -> list[dict[str, Any]]:
        """Every separator with its wells and latest reading (time, total, residual)."""
        out = []
        for sep in self.members:
            v = self.view(sep, recent=1)
            latest = v["latest"] or {}
            out.append(
                {
                    "separator": sep,
                    "wells": v["wells"],
                    "units": "Sm3/h",
                    "time": latest.get("time"),
                    "q_total": latest.get("q_total"),
                    "predicted": latest.get("predicted"),
                    "residual": latest.get("residual"),
                    "status": latest.get("status"),
                    "readings": v["readings"],
                }
            )
        return out

    def latest_residuals(self) -> dict[str, float]:
        """The reconciliation residual of each separator's latest allocation published
        since the start (Sm3/h), for /metrics."""
        with self._lock:
            return {
                sep: float(m["residual"])
                for sep, m in self._latest.items()
                if m.get("residual") is not None and math.isfinite(m["residual"])
            }


def submit_item(separator: str, measurement: Measurement) -> tuple[SeparatorItem, Future[Any]]:
    """A reading posted over HTTP, as a queued item with the future that answers it."""
    future: Future[Any] = Future()
    item = SeparatorItem(
        separator, measurement, SEPARATOR_SOURCE, time.time_ns(), via="http", future=future
    )
    return item, future


def _one_sample_each(joint: list[_Member]) -> tuple[DataBatch, torch.Tensor]:
    """One sample per well (the one that counts; padded with a flowing one's for a
    shut-in well) as a batch [M, 1], and which wells flow [M]."""
    m = len(joint)
    samples = [j.sample if j.flowing else None for j in joint]
    pad = next(s.inputs for s in samples if s is not None)
    x = torch.tensor([list(pad if s is None else s.inputs) for s in samples], dtype=DTYPE).reshape(
        m, 1, len(INPUT_FIELDS)
    )
    live = torch.tensor([s is not None for s in samples])
    t = torch.tensor([[NEVER if s is None else s.time_ns] for s in samples], dtype=torch.int64)
    mask = live.reshape(m, 1)
    batch = DataBatch(
        [j.well for j in joint],
        x,
        torch.zeros(m, 1, dtype=DTYPE),
        mask,
        t,
        torch.zeros(m, 1, dtype=torch.int64),
        torch.zeros(m, 1, dtype=torch.bool),
    )
    return batch, live


def _allocated_rows(joint: list[_Member], alloc: Allocation) -> list[dict[str, Any]]:
    """The allocation's rows of the joint wells (Sm3/h; 0 for a shut-in one)."""
    rows = []
    for k, m in enumerate(joint):
        rows.append(
            {
                "well": m.well,
                "sample_time": iso(m.sample.time_ns) if m.sample is not None else None,
                "flowing": m.flowing,
                "q_pred": float(alloc.q_pred[k]),
                "q_alloc": float(alloc.q_alloc[k]),
                "lo90": float(alloc.lo90[k]),
                "hi90": float(alloc.hi90[k]),
            }
        )
    return rows
