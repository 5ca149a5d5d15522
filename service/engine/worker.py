"""The worker threads: take items, handle them, commit once, publish, answer.

Each worker owns the wells that hash to it and loops over its
:class:`~service.engine.fairqueue.FairQueue`: each well's items in arrival order, the
wells in turn (round robin), so a flooding well cannot hold back the others. Items are
handled into a :class:`~service.engine.items.Batch`; the batch is committed to the store
in one transaction (group commit) when the queue runs dry, the batch holds
``queues.batch_max`` items, or it has run for ``queues.batch_ms`` (so a slow learning
step does not hold back the predictions already made). A worker takes its items a few at a
time (one lock for up to 16, in the queue's order); what a batch leaves starts the next
one. Only after the commit are its
predictions published and its HTTP callers answered: nothing unstored is ever
acknowledged. Every half second a worker also settles the measurements of its wells that
waited too long for their sample.

A sensor sample is handled here: refused if it is not after the well's previous one
(``duplicate`` or ``time going backwards``), else predicted, stored with its prediction
(and its interval, with a method that gives one), published, and the measurements waiting
for it are settled. The samples of a batch are predicted together: each is checked as it
is taken, then all those taken are predicted in one call
(:func:`vfm_core.learning.streaming.predict_many`: the wells' models stacked into one model call),
then each is stored and published in arrival order. Anything else (a measurement, a model
change, a retirement) first has the samples before it predicted, and so does a well's next
sample when its model may change at that sample (a scheduled retrain, or a measurement
waiting for the sample before); so each well sees exactly the order of one-by-one handling.
A measurement of a well with its own model and no sample taken in the batch is the one
exception: it changes no other well's model, so the other wells' samples keep waiting for
the batch's one call (a field-wide ``mtl`` model, or a separator's member whose step is
carried to its partners over kept cross-covariances, still has them predicted first; and a
member's sample is predicted after a partner's sample at which that partner may learn).
Learning is batched the same way: a paired measurement's learning step waits, and the
batch's waiting steps of all wells run in one call
(:func:`vfm_core.learning.streaming.learn_many`, via :meth:`Learning.run_deferred
<service.engine.learning.Learning.run_deferred>`) before the commit, or earlier when
anything else of such a well comes (its next sample, another of its measurements) and
before a model change or a retirement. The first message of a new well builds the well
here, on its worker (never on the receiver thread). A :class:`~service.engine.items.RetireStep` retires a
well after everything queued for it before (``DELETE /wells/{well}``).

A sensor block (:class:`~service.engine.items.SensorBlockItem`, many samples of one well in
one message, checked at intake) is answered at once: its rows not after the well's previous
sample are refused, the others go through the well's model in one call
(:meth:`~vfm_core.learning.streaming.WellLearner.predict_block`), are stored row by row and answered
with one prediction block. Its rows are fed to the instrument-fault detectors first
(:meth:`WellState.watch_block <service.engine.state.WellState.watch_block>`): a row at which
an input stands in (:mod:`vfm_core.sensor_faults`) is taken as a single sample, predicted
with its fallback and answered on its own, and the block is split there, so a fault raised
or ended inside a block changes the predictions from its row on, as one by one. A well
whose model may change within the block (a measurement waits for one of its samples, a
scheduled retrain due by the block's last row), or that is not ready, takes the rows one by one as single samples, so
a block is always answered as its rows sent one by one.

Every sample is fed to the detectors when it is admitted, before it is predicted; a
sample with a stand-in is the last of its well in its prediction call (its fallback is
asked of the model right after, at the sample's features and clock).
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING

import numpy as np

from service.config import Settings
from service.engine.checkpoints import Checkpoints
from service.engine.fairqueue import CLOSED, FairQueue
from service.engine.intake import Intake, worker_of
from service.engine.items import (
    Batch,
    Item,
    MeasurementItem,
    ModelStep,
    RetireStep,
    SensorBlockItem,
    SensorItem,
    refuse,
)
from service.engine.learners import new_learner
from service.engine.learning import Learning
from service.engine.model_change import ModelChanges
from service.engine.pairing import Pairing
from service.engine.registry import Registry
from service.engine.separators import SeparatorItem, Separators
from service.engine.state import Sample, WellState
from service.errors import Duplicate, InvalidRequest, ServiceError, Stopping, UnknownWell
from service.inputs import Counters
from service.store import AddWell, InsertSample, RetireWell, Store, purge_ops
from vfm_core.learning.streaming import model_fixed_when_predicting
from vfm_core.messages import prediction_json
from vfm_core.timeutil import iso, iso_many

if TYPE_CHECKING:  # the engine knows no transport; a Source is what it is handed
    from service.transport import Source

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
        queues: list[FairQueue],
        learning: Learning,
        pairing: Pairing,
        checkpoints: Checkpoints,
        model_changes: ModelChanges,
        registry: Registry,
    ) -> None:
        self.settings = settings
        self.registry = registry
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
        #: each worker's items taken from its queue and not handled yet (:meth:`_run`)
        self._taken: list[deque[Item]] = [deque() for _ in queues]
        #: the messages the one worker takes itself (no receiver thread), and the intake
        #: they pass through (:meth:`start`)
        self._source: Source | None = None
        self._intake: Intake | None = None
        #: the separators' readings (service.engine.separators; None: none configured)
        self.separators: Separators | None = None

    def start(self, source: Source | None = None, intake: Intake | None = None) -> None:
        """Start the worker threads; with ``source`` (one worker only) the worker takes the
        messages from it itself, through ``intake``, between its items (see :meth:`_take_in`)."""
        if source is not None:
            if len(self.queues) != 1 or intake is None:
                raise ValueError("A worker takes the messages itself only when it is the only one.")
            self._source, self._intake = source, intake
            intake.hold = True
            self.queues[0].on_put = self._wake
        for i, q in enumerate(self.queues):
            t = threading.Thread(target=self._run, args=(i, q), name=f"vfm-worker-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout: float = 30.0) -> bool:
        """Let the workers finish what is queued and end; answer the callers they did not
        reach. True when every worker ended within ``timeout`` s."""
        deadline = time.monotonic() + timeout
        for q in self.queues:
            q.close()
        for t in self._threads:
            t.join(max(0.1, deadline - time.monotonic()))
        ended = not any(t.is_alive() for t in self._threads)
        if not ended:
            logger.warning(
                "A worker did not finish within %.0f s (a long learning step); stopping anyway.",
                timeout,
            )
        self._threads.clear()
        # callers still waiting on items the workers did not reach: queued, or taken by
        # a worker that did not end
        left = [item for taken in self._taken for item in list(taken)]
        for q in self.queues:
            left.extend(q.drain())
        for item in left:
            future = getattr(item, "future", None)
            if future is not None and not future.done():
                what = {ModelStep: "model change", RetireStep: "retirement"}.get(
                    type(item), "well test"
                )
                future.set_exception(Stopping(f"The service stopped before the {what} ran."))
        return ended

    # -- the loop -------------------------------------------------------------------------
    def _run(self, index: int, q: FairQueue) -> None:
        last_expiry = time.monotonic()
        stopping = False
        # items taken from the queue a few at a time (one lock for them), handled in order;
        # what a batch leaves starts the next one
        taken = self._taken[index]
        source = self._source if index == 0 else None
        while not stopping:
            b = Batch()
            item: Item | None
            if taken:
                item = taken.popleft()
            elif source is not None and not source.stopped:
                item = self._take_in(q, source, wait=True)
            else:
                item = q.get(timeout=0.5)
            began = time.monotonic()
            n = 0
            while item is not None:
                if item is CLOSED:
                    stopping = True
                    break
                self._handle(item, b)
                n += 1
                if n >= self.batch_max or time.monotonic() - began > self.batch_s:
                    break
                if not taken:
                    if source is not None and not source.stopped:
                        self._take_in(q, source, wait=False)
                    taken.extend(q.get_many(_TAKE))
                item = taken.popleft() if taken else None
            self._predict_samples(b)
            now = time.monotonic()
            if now - last_expiry > 0.5:
                last_expiry = now
                for st in list(self.wells.values()):
                    if st.worker == index and st.pending:
                        self.pairing.expire(st, b, now)
                if self.separators is not None:
                    self.separators.expire(index, b, now)
            self.flush(b)

    def _take_in(self, q: FairQueue, source: Source, wait: bool) -> Item | None:
        """The one worker takes the messages that have arrived (at most
        ``queues.receive_capacity`` at a time, none while one is held for a full queue);
        with ``wait`` it then answers the next item of its queue, waiting in the source for
        one (a message, a wake, or half a second: None) when the queue is empty."""
        intake = self._intake
        assert intake is not None
        room = intake.retry_held
        if room():
            source.poll(self.settings.queues.receive_capacity, room)
        if not wait:
            return None
        item = q.get_nowait()
        if item is None and not source.stopped:
            # ready when something is queued (a well test, a model change) or at a stop
            source.wait(lambda: q.qsize() > 0 or q.closed)
            if room():
                source.poll(self.settings.queues.receive_capacity, room)
            item = q.get_nowait()
        return item  # type: ignore[no-any-return]

    def _wake(self) -> None:
        """Something was put in the queue (or it was closed): end the worker's wait in the
        source, if it waits (from another thread; the worker's own puts find it busy)."""
        if self._source is not None:
            self._source.wake()

    def _handle(self, item: Item, b: Batch) -> None:
        if isinstance(item, SensorItem):
            first = item.well in b.sample_wells and not b.sample_wells[item.well]
            if first and item.well in b.sample_due:
                # a scheduled retrain only: this sample joins when it comes before it is due
                first = not model_fixed_when_predicting(self.wells[item.well].learner, item.time_ns)
            # a separator's reading waits for this well: its later samples come after it;
            # or a partner's learning step at its sample may move this well (cross)
            first |= self.separators is not None and (
                self.separators.waits_on(item.well)
                or self.separators.partner_may_learn(item.well, b.sample_wells)
            )
        elif isinstance(item, SensorBlockItem):
            first = item.well in b.sample_wells  # a block is answered at once, in order
            first |= self.separators is not None and self.separators.partner_may_learn(
                item.well, b.sample_wells
            )
        elif isinstance(item, MeasurementItem) and item.well not in b.sample_wells:
            # a measurement changes its own well's model only, unless the model is shared
            # (field-wide, mtl): the other wells' samples taken so far need not wait
            # (or a separator's kept cross-covariances carry the step to its partners)
            # (or a well test pooled with the other wells' errors, cal_pool: their intervals)
            st = self.wells.get(item.well)
            first = (
                st is None
                or st.learner.shares_model
                or self.learning.moves_others(st.well)
                or self.learning.pools_now(st, item.source)
            )
        else:
            first = True
        if first:
            # the samples taken so far are predicted first: this item may change their
            # wells' models (a measurement, a model change), or is the next sample of a
            # well whose model may change at its next sample (a scheduled retrain)
            self._predict_samples(b)
        if b.learn_wells and (
            isinstance(item, ModelStep | RetireStep) or item.well in b.learn_wells
        ):
            # the learning steps waiting come first: this item reads or changes a model
            self.learning.run_deferred(b)
        try:
            if isinstance(item, ModelStep):
                self.model_changes.on_step(item, b, self.flush)
                return
            if isinstance(item, RetireStep):
                self._retire(item, b)
                return
            if isinstance(item, SeparatorItem):
                assert self.separators is not None  # queued only when configured
                self.separators.on_item(item, b)
                return
            st = self._state(item, b)
            if st is None:
                return
            if isinstance(item, SensorItem):
                if self.separators is not None:  # a reading before it is settled first
                    self.separators.before_sample(item.well, item.time_ns, b)
                self._admit_sample(st, item, b)
            elif isinstance(item, SensorBlockItem):
                self._on_block(st, item, b)
            else:
                self.pairing.on_measurement(st, item, b)
        except Exception as exc:  # one bad message must not stop the worker
            logger.exception(
                "Unexpected error on %s of %s: %s", type(item).__name__, item.well, exc
            )
            self.counters.event("internal errors")
            b.answer(getattr(item, "future", None), exc)

    def flush(self, b: Batch) -> None:
        """Predict the samples taken, run the learning steps waiting, commit the batch, then
        publish its predictions and answer its callers."""
        self._predict_samples(b)
        self.learning.run_deferred(b)
        try:
            self.store.write(b.ops)
        except Exception as exc:
            logger.exception("The store could not commit %d write(s): %s", len(b.ops), exc)
            self.counters.event("store errors")
            for fut, _ in b.answers:
                fut.set_exception(exc)
            return  # nothing unstored is published or acknowledged
        published = 0
        for well, payload in b.outbox:
            try:
                self.publish(well, payload)
                published += 1
            except Exception as exc:  # pragma: no cover - session closed under us
                self.counters.event("publish errors")
                logger.warning("Publishing the prediction of %s failed: %s", well, exc)
        if published:  # counted once per commit: the counters take a lock
            self.counters.event("predictions published", published)
        for fut, result in b.answers:
            if fut.done():
                continue
            if isinstance(result, BaseException):
                fut.set_exception(result)
            else:
                fut.set_result(result)

    # -- wells --------------------------------------------------------------------------------
    def _state(self, item: Item, b: Batch) -> WellState | None:
        """The item's well; a new one (admitted by the registry) is built here, on its worker."""
        st = self.wells.get(item.well)
        if st is not None:
            return st
        future = getattr(item, "future", None)
        if not self.registry.expected(item.well):  # retired (or purged) after it was queued
            error: ServiceError = (
                InvalidRequest(
                    f"The well {item.well} was retired; its messages are refused.", "retired well"
                )
                if self.registry.is_retired(item.well)
                else UnknownWell(
                    f"The well {item.well} is no longer known to this service.", "unknown well"
                )
            )
            refuse(self.counters, error, item.well, b, future)
            return None
        st = WellState(
            item.well,
            new_learner(item.well, self.settings.model),
            self.settings,
            worker_of(self.settings.separators.route(item.well), len(self.queues)),
            self.learning.pools,
        )
        b.ops.append(AddWell(well=item.well, created_ns=time.time_ns(), origin="first sight"))
        self.registry.created(item.well, st)
        self.counters.event("wells created")
        logger.info(
            "New well %s (first sight); it gets predictions once it has a measurement.", item.well
        )
        return st

    def _retire(self, item: RetireStep, b: Batch) -> None:
        """Retire a well: stop serving it, then keep its data (with a last checkpoint) or purge it."""
        st = self.wells.get(item.well)
        if st is None:
            self.registry.unretire(item.well)
            b.answer(
                item.future, UnknownWell(f"The well {item.well} is not known to this service.")
            )
            return
        self.flush(b)  # what was handled before is committed first
        b.clear()
        ops = (
            purge_ops(item.well)
            if item.purge
            else [*self.checkpoints.ops(st), RetireWell(well=item.well, retired_ns=item.when_ns)]
        )
        self.store.write(ops)
        self.learning.pools.leave(item.well)  # its errors no longer set the others' priors
        self.registry.retired_done(item.well, item.purge)
        self.counters.event("wells retired")
        logger.info("Well %s retired%s.", item.well, " and its data removed" if item.purge else "")
        b.answer(
            item.future,
            {
                "well": item.well,
                "retired": iso(item.when_ns),
                "purged": item.purge,
                "samples": st.samples,
                "measurements": st.measurements,
                "version": st.learner.version,
            },
        )

    # -- samples ----------------------------------------------------------------------------
    def _admit_sample(self, st: WellState, item: SensorItem, b: Batch) -> None:
        """First pass: refuse a sample that is not after the well's previous one, else feed
        it to the instrument-fault detectors (unless its block did) and keep it for the
        batch's one prediction call (:meth:`_predict_samples`)."""
        t, inputs = item.time_ns, item.inputs
        # the well's previous sample: one taken in this batch, else the last one stored
        last_ns, last_inputs = b.sample_last.get(item.well, (st.last_time_ns, st.last_inputs))
        if last_ns is not None and t <= last_ns:
            refuse(
                self.counters,
                _out_of_order(item.well, t, inputs, last_ns, last_inputs),
                item.well,
                b,
            )
            return
        if item.stand_ins is None:  # instrument faults (vfm_core.sensor_faults), in order
            item.stand_ins = st.watch_sample(t, inputs)
        b.samples.append((st, item, t, inputs))
        # another sample of the well may join the call unless its model can change first:
        # a scheduled retrain due by that sample (pbl, bayes's refresh: sample_due keeps
        # the wells whose model changes only so), or a measurement this sample settles and learns; nor
        # after a sample with a stand-in: its fallback is asked of the model after the call,
        # which must leave the model's features and clock at this sample
        settled = not st.pending and not item.stand_ins
        b.sample_wells[item.well] = settled and model_fixed_when_predicting(st.learner)
        if settled and not b.sample_wells[item.well] and model_fixed_when_predicting(st.learner, t):
            b.sample_due.add(item.well)  # its model changes only at a retrain due after t
        else:
            b.sample_due.discard(item.well)
        b.sample_last[item.well] = (t, inputs)

    def _on_block(self, st: WellState, item: SensorBlockItem, b: Batch) -> None:
        """A well's sensor block (rows checked at intake): a row not after the well's
        previous sample (or the block's row before it that was taken) is refused, as one
        by one; the others are predicted in one model call
        (:meth:`WellLearner.predict_block <vfm_core.learning.streaming.WellLearner.predict_block>`),
        stored row by row, and answered with one prediction block. A well whose model may
        change within the block (a measurement waits for one of its samples, a scheduled
        retrain), that is not ready, or that is not a per-well learner takes the rows one
        by one instead, as single samples: the same answers, one prediction message each."""
        t, x = item.times_ns, item.inputs
        last_ns = st.last_time_ns
        if (last_ns is not None and t[0] <= last_ns) or (len(t) > 1 and (np.diff(t) <= 0).any()):
            # as one by one: each row against the well's previous accepted sample
            keep: list[int] = []
            last_inputs = st.last_inputs
            for i in range(len(t)):
                ti, row = int(t[i]), tuple(x[i].tolist())
                if last_ns is not None and ti <= last_ns:
                    error = _out_of_order(item.well, ti, row, last_ns, last_inputs)
                    refuse(self.counters, error, item.well, b)
                    continue
                keep.append(i)
                last_ns, last_inputs = ti, row
            if not keep:
                return
            t, x = t[keep], x[keep]
        learner = st.learner
        if (
            st.trial is None  # on trial: one by one, so that the shadow sees every row
            and not st.pending
            and not (self.separators is not None and self.separators.waits_on(st.well))
            and model_fixed_when_predicting(learner, int(t[-1]))
            and learner.ready
        ):
            self._split_block(st, item, t, x, b)
            return
        for ti, row in zip(t.tolist(), x.tolist(), strict=True):
            self._handle(SensorItem(item.well, ti, tuple(row), item.received_ns), b)

    def _split_block(
        self, st: WellState, item: SensorBlockItem, t: np.ndarray, x: np.ndarray, b: Batch
    ) -> None:
        """A block's rows to the instrument-fault detectors first, then predicted: each row
        at which an input stands in as a single sample with its stand-ins (predicted with
        its fallback by :meth:`_on_sample`, one message each, as one by one), each run of
        the other rows in one model call (:meth:`_predict_run`). Without a flagged input
        (the usual case) the block is one run."""
        rows = [tuple(r) for r in x.tolist()]
        used = st.watch_block(t.tolist(), rows)  # instrument faults (vfm_core.sensor_faults)
        start = 0
        for i in [*used, len(rows)]:
            if start < i:
                self._predict_run(st, item, t[start:i], x[start:i], b)
            if i < len(rows):
                if st.well in b.sample_wells:  # the row before had a stand-in too: first
                    self._predict_samples(b)
                one = SensorItem(item.well, int(t[i]), rows[i], item.received_ns, used[i])
                self._admit_sample(st, one, b)  # predicted with the batch's samples
            start = i + 1

    def _predict_run(
        self, st: WellState, item: SensorBlockItem, t: np.ndarray, x: np.ndarray, b: Batch
    ) -> None:
        """Rows of a block (watched, none standing in) in one model call, stored and
        answered with one prediction block; row by row, as single samples, when the call
        fails (they say what fails)."""
        if st.well in b.sample_wells:  # a row before it went as a single sample: first
            self._predict_samples(b)
        try:
            rates = self.learning.predict_block(st, x, t)
        except Exception as exc:
            logger.debug("A block of %s went one by one: %s", item.well, exc)
            for ti, row in zip(t.tolist(), x.tolist(), strict=True):
                self._admit_sample(
                    st, SensorItem(item.well, ti, tuple(row), item.received_ns, ()), b
                )
            return
        self._store_block(st, item, t, x, rates, b)

    def _store_block(
        self,
        st: WellState,
        item: SensorBlockItem,
        t: np.ndarray,
        x: np.ndarray,
        rates: dict[str, np.ndarray],
        b: Batch,
    ) -> None:
        """Store a block's rows with their predictions; queue its one prediction message."""
        learner = st.learner
        if learner.version != st.snapshot.get("version"):
            self.checkpoints.changed(st, b.ops, int(t[0]))
        version = learner.version
        columns = {k: v.tolist() for k, v in rates.items()}
        q_total = columns["q_total"]
        none = [None] * len(q_total)
        q_gas, q_oil, q_water = columns["q_gas"], columns["q_oil"], columns["q_water"]
        std = columns.get("q_total_std", none)
        p05, p95 = columns.get("q_total_p05", none), columns.get("q_total_p95", none)
        times, rows = t.tolist(), [tuple(r) for r in x.tolist()]
        ok = np.isfinite(rates["q_total"])
        answered = int(ok.sum())
        payload = None
        if answered:  # the message first: what it cannot hold must not leave half a block
            keep = ok if answered < len(times) else slice(None)
            message: dict[str, object] = {"time": iso_many(t[keep])}
            for name in ("q_total", "q_gas", "q_oil", "q_water"):
                message[name] = _json_floats(rates[name][keep])
            message["model"], message["version"] = learner.name, version
            for name in ("q_total_std", "q_total_p05", "q_total_p95"):
                message[name] = _json_floats(rates[name][keep]) if name in rates else None
            payload = json.dumps(message, allow_nan=False).encode()
        recent, ops, well, received = st.recent, b.ops, item.well, item.received_ns
        st.fallback = None  # every input used as read (watched before: _split_block)
        for i, (ti, row) in enumerate(zip(times, rows, strict=True)):
            if ok[i]:
                q = q_total[i]
                recent.append(Sample(ti, row, q))
                ops.append(
                    InsertSample(
                        well,
                        ti,
                        row,
                        received,
                        q,
                        q_gas[i],
                        q_oil[i],
                        q_water[i],
                        version,
                        std[i],
                        p05[i],
                        p95[i],
                    )
                )
            else:  # no finite answer: stored without one, as a single sample would be
                recent.append(Sample(ti, row, None))
                ops.append(InsertSample(well, ti, row, received, None, None, None, None, None))
        st.last_time_ns, st.last_inputs = times[-1], rows[-1]
        st.samples += len(times)
        self.counters.accept("sensors", len(times))
        if answered < len(times):
            self.counters.event("model not ready", len(times) - answered)
        if payload is not None:
            b.outbox.append((well, payload))
        if self.separators is not None:  # a separator's reading may now be complete
            self.separators.on_sample(well, b)

    def _predict_samples(self, b: Batch) -> None:
        """Second pass: predict every admitted sample of the batch in one call, then store
        and publish each in order. A well may have several (its model cannot change while
        predicting, ``ol`` or ``bayes``); with scheduled retrains (``pbl``, ``bayes``'s
        refresh) a well's next sample joins it when it comes before the retrain is due, and
        otherwise waits for this call."""
        if not b.samples:
            return
        if b.learn_wells and any(st.well in b.learn_wells for st, _, _, _ in b.samples):
            self.learning.run_deferred(b)  # a sample is predicted after what was learned before it
        taken = b.samples
        b.samples, b.sample_wells, b.sample_last = [], {}, {}
        b.sample_due = set()
        try:
            answers = self.learning.predict_many(
                [st for st, _, _, _ in taken],
                [inputs for _, _, _, inputs in taken],
                [t for _, _, t, _ in taken],
            )
        except Exception as exc:  # pragma: no cover - predict_many answers errors in place
            answers = [exc] * len(taken)
        accepted = 0
        for (st, item, t, inputs), rates in zip(taken, answers, strict=True):
            try:
                if isinstance(rates, BaseException):
                    raise rates
                self._on_sample(st, item, t, inputs, rates, b)
                accepted += 1
            except Exception as exc:  # one bad message must not stop the worker
                logger.exception("Unexpected error on SensorItem of %s: %s", item.well, exc)
                self.counters.event("internal errors")
        self.counters.accept("sensors", accepted)  # once per call: the counters take a lock

    def _on_sample(
        self,
        st: WellState,
        item: SensorItem,
        t: int,
        inputs: tuple[float, ...],
        rates: dict[str, float | None] | None,
        b: Batch,
    ) -> None:
        """Third pass, per sample: store it with its prediction, publish, settle what waited."""
        learner = st.learner
        if learner.version != st.snapshot.get("version"):  # a pbl retrain ran
            self.checkpoints.changed(st, b.ops, t)
        # a flagged input: its fallback stands in, the interval widened (raw inputs stored)
        rates, fallback = self.learning.fallback(st, inputs, rates, item.stand_ins or (), t)
        q_total = rates.get("q_total") if rates else None
        st.recent.append(Sample(t, inputs, q_total))
        st.last_time_ns, st.last_inputs = t, inputs
        st.samples += 1
        if not rates or q_total is None:
            b.ops.append(InsertSample(item.well, t, inputs, item.received_ns, *_NOT_READY))
            self.counters.event("model not ready")
        else:
            get = rates.get
            version = learner.version
            q_gas, q_oil, q_water = rates["q_gas"], rates["q_oil"], rates["q_water"]
            std, p05, p95 = get("q_total_std"), get("q_total_p05"), get("q_total_p95")
            b.ops.append(
                InsertSample(
                    item.well,
                    t,
                    inputs,
                    item.received_ns,
                    q_total,
                    q_gas,
                    q_oil,
                    q_water,
                    version,
                    std,
                    p05,
                    p95,
                )
            )
            message = prediction_json(
                t, q_total, q_gas, q_oil, q_water, learner.name, version, std, p05, p95, fallback
            )
            b.outbox.append((item.well, message))
        if st.trial is not None:  # a model change on trial: its shadow predicts the sample too
            st.trial.on_sample(self.learning, t, inputs)
        if st.pending:
            self.pairing.resolve(st, b, upto=t)
        if self.separators is not None:  # a separator's reading may now be complete
            self.separators.on_sample(item.well, b)


#: items a worker takes from its queue at once (:meth:`FairQueue.get_many`: one lock for
#: them); taken items keep their order, and a batch's leftovers start the next batch
_TAKE = 16

#: an InsertSample's rates and version for a sample without a prediction (the model not ready)
_NOT_READY = (None, None, None, None, None)


def _out_of_order(
    well: str,
    t: int,
    inputs: tuple[float, ...],
    last_ns: int,
    last_inputs: tuple[float, ...] | None,
) -> ServiceError:
    """Why a sample at ``t`` (epoch ns), not after the well's previous one at ``last_ns``,
    is refused: the same sample again, or time going backwards."""
    if t == last_ns and inputs == last_inputs:
        return Duplicate(f"The sample of {well} at {iso(t)} arrived before.", "duplicate")
    return InvalidRequest(
        f"The sample of {well} at {iso(t)} is not after the well's previous sample at "
        f"{iso(last_ns)}; samples of a well must arrive in time order.",
        "time going backwards",
    )


def _json_floats(values: np.ndarray) -> list[float] | list[float | None]:
    """Numbers for a JSON message: a value that is not finite is null (as pydantic writes
    one sample's prediction)."""
    out: list[float] = values.tolist()
    if np.isfinite(values).all():
        return out
    return [v if math.isfinite(v) else None for v in out]
