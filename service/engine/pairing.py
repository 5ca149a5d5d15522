"""Pairing a measurement with the well's sensor sample nearest its time, on the well's worker.

A measurement (MPFM reading or well test) is paired with the sample nearest its time
within ``inputs.pair_tolerance_s``: from the recent samples in memory, else from the
store. If no sample at or after its time has arrived yet it waits, stored as ``pending``
(at most ``inputs.pending_max`` per well, ``inputs.pending_timeout_s`` of wall time), and
is settled when a later sample arrives or the wait runs out: learned from if a sample
lies within the tolerance (``held`` instead, not learned, when an input of that sample has
an instrument fault: :mod:`vfm_core.sensor_faults`), else marked ``unpaired``. A rate far from the well's recent
ones (:meth:`~service.engine.state.WellState.rate_problem`) is refused before anything
is stored (``implausible rate``). A stored well test is compared with the MPFM readings
near it (:mod:`service.engine.alarms`). A sample is always predicted before
the measurement at its time is learned from (prequential order, as in ``vfm evaluate``).

Well-test QC: a paired well test far outside the model's predictive distribution and off
the MPFM near it (:class:`service.engine.alarms.WellTestReview`) is stored with status
``review``, counted (``held for review``) and not learned from; the operator's decision
(:class:`ReviewItem`, ``POST /wells/{well}/measurements/review``) learns it now, paired
with its stored sample (``accept``), or marks it ``rejected`` (``reject``), recorded in
the store's ``reviews`` table with the time of the decision and counted (events
``reviews accepted``, ``reviews rejected``).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass

from service.config import Settings
from service.engine.alarms import MpfmCheck, WellTestReview
from service.engine.items import Batch, MeasurementItem, refuse
from service.engine.learning import Learning
from service.engine.state import Pending, Sample, WellState, WellTestResult
from service.errors import Conflict, Duplicate, InvalidRequest
from service.inputs import Counters
from service.store import (
    DecideReview,
    InsertMeasurement,
    InsertReview,
    MarkHeld,
    MarkRejected,
    MarkReview,
    MarkUnpaired,
    ReviewRow,
    Store,
)
from vfm_core.timeutil import iso, to_ns

__all__ = ["Pairing", "ReviewItem", "nearest_in"]


@dataclass(slots=True)
class ReviewItem(MeasurementItem):
    """The operator's decision on a measurement held for review, run by the well's worker:
    the measurement is named by ``source`` and ``measurement.time`` (its ``q_total`` is not
    used); ``decision``: accept | reject; ``decided_ns``: when (wall time, epoch ns)."""

    decision: str = "accept"
    decided_ns: int = 0


def nearest_in(recent: deque[Sample], time_ns: int) -> Sample:
    """The sample of ``recent`` (in time order, not empty) nearest to ``time_ns``."""
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


class Pairing:
    """Measurements in: duplicates refused, paired at once, or kept pending for their sample."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        counters: Counters,
        learning: Learning,
        alarms: MpfmCheck | None = None,
        review: WellTestReview | None = None,
    ) -> None:
        self.store = store
        self.alarms = alarms
        self.review = review
        self.residuals_kept = settings.well_test_review.residuals
        self.counters = counters
        self.learning = learning
        self.tolerance_s = settings.inputs.pair_tolerance_s
        self.pending_max = settings.inputs.pending_max
        self.pending_timeout_s = settings.inputs.pending_timeout_s
        self._tol_ns = int(settings.inputs.pair_tolerance_s * 1e9)

    def nearest(self, st: WellState, time_ns: int) -> Sample | None:
        """The well's sample nearest ``time_ns`` within the tolerance (memory, then store).

        Before the oldest sample in memory the store is asked, and the oldest in memory
        still competes: it may not be committed yet (a well's first sample, say).
        """
        if st.recent and time_ns >= st.recent[0].time_ns:
            found: list[Sample] = [nearest_in(st.recent, time_ns)]
        else:
            stored = self.store.nearest_sample(st.well, time_ns, self._tol_ns)
            found = [s for s in (stored, st.recent[0] if st.recent else None) if s is not None]
        best = min(found, key=lambda s: abs(s.time_ns - time_ns), default=None)
        return best if best is not None and abs(best.time_ns - time_ns) <= self._tol_ns else None

    def on_measurement(self, st: WellState, item: MeasurementItem, b: Batch) -> None:
        """A measurement: refuse a duplicate, store it, then learn from it or let it wait."""
        if isinstance(item, ReviewItem):
            self.decide(st, item, b)
            return
        m = item.measurement
        t = to_ns(m.time)
        if (item.source, t) in st.seen or self.store.measurement_exists(item.well, item.source, t):
            duplicate = Duplicate(
                f"The {item.source} measurement of {item.well} at {iso(t)} arrived before; "
                "it is stored once.",
                "duplicate",
            )
            refuse(self.counters, duplicate, item.well, b, item.future)
            return
        problem = st.rate_problem(m.q_total)
        if problem is not None:
            refuse(
                self.counters,
                InvalidRequest(problem, "implausible rate"),
                item.well,
                b,
                item.future,
            )
            return
        sample: Sample | None = None
        if st.last_time_ns is not None and t <= st.last_time_ns:
            sample = self.nearest(st, t)
            if sample is None:
                error = InvalidRequest(
                    f"No sensor sample of {item.well} lies within {self.tolerance_s:g} s of "
                    f"the measurement at {iso(t)}, so it cannot be paired with inputs; it was not stored.",
                    "no sensor sample within tolerance",
                )
                refuse(self.counters, error, item.well, b, item.future)
                return
        b.ops.append(
            InsertMeasurement(
                well=item.well,
                time_ns=t,
                source=item.source,
                q_total=m.q_total,
                received_ns=item.received_ns,
                via=item.via,
            )
        )
        st.remember_measurement(item.source, t)
        st.rates.append(m.q_total)
        st.measurements += 1
        self.counters.accept("well_tests" if item.via == "http" else "measurements")
        if item.via == "http":
            # stored durably first, then learned from
            self.store.write(b.ops)
            b.ops.clear()
        if self.alarms is not None:  # once per well test; a cheap comparison per reading
            if item.source == "well_test":
                self.alarms.on_well_test(st, t, m.q_total, b.ops)
            else:
                self.alarms.on_mpfm(st, t, b.ops)
        p = Pending(t, item.source, m.q_total, item.via, time.monotonic(), item.future)
        if sample is not None:
            self._learn_unless_held(st, p, sample, b)
            return
        self._wait(st, p, b)

    def _wait(self, st: WellState, p: Pending, b: Batch) -> None:
        """A stored measurement waits for its sample (the oldest waiting one settled when
        ``inputs.pending_max`` are waiting); a caller is answered ``pending`` now."""
        if len(st.pending) >= self.pending_max:
            oldest = st.pending.pop(0)
            self.counters.event("pending forced")
            self._settle(st, oldest, b, force=True)
        st.pending.append(p)
        if p.future is not None:
            b.answer(
                p.future,
                WellTestResult(
                    st.well,
                    iso(p.time_ns) or "",
                    p.q_total,
                    "pending",
                    f"Stored. No sensor sample of {st.well} at or after {iso(p.time_ns)} has "
                    "arrived yet; the well test is learned from when it does.",
                    version_before=st.learner.version,
                    version_after=st.learner.version,
                ),
            )
            p.future = None

    def resolve(self, st: WellState, b: Batch, upto: int) -> None:
        """A sample at ``upto`` (epoch ns) arrived: settle the measurements at or before it."""
        due = [p for p in st.pending if p.time_ns <= upto]
        if not due:
            return
        st.pending = [p for p in st.pending if p.time_ns > upto]
        for p in due:
            self._settle(st, p, b)

    def expire(self, st: WellState, b: Batch, now: float) -> None:
        """Settle the measurements that waited longer than ``inputs.pending_timeout_s``."""
        wait = self.pending_timeout_s
        due = [p for p in st.pending if now - p.since > wait]
        if due:
            st.pending = [p for p in st.pending if now - p.since <= wait]
            for p in due:
                self._settle(st, p, b, force=True)

    def _settle(self, st: WellState, p: Pending, b: Batch, force: bool = False) -> None:
        sample = self.nearest(st, p.time_ns)
        if sample is None:
            b.ops.append(MarkUnpaired(well=st.well, source=p.source, time_ns=p.time_ns))
            error = InvalidRequest(
                f"No sensor sample of {st.well} arrived within {self.tolerance_s:g} s of the "
                f"{p.source} measurement at {iso(p.time_ns)}"
                + (" before the wait ran out" if force else "")
                + "; it is stored but not learned from.",
                "no sensor sample within tolerance",
            )
            refuse(self.counters, error, st.well, b, p.future)
            return
        self._learn_unless_held(st, p, sample, b)

    def _learn_unless_held(self, st: WellState, p: Pending, sample: Sample, b: Batch) -> None:
        """Learn from the measurement, unless its sample has an input with an instrument
        fault (vfm_core.sensor_faults): then it is kept (status ``held``), counted, not
        learned from (learn nothing wrong). An MPFM rate feeds the choke-rate witness
        first (held or not: the witness takes the rate, not the learner)."""
        st.watch_rate(p.source, sample.time_ns, p.q_total, sample.inputs)
        if st.stand_in_answers:  # a rate measured at a stood-in sample: its witness
            self.learning.follow_rate(st, sample.time_ns, p.q_total, p.source)
        fault = st.sensor_faults.suspect(sample.time_ns, values=sample.inputs)
        if fault is None:
            if self.review is not None and self.review.enabled and p.source == "well_test":
                if st.well in b.learn_wells:  # judged by the model after what came before
                    self.learning.run_deferred(b)
                self._seed_residuals(st)
                row = self.review.judge(st, p.source, p.time_ns, p.q_total, sample, b.ops)
                if row is not None:
                    self._hold(st, p, row, b)
                    return
            self._note_residual(st, p.source, p.time_ns, p.q_total, sample)
            self.learning.learn_paired(st, p, sample, b)
            return
        b.ops.append(MarkHeld(well=st.well, source=p.source, time_ns=p.time_ns))
        error = InvalidRequest(
            f"The {p.source} measurement of {st.well} at {iso(p.time_ns)} is stored but "
            f"not learned from: at its sample ({iso(sample.time_ns)}) {fault.sensor} had "
            f"{'an' if fault.kind[0] in 'aeiou' else 'a'} {fault.kind} fault since "
            f"{iso(fault.start_ns)}. {fault.evidence}",
            "sensor fault at the sample",
        )
        refuse(self.counters, error, st.well, b, p.future)

    # -- well-test QC ---------------------------------------------------------------------
    def _seed_residuals(self, st: WellState) -> None:
        """Once per well: its latest learned residuals and well test from the store (after
        a restart)."""
        if st.residuals_seeded:
            return
        st.residuals_seeded = True
        earlier = [
            math.log(e.measured / e.predicted)
            for e in self.store.recent_errors(st.well, self.residuals_kept)
            if e.predicted is not None and e.predicted > 0 and e.measured > 0
        ]
        st.log_residuals.extendleft(reversed(earlier[-(st.log_residuals.maxlen or 1) :]))
        latest = self.store.latest_learned(st.well, "well_test")
        if latest is not None and latest > st.last_learned_ns.get("well_test", -1):
            st.last_learned_ns["well_test"] = latest

    def _note_residual(
        self, st: WellState, source: str, time_ns: int, q_total: float, sample: Sample
    ) -> None:
        """A measurement about to be learned: its residual against the prediction made at
        its sample (the spread of :class:`~service.engine.alarms.WellTestReview`)."""
        if source == "mpfm" and sample.predicted is not None and sample.predicted > 0:
            if q_total > 0:  # the MPFM's bias and noise about the model (Learning.follow_rate)
                st.mpfm_residuals.append(math.log(q_total / sample.predicted))
        if self.review is None or not self.review.enabled:
            return
        self._seed_residuals(st)
        if time_ns > st.last_learned_ns.get(source, -1):
            st.last_learned_ns[source] = time_ns
        if sample.predicted is not None and sample.predicted > 0 and q_total > 0:
            st.log_residuals.append(math.log(q_total / sample.predicted))

    def _hold(self, st: WellState, p: Pending, row: ReviewRow, b: Batch) -> None:
        """Hold a measurement for review: stored with its evidence, counted, not learned."""
        b.ops.append(InsertReview(row))
        b.ops.append(MarkReview(well=st.well, source=p.source, time_ns=p.time_ns))
        st.hold_for_review(row)
        self.counters.reject("held for review", row.reason, where=st.well, well=st.well)
        version = st.learner.version
        b.answer(
            p.future,
            WellTestResult(
                st.well,
                iso(p.time_ns) or "",
                p.q_total,
                "review",
                row.reason,
                paired_sample_time=iso(row.sample.time_ns),
                before={"q_total": row.predicted},
                version_before=version,
                version_after=version,
            ),
        )

    def decide(self, st: WellState, item: ReviewItem, b: Batch) -> None:
        """The operator's decision on a held measurement: accept (learned now, paired with
        its stored sample) or reject (status ``rejected``); recorded and counted."""
        t = to_ns(item.measurement.time)
        row = st.reviews.get((item.source, t))
        if row is None:
            stored = self.store.reviews(st.well, item.source, t)
            if stored and stored[0].decision is not None:
                error: InvalidRequest | Conflict = Conflict(
                    f"The {item.source} measurement of {st.well} at {iso(t)} was decided before "
                    f"({stored[0].decision} at {iso(stored[0].decided_ns)}); a decision is final.",
                    "no such review",
                )
                refuse(self.counters, error, st.well, b, item.future)
                return
            if not stored:
                error = InvalidRequest(
                    f"No {item.source} measurement of {st.well} at {iso(t)} is held for review; "
                    f"GET /wells/{st.well} lists them under held_for_review.",
                    "no such review",
                )
                refuse(self.counters, error, st.well, b, item.future)
                return
            row = stored[0]
        b.ops.append(
            DecideReview(
                well=st.well,
                source=item.source,
                time_ns=t,
                decision=item.decision,
                decided_ns=item.decided_ns,
            )
        )
        st.decided(item.source, t)
        version = st.learner.version
        if item.decision == "accept":
            self.counters.event("reviews accepted")
            self._note_residual(st, item.source, t, row.q_total, row.sample)
            p = Pending(t, item.source, row.q_total, "http", time.monotonic(), item.future)
            self.learning.learn_paired(st, p, row.sample, b)
            return
        self.counters.event("reviews rejected")
        b.ops.append(MarkRejected(well=st.well, source=item.source, time_ns=t))
        b.answer(
            item.future,
            WellTestResult(
                st.well,
                iso(t) or "",
                row.q_total,
                "rejected",
                f"Rejected on review: the {item.source} measurement of {st.well} at {iso(t)} "
                "stays stored (status rejected) and is never learned from.",
                paired_sample_time=iso(row.sample.time_ns),
                before={"q_total": row.predicted},
                version_before=version,
                version_after=version,
            ),
        )
