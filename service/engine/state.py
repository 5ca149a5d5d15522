"""What the engine keeps in memory per well, owned by the well's worker thread.

:class:`WellState` holds the well's learner and what feeding it needs: the recent samples
(for pairing), the measurements waiting for a sample, the duplicate check, the learning
order (``learn_seq``), the rolling error, the drift detector and its reference inputs,
and the model changes made over HTTP, and its recent measured rates (whose median is the
reference of the plausible-rate check). Only the well's worker writes to it; the HTTP API
reads :attr:`WellState.snapshot` (replaced whole, never half-written) and the small views
below.
"""

from __future__ import annotations

import logging
import math
import statistics
from collections import OrderedDict, deque
from collections.abc import Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.config import Settings
from service.engine.learners import Learner, describe
from service.engine.pools import Pools
from service.engine.residual_alarms import WellResidualAlarm, disabled_view
from service.store import ReviewRow, SampleRow
from vfm_core.hotelling import StreamingHotelling
from vfm_core.meter_check import awaiting_well_test, which_moved
from vfm_core.sensor_faults import (
    Fallback,
    SensorFault,
    WellSensorFaults,
    feed_frame,
    raises_alarm,
)
from vfm_core.timeutil import iso

__all__ = [
    "RECENT_SAMPLES",
    "SEEN_MEASUREMENTS",
    "Sample",
    "Pending",
    "WellTestResult",
    "WellState",
    "CatchUp",
]

logger = logging.getLogger("vfm.service.engine")

RECENT_SAMPLES = 512  # per well, in memory, for pairing; older ones are looked up in the store
SEEN_MEASUREMENTS = 1024  # per well, recent measurement keys for the duplicate check
REVIEWS_KEPT = 100  # per well, open reviews in memory (GET /wells/{well}); the store has all

#: a sensor sample as pairing and learning use it: time (epoch ns), six inputs, prediction made
Sample = SampleRow

#: what a well learned while its new model was being fitted: inputs, q_total, time (ns), source
CatchUp = tuple[tuple[float, ...], float, int, str]


@dataclass
class WellTestResult:
    """What a well test did: stored (always), learned or still waiting for its sample."""

    well: str
    time: str
    q_total: float
    status: str  # learned | pending | review (held for review, not learned) | rejected
    message: str
    paired_sample_time: str | None = None
    before: dict[str, float | None] = field(default_factory=dict)
    after: dict[str, float | None] = field(default_factory=dict)
    version_before: int = 0
    version_after: int = 0
    model_changed: bool = False


@dataclass(slots=True)
class Pending:
    """A stored measurement waiting for the sensor sample at its time."""

    time_ns: int
    source: str
    q_total: float  # Sm3/h
    via: str  # zenoh | http
    since: float  # time.monotonic() when it started waiting
    future: Future[WellTestResult] | None = None


def _drift_detector(settings: Settings) -> StreamingHotelling | None:
    """A well's streaming Hotelling T^2 test on its inputs (None: ``drift.enabled`` off)."""
    d = settings.drift
    if not d.enabled:
        return None
    return StreamingHotelling(reference_size=d.reference_size, alpha=d.alpha, confirm=d.confirm)


