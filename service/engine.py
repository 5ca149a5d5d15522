"""The service's core, free of Zenoh and HTTP: per-well state, workers, pairing, learning.

Data flow::

    transport receiver thread            worker thread(s), one owner per well
    ------------------------            ------------------------------------------------
    key + JSON -> checks -> item  --->  bounded queue -> batch -> predict / pair / learn
    (Rejected: counted by reason)        -> one store commit -> publish predictions
                                         -> answer HTTP callers

Receiving never waits for learning: the receiver only checks and queues. A well always
goes to the same worker, so its messages are handled in arrival order (a sample is
predicted before the measurement at its time is learned from, as in
:func:`vfm_core.jobs.study.run_prequential`). When a worker queue is full the receiver waits
up to ``queues.block_s`` (back-pressure: Zenoh's BLOCK congestion control then slows the
publisher), then drops the message and counts a ``queue overflow``.

Every accepted sample, measurement and prediction is written to the store and committed
before its prediction is published or its HTTP caller answered; checkpoints go into the
same transactions, so the store never holds a model that is ahead of its data. On start
the engine restores each well from its latest checkpoint and re-learns the measurements
learned after it, in the same order, which gives back the same model.
"""

from __future__ import annotations

import inspect
import logging
import math
import queue
import threading
import time
import zlib
from collections import OrderedDict, deque
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np

from service.config import Settings
from service.inputs import Counters, Rejected, parse_measurement, parse_sensor, route_key
from service.learning import describe, fit_history, load_history, new_learner
from service.store import Op, Store
from vfm_core.effects import effect_spec, resolve_effects
from vfm_core.errors import VFMError
from vfm_core.messages import Measurement, Prediction, SensorSample
from vfm_core.streaming import WellLearner

try:  # the lead's streaming Hotelling detector; the service runs without it
    from vfm_core.drift import StreamingHotelling
except ImportError:  # pragma: no cover - depends on the vfm_core version
    StreamingHotelling = None  # type: ignore[assignment,misc]

# vfm_core's WellLearner.predict takes the sample time (pbl retrains on the study's calendar)
_PREDICT_TAKES_WHEN = "when" in inspect.signature(WellLearner.predict).parameters

__all__ = [
    "Engine",
    "SensorItem",
    "MeasurementItem",
    "WellTestResult",
    "ModelChangeRefused",
    "to_ns",
    "from_ns",
]

logger = logging.getLogger("vfm.service.engine")

_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_RECENT_SAMPLES = 512  # per well, in memory, for pairing; older ones are looked up in the store
_SEEN_MEASUREMENTS = 1024  # per well, recent measurement keys for the duplicate check


