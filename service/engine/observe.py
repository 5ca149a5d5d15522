"""What the committed writes tell the outside: live events for the page, and numbers for /metrics.

The store calls :meth:`Observer.committed` with the ops of every successful commit, on the
worker thread that wrote them, so only what is durable is ever shown. The observer must
never make a worker wait: it only appends to bounded in-memory structures under one short
lock, and never serializes, sends or sleeps.

* **Live events** (``GET /events``, server-sent events): each subscriber has a bounded
  queue (:class:`Subscription`); when a slow client lets it fill up the oldest event is
  dropped and counted (``dropped``), the worker never blocks on a client. Events:
  ``prediction`` (a stored sample with its prediction, Sm3/h, and interval),
  ``measurement`` (an MPFM reading or well test stored), ``learned`` (a measurement
  learned from: the prediction made at its sample, the measured rate, the version after),
  ``drift`` (a confirmed input drift: the operating point left the training data),
  ``alarm`` (a residual alarm began, ``kind`` start, or ended, ``end``; see
  :mod:`service.engine.residual_alarms`) and ``model`` (a model change over HTTP).
* **Numbers** the per-well state does not keep: the interval coverage (share of learned
  measurements inside the 90 % interval p05..p95 predicted at their sample, over the last
  ``rolling_window`` that had an interval), drift events, model changes and predictions
  stored since start, and the latency from a sample's arrival to its stored prediction (a histogram, seconds).
"""

from __future__ import annotations

import math
import threading
import time
from bisect import bisect_left
from collections import Counter, OrderedDict, deque
from collections.abc import Sequence
from typing import Any

import numpy as np
from prometheus_client.core import Metric
from prometheus_client.utils import floatToGoString

from service.store import (
    InsertDriftEvent,
    InsertMeasurement,
    InsertResidualAlarm,
    InsertSample,
    InsertTrial,
    MarkLearned,
    Op,
)
from vfm_core.timeutil import iso

__all__ = ["Observer", "Subscription", "LatencyHistogram", "LATENCY_BUCKETS_S"]

#: buckets of the prediction latency histogram, s (arrival to stored prediction)
LATENCY_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
#: commits of fewer latencies than this are counted without numpy (see LatencyHistogram)
_SMALL_COMMIT = 16
#: intervals remembered per well for the coverage (sample time -> p05, p95)
_INTERVALS_KEPT = 4096
#: measured rates remembered until learned (all wells)
_MEASURED_KEPT = 8192


class LatencyHistogram:
    """A Prometheus histogram filled a commit at a time (:meth:`observe_many`): one call
    and one lock per commit instead of per sample (a ``prometheus_client.Histogram``
    takes a lock per bucket and sum on every ``observe``). :meth:`collect` gives the
    metric family, as a Histogram's does: cumulative buckets ``le``, count and sum.

    Kept beside the library's Histogram for a measured reason
    (``benchmarks/bench_hand_vs_library.py``, CPU a sample, three runs): 0.05 µs against
    0.68-0.80 for commits of 256 samples, 0.27 against 0.69-0.79 for commits of 16. The
    service spends about 18 µs a sample on its fastest path (blocks of 200 samples), so
    the library would cost 3-4 % of it, above the 2 % (0.36 µs) that no user would notice.
    A commit of fewer than :data:`_SMALL_COMMIT` samples is counted with a bisection per
    value: numpy's fixed cost a call made a one-sample commit cost 3.8 µs against the
    library's 0.8; counted so, it costs 1.0-1.1."""

    def __init__(self, name: str, documentation: str, buckets: Sequence[float]) -> None:
        self.name = name
        self.documentation = documentation
        self.bounds = np.asarray(sorted(float(b) for b in buckets), dtype=float)
        self._bound_list: list[float] = self.bounds.tolist()
        self._counts = np.zeros(len(self.bounds) + 1, dtype=np.int64)  # the last: +Inf
        self._sum = 0.0
        self._created = time.time()
        self._lock = threading.Lock()

    def observe_many(self, values: Sequence[float]) -> None:
        """Count each value (seconds) in the first bucket whose bound is not below it."""
        if not len(values):
            return
        if len(values) < _SMALL_COMMIT:
            bounds = self._bound_list
            # NaN in the +Inf bucket, where searchsorted puts it on the path below
            index = [bisect_left(bounds, x) if x == x else len(bounds) for x in values]
            total = float(sum(values))
            with self._lock:
                for i in index:
                    self._counts[i] += 1
                self._sum += total
            return
        v = np.asarray(values, dtype=float)
        counts = np.bincount(
            np.searchsorted(self.bounds, v, side="left"), minlength=len(self._counts)
        )
        total = float(v.sum())
        with self._lock:
            self._counts += counts
            self._sum += total

    def observe(self, value: float) -> None:
        self.observe_many([value])

    def collect(self) -> list[Metric]:
        """The metric family, sample for sample as a ``prometheus_client.Histogram`` gives
        it: the cumulative buckets, ``_count``, ``_sum`` and ``_created``."""
        with self._lock:
            cumulative = np.cumsum(self._counts).tolist()
            total = self._sum
        family = Metric(self.name, self.documentation, "histogram")
        for bound, count in zip([*self.bounds.tolist(), math.inf], cumulative, strict=True):
            family.add_sample(f"{self.name}_bucket", {"le": floatToGoString(bound)}, float(count))
        family.add_sample(f"{self.name}_count", {}, float(cumulative[-1]))
        family.add_sample(f"{self.name}_sum", {}, total)
        family.add_sample(f"{self.name}_created", {}, self._created)
        return [family]


