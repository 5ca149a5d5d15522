"""The well's alarm when its MPFM disagrees with its well tests, and the well-test QC.

A well test is the reference a multiphase meter is checked against. When a well test is
stored, :meth:`MpfmCheck.on_well_test` compares it (the rule of
:func:`vfm_core.meter_check.compare`, which :func:`vfm_core.meter_check.mpfm_checks` applies
offline) with the median of the well's MPFM
readings within ``alarms.mpfm_well_test_window_s`` (24 h) of it, either side; when they
differ by more than ``alarms.mpfm_well_test_rel`` (10 %) of the well test, the well's
state carries the alarm "MPFM reads X % above/below the well test of <date>" until a
later well test agrees. Readings after the well test may not have arrived yet when it is
stored (a replay, or a well test entered as it happens): the comparison is made again
once, when the first MPFM reading past the window arrives. A well test with no MPFM
reading in its window leaves the previous comparison in place.

Each compared well test is also set against the well's earlier ones
(:func:`vfm_core.meter_check.against_usual`: ``usual_difference``, ``usual_spread``, ``z``,
``shifted``; while the MPFM's residual alarm is active, against the ones before the alarm
began), which is what tells, beside that alarm, whether the meter or the well moved
(:func:`vfm_core.meter_check.which_moved`).

It runs on the well's worker, once or twice per well test (one indexed query each),
never per sample; at start, once per well on each of its last 40 stored well tests.

:class:`WellTestReview` is the well-test QC: a well test far outside the model's
predictive distribution and off the MPFM near it is held for the operator's review
(status ``review``, not learned) instead of being learned; see its docstring for the rule.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Sequence
from functools import lru_cache

from scipy import stats

from service.config import Settings
from service.engine.state import WellState
from service.store import InsertMeasurement, InsertSample, Op, ReviewRow, SampleRow, Store
from vfm_core.meter_check import USUAL_PAIRS, against_usual, compare, steady_span
from vfm_core.timeutil import iso

__all__ = ["MpfmCheck", "WellTestReview"]

#: the standard normal quantile of 95 %: a central 90 % interval spans +-1.645 sd
_Z90 = 1.6448536269514722


class MpfmCheck:
    """Compares each well test with the MPFM readings near it; see the module docstring."""

    def __init__(self, settings: Settings, store: Store) -> None:
        self.store = store
        self.rel = settings.alarms.mpfm_well_test_rel
        self.window_s = settings.alarms.mpfm_well_test_window_s
        self.window_ns = int(self.window_s * 1e9)

    @property
    def enabled(self) -> bool:
        return self.rel > 0

    def on_well_test(
        self, st: WellState, time_ns: int, q_total: float, uncommitted: Sequence[Op] = ()
    ) -> None:
        """A well test of ``q_total`` Sm3/h at ``time_ns`` was stored: compare it now, and
        once more when its window has passed."""
        if not self.enabled:
            return
        self._compare(st, time_ns, q_total, uncommitted)
        st.mpfm_recheck = (time_ns, q_total)

    def on_mpfm(self, st: WellState, time_ns: int, uncommitted: Sequence[Op] = ()) -> None:
        """An MPFM reading at ``time_ns`` was stored: compare the latest well test again if
        this reading closes its window."""
        due = st.mpfm_recheck
        if due is None or time_ns <= due[0] + self.window_ns:
            return
        st.mpfm_recheck = None
        self._compare(st, due[0], due[1], uncommitted)

    def near(self, st: WellState, time_ns: int, uncommitted: Sequence[Op] = ()) -> list[float]:
        """The q_total (Sm3/h) of the well's MPFM readings within the window of ``time_ns``
        and at the choke of the sample nearest it (no choke move between them:
        :func:`vfm_core.meter_check.steady_span`; all of the window's when no sample lies in
        it): stored, and of this batch (``uncommitted``, not in the store yet)."""
        lo, hi = time_ns - self.window_ns, time_ns + self.window_ns
        readings = self.store.mpfm_near(st.well, time_ns, self.window_ns)
        samples = dict(self.store.chokes_near(st.well, time_ns, self.window_ns))
        for op in uncommitted:
            if not isinstance(op, InsertMeasurement | InsertSample) or op.well != st.well:
                continue
            if not lo <= op.time_ns <= hi:
                continue
            if isinstance(op, InsertSample):
                samples[op.time_ns] = op.inputs[0]  # INPUT_FIELDS: the choke first
            elif op.source == "mpfm":
                readings.append((op.time_ns, op.q_total))
        times = sorted(samples)
        span = steady_span(times, [samples[t] for t in times], time_ns)
        if span is None:
            return [q for _, q in readings]
        return [q for t, q in readings if span[0] <= t <= span[1]]

    def _compare(
        self, st: WellState, time_ns: int, q_total: float, uncommitted: Sequence[Op]
    ) -> None:
        if q_total <= 0:
            return
        found = compare(self.near(st, time_ns, uncommitted), q_total, self.rel)
        if found is None:
            return
        rel = found["relative_difference"]
        cut = time_ns  # while the MPFM's residual alarm is active: the pairs before it
        det = None if st.residual_alarm is None else st.residual_alarm.detectors.get("mpfm")
        if det is not None and det.alarm and det.since_ns is not None:
            cut = min(cut, det.since_ns)
        usual = against_usual([r for t, r in st.mpfm_pairs if t < cut], rel)
        self._remember(st, time_ns, rel)
        when = (iso(time_ns) or "")[:16].replace("T", " ") + " UTC"
        st.mpfm_check = {
            "well_test_time": iso(time_ns),
            "well_test_q_total": q_total,
            "mpfm_median": found["mpfm_median"],
            "mpfm_readings": found["mpfm_readings"],
            "window_s": self.window_s,
            "relative_difference": rel,
            "threshold": self.rel,
            "agrees": found["agrees"],
            "alarm": None
            if found["agrees"]
            else (
                f"MPFM reads {abs(rel) * 100:.0f} % {'above' if rel > 0 else 'below'} "
                f"the well test of {when}"
            ),
            # against the well's earlier pairs (vfm_core.meter_check.against_usual)
            **(usual or dict.fromkeys(("usual_difference", "usual_spread", "z", "shifted"))),
        }

    @staticmethod
    def _remember(st: WellState, time_ns: int, rel: float) -> None:
        """Keep the pair (a well test compared again replaces its first comparison), the
        last ``2 * USUAL_PAIRS`` in time order (the usual ones before an alarm stay while
        it lasts)."""
        pairs = [p for p in st.mpfm_pairs if p[0] != time_ns]
        pairs.append((time_ns, rel))
        pairs.sort()
        st.mpfm_pairs = pairs[-2 * USUAL_PAIRS :]

    def load(self, st: WellState) -> None:
        """At start: compare the well's last ``2 * USUAL_PAIRS`` stored well tests in time
        order (all their readings are in), so the latest is set against the ones before it
        as it was live; one indexed query each."""
        if not self.enabled:
            return
        tests = self.store.latest_well_tests(st.well, 2 * USUAL_PAIRS)
        for time_ns, q_total in tests:
            self._compare(st, time_ns, q_total, ())
        if tests:
            st.mpfm_recheck = tests[-1]  # its window may not have passed yet


@lru_cache(maxsize=1024)
def _t_threshold(k: float, n: int) -> float:
    """The |z| threshold with the false-hold rate of a Gaussian at ``k`` when the spread is
    estimated from ``n`` residuals: Student's t with n - 1 degrees of freedom."""
    alpha = 2.0 * float(stats.norm.sf(k))
    return float(stats.t.ppf(1.0 - alpha / 2.0, max(n - 1, 1)))


