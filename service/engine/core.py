"""The engine's facade: what the service and the HTTP layer call, free of Zenoh and HTTP.

Data flow::

    transport receiver thread           worker thread(s), one owner per well
    -------------------------           ------------------------------------------------
    key + JSON -> checks -> item  --->  per-well FIFOs, round robin -> batch -> predict /
    (intake; refusals counted)          pair / learn -> one store commit -> publish
                                        predictions -> answer HTTP callers

With one worker (``queues.receiver = "worker"``) the left column runs on the worker's
thread too, between its items: no receiver thread, no hand-over of the GIL per message.

:class:`Engine` wires the parts, each in its own module: :mod:`~service.engine.recovery`
(restore, re-learn, fit on the history), :mod:`~service.engine.intake` (receiving,
routing, back-pressure), :mod:`~service.engine.worker` (the loop, group commit, publish,
answers), :mod:`~service.engine.pairing`, :mod:`~service.engine.learning` (predict,
learn, rolling error, drift), :mod:`~service.engine.checkpoints`,
:mod:`~service.engine.model_change`, :mod:`~service.engine.fairqueue` (the per-well
queues) and :mod:`~service.engine.registry` (which wells exist; new and retired ones). It raises the domain errors of :mod:`service.errors`,
never an HTTP status.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future
from datetime import datetime
from typing import TYPE_CHECKING, Any

from service.config import Settings
from service.engine.alarms import MpfmCheck, WellTestReview
from service.engine.checkpoints import Checkpoints
from service.engine.fairqueue import FairQueue
from service.engine.intake import Intake, worker_of
from service.engine.items import RetireStep
from service.engine.learning import Learning
from service.engine.model_change import ModelChanges
from service.engine.observe import Observer
from service.engine.pairing import Pairing, ReviewItem
from service.engine.recovery import Recovery
from service.engine.registry import Registry
from service.engine.separators import Separators, submit_item
from service.engine.state import WellState, WellTestResult
from service.engine.worker import Workers
from service.errors import Busy, InvalidRequest, Stopping, UnknownWell, unknown_well
from service.inputs import Counters
from service.store import Store
from vfm_core.messages import Measurement
from vfm_core.timeutil import iso

if TYPE_CHECKING:  # the engine knows no transport; a Source is what it is handed
    from service.transport import Source

__all__ = ["Engine"]

logger = logging.getLogger("vfm.service.engine")


class Engine:
    """Per-well learners behind bounded worker queues; see the module docstring."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        counters: Counters,
        publish: Callable[[str, bytes], None],
        forget: Callable[[str], None] | None = None,
        publish_key: Callable[[str, bytes], None] | None = None,
    ) -> None:
        """``forget(well)``: the transport lets go of what it holds for a retired well (e.g.
        its prediction key); ``publish_key(key, payload)`` puts a message on any key (the
        separators' allocations)."""
        self.settings = settings
        self.store = store
        self.counters = counters
        self._wells: dict[str, WellState] = {}
        self._queues: list[FairQueue] = _worker_queues(settings)
        self._stopping = threading.Event()
        self._forget = forget
        #: live events and monitoring numbers from every commit (``GET /events``, ``/metrics``)
        self.observer = Observer(settings.rolling_window)
        store.on_commit = self.observer.committed
        self._registry = Registry(settings, self._wells)
        self._checkpoints = Checkpoints(settings)
        self._learning = Learning(settings, counters, self._checkpoints)
        #: the MPFM against well tests alarm (service.engine.alarms)
        self.mpfm_check = MpfmCheck(settings, store)
        #: the well-test QC: a well test off the model and the MPFM is held for review
        self.review = WellTestReview(settings, self.mpfm_check)
        self._pairing = Pairing(
            settings, store, counters, self._learning, self.mpfm_check, self.review
        )
        self._intake = Intake(settings, counters, self._registry, self._queues)
        self._model_changes = ModelChanges(
            settings,
            store,
            self._wells,
            self._queues,
            self._checkpoints,
            self._stopping,
            self._learning.catch_up,
        )
        self._workers = Workers(
            settings,
            store,
            counters,
            publish,
            self._wells,
            self._queues,
            self._learning,
            self._pairing,
            self._checkpoints,
            self._model_changes,
            self._registry,
        )
        self._recovery = Recovery(
            settings,
            store,
            self._learning,
            self._checkpoints,
            self._worker_of,
        )
        #: the separators' readings (service.engine.separators); None without separators
        self.separators: Separators | None = None
        if settings.separators.members:
            self.separators = Separators(
                settings,
                store,
                counters,
                self._learning,
                self._checkpoints,
                self._wells,
                publish_key,
                self._worker_of,
            )
            self._workers.separators = self.separators

    def _worker_of(self, well: str) -> int:
        """The worker that owns ``well`` (a separator's wells: the separator's worker)."""
        return worker_of(self.settings.separators.route(well), len(self._queues))

    # -- life cycle -----------------------------------------------------------------------
    def load(self) -> None:
        """Restore every known well from the store, or fit it on the history; re-learn the rest."""
        self._registry.retired.update(self.store.retired_wells())
        self._wells.update(self._recovery.load(set(self._registry.retired)))
        for well in self._wells:  # the field view's interval width survives a restart
            self.observer.seed_latest(well, self.store.latest_prediction(well))
        for st in self._wells.values():
            self.mpfm_check.load(st)
            for row in self.store.reviews(st.well):  # the reviews still open
                st.hold_for_review(row)
        if self.separators is not None:  # the readings still waiting for their samples
            self.separators.load()

    def start(self, source: Source | None = None) -> None:
        """Start the worker threads; with ``source`` (one worker) the worker takes the
        messages from it itself, no receiver thread (see :class:`service.transport.Source`)."""
        self._workers.start(source, self._intake if source is not None else None)

    def stop(self, timeout: float = 30.0) -> bool:
        """Let the workers finish what is queued, checkpoint, and stop. A model change still
        fitting is waited for (at most 10 s) and then abandoned. True when everything ended
        in time; the checkpoints are written either way, of the wells whose worker ended."""
        self._stopping.set()
        self.observer.close()
        fits_done = self._model_changes.wait(min(10.0, timeout))
        ended = self._workers.stop(timeout)
        if ended:
            try:
                self.store.write(self._checkpoints.final_ops(self._wells.values()))
            except Exception as exc:  # pragma: no cover - disk full at shutdown
                logger.error("Final checkpoints not written: %s", exc)
        else:  # a worker still owns its wells' learners: the store has their data anyway
            logger.warning("Final checkpoints skipped; a restart re-learns from the store.")
        return ended and fits_done

    # -- what comes in --------------------------------------------------------------------
    def deliver(self, key: str, payload: bytes, received_ns: int) -> None:
        """One inbound message from the transport's receiver thread: check and queue."""
        self._intake.deliver(key, payload, received_ns)

    def submit_well_test(self, well: str, measurement: Measurement) -> Future[WellTestResult]:
        """Queue a well test; the future answers once it is stored (and learned, or pending)."""
        return self._intake.submit_well_test(well, measurement)

    def submit_review(
        self, well: str, when: datetime, source: str, decision: str
    ) -> Future[WellTestResult]:
        """Queue the operator's decision (accept | reject) on the ``source`` measurement of
        ``well`` at ``when`` held for review; the future answers once it is stored (accept:
        learned, as a well test is). Raises :class:`UnknownWell` or :class:`Busy` before
        queueing, :class:`InvalidRequest` for a bad time, source or decision."""
        if well not in self._wells:
            raise unknown_well(well)
        if source not in ("well_test", "mpfm") or decision not in ("accept", "reject"):
            raise InvalidRequest(
                "A review decision names source 'well_test' or 'mpfm' and decision 'accept' "
                "or 'reject'.",
                "wrong type",
            )
        self._intake.check_time(when, "review")
        fut: Future[WellTestResult] = Future()
        item = ReviewItem(
            well,
            Measurement(time=when, q_total=0.0),
            source,
            time.time_ns(),
            via="http",
            future=fut,
            decision=decision,
            decided_ns=time.time_ns(),
        )
        full = self._queues[self._worker_of(well)].put(well, item, timeout=2.0)
        if full != "ok":
            raise Busy(
                "The service is busy (its queue is full); retry in a few seconds.",
                "well flooding" if full == "well" else "queue overflow",
            )
        return fut

    def change_model(
        self,
        well: str,
        model: str | None = None,
        effects: list[str] | None = None,
        method: str | None = None,
        confirm_worse: bool = False,
    ) -> dict[str, Any]:
        """Replace a well's model (see :mod:`service.engine.model_change`); blocks until done.
        A change the held-out check finds worse is refused unless ``confirm_worse``."""
        change = self._model_changes.change(
            well, model, effects, method, confirm_worse=confirm_worse
        )
        self._observe_change(well, change)
        return change

    def rollback_model(self, well: str, version: int) -> dict[str, Any]:
        """Bring back the well's kept model ``version`` (``POST /wells/{well}/model/rollback``,
        see :meth:`service.engine.model_change.ModelChanges.rollback`); blocks until done."""
        change = self._model_changes.rollback(well, version)
        self._observe_change(well, change)
        return change

    def _observe_change(self, well: str, change: dict[str, Any]) -> None:
        """Tell the live events (``GET /events``) and /metrics about a change of model."""
        st = self._wells.get(well)
        self.observer.model_changed(well, change, st.last_time_ns if st is not None else None)

    def retire_well(self, well: str, purge: bool = False, timeout: float = 30.0) -> dict[str, Any]:
        """Stop serving a well (``DELETE /wells/{well}``) after what is queued for it: its
        data stay in the store (a last checkpoint is written) and it is not loaded again, or
        with ``purge`` every row of it is deleted and the id is free. Its messages are refused
        from now on (``retired well``)."""
        if well not in self._wells:
            raise unknown_well(well)
        if self._stopping.is_set():
            raise Stopping("The service is stopping; retry after it restarts.")
        when = time.time_ns()
        self._registry.retiring(well, when)
        fut: Future[dict[str, Any]] = Future()
        q = self._queues[self._worker_of(well)]
        q.put(well, RetireStep(well, purge, when, fut), force=True)
        try:
            result = fut.result(timeout)
            self.counters.forget(well)
            if self._forget is not None:
                self._forget(well)
            return result
        except TimeoutError:
            raise Busy(
                f"The retirement of {well} is queued but did not run within {timeout:g} s; "
                "it runs once the well's queue is through. Check GET /wells."
            ) from None

    def submit_reading(self, separator: str, measurement: Measurement) -> Future[Any]:
        """Queue a separator's reading posted over HTTP; the future answers once it is
        stored (with its allocation, or ``pending`` while it waits for its wells' samples).
        Raises :class:`UnknownWell` for a separator not configured, :class:`InvalidRequest`
        for a bad time or rate, :class:`Busy` when the queue stays full."""
        if self.separators is None or separator not in self.separators.members:
            raise unknown_separator(separator)
        item, fut = submit_item(separator, measurement)
        self._intake.submit_reading(item)
        return fut

    def separator_view(self, separator: str) -> dict[str, Any]:
        """``GET /separators/{name}`` (see :meth:`Separators.view`)."""
        if self.separators is None or separator not in self.separators.members:
            raise unknown_separator(separator)
        return self.separators.view(separator)

    def separator_overview(self) -> list[dict[str, Any]]:
        """``GET /separators``: every separator with its latest reading."""
        return [] if self.separators is None else self.separators.overview()

    # -- what the API reads -----------------------------------------------------------------
    @property
    def wells(self) -> Mapping[str, WellState]:
        """The wells' state by id (read-only outside the engine)."""
        return self._wells

    def has_well(self, well: str) -> bool:
        return well in self._wells

    def well_summaries(self) -> list[dict[str, Any]]:
        """Every well's model, method, readiness, version and updates."""
        return [
            {
                **st.snapshot,
                "mpfm_check": st.mpfm_check,
                "rejected": self.counters.rejected_of(st.well),
            }
            for st in list(self._wells.values())
        ]

    def well_view(self, well: str) -> dict[str, Any]:
        """One well's full state: the summary, parameters, rolling MAPE, drift, changes."""
        st = self._wells.get(well)
        if st is None:
            raise unknown_well(well)
        out = dict(st.snapshot)
        out.update(
            rolling_mape=st.rolling_mape(),
            drift=st.drift_state(),
            samples=st.samples,
            measurements=st.measurements,
            last_sample_time=iso(st.last_time_ns),
            pending_measurements=len(st.pending),
            model_changes=list(st.model_changes),
            mpfm_check=st.mpfm_check,
            rejected=self.counters.rejected_of(well),
            held_for_review=st.held_for_review_view(),
        )
        return out

    def queue_depths(self) -> list[int]:
        return [q.qsize() for q in self._queues]

    def busy_wells(self) -> list[int]:
        """Per worker: the wells with messages waiting."""
        return [q.busy_wells() for q in self._queues]

    @property
    def retired(self) -> dict[str, int]:
        """Retired wells (data kept) -> when (epoch ns)."""
        return dict(self._registry.retired)

    def pending_measurements(self) -> int:
        """Measurements of all wells still waiting for their sensor sample."""
        return sum(len(st.pending) for st in list(self._wells.values()))


def unknown_separator(name: str) -> UnknownWell:
    """The refusal of a request about a separator that ``separators.members`` does not list."""
    return UnknownWell(
        f"The separator '{name}' is not known to this service; GET /separators lists them "
        "(separators.members in the configuration)."
    )


def _worker_queues(settings: Settings) -> list[FairQueue]:
    """One :class:`FairQueue` per worker; a separator's wells and readings share one FIFO,
    in arrival order, holding ``queues.well_capacity`` per member (fairqueue.py)."""
    q, seps = settings.queues, settings.separators
    sizes = {sep: len(wells) for sep, wells in seps.members.items()}
    return [
        FairQueue(
            q.worker_capacity,
            q.well_capacity,
            fifo_of=seps.route,
            fifo_capacity=lambda fifo: q.well_capacity * sizes.get(fifo, 1),
        )
        for _ in range(q.workers)
    ]