def to_ns(when: datetime) -> int:
    """Epoch nanoseconds of an aware datetime (microsecond precision, exact integer arithmetic)."""
    return ((when - _EPOCH) // timedelta(microseconds=1)) * 1000


def from_ns(ns: int) -> datetime:
    return _EPOCH + timedelta(microseconds=ns // 1000)


def _iso(ns: int | None) -> str | None:
    return None if ns is None else from_ns(ns).isoformat().replace("+00:00", "Z")


@dataclass(slots=True)
class SensorItem:
    well: str
    sample: SensorSample
    received_ns: int


@dataclass(slots=True)
class MeasurementItem:
    well: str
    measurement: Measurement
    source: str
    received_ns: int
    via: str = "zenoh"
    future: Future[WellTestResult] | None = None


@dataclass(slots=True)
class _Sample:
    time_ns: int
    inputs: tuple[float, ...]
    predicted: float | None


@dataclass(slots=True)
class _Pending:
    time_ns: int
    source: str
    q_total: float
    via: str
    since: float  # time.monotonic() when it started waiting
    future: Future[WellTestResult] | None = None


@dataclass
class WellTestResult:
    """What a well test did: stored (always), learned or still waiting for its sample."""

    well: str
    time: str
    q_total: float
    status: str  # learned | pending
    message: str
    paired_sample_time: str | None = None
    before: dict[str, float | None] = field(default_factory=dict)
    after: dict[str, float | None] = field(default_factory=dict)
    version_before: int = 0
    version_after: int = 0
    model_changed: bool = False


class ModelChangeRefused(Exception):
    """A model change that cannot be made: an HTTP status and a sentence."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status
        self.message = message


@dataclass
class _ModelStep:
    """A step of a model change, run by the well's worker: take a copy, or swap in the new model."""

    well: str
    kind: str  # snapshot | swap | cancel
    future: Future[Any]
    learner: WellLearner | None = None
    scores: dict[str, Any] = field(default_factory=dict)


def _checkpoint_fits(row: Any, spec: list[Any], configured: str) -> tuple[bool, str]:
    """Whether a well's checkpoint may be restored under the configured model, and why.

    Yes when it holds the configured model, effects (with their settings) and method; or
    when its model was chosen over HTTP and the config has not changed since that choice
    (a later edit of the config wins, and is said so).
    """
    import json

    try:
        extra = json.loads(row.extra)
    except ValueError:
        extra = {}
    saved = extra.get("spec") if isinstance(extra, dict) else None
    if saved is None:  # checkpoints before effects: compare names
        return (row.model, row.method) == (configured, spec[2]), ""
    if saved == spec:
        return True, ""
    changes = extra.get("model_changes") or []
    if changes and changes[-1].get("config") == spec:
        return True, (
            f"keeps {row.model} ({row.method}), chosen over HTTP at {changes[-1].get('time')}; "
            "edit the config's model to replace it"
        )
    if changes:
        return False, (
            f"the config changed since {row.model} was chosen over HTTP; building {configured} "
            "from the history and the stored measurements"
        )
    return False, ""


class _Batch:
    """What one worker batch writes, publishes and answers (after one commit)."""

    __slots__ = ("ops", "outbox", "answers")

    def __init__(self) -> None:
        self.ops: list[Op] = []
        self.outbox: list[tuple[str, bytes]] = []
        self.answers: list[tuple[Future[WellTestResult], WellTestResult | BaseException]] = []


class WellState:
    """One well: its learner and what the service needs to feed it (owned by one worker)."""

    def __init__(self, well: str, learner: WellLearner, settings: Settings, worker: int) -> None:
        self.well = well
        self.learner = learner
        self.worker = worker
        self.recent: deque[_Sample] = deque(maxlen=_RECENT_SAMPLES)
        self.last_time_ns: int | None = None
        self.last_inputs: tuple[float, ...] | None = None
        self.pending: list[_Pending] = []
        self.seen: OrderedDict[tuple[str, int], None] = OrderedDict()
        self.learn_seq = 0
        self.checkpoint_version = learner.version
        self.errors: deque[float] = deque(maxlen=settings.rolling_window)
        self.learned_inputs: deque[tuple[float, ...]] = deque(maxlen=settings.drift.reference_size)
        self.detector: Any = None
        self.drift_events: deque[dict[str, Any]] = deque(maxlen=20)
        # model changes over HTTP: what was swapped in, when, and its held-out scores
        self.model_changes: deque[dict[str, Any]] = deque(maxlen=20)
        # while a new model is fitted off the worker: what the old one learned meanwhile
        self.catch_up: list[tuple[tuple[float, ...], float, int, str]] | None = None
        self.samples = 0
        self.measurements = 0
        self.snapshot: dict[str, Any] = {}
        if settings.drift.enabled and StreamingHotelling is not None:
            d = settings.drift
            self.detector = StreamingHotelling(
                reference_size=d.reference_size, alpha=d.alpha, confirm=d.confirm
            )
        self.refresh()

    def refresh(self) -> None:
        """Rebuild the snapshot the HTTP API reads (replaced whole, so readers never see half)."""
        snap = describe(self.learner)
        snap["well"] = self.well
        self.snapshot = snap

    def remember_measurement(self, source: str, time_ns: int) -> None:
        self.seen[(source, time_ns)] = None
        if len(self.seen) > _SEEN_MEASUREMENTS:
            self.seen.popitem(last=False)

    def drift_state(self) -> dict[str, Any]:
        det = self.detector
        if det is None:
            return {
                "enabled": False,
                "detected": False,
                "note": "vfm_core.drift is not available"
                if StreamingHotelling is None
                else "disabled",
            }
        stat = float(getattr(det, "statistic", float("nan")))
        pval = float(getattr(det, "p_value", float("nan")))
        return {
            "enabled": True,
            "detected": bool(det.drift_detected) or bool(self.drift_events),
            "active": bool(det.drift_detected),
            "statistic": stat if math.isfinite(stat) else None,
            "p_value": pval if math.isfinite(pval) else None,
            "n_seen": int(getattr(det, "n_seen", 0)),
            "events": list(self.drift_events),
        }

    def rolling_mape(self) -> dict[str, Any]:
        errors = list(self.errors)  # a copy: the worker appends while the API reads
        n = len(errors)
        value = float(np.mean(errors) * 100.0) if n else None
        return {"value": value, "n": n, "window": self.errors.maxlen, "unit": "%"}


class Engine:
    """Per-well learners behind bounded worker queues; see the module docstring."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        counters: Counters,
        publish: Callable[[str, bytes], None],
    ) -> None:
        self.settings = settings
        self.store = store
        self.counters = counters
        self.publish = publish
        self.wells: dict[str, WellState] = {}
        self._wells_lock = threading.Lock()
        n = settings.queues.workers
        self._queues: list[queue.Queue[Any]] = [
            queue.Queue(settings.queues.worker_capacity) for _ in range(n)
        ]
        self._threads: list[threading.Thread] = []
        self._stop = object()
        self._changing: set[str] = set()
        self._stopping = False
        self._tol_ns = int(settings.inputs.pair_tolerance_s * 1e9)
        self._future_ns = int(settings.inputs.max_future_s * 1e9)
        self.started_at = time.time()

    # -- start-up -------------------------------------------------------------------------
    def _worker_of(self, well: str) -> int:
        return zlib.crc32(well.encode()) % len(self._queues)

    def load(self) -> None:
        """Restore every known well from the store, or fit it on the history; re-learn the rest."""
        cfg = self.settings
        history = load_history(cfg.model) if cfg.model.history is not None else None
        names = list(
            dict.fromkeys(
                [
                    *cfg.inputs.wells,
                    *self.store.wells(),
                    *(
                        []
                        if history is None or history.empty
                        else history["well"].astype(str).tolist()
                    ),
                ]
            )
        )
        learners: dict[str, WellLearner] = {}
        checkpoints: dict[str, Any] = {}
        method = cfg.model.method
        configured = cfg.model.full_name
        spec = self._configured_spec()
        for well in names:
            row = self.store.latest_checkpoint(well)
            usable, why = _checkpoint_fits(row, spec, configured) if row else (False, "")
            if why:
                logger.info("%s: %s", well, why)
            if row is not None and usable:
                try:
                    learners[well] = WellLearner.restore(row.blob)
                    checkpoints[well] = row
                    continue
                except VFMError as exc:
                    logger.warning(
                        "Checkpoint of %s unusable (%s); rebuilding it from the store.", well, exc
                    )
            elif row is not None:
                logger.warning(
                    "The store holds a %s/%s model for %s but the config asks for %s/%s; building a new "
                    "model from the history and every stored measurement.",
                    row.model,
                    row.method,
                    well,
                    configured,
                    method,
                )
            learners[well] = new_learner(well, cfg.model)
        fresh = [w for w in names if w not in checkpoints]
        fitted: list[str] = []
        if history is not None and fresh:
            started = time.perf_counter()
            fitted = fit_history({w: learners[w] for w in fresh}, history, cfg.model)
            if fitted:
                logger.info(
                    "Fitted %d well(s) on the history in %.1f s.",
                    len(fitted),
                    time.perf_counter() - started,
                )
        ops: list[Op] = []
        now = time.time_ns()
        restored = relearned_total = 0
        by_well = (
            {str(w): g for w, g in history.groupby("well", sort=False)}
            if history is not None and not history.empty
            else {}
        )
        for well in names:
            ops.append(("well", (well, now, "history" if well in fitted else "config/store")))
            st = WellState(well, learners[well], cfg, self._worker_of(well))
            row = checkpoints.get(well)
            if row is not None:
                st.learn_seq = row.learn_seq
                self._restore_extra(st, row.extra)
            elif well in fitted and st.detector is not None and by_well:
                own = by_well[well]
                own = own[own["q_total"].notna()]
                ref = own[["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil"]].to_numpy(
                    dtype=float
                )
                ref = ref[-cfg.drift.reference_size :]
                st.learned_inputs.extend(tuple(map(float, r)) for r in ref)
                if len(ref) >= cfg.drift.reference_size:
                    st.detector.reset(ref)
            relearned = self._relearn(st, ops)
            if well in fitted or (row is None and relearned):
                ops.extend(self._checkpoint_ops(st))
            self._load_recent(st)
            st.refresh()
            self.wells[well] = st
            restored += row is not None
            relearned_total += relearned
        self.store.write(ops)
        logger.info(
            "%d well(s): %d restored from checkpoints, %d fitted on the history; %d measurement(s) "
            "re-learned after the checkpoints.",
            len(names),
            restored,
            len(fitted),
            relearned_total,
        )

    def _restore_extra(self, st: WellState, extra: str) -> None:
        import json

        try:
            data = json.loads(extra)
        except ValueError:
            return
        if st.detector is not None and data.get("drift"):
            try:
                st.detector.load_state_dict(data["drift"])
            except (KeyError, TypeError, ValueError, VFMError) as exc:
                logger.warning(
                    "Drift state of %s not restored (%s); the detector starts over.", st.well, exc
                )
        st.learned_inputs.extend(tuple(x) for x in data.get("learned_inputs", []))
        st.drift_events.extend(data.get("drift_events", []))
        st.model_changes.extend(data.get("model_changes", []))

    def _relearn(self, st: WellState, ops: list[Op]) -> int:
        rows = self.store.learned_after(st.well, st.learn_seq)
        for seq, time_ns, source, q_total, sample_ns, *rest in rows:
            inputs, predicted = tuple(rest[:6]), rest[6]
            self._apply_learning(
                st, _Sample(sample_ns, inputs, predicted), q_total, time_ns, ops, source
            )
            st.learn_seq = seq
        since = int(st.model_changes[-1]["version_after"]) if st.model_changes else None
        for predicted, measured in self.store.recent_errors(
            st.well, self.settings.rolling_window, since
        ):
            if predicted is not None and measured:
                st.errors.append(abs(predicted - measured) / abs(measured))
        return len(rows)

    def _load_recent(self, st: WellState) -> None:
        for time_ns, *rest in self.store.recent_samples(st.well, _RECENT_SAMPLES):
            st.recent.append(_Sample(time_ns, tuple(rest[:6]), rest[6]))
        if st.recent:
            st.last_time_ns = st.recent[-1].time_ns
            st.last_inputs = st.recent[-1].inputs
        now = time.monotonic()
        for time_ns, source, q_total, via in self.store.pending(st.well):
            st.pending.append(_Pending(time_ns, source, q_total, via, now))

    def start(self) -> None:
        for i, q in enumerate(self._queues):
            t = threading.Thread(target=self._run, args=(i, q), name=f"vfm-worker-{i}", daemon=True)
            t.start()
            self._threads.append(t)

    def stop(self, timeout: float = 30.0) -> None:
        """Let the workers finish what is queued, checkpoint, and stop."""
        deadline = time.monotonic() + timeout
        self._stopping = True
        for q in self._queues:
            while True:
                try:
                    q.put(self._stop, timeout=0.5)
                    break
                except queue.Full:
                    if time.monotonic() > deadline:
                        break
        for t in self._threads:
            t.join(max(0.1, deadline - time.monotonic()))
        self._threads.clear()
        for q in self._queues:  # answer model-change steps the workers did not reach
            while True:
                try:
                    item = q.get_nowait()
                except queue.Empty:
                    break
                if isinstance(item, _ModelStep) and not item.future.done():
                    item.future.set_exception(
                        ModelChangeRefused(503, "The service stopped before the model change ran.")
                    )
        ops: list[Op] = []
        for st in self.wells.values():
            if st.learner.version != st.checkpoint_version:
                ops.extend(self._checkpoint_ops(st))
        try:
            self.store.write(ops)
        except Exception as exc:  # pragma: no cover - disk full at shutdown
            logger.error("Final checkpoints not written: %s", exc)

    # -- receiving (transport thread) -----------------------------------------------------
    def well_state(self, well: str, *, create: bool = True) -> WellState:
        """The well's state; unknown wells are created or rejected as configured."""
        st = self.wells.get(well)
        if st is not None:
            return st
        if not create or self.settings.inputs.unknown_wells == "reject":
            raise Rejected(
                "unknown well",
                f"The well '{well}' is not known to this service; add it to inputs.wells or set "
                "inputs.unknown_wells = 'create'.",
                status=404,
            )
        if not well or any(ch in well for ch in "/*$?#"):
            raise Rejected(
                "unparseable key", f"The well id '{well}' cannot be used in a key expression."
            )
        with self._wells_lock:
            st = self.wells.get(well)
            if st is None:
                st = WellState(
                    well,
                    new_learner(well, self.settings.model),
                    self.settings,
                    self._worker_of(well),
                )
                self.store.write([("well", (well, time.time_ns(), "first sight"))])
                self.wells[well] = st
                logger.info(
                    "New well %s (first sight); it gets predictions once it has a measurement.",
                    well,
                )
        return st

    def check_time(self, when: datetime, what: str) -> None:
        ahead = to_ns(when) - time.time_ns()
        if ahead > self._future_ns:
            raise Rejected(
                "time in the future",
                f"The {what} time {when.isoformat()} lies {ahead / 3.6e12:.1f} h in the future; "
                f"at most {self.settings.inputs.max_future_s / 3600:g} h ahead is accepted (inputs.max_future_s).",
            )

    def on_message(self, key: str, payload: bytes, received_ns: int) -> None:
        """One inbound Zenoh message: check, then queue for the well's worker (never learns)."""
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
        except Rejected as r:
            self.counters.reject(r.reason, r.message, where=key)
            return
        self._enqueue(st.worker, item, key)

    def _enqueue(self, worker: int, item: Any, where: str) -> None:
        q = self._queues[worker]
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

    def submit_well_test(self, well: str, measurement: Measurement) -> Future[WellTestResult]:
        """Queue a well test posted over HTTP; the future answers after it is stored (and learned)."""
        self.check_time(measurement.time, "well test")
        st = self.well_state(well)
        fut: Future[WellTestResult] = Future()
        item = MeasurementItem(
            well, measurement, "well_test", time.time_ns(), via="http", future=fut
        )
        try:
            self._queues[st.worker].put(item, timeout=2.0)
        except queue.Full:
            raise Rejected(
                "queue overflow",
                "The service is busy (its queue is full); retry in a few seconds.",
                status=503,
            ) from None
        return fut

    # -- model changes (HTTP thread; the swap itself runs on the well's worker) ---------------
    def change_model(
        self,
        well: str,
        model: str | None = None,
        effects: list[str] | None = None,
        method: str | None = None,
    ) -> dict[str, Any]:
        """Replace a well's model: fit the new one on the well's stored history, then swap.

        The worker hands out a copy of the learner (so learning goes on meanwhile), the new
        model is fitted on the copy's history here, and the worker then teaches it what the
        old one learned in the meantime and swaps it in, with a higher version, in one step
        between two messages. The change is checkpointed before this returns. Effects given
        as ``module:Class`` must come from a module listed in ``model.effect_modules``.
        """
        st = self.wells.get(well)
        if st is None:
            raise ModelChangeRefused(
                404, f"The well '{well}' is not known to this service; GET /wells lists the wells."
            )
        effects = list(effects or [])
        allowed = set(self.settings.model.effect_modules)
        for text in effects:
            base = text.split("=", 1)[0].rsplit(":", 1)[0] if "=" in text else text
            module = base.split(":", 1)[0] if ":" in base else None
            if module is not None and module not in allowed:
                raise ModelChangeRefused(
                    403,
                    f"The effect '{text}' names the module '{module}', which is not in "
                    "model.effect_modules; over HTTP only the library's effects and classes from "
                    "those modules can be used.",
                )
        old = st.learner
        model = model or old.model_name
        try:  # check the request before any work: a typo fails at once
            WellLearner(well, model, method or old.method.text, effects=effects)
        except VFMError as exc:
            raise ModelChangeRefused(422, str(exc)) from None
        with self._wells_lock:
            if well in self._changing:
                raise ModelChangeRefused(
                    409, f"A model change of {well} is already running; wait for it to finish."
                )
            self._changing.add(well)
        try:
            copy: WellLearner = self._step(st, "snapshot")
            started = time.perf_counter()
            try:
                new, scores = copy.refit_as(model, effects, method)
            except BaseException as exc:
                self._step(st, "cancel")
                if isinstance(exc, VFMError):
                    raise ModelChangeRefused(422, str(exc)) from None
                raise
            scores["fit_s"] = round(time.perf_counter() - started, 2)
            change: dict[str, Any] = self._step(st, "swap", new, scores)
            return change
        finally:
            with self._wells_lock:
                self._changing.discard(well)

    def _step(
        self,
        st: WellState,
        kind: str,
        learner: WellLearner | None = None,
        scores: dict[str, Any] | None = None,
    ) -> Any:
        """Run one step of a model change on the well's worker and wait for it.

        The snapshot waits at most 5 s for queue room (busy: 503); a swap or cancel waits
        for room as long as it takes, since it must not be dropped once the copy is out.
        """
        if self._stopping:
            raise ModelChangeRefused(503, "The service is stopping; retry after it restarts.")
        fut: Future[Any] = Future()
        item = _ModelStep(st.well, kind, fut, learner, scores or {})
        try:
            self._queues[st.worker].put(item, timeout=5.0 if kind == "snapshot" else None)
        except queue.Full:
            raise ModelChangeRefused(
                503, "The service is busy (its queue is full); retry in a few seconds."
            ) from None
        return fut.result()

    def _on_model_step(self, item: _ModelStep, b: _Batch) -> None:
        st = self.wells[item.well]
        if item.kind == "snapshot":
            copy = WellLearner.restore(st.learner.checkpoint())
            st.catch_up = []
            item.future.set_result(copy)
            return
        if item.kind == "cancel":
            st.catch_up = None
            item.future.set_result(None)
            return
        new, old = item.learner, st.learner
        assert new is not None
        try:
            caught_up = list(st.catch_up or [])
            for inputs, q_total, time_ns, source in caught_up:
                new.learn(list(inputs), q_total, from_ns(time_ns), source)
        finally:
            st.catch_up = None
        new.version = max(new.version, old.version + 1)
        before = st.rolling_mape()
        change = {
            "time": _iso(time.time_ns()),
            "model_before": old.name,
            "model_after": new.name,
            "effects": list(new.effects),
            "method": new.method.text,
            "version_before": old.version,
            "version_after": new.version,
            "holdout": item.scores,
            "caught_up": len(caught_up),
            "rolling_mape_before": before["value"],
            "config": self._configured_spec(),
        }
        # commit what the batch holds so far, then the new model's checkpoint on its own:
        # the swap happens only once that checkpoint is in the store
        self._flush(b)
        b.ops, b.outbox, b.answers = [], [], []
        saved_version = st.checkpoint_version
        st.learner = new
        st.model_changes.append(change)
        try:
            self.store.write(self._checkpoint_ops(st))
        except Exception:
            st.learner, st.checkpoint_version = old, saved_version
            st.model_changes.pop()
            raise
        st.errors.clear()  # the rolling error from now on is the new model's
        st.refresh()
        logger.info(
            "Model of %s changed from %s (version %d) to %s (version %d); held-out MAPE %s -> %s %%.",
            st.well,
            old.name,
            old.version,
            new.name,
            new.version,
            item.scores.get("before"),
            item.scores.get("after"),
        )
        b.answers.append((item.future, change))  # type: ignore[arg-type]

    def _configured_spec(self) -> list[Any]:
        """The configured model as [name, effect specs, method], to compare with checkpoints."""
        m = self.settings.model
        return [m.name, [effect_spec(c) for c in resolve_effects(m.effects)], m.method]

    def queue_depths(self) -> list[int]:
        return [q.qsize() for q in self._queues]

    # -- the worker -----------------------------------------------------------------------
    def _run(self, index: int, q: queue.Queue[Any]) -> None:
        """Take items in arrival order; commit and publish when the queue runs dry, the batch
        is full, or it has run for ``queues.batch_ms`` (so a slow learning step does not hold
        back the predictions already made)."""
        batch_max = self.settings.queues.batch_max
        batch_s = self.settings.queues.batch_ms / 1000.0
        last_expiry = time.monotonic()
        stopping = False
        while not stopping:
            b = _Batch()
            try:
                item = q.get(timeout=0.5)
            except queue.Empty:
                item = None
            began = time.monotonic()
            n = 0
            while item is not None:
                if item is self._stop:
                    stopping = True
                    break
                self._handle(item, b)
                n += 1
                if n >= batch_max or time.monotonic() - began > batch_s:
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
                        self._expire_pending(st, b, now)
            self._flush(b)

    def _handle(self, item: Any, b: _Batch) -> None:
        try:
            if isinstance(item, SensorItem):
                self._on_sample(item, b)
            elif isinstance(item, _ModelStep):
                self._on_model_step(item, b)
            else:
                self._on_measurement(item, b)
        except Exception as exc:  # one bad message must not stop the worker
            logger.exception(
                "Unexpected error on %s of %s: %s", type(item).__name__, item.well, exc
            )
            self.counters.event("internal errors")
            fut = getattr(item, "future", None)
            if fut is not None:
                b.answers.append((fut, exc))

    def _flush(self, b: _Batch) -> None:
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

    def _reject(self, item: Any, r: Rejected, b: _Batch) -> None:
        self.counters.reject(r.reason, r.message, where=f"{item.well}")
        fut = getattr(item, "future", None)
        if fut is not None:
            b.answers.append((fut, r))

    # -- samples --------------------------------------------------------------------------
    def _on_sample(self, item: SensorItem, b: _Batch) -> None:
        st = self.wells[item.well]
        sample = item.sample
        t = to_ns(sample.time)
        inputs = tuple(sample.inputs())
        if st.last_time_ns is not None and t <= st.last_time_ns:
            if t == st.last_time_ns and inputs == st.last_inputs:
                r = Rejected(
                    "duplicate",
                    f"The sample of {item.well} at {_iso(t)} arrived before.",
                    status=409,
                )
            else:
                r = Rejected(
                    "time going backwards",
                    f"The sample of {item.well} at {_iso(t)} is not after the well's previous sample at "
                    f"{_iso(st.last_time_ns)}; samples of a well must arrive in time order.",
                )
            self._reject(item, r, b)
            return
        learner = st.learner
        rates: dict[str, float | None] | None
        if _PREDICT_TAKES_WHEN:  # pbl: a retrain that is due runs first, on the study's calendar
            rates = learner.predict(list(inputs), when=sample.time)
            if rates.get("q_total") is None:
                rates = None
        else:  # pragma: no cover - older vfm_core
            rates = learner.predict(list(inputs)) if learner.ready else None
        if learner.version != st.snapshot.get("version"):
            self._changed(st, b.ops)
        q_total = rates["q_total"] if rates else None
        if q_total is not None and not math.isfinite(q_total):
            rates, q_total = None, None
        st.recent.append(_Sample(t, inputs, q_total))
        st.last_time_ns, st.last_inputs = t, inputs
        st.samples += 1
        self.counters.accept("sensors")
        b.ops.append(
            (
                "sample",
                (
                    item.well,
                    t,
                    *inputs,
                    item.received_ns,
                    q_total,
                    *(rates[k] if rates else None for k in ("q_gas", "q_oil", "q_water")),
                    learner.version if rates else None,
                ),
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
            self._resolve_pending(st, b, upto=t)

    # -- measurements ---------------------------------------------------------------------
    def _nearest(self, st: WellState, time_ns: int) -> _Sample | None:
        if st.recent and time_ns >= st.recent[0].time_ns:
            best = _bisect(st.recent, time_ns)
            return best if abs(best.time_ns - time_ns) <= self._tol_ns else None
        row = self.store.nearest_sample(st.well, time_ns, self._tol_ns)
        return None if row is None else _Sample(row[0], tuple(row[1:7]), row[7])

    def _on_measurement(self, item: MeasurementItem, b: _Batch) -> None:
        st = self.wells[item.well]
        m = item.measurement
        t = to_ns(m.time)
        key = (item.source, t)
        if key in st.seen or self.store.measurement_exists(item.well, item.source, t):
            self._reject(
                item,
                Rejected(
                    "duplicate",
                    f"The {item.source} measurement of {item.well} at {_iso(t)} arrived before; "
                    "it is stored once.",
                    status=409,
                ),
                b,
            )
            return
        sample: _Sample | None = None
        if st.last_time_ns is not None and t <= st.last_time_ns:
            sample = self._nearest(st, t)
            if sample is None:
                self._reject(
                    item,
                    Rejected(
                        "no sensor sample within tolerance",
                        f"No sensor sample of {item.well} lies within {self.settings.inputs.pair_tolerance_s:g} s of "
                        f"the measurement at {_iso(t)}, so it cannot be paired with inputs; it was not stored.",
                    ),
                    b,
                )
                return
        b.ops.append(
            ("measurement", (item.well, t, item.source, m.q_total, item.received_ns, item.via))
        )
        st.remember_measurement(item.source, t)
        st.measurements += 1
        self.counters.accept("well_tests" if item.via == "http" else "measurements")
        if item.via == "http":
            # stored durably first, then learned from
            self.store.write(b.ops)
            b.ops.clear()
        p = _Pending(t, item.source, m.q_total, item.via, time.monotonic(), item.future)
        if sample is not None:
            self._learn(st, p, sample, b)
            return
        if len(st.pending) >= self.settings.inputs.pending_max:
            oldest = st.pending.pop(0)
            self.counters.event("pending forced")
            self._settle(st, oldest, b, force=True)
        st.pending.append(p)
        if p.future is not None:
            b.answers.append(
                (
                    p.future,
                    WellTestResult(
                        st.well,
                        _iso(t) or "",
                        m.q_total,
                        "pending",
                        f"Stored. No sensor sample of {st.well} at or after {_iso(t)} has arrived yet; the well test "
                        "is learned from when it does.",
                        version_before=st.learner.version,
                        version_after=st.learner.version,
                    ),
                )
            )
            p.future = None

    def _resolve_pending(self, st: WellState, b: _Batch, upto: int) -> None:
        due = [p for p in st.pending if p.time_ns <= upto]
        if not due:
            return
        st.pending = [p for p in st.pending if p.time_ns > upto]
        for p in due:
            self._settle(st, p, b)

    def _expire_pending(self, st: WellState, b: _Batch, now: float) -> None:
        wait = self.settings.inputs.pending_timeout_s
        due = [p for p in st.pending if now - p.since > wait]
        if due:
            st.pending = [p for p in st.pending if now - p.since <= wait]
            for p in due:
                self._settle(st, p, b, force=True)

    def _settle(self, st: WellState, p: _Pending, b: _Batch, force: bool = False) -> None:
        sample = self._nearest(st, p.time_ns)
        if sample is None:
            b.ops.append(("unpaired", (st.well, p.source, p.time_ns)))
            r = Rejected(
                "no sensor sample within tolerance",
                f"No sensor sample of {st.well} arrived within {self.settings.inputs.pair_tolerance_s:g} s of the "
                f"{p.source} measurement at {_iso(p.time_ns)}"
                + (" before the wait ran out" if force else "")
                + "; it is stored but not learned from.",
            )
            self.counters.reject(r.reason, r.message, where=st.well)
            if p.future is not None:
                b.answers.append((p.future, r))
            return
        self._learn(st, p, sample, b)

    def _learn(self, st: WellState, p: _Pending, sample: _Sample, b: _Batch) -> None:
        learner = st.learner
        version_before = learner.version
        before = learner.predict(list(sample.inputs)) if p.future is not None else {}
        self._apply_learning(st, sample, p.q_total, p.time_ns, b.ops, p.source)
        st.learn_seq += 1
        self._changed(st, b.ops)
        b.ops.append(
            (
                "learned",
                (
                    st.learn_seq,
                    sample.time_ns,
                    *sample.inputs,
                    sample.predicted,
                    learner.version,
                    st.well,
                    p.source,
                    p.time_ns,
                ),
            )
        )
        self.counters.event("learned")
        if p.future is not None:
            after = learner.predict(list(sample.inputs))
            changed = learner.version != version_before
            b.answers.append(
                (
                    p.future,
                    WellTestResult(
                        st.well,
                        _iso(p.time_ns) or "",
                        p.q_total,
                        "learned",
                        "Stored and learned from: the model was updated."
                        if changed
                        else "Stored; the model keeps it for its next periodic retrain (method "
                        f"{learner.method.text}).",
                        paired_sample_time=_iso(sample.time_ns),
                        before=before,
                        after=after,
                        version_before=version_before,
                        version_after=learner.version,
                        model_changed=changed,
                    ),
                )
            )

    def _apply_learning(
        self,
        st: WellState,
        sample: _Sample,
        q_total: float,
        time_ns: int,
        ops: list[Op],
        source: str = "mpfm",
    ) -> None:
        """Learn, score the earlier prediction, run the drift test (also used when re-learning)."""
        learner = st.learner
        learner.learn(list(sample.inputs), q_total, from_ns(time_ns), source)
        if st.catch_up is not None:
            st.catch_up.append((sample.inputs, q_total, time_ns, source))
        if sample.predicted is not None and q_total:
            st.errors.append(abs(sample.predicted - q_total) / abs(q_total))
        st.learned_inputs.append(sample.inputs)
        det = st.detector
        if det is None:
            return
        was = bool(det.drift_detected)
        det.update(list(sample.inputs))
        if det.drift_detected and not was:
            action = "recorded"
            if self.settings.drift.on_drift == "retrain":
                learner.retrain(from_ns(time_ns))
                action = "retrained"
            event = {
                "time": _iso(time_ns),
                "statistic": float(det.statistic),
                "p_value": float(det.p_value),
                "action": action,
            }
            st.drift_events.append(event)
            ops.append(("drift", (st.well, time_ns, event["statistic"], event["p_value"], action)))
            logger.info(
                "Drift confirmed on %s at %s (T2 = %.1f, p = %.2g); %s.",
                st.well,
                event["time"],
                event["statistic"],
                event["p_value"],
                action,
            )
            self.counters.event("drifts")
            ref = np.asarray(st.learned_inputs, dtype=float)
            det.reset(ref if len(ref) >= self.settings.drift.reference_size else None)

    def _changed(self, st: WellState, ops: list[Op]) -> None:
        """The model's version moved: refresh what the API shows, checkpoint when due."""
        if st.learner.version - st.checkpoint_version >= self.settings.store.checkpoint_every:
            ops.extend(self._checkpoint_ops(st))
        st.refresh()

    def _checkpoint_ops(self, st: WellState) -> list[Op]:
        import json

        extra = {
            "drift": st.detector.state_dict() if st.detector is not None else None,
            "learned_inputs": [list(x) for x in st.learned_inputs],
            "drift_events": list(st.drift_events),
            "model_changes": list(st.model_changes),
            "spec": [st.learner.model_name, list(st.learner.effects), st.learner.method.text],
        }
        learner = st.learner
        st.checkpoint_version = learner.version
        keep = self.settings.store.keep_checkpoints
        return [
            (
                "checkpoint",
                (
                    st.well,
                    time.time_ns(),
                    learner.version,
                    st.learn_seq,
                    learner.name,
                    learner.method.text,
                    learner.checkpoint(),
                    json.dumps(extra),
                ),
            ),
            ("prune_checkpoints", (st.well, st.well, keep)),
        ]


def _bisect(recent: deque[_Sample], time_ns: int) -> _Sample:
    """The sample nearest in time (recent is in time order)."""
    lo, hi = 0, len(recent) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if recent[mid].time_ns < time_ns:
            lo = mid + 1
        else:
            hi = mid
    best = recent[lo]
    if lo > 0 and abs(recent[lo - 1].time_ns - time_ns) <= abs(best.time_ns - time_ns):
        best = recent[lo - 1]
    return best