class WellTestReview:
    """Well-test QC: holds for review a well test inconsistent with the model's predictive
    distribution and with the MPFM readings near it (see :meth:`judge`).

    The rule, for a well test of ``y`` Sm3/h paired with a sample where the model now
    predicts ``q``: ``z = log(y / q) / s``, with ``s`` the predictive sd in log space:

    * a method with an interval (``bayes``): from its central 90 % interval,
      ``s = log(p95 / p05) / (2 * 1.645)`` (the filter's own spread, parameters and the well
      test's noise, with its calibration factor);
    * and, for every method, a robust spread of the well's own recent residuals
      (``log(measured / predicted)`` of its last ``well_test_review.residuals`` learned
      measurements, MPFM and well tests, each against the prediction made at its sample
      before it was learned): ``s = 1.4826 * median(|r|)`` (the MAD about zero, so a bias
      of the model counts as spread), once ``well_test_review.min_residuals`` are known.

    Each ``s`` is at least ``well_test_review.min_sd``. The well test is suspect when
    ``|z| > k`` (``well_test_review.k``, 3.29: one well test in 1,000 of those the model's
    own Gaussian distribution would produce; with a spread from ``n`` residuals the
    threshold is Student's t quantile of the same rate with n - 1 degrees of freedom, so
    the rate stays about that) for every spread known (an interval narrower than the
    errors the model shows does not hold good well tests); with none, nothing is held. A
    suspect well test is held unless an MPFM reading lies within
    ``alarms.mpfm_well_test_window_s`` of it and their median agrees with it within
    ``alarms.mpfm_well_test_rel``, or the well's previous well test was held too and agrees
    with it (:meth:`_confirmed`): then the well itself changed, and it is learned (a model
    held back would otherwise never catch up with a changed well). The
    learner's own outlier gate (``bayes``: ``gate``) still applies to what is learned: it
    is the last line, this rule the first.
    """

    def __init__(self, settings: Settings, mpfm: MpfmCheck) -> None:
        cfg = settings.well_test_review
        self.enabled = cfg.enabled
        self.k = cfg.k
        self.min_residuals = cfg.min_residuals
        self.min_sd = cfg.min_sd
        self.mpfm = mpfm

    def spread(self, st: WellState, rates: dict[str, float | None]) -> tuple[float, float] | None:
        """The predictive sd in log space and the |z| threshold, or None when unknown: of
        the interval's and the residuals', the one that allows the larger |log ratio|."""
        found: list[tuple[float, float]] = []
        p05, p95 = rates.get("q_total_p05"), rates.get("q_total_p95")
        if p05 is not None and p95 is not None and math.isfinite(p05 + p95) and 0 < p05 < p95:
            found.append((max(math.log(p95 / p05) / (2.0 * _Z90), self.min_sd), self.k))
        n = len(st.log_residuals)
        if n >= self.min_residuals:
            mad = float(statistics.median(abs(r) for r in st.log_residuals))
            found.append((max(1.4826 * mad, self.min_sd), _t_threshold(self.k, n)))
        return max(found, key=lambda f: f[0] * f[1], default=None)

    def judge(
        self,
        st: WellState,
        source: str,
        time_ns: int,
        q_total: float,
        sample: SampleRow,
        uncommitted: Sequence[Op] = (),
    ) -> ReviewRow | None:
        """The review row when the ``source`` measurement of ``q_total`` Sm3/h at
        ``time_ns``, paired with ``sample``, is to be held; None to learn it."""
        if not self.enabled or source != "well_test" or q_total <= 0:
            return None
        rates = st.learner.predict(list(sample.inputs)) if st.learner.ready else {}
        q = rates.get("q_total")
        if q is None or not math.isfinite(q) or q <= 0:
            return None  # no model yet: nothing to compare with
        spread = self.spread(st, rates)
        if spread is None:
            return None
        sd, threshold = spread
        z = math.log(q_total / q) / sd
        if abs(z) <= threshold:
            return None
        if self._confirmed(st, source, q_total, sd, threshold):
            return None  # a second well test in a row off the model, like the one held
        off = (q_total - q) / q
        what = (
            f"The well test of {st.well} at {iso(time_ns)} ({q_total:.6g} Sm3/h) is "
            f"{abs(off) * 100:.0f} % {'above' if off > 0 else 'below'} the model's prediction "
            f"({q:.6g} Sm3/h): |z| = {abs(z):.1f} > {threshold:.2f} predictive sd "
            f"(sd {sd * 100:.1f} % in log space)"
        )
        median: float | None = None
        if self.mpfm.enabled:
            readings = self.mpfm.near(st, time_ns, uncommitted)
            if readings:
                median = float(statistics.median(readings))
                rel = (q_total - median) / median if median > 0 else math.inf
                if abs(rel) <= self.mpfm.rel:
                    return None  # the MPFM confirms it: the well changed, learn it
                what += (
                    f", and {abs(rel) * 100:.0f} % {'above' if rel > 0 else 'below'} the "
                    f"median of the {len(readings)} MPFM reading(s) within "
                    f"{self.mpfm.window_s / 3600:g} h at its choke ({median:.6g} Sm3/h)"
                )
        if median is None:
            what += f"; no MPFM reading within {self.mpfm.window_s / 3600:g} h confirms it"
        what += (
            ". It is stored, held for review and not learned from: accept or reject it with "
            f"POST /wells/{st.well}/measurements/review."
        )
        return ReviewRow(
            st.well, time_ns, source, q_total, q, sd, z, median, what, sample, time.time_ns()
        )

    @staticmethod
    def _confirmed(st: WellState, source: str, q_total: float, sd: float, threshold: float) -> bool:
        """True when the well's latest measurement of ``source`` held for review (still
        open, and later than the last one learned) agrees with this one within
        ``threshold * sd * sqrt(2)`` (the spread of their difference): two well tests in a
        row off the model and alike mean the well changed (by chance: about 1 in 10^6)."""
        held = [r for r in st.reviews.values() if r.source == source]
        if not held or held[-1].time_ns < st.last_learned_ns.get(source, -1):
            return False
        return abs(math.log(q_total / held[-1].q_total)) <= threshold * sd * math.sqrt(2.0)
