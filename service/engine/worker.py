"""The worker threads: take items in arrival order, handle them, commit once, publish, answer.

Each worker owns the wells that hash to it and loops over its bounded queue. Items are
handled into a :class:`~service.engine.items.Batch`; the batch is committed to the store
in one transaction (group commit) when the queue runs dry, the batch holds
``queues.batch_max`` items, or it has run for ``queues.batch_ms`` (so a slow learning
step does not hold back the predictions already made). Only after the commit are its
predictions published and its HTTP callers answered: nothing unstored is ever
acknowledged. Every half second a worker also settles the measurements of its wells that
waited too long for their sample.

A sensor sample is handled here: refused if it is not after the well's previous one
(``duplicate`` or ``time going backwards``), else predicted, stored with its prediction,
published, and the measurements waiting for it are settled.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

from service.config import Settings
from service.engine.checkpoints import Checkpoints
from service.engine.items import STOP, Batch, Item, ModelStep, SensorItem, refuse
from service.engine.learning import Learning
from service.engine.model_change import ModelChanges
from service.engine.pairing import Pairing
from service.engine.state import Sample, WellState
from service.errors import Duplicate, InvalidRequest, ServiceError, Stopping
from service.inputs import Counters
from service.store import InsertSample, Store
from vfm_core.messages import Prediction
from vfm_core.timeutil import iso, to_ns

__all__ = ["Workers"]

logger = logging.getLogger("vfm.service.engine")

Publish = Callable[[str, bytes], None]


class Workers:
    """The worker threads of the engine, one per queue; see the module docstring."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        counters: Counters,
        publish: Publish,
        wells: Mapping[str, WellState],
        queues: list[queue.Queue[Any]],
        learning: Learning,
        pairing: Pairing,
        checkpoints: Checkpoints,
        model_changes: ModelChanges,
    ) -> None:
        self.store = store
        self.counters = counters
        self.publish = publish
        self.wells = wells
        self.queues = queues
        self.learning = learning
        self.pairing = pairing
        self.checkpoints = checkpoints
        self.model_changes = model_changes
        self.batch_max = settings.queues.batch_max
        self.batch_s = settings.queues.batch_ms / 1000.0
        self._threads: list[threading.Thread] = []

    def start(self) -> None:
        for i, q in enumerate(self.queues):
            t = threading.Thread(target=self._run, args=(i, q), name=f"vfm-worker-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout: float = 30.0) -> None:
        """Let the workers finish what is queued and end; answer the callers they did not reach."""
        deadline = time.monotonic() + timeout
        for q in self.queues:
            while True:
                try:
                    q.put(STOP, timeout=0.5)
                    break
                except queue.Full:
                    if time.monotonic() > deadline:
                        break
        for t in self._threads:
            t.join(max(0.1, deadline - time.monotonic()))
        self._threads.clear()
        for q in self.queues:  # callers still waiting on items the workers did not reach
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                future = getattr(item, "future", None)
                if future is not None and not future.done():
                    what = "model change" if isinstance(item, ModelStep) else "well test"
                    future.set_exception(Stopping(f"The service stopped before the {what} ran."))

    # -- the loop -------------------------------------------------------------------------
    def _run(self, index: int, q: queue.Queue[Any]) -> None:
        last_expiry = time.monotonic()
        stopping = False
        while not stopping:
            b = Batch()
            try:
                item = q.get(timeout=0.5)
            except queue.Empty:
                item = None
            began = time.monotonic()
            n = 0
            while item is not None:
                if item is STOP:
                    stopping = True
                    break
                self._handle(item, b)
                n += 1
                if n >= self.batch_max or time.monotonic() - began > self.batch_s:
                    break
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
            now = time.monotonic()
            if now - last_expiry > 0.5:
                last_expiry = now
                for st in list(self.wells.values()):
                    if st.worker == index and st.pending:
                        self.pairing.expire(st, b, now)
            self.flush(b)

    def _handle(self, item: Item, b: Batch) -> None:
        try:
            if isinstance(item, SensorItem):
                self._on_sample(self.wells[item.well], item, b)
            elif isinstance(item, ModelStep):
                self.model_changes.on_step(item, b, self.flush)
            else:
                self.pairing.on_measurement(self.wells[item.well], item, b)
        except Exception as exc:  # one bad message must not stop the worker
            logger.exception(
                "Unexpected error on %s of %s: %s", type(item).__name__, item.well, exc
            )
            self.counters.event("internal errors")
            b.answer(getattr(item, "future", None), exc)

    def flush(self, b: Batch) -> None:
        """Commit the batch, then publish its predictions and answer its callers."""
        try:
            self.store.write(b.ops)
        except Exception as exc:
            logger.exception("The store could not commit %d write(s): %s", len(b.ops), exc)
            self.counters.event("store errors")
            for fut, _ in b.answers:
                fut.set_exception(exc)
            return  # nothing unstored is published or acknowledged
        for well, payload in b.outbox:
            try:
                self.publish(well, payload)
                self.counters.event("predictions published")
            except Exception as exc:  # pragma: no cover - session closed under us
                self.counters.event("publish errors")
                logger.warning("Publishing the prediction of %s failed: %s", well, exc)
        for fut, result in b.answers:
            if fut.done():
                continue
            if isinstance(result, BaseException):
                fut.set_exception(result)
            else:
                fut.set_result(result)

    # -- samples ----------------------------------------------------------------------------
    def _on_sample(self, st: WellState, item: SensorItem, b: Batch) -> None:
        sample = item.sample
        t = to_ns(sample.time)
        inputs = tuple(sample.inputs())
        if st.last_time_ns is not None and t <= st.last_time_ns:
            if t == st.last_time_ns and inputs == st.last_inputs:
                error: ServiceError = Duplicate(
                    f"The sample of {item.well} at {iso(t)} arrived before.", "duplicate"
                )
            else:
                error = InvalidRequest(
                    f"The sample of {item.well} at {iso(t)} is not after the well's previous sample at "
                    f"{iso(st.last_time_ns)}; samples of a well must arrive in time order.",
                    "time going backwards",
                )
            refuse(self.counters, error, item.well, b)
            return
        learner = st.learner
        rates = self.learning.predict(st, inputs, sample.time)
        if learner.version != st.snapshot.get("version"):  # a pbl retrain ran
            self.checkpoints.changed(st, b.ops)
        q_total = rates["q_total"] if rates else None
        st.recent.append(Sample(t, inputs, q_total))
        st.last_time_ns, st.last_inputs = t, inputs
        st.samples += 1
        self.counters.accept("sensors")
        b.ops.append(
            InsertSample(
                well=item.well,
                time_ns=t,
                inputs=inputs,
                received_ns=item.received_ns,
                q_total=q_total,
                q_gas=rates["q_gas"] if rates else None,
                q_oil=rates["q_oil"] if rates else None,
                q_water=rates["q_water"] if rates else None,
                version=learner.version if rates else None,
            )
        )
        if rates is None or q_total is None:
            self.counters.event("model not ready")
        else:
            pred = Prediction(
                time=sample.time,
                q_total=q_total,
                q_gas=rates["q_gas"],
                q_oil=rates["q_oil"],
                q_water=rates["q_water"],
                model=learner.name,
                version=learner.version,
            )
            b.outbox.append((item.well, pred.model_dump_json().encode()))
        if st.pending:
            self.pairing.resolve(st, b, upto=t)