class WellState:
    """One well: its learner and what the service needs to feed it (owned by one worker)."""

    def __init__(
        self,
        well: str,
        learner: Learner,
        settings: Settings,
        worker: int,
        pools: Pools | None = None,
    ) -> None:
        self.well = well
        #: the engine's calibration pools (``bayes:cal_pool=on``): the well's learner joins
        #: its pool whenever it becomes the well's learner (see :attr:`learner`)
        self.pools = pools
        self.learner = learner
        self.worker = worker
        self.recent: deque[Sample] = deque(maxlen=RECENT_SAMPLES)
        self.last_time_ns: int | None = None
        self.last_inputs: tuple[float, ...] | None = None
        self.pending: list[Pending] = []
        self.seen: OrderedDict[tuple[str, int], None] = OrderedDict()
        self.learn_seq = 0
        self.checkpoint_version = learner.version
        self.errors: deque[float] = deque(maxlen=settings.rolling_window)
        self.learned_inputs: deque[tuple[float, ...]] = deque(maxlen=settings.drift.reference_size)
        self.detector = _drift_detector(settings)
        self.drift_events: deque[dict[str, Any]] = deque(maxlen=20)
        # the alarm on the model's standardised residuals (service.engine.residual_alarms)
        self.residual_alarm: WellResidualAlarm | None = (
            WellResidualAlarm(settings.residual_alarm) if settings.residual_alarm.enabled else None
        )
        # instrument faults of the well's inputs (vfm_core.sensor_faults), fed every sample
        self.sensor_faults = WellSensorFaults(
            false_per_well_year=settings.sensor_faults.false_per_well_year
        )
        self.watch_faults = settings.sensor_faults.enabled
        #: the inputs replaced at the latest sample (Learning.fallback), None when none
        self.fallback: list[dict[str, Any]] | None = None
        #: per recent sample predicted with a stand-in (time ns, oldest first): the
        #: stand-ins and the model's answers at their points, for the measured rate to
        #: witness (Learning.follow_rate); not checkpointed (a restart skips one witness)
        self.stand_in_answers: OrderedDict[
            int, tuple[tuple[Fallback, ...], list[dict[str, float | None]]]
        ] = OrderedDict()
        # model changes over HTTP: what was swapped in, when, and its held-out scores
        self.model_changes: deque[dict[str, Any]] = deque(maxlen=20)
        # while a new model is fitted off the worker: what the old one learned meanwhile
        self.catch_up: list[CatchUp] | None = None
        # the running trial of the last model change against its shadow (None when none
        # runs; the hot path reads only this) and the ended ones (service.engine.trial)
        self.trial: Any = None
        self.trials: deque[dict[str, Any]] = deque(maxlen=10)
        self.samples = 0
        self.measurements = 0
        # the parameter history: version and model of the well's last recorded row
        self.params_version: int | None = None
        self.params_model: str | None = None
        # the latest well test against the MPFM readings near it (service.engine.alarms),
        # replaced whole; and a well test to compare again once its window has passed
        self.mpfm_check: dict[str, Any] | None = None
        #: (epoch ns, MPFM's relative difference) of the last compared well tests, oldest first
        self.mpfm_pairs: list[tuple[int, float]] = []
        self.mpfm_recheck: tuple[int, float] | None = None
        # well-test QC (service.engine.alarms.WellTestReview): log(measured / predicted) of
        # the latest learned measurements (seeded from the store on first use), and the
        # measurements held for review, not decided yet, by (source, time ns), oldest first
        self.log_residuals: deque[float] = deque(maxlen=settings.well_test_review.residuals)
        self.residuals_seeded = False
        #: log(measured / predicted) of the latest learned MPFM rates (not seeded after a
        #: restart): the MPFM's bias and noise about the model (Learning.follow_rate)
        self.mpfm_residuals: deque[float] = deque(maxlen=settings.well_test_review.residuals)
        self.last_learned_ns: dict[str, int] = {}  # source -> time of the latest learned (ns)
        self.reviews: OrderedDict[tuple[str, int], ReviewRow] = OrderedDict()
        self._reviews_view: tuple[ReviewRow, ...] = ()  # what the API reads, replaced whole
        inputs = settings.inputs
        self._rate_factor = inputs.rate_factor
        self._rate_min = inputs.rate_min_history
        #: the latest measured rates (Sm3/h), from the learner's memory on, for rate_problem
        self.rates: deque[float] = deque(maxlen=inputs.rate_history)
        self.seed_rates()
        self.snapshot: dict[str, Any] = {}
        self.refresh()

    def seed_rates(self) -> None:
        """Refill the recent rates from what the learner remembers (after a restore)."""
        self.rates.clear()
        if self.learner.remembered:
            n = self.rates.maxlen or 1
            self.rates.extend(float(v) for v in self.learner.memory.y[-n:].tolist())

    def rate_problem(self, q_total: float) -> str | None:
        """Why a measured rate (Sm3/h) is implausible for this well, as a sentence; None if not.

        Once the well has ``inputs.rate_min_history`` measurements, a rate more than
        ``inputs.rate_factor`` times above or below their median is refused (a meter in the
        wrong unit, a stuck or zero reading): learning from it would wreck the model.
        """
        if self._rate_factor <= 0 or len(self.rates) < self._rate_min:
            return None
        median = float(statistics.median(self.rates))  # a few dozen: numpy's call costs more
        if median <= 0:
            return None
        factor = self._rate_factor
        if q_total > median * factor or q_total < median / factor:
            side = "above" if q_total > median else "below"
            return (
                f"q_total = {q_total:.6g} Sm3/h of {self.well} is more than {factor:g} times {side} "
                f"the median of its last {len(self.rates)} measurements ({median:.6g} Sm3/h; "
                "inputs.rate_factor). Check the meter (unit, stuck or zero reading); if the well "
                "really changed that much, raise inputs.rate_factor or set it to 0."
            )
        return None

    @property
    def learner(self) -> Learner:
        """The well's learner; setting it (at start-up, a model change, a rollback, a
        trial's end) puts it in its calibration pool (:class:`service.engine.pools.Pools`)."""
        return self._learner

    @learner.setter
    def learner(self, learner: Learner) -> None:
        self._learner = learner
        if self.pools is not None:
            self.pools.join(self.well, learner)

    def refresh(self) -> None:
        """Rebuild the snapshot the HTTP API reads (replaced whole, so readers never see half)."""
        snap = describe(self.learner)
        snap["well"] = self.well
        self.snapshot = snap

    def remember_measurement(self, source: str, time_ns: int) -> None:
        self.seen[(source, time_ns)] = None
        if len(self.seen) > SEEN_MEASUREMENTS:
            self.seen.popitem(last=False)

    def drift_state(self) -> dict[str, Any]:
        """The drift detector's state for the API (statistic, p-value, events)."""
        det = self.detector
        if det is None:
            return {"enabled": False, "detected": False, "note": "disabled"}
        stat = float(det.statistic)
        pval = float(det.p_value)
        return {
            "enabled": True,
            "detected": bool(det.drift_detected) or bool(self.drift_events),
            "active": bool(det.drift_detected),
            "statistic": stat if math.isfinite(stat) else None,
            "p_value": pval if math.isfinite(pval) else None,
            "n_seen": int(det.n_seen),
            "events": list(self.drift_events),
        }

    def residual_alarm_state(self) -> dict[str, Any]:
        """The residual alarm for the API (GET /wells/{well} ``residual_alarm``), with
        ``which_moved`` (:func:`vfm_core.meter_check.which_moved`) and
        ``awaiting_well_test`` (:func:`vfm_core.meter_check.awaiting_well_test`) while an
        alarm is active (its size against the meter's usual error, ``small`` and
        ``typical_error_percent``, comes with the alarm: :func:`vfm_core.residual_alarm.alarm_size`)."""
        alarm = self.residual_alarm
        if alarm is None:
            return disabled_view()
        view = alarm.view()
        if view["active"]:
            view["which_moved"] = which_moved(view, self.mpfm_check, self.mpfm_pairs)
            tests = [t for t, _ in self.mpfm_pairs]
            view["awaiting_well_test"] = awaiting_well_test(
                view, self.mpfm_check, tests, self.last_time_ns
            )
        return view

    def watch_sensors(self, time_ns: int, inputs: tuple[float, ...]) -> list[SensorFault]:
        """Feed one accepted sample (epoch ns, the six inputs) to the instrument-fault
        detectors; the faults that began or ended at it (each logged). Nothing when
        ``sensor_faults.enabled`` is false."""
        if not self.watch_faults:
            return []
        events = self.sensor_faults.update(time_ns, inputs)
        self._log_faults(events)
        return events

    def prime_sensor_faults(self, rows: Any) -> list[SensorFault]:
        """Feed the history's rows (a frame in time order, see
        :func:`vfm_core.sensor_faults.feed_frame`) to the instrument-fault detectors before
        the first live sample, so that their references start from the well's history as
        the study's do (see :mod:`service.engine.recovery`). The faults found there are
        kept (one still open goes on live) and logged in one line. Nothing when
        ``sensor_faults.enabled`` is false."""
        if not self.watch_faults or len(rows) == 0:
            return []
        found = feed_frame(self.sensor_faults, rows)
        began = [f"{e.sensor} {e.kind}" for e in found if e.start_ns is not None]
        still = [f"{s.sensor} {s.kind}" for s in self.sensor_faults.active]
        logger.info(
            "Instrument-fault detectors of %s primed on %d history rows; faults there: %s%s.",
            self.well,
            len(rows),
            ", ".join(dict.fromkeys(began)) or "none",
            f" (still open: {', '.join(still)})" if still else "",
        )
        return found

    def _log_faults(self, events: Sequence[SensorFault]) -> None:
        """Log each fault that began (with its evidence: a warning for one that raises an
        alarm, :func:`vfm_core.sensor_faults.raises_alarm`, info for one only shown) or ended
        (info)."""
        for e in events:
            if e.end_ns is None:
                alarm = raises_alarm(e.sensor, e.kind)
                logger.log(
                    logging.WARNING if alarm else logging.INFO,
                    "Sensor fault on %s: %s %s%s. %s",
                    self.well,
                    e.sensor,
                    e.kind,
                    "" if alarm else " (shown, not an alarm: its false rate is above the budget)",
                    e.evidence,
                )
            else:
                logger.info("Sensor fault on %s ended: %s %s.", self.well, e.sensor, e.kind)

    def watch_rate(
        self, source: str, time_ns: int, q_total: float, inputs: tuple[float, ...]
    ) -> None:
        """Feed a paired MPFM rate (Sm3/h, its sample's time and six inputs) to the
        detectors' choke-rate witness (:mod:`vfm_core.rate_witness`: a move of the choke's
        reading that the rate does not follow is a choke offset); other sources are too
        sparse for it. Nothing when ``sensor_faults.enabled`` is false."""
        if not self.watch_faults or source != "mpfm":
            return
        self._log_faults(self.sensor_faults.measure(time_ns, q_total, inputs))

    def watch_sample(self, time_ns: int, inputs: tuple[float, ...]) -> tuple[Fallback, ...]:
        """Feed one accepted sample to the instrument-fault detectors (:meth:`watch_sensors`)
        before it is predicted; the stand-ins its prediction uses: one per input that then
        has an open fault of a kind that stands in
        (:meth:`WellSensorFaults.fallbacks <vfm_core.sensor_faults.WellSensorFaults.fallbacks>`),
        empty (the usual case: one set test) when none does or the detectors are off."""
        self.watch_sensors(time_ns, inputs)
        faults = self.sensor_faults
        if not self.watch_faults or not faults.stands_in():
            return ()
        return tuple(faults.fallbacks(time_ns, inputs))

    def watch_block(
        self, times_ns: Sequence[int], rows: Sequence[tuple[float, ...]]
    ) -> dict[int, tuple[Fallback, ...]]:
        """:meth:`watch_sample` for a sensor block's rows (epoch ns, the six inputs each),
        in order, before any row is predicted: the rows that some stand-in replaces an
        input of, by their index in the block, with their stand-ins (so a fault raised or
        ended in the middle of a block changes the predictions from that row on, as one
        by one). Empty, the usual case, while no input is flagged."""
        used: dict[int, tuple[Fallback, ...]] = {}
        for i, (t, row) in enumerate(zip(times_ns, rows, strict=True)):
            if stand_ins := self.watch_sample(t, row):
                used[i] = stand_ins
        return used

    def sensor_faults_view(self) -> list[dict[str, Any]]:
        """GET /wells/{well} ``sensor_faults``: the recent faults, ``end`` null while active."""
        return self.sensor_faults.view()

    def hold_for_review(self, row: ReviewRow) -> None:
        """Keep an open review in memory (the oldest beyond :data:`REVIEWS_KEPT` only in the store)."""
        self.reviews[(row.source, row.time_ns)] = row
        while len(self.reviews) > REVIEWS_KEPT:
            self.reviews.popitem(last=False)
        self._reviews_view = tuple(self.reviews.values())

    def decided(self, source: str, time_ns: int) -> None:
        """An open review was decided: no longer shown."""
        self.reviews.pop((source, time_ns), None)
        self._reviews_view = tuple(self.reviews.values())

    def held_for_review_view(self) -> list[dict[str, Any]]:
        """GET /wells/{well} ``held_for_review``: the measurements held for review and not
        decided yet, oldest first (rates Sm3/h; ``z`` in predictive sd; ``mpfm``: the median
        of the MPFM readings near it, null when none)."""
        return [
            {
                "time": iso(r.time_ns),
                "source": r.source,
                "q_total": r.q_total,
                "predicted": r.predicted,
                "z": r.z,
                "mpfm": r.mpfm,
                "reason": r.reason,
            }
            for r in self._reviews_view
        ]

    def rolling_mape(self) -> dict[str, Any]:
        """MAPE (%) of the predictions made at the last paired measurements' samples."""
        errors = list(self.errors)  # a copy: the worker appends while the API reads
        n = len(errors)
        value = float(np.mean(errors) * 100.0) if n else None
        return {"value": value, "n": n, "window": self.errors.maxlen, "unit": "%"}