class Subscription:
    """One live client's bounded queue of events; drop-oldest when full (see ``dropped``)."""

    def __init__(self, well: str | None, capacity: int) -> None:
        self.well = well
        self.events: deque[dict[str, Any]] = deque(maxlen=capacity)
        self.dropped = 0
        self._lock = threading.Lock()

    def put(self, event: dict[str, Any]) -> bool:
        """Queue an event; False when the oldest one had to be dropped for it."""
        with self._lock:
            full = len(self.events) == self.events.maxlen
            self.events.append(event)
            if full:
                self.dropped += 1
            return not full

    def take(self) -> tuple[list[dict[str, Any]], int]:
        """Everything queued, and how many were dropped since the last take."""
        with self._lock:
            out = list(self.events)
            self.events.clear()
            dropped, self.dropped = self.dropped, 0
            return out, dropped


class Observer:
    """Turns committed store writes into live events and monitoring numbers."""

    def __init__(self, window: int = 100, client_capacity: int = 1000) -> None:
        self.window = window
        self.client_capacity = client_capacity
        self._lock = threading.Lock()
        self._subscribers: set[Subscription] = set()
        self._intervals: dict[str, OrderedDict[int, tuple[float, float]]] = {}
        #: per well, its latest stored prediction: time ns, q_total, p05, p95 (Sm3/h)
        self._latest: dict[str, tuple[int, float, float | None, float | None]] = {}
        self._measured: OrderedDict[tuple[str, str, int], float] = OrderedDict()
        self._coverage: dict[str, deque[bool]] = {}
        self.drift_events: Counter[str] = Counter()
        self.residual_alarms: Counter[str] = Counter()  # alarms raised per well since start
        self.model_changes: Counter[str] = Counter()
        self.predictions: Counter[str] = Counter()  # predictions stored per well since start
        self.dropped = 0
        self.closed = threading.Event()
        self.latency = LatencyHistogram(
            "vfm_prediction_latency_seconds",
            "Time from a sensor sample's arrival to its stored prediction, s.",
            LATENCY_BUCKETS_S,
        )

    # -- subscribers --------------------------------------------------------------------
    def subscribe(self, well: str | None = None) -> Subscription:
        """A live queue of the events of ``well`` (all wells with None)."""
        sub = Subscription(well, self.client_capacity)
        with self._lock:
            self._subscribers.add(sub)
        return sub

    def unsubscribe(self, sub: Subscription) -> None:
        with self._lock:
            self._subscribers.discard(sub)

    @property
    def subscribers(self) -> int:
        return len(self._subscribers)

    def close(self) -> None:
        """The service is stopping: live streams end."""
        self.closed.set()

    def _emit(self, event: dict[str, Any]) -> None:  # under self._lock
        for sub in self._subscribers:
            if sub.well is None or sub.well == event["well"]:
                if not sub.put(event):
                    self.dropped += 1

    # -- what the engine reports ----------------------------------------------------------
    def committed(self, ops: Sequence[Op]) -> None:
        """The ops of one successful commit (called on the worker thread; never blocks long)."""
        now_ns = time.time_ns()
        waited: list[float] = []  # the commit's latencies, counted at once
        with self._lock:
            live = bool(self._subscribers)
            for op in ops:
                if isinstance(op, InsertSample):
                    self._sample(op, now_ns, live, waited)
                elif isinstance(op, InsertMeasurement):
                    key = (op.well, op.source, op.time_ns)
                    self._measured[key] = op.q_total
                    if len(self._measured) > _MEASURED_KEPT:
                        self._measured.popitem(last=False)
                    if live:
                        self._emit(
                            {
                                "type": "measurement",
                                "well": op.well,
                                "time": iso(op.time_ns),
                                "source": op.source,
                                "q_total": op.q_total,
                                "via": op.via,
                            }
                        )
                elif isinstance(op, MarkLearned):
                    self._learned(op, live)
                elif isinstance(op, InsertResidualAlarm):
                    if op.kind == "start":
                        self.residual_alarms[op.well] += 1
                    if live:
                        self._emit(
                            {
                                "type": "alarm",
                                "well": op.well,
                                "time": iso(op.time_ns),
                                "kind": op.kind,
                                "source": op.source,
                                "direction": op.direction,
                                "statistic": op.statistic,
                                "threshold": op.threshold,
                            }
                        )
                elif isinstance(op, InsertTrial):  # a trial ended (service.engine.trial)
                    if op.outcome == "rolled_back":  # the shadow is live again
                        self.model_changes[op.well] += 1
                    if live:
                        self._trial_ended(op)
                elif isinstance(op, InsertDriftEvent):
                    self.drift_events[op.well] += 1
                    if live:
                        self._emit(
                            {
                                "type": "drift",
                                "well": op.well,
                                "time": iso(op.time_ns),
                                "statistic": op.statistic,
                                "p_value": op.p_value,
                                "action": op.action,
                            }
                        )
        self.latency.observe_many(waited)

    def _trial_ended(self, op: InsertTrial) -> None:  # under self._lock
        """A ``trial`` event; a rollback by the trial is also a ``model`` event (a marker)."""
        when = iso(op.ended_ns)
        self._emit(
            {
                "type": "trial",
                "well": op.well,
                "time": when,
                "outcome": op.outcome,
                "model": op.model,
                "shadow_model": op.shadow_model,
            }
        )
        if op.outcome == "rolled_back":
            self._emit(
                {
                    "type": "model",
                    "well": op.well,
                    "time": when,
                    "model_before": op.model,
                    "model_after": op.shadow_model,
                    "version_after": None,
                }
            )

    def _sample(self, op: InsertSample, now_ns: int, live: bool, waited: list[float]) -> None:
        if op.q_total is None:
            return
        self.predictions[op.well] += 1
        latest = self._latest.get(op.well)
        if latest is None or op.time_ns >= latest[0]:
            self._latest[op.well] = (op.time_ns, op.q_total, op.q_total_p05, op.q_total_p95)
        if op.received_ns > 0 and now_ns >= op.received_ns:
            waited.append((now_ns - op.received_ns) / 1e9)
        if op.q_total_p05 is not None and op.q_total_p95 is not None:
            kept = self._intervals.setdefault(op.well, OrderedDict())
            kept[op.time_ns] = (op.q_total_p05, op.q_total_p95)
            if len(kept) > _INTERVALS_KEPT:
                kept.popitem(last=False)
        if live:
            choke, p_up, p_down, t_up = op.inputs[:4]
            self._emit(
                {
                    "type": "prediction",
                    "well": op.well,
                    "time": iso(op.time_ns),
                    "q_total": op.q_total,
                    "q_total_p05": op.q_total_p05,
                    "q_total_p95": op.q_total_p95,
                    "version": op.version,
                    "choke": choke,
                    "p_up": p_up,
                    "p_down": p_down,
                    "t_up": t_up,
                }
            )

    def _learned(self, op: MarkLearned, live: bool) -> None:
        q = self._measured.pop((op.well, op.source, op.time_ns), None)
        kept = self._intervals.get(op.well)
        interval = kept.get(op.sample.time_ns) if kept is not None else None
        if q is not None and interval is not None:
            cover = self._coverage.setdefault(op.well, deque(maxlen=self.window))
            cover.append(interval[0] <= q <= interval[1])
        if live:
            self._emit(
                {
                    "type": "learned",
                    "well": op.well,
                    "time": iso(op.time_ns),
                    "source": op.source,
                    "q_total": q,
                    "predicted": op.sample.predicted,
                    "sample_time": iso(op.sample.time_ns),
                    "version_after": op.version_after,
                }
            )

    def model_changed(self, well: str, change: dict[str, Any], data_time_ns: int | None) -> None:
        """A model change over HTTP is done (``data_time_ns``: the well's latest sample then)."""
        with self._lock:
            self.model_changes[well] += 1
            self._emit(
                {
                    "type": "model",
                    "well": well,
                    "time": iso(data_time_ns) if data_time_ns is not None else change.get("time"),
                    "model_before": change.get("model_before"),
                    "model_after": change.get("model_after"),
                    "version_after": change.get("version_after"),
                }
            )

    def seed_latest(
        self, well: str, latest: tuple[int, float, float | None, float | None] | None
    ) -> None:
        """At start-up: the well's latest prediction read back from the store (time ns,
        q_total, p05, p95; Sm3/h), unless a newer one was stored since."""
        if latest is None:
            return
        with self._lock:
            held = self._latest.get(well)
            if held is None or latest[0] > held[0]:
                self._latest[well] = latest

    def latest_prediction(self, well: str) -> dict[str, Any] | None:
        """The well's latest stored prediction (after a restart, the store's until a new
        one comes): ``time`` (ISO 8601 UTC), ``q_total`` and its 90 % interval
        ``q_total_p05``, ``q_total_p95`` (Sm3/h; null for a method without one); None
        before any. The page reads its interval width from it when no live prediction has
        reached it yet."""
        with self._lock:
            v = self._latest.get(well)
        if v is None:
            return None
        return {"time": iso(v[0]), "q_total": v[1], "q_total_p05": v[2], "q_total_p95": v[3]}

    # -- what /metrics reads ----------------------------------------------------------------
    def coverage(self) -> dict[str, tuple[float, int]]:
        """Per well: the share of recent learned measurements inside p05..p95, and how many."""
        with self._lock:
            return {w: (sum(c) / len(c), len(c)) for w, c in self._coverage.items() if c}
