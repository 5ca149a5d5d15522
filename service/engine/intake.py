"""Receiving: check each inbound message, route it to the worker that owns its well, back-pressure.

The transport's receiver thread calls :meth:`Intake.deliver` with every message. It only
checks (key, payload, time, well) and queues; it never learns, so receiving never waits
for learning. A well always goes to the same worker (a hash of its id), so its messages
are handled in arrival order. When that worker's queue is full the receiver waits up to
``queues.block_s`` (back-pressure: Zenoh's BLOCK congestion control then slows the
publisher), then drops the message and counts a ``queue overflow``. Well tests posted
over HTTP enter here too (:meth:`Intake.submit_well_test`).

A well not seen before is created on first sight (``inputs.unknown_wells = "create"``),
if its id passes :func:`vfm_core.messages.well_id_problem`, the one rule for well ids.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import zlib
from concurrent.futures import Future
from datetime import datetime
from typing import Any

from service.config import Settings
from service.engine.items import MeasurementItem, SensorItem
from service.engine.state import WellState, WellTestResult
from service.errors import Busy, InvalidRequest, ServiceError, UnknownWell
from service.inputs import Counters, parse_measurement, parse_sensor, route_key
from service.learning import new_learner
from service.store import AddWell, Store
from vfm_core.messages import Measurement, well_id_problem
from vfm_core.timeutil import to_ns

__all__ = ["Intake", "worker_of"]

logger = logging.getLogger("vfm.service.engine")


def worker_of(well: str, workers: int) -> int:
    """The worker that owns ``well`` (stable across restarts)."""
    return zlib.crc32(well.encode()) % workers


class Intake:
    """The receiving side of the engine; see the module docstring."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        counters: Counters,
        wells: dict[str, WellState],
        queues: list[queue.Queue[Any]],
    ) -> None:
        self.settings = settings
        self.store = store
        self.counters = counters
        self.wells = wells
        self.queues = queues
        self._lock = threading.Lock()
        self._future_ns = int(settings.inputs.max_future_s * 1e9)

    def deliver(self, key: str, payload: bytes, received_ns: int) -> None:
        """One inbound message: check, then queue for the well's worker (never learns)."""
        try:
            well, kind, source = route_key(self.settings.prefix, key)
            if kind == "prediction":
                return  # outputs, e.g. of another service instance: not ours to take in
            item: SensorItem | MeasurementItem
            if kind == "sensors":
                sample = parse_sensor(payload)
                self.check_time(sample.time, "sample")
                item = SensorItem(well, sample, received_ns)
            else:
                measurement = parse_measurement(payload)
                self.check_time(measurement.time, "measurement")
                item = MeasurementItem(well, measurement, str(source), received_ns)
            st = self.well_state(well)
        except ServiceError as error:  # every refusal here is of an input: it has a reason
            if error.reason is not None:
                self.counters.reject(error.reason, error.message, where=key)
            return
        self._enqueue(st.worker, item, key)

    def submit_well_test(self, well: str, measurement: Measurement) -> Future[WellTestResult]:
        """Queue a well test; the future answers after it is stored (and learned).

        Raises (before queueing) :class:`InvalidRequest` for a time too far ahead or a bad
        well id, :class:`UnknownWell`, or :class:`Busy` when the queue stays full.
        """
        self.check_time(measurement.time, "well test")
        st = self.well_state(well)
        fut: Future[WellTestResult] = Future()
        item = MeasurementItem(
            well, measurement, "well_test", time.time_ns(), via="http", future=fut
        )
        try:
            self.queues[st.worker].put(item, timeout=2.0)
        except queue.Full:
            raise Busy(
                "The service is busy (its queue is full); retry in a few seconds.",
                "queue overflow",
            ) from None
        return fut

    def well_state(self, well: str, *, create: bool = True) -> WellState:
        """The well's state; unknown wells are created or refused as configured."""
        st = self.wells.get(well)
        if st is not None:
            return st
        if not create or self.settings.inputs.unknown_wells == "reject":
            raise UnknownWell(
                f"The well '{well}' is not known to this service; add it to inputs.wells or set "
                "inputs.unknown_wells = 'create'.",
                "unknown well",
            )
        problem = well_id_problem(well)
        if problem is not None:
            raise InvalidRequest(problem, "unparseable key")
        with self._lock:
            st = self.wells.get(well)
            if st is None:
                st = WellState(
                    well,
                    new_learner(well, self.settings.model),
                    self.settings,
                    worker_of(well, len(self.queues)),
                )
                self.store.write(
                    [AddWell(well=well, created_ns=time.time_ns(), origin="first sight")]
                )
                self.wells[well] = st
                logger.info(
                    "New well %s (first sight); it gets predictions once it has a measurement.",
                    well,
                )
        return st

    def check_time(self, when: datetime, what: str) -> None:
        """Refuse a time further ahead than ``inputs.max_future_s``."""
        ahead = to_ns(when) - time.time_ns()
        if ahead > self._future_ns:
            raise InvalidRequest(
                f"The {what} time {when.isoformat()} lies {ahead / 3.6e12:.1f} h in the future; "
                f"at most {self.settings.inputs.max_future_s / 3600:g} h ahead is accepted (inputs.max_future_s).",
                "time in the future",
            )

    def _enqueue(self, worker: int, item: SensorItem | MeasurementItem, where: str) -> None:
        q = self.queues[worker]
        try:
            q.put_nowait(item)
            return
        except queue.Full:
            self.counters.event("backpressure waits")
        try:
            q.put(item, timeout=self.settings.queues.block_s)
        except queue.Full:
            self.counters.event("overflow")
            self.counters.reject(
                "queue overflow",
                f"The worker queue stayed full for {self.settings.queues.block_s:g} s; the message was dropped. "
                "The service cannot keep up: add workers (queues.workers) or slow the sender.",
                where=where,
            )
