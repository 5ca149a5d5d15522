"""The well's alarm when its MPFM disagrees with its well tests.

A well test is the reference a multiphase meter is checked against. When a well test is
stored, :meth:`MpfmCheck.on_well_test` compares it with the median of the well's MPFM
readings within ``alarms.mpfm_well_test_window_s`` (24 h) of it, either side; when they
differ by more than ``alarms.mpfm_well_test_rel`` (10 %) of the well test, the well's
state carries the alarm "MPFM reads X % above/below the well test of <date>" until a
later well test agrees. Readings after the well test may not have arrived yet when it is
stored (a replay, or a well test entered as it happens): the comparison is made again
once, when the first MPFM reading past the window arrives. A well test with no MPFM
reading in its window leaves the previous comparison in place.

It runs on the well's worker, once or twice per well test (one indexed query each),
never per sample; at start, once per well on its latest stored well test.
"""

from __future__ import annotations

import statistics
from collections.abc import Sequence
from typing import Any

from service.config import Settings
from service.engine.state import WellState
from service.store import InsertMeasurement, Op, Store
from vfm_core.timeutil import iso

__all__ = ["MpfmCheck"]


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

    def _compare(
        self, st: WellState, time_ns: int, q_total: float, uncommitted: Sequence[Op]
    ) -> None:
        if q_total <= 0:
            return
        lo, hi = time_ns - self.window_ns, time_ns + self.window_ns
        readings = self.store.mpfm_near(st.well, time_ns, self.window_ns)
        readings += [
            op.q_total
            for op in uncommitted  # this batch's readings, not in the store yet
            if isinstance(op, InsertMeasurement)
            and op.well == st.well
            and op.source == "mpfm"
            and lo <= op.time_ns <= hi
        ]
        if not readings:
            return
        median = float(statistics.median(readings))
        rel = (median - q_total) / q_total
        agrees = abs(rel) <= self.rel
        when = (iso(time_ns) or "")[:16].replace("T", " ") + " UTC"
        check: dict[str, Any] = {
            "well_test_time": iso(time_ns),
            "well_test_q_total": q_total,
            "mpfm_median": median,
            "mpfm_readings": len(readings),
            "window_s": self.window_s,
            "relative_difference": rel,
            "threshold": self.rel,
            "agrees": agrees,
            "alarm": None
            if agrees
            else (
                f"MPFM reads {abs(rel) * 100:.0f} % {'above' if rel > 0 else 'below'} "
                f"the well test of {when}"
            ),
        }
        st.mpfm_check = check

    def load(self, st: WellState) -> None:
        """At start: compare the well's latest stored well test (all its readings are in)."""
        if not self.enabled:
            return
        latest = self.store.latest_well_test(st.well)
        if latest is not None:
            self._compare(st, latest[0], latest[1], ())
            st.mpfm_recheck = latest  # its window may not have passed yet
