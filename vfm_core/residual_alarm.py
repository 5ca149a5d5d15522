"""An alarm on the model's standardised residuals: a self-starting two-sided CUSUM.

What the operator cares about is whether the model's error changed in a way the learner
does not absorb (a sand event, a choke that wears faster than the model follows, a meter
that starts to read off), not whether the inputs moved (depletion, choke changes: the
model handles those; :mod:`vfm_core.hotelling` tests the inputs and says "operating point
outside the training data").

The rule, per well and per meter (MPFM and well tests are separate streams: they differ
in noise and in rate)
------------------------------------------------------------------------------------------

1. **Residual** of each measurement against the prediction made for it before learning
   from it (prequential, as the service runs): with a predictive standard deviation
   ``sd`` (the ``bayes`` method's ``q_total_std``) ``(measured - predicted) / sd``;
   without one the relative error ``ln(measured / predicted)``
   (:func:`standardised_residual`).
2. **Aggregation**: the residuals of one period (``period_s``, 1 day for the MPFM; 0 for
   well tests, days to months apart: each is its own period) are averaged. Within a day
   meter errors are correlated (a slug, a meter's slow wander); the period mean is
   standardised by the spread of earlier period means, so whatever correlation there is
   within a period is in the scale. A period closes when the stream's first reading of a
   later period arrives.
3. **Self-starting scale**: each period mean ``m`` becomes ``x = (m - centre) / scale``
   over the last ``window`` in-control period means (not the current one, none from
   inside an alarm). With ``scale="winsorised"`` (the residual alarm's default) the centre
   and scale are the mean and standard deviation of those period means clipped at their
   median +- 3 robust sd (1.4826 MAD); with ``scale="mad"`` (the class default, which the
   instrument-fault detectors use) the median and 1.4826 MAD themselves. The MAD is too
   narrow for the residual alarm: a day holds one to seven MPFM readings, so the period
   means are a scale mixture with tails heavier than a Gaussian's, their standard
   deviation exceeds 1.4826 MAD by 5 to 15 % on simulated fields, and a CUSUM whose scale
   is 10 % short runs 40 % of its designed length between false alarms. The scale is
   multiplied by the long-run factor
   ``f = sqrt(1 + 2 sum_j (1 - j/(L+1)) rho_j)`` (at least 1; Bartlett weights over
   ``lags`` periods, estimated on the same reference): day-to-day correlation of meter
   errors and of an online learner's corrections would otherwise raise false alarms far
   more often than designed. Nothing is tested until ``min_periods`` are in. Centring on
   the recent centre means a model that carries a steady offset is not news (the rolling
   error shows it); a *change* of the error is.
   ``x`` is clipped to +-``clip`` so that one wild reading (a spike, a test booked to the
   wrong well) cannot raise an alarm alone.
4. **Two-sided CUSUM** (Page 1954): ``S+ = max(0, S+ + x - k)``, ``S- = max(0, S- - x - k)``;
   an alarm when either exceeds ``h``. ``k = 0.5`` is the optimal reference for a shift of
   one standard deviation of the period mean. ``h`` follows from the target in-control
   run length ``arl0`` (periods between false alarms when nothing changes) by Siegmund's
   approximation for Gaussian data (:func:`cusum_threshold`): one-sided
   ``ARL = (exp(2 k b) - 2 k b - 1) / (2 k^2)`` with ``b = h + 1.166``, and the two-sided
   run length is half the one-sided for a symmetric pair. The default ``arl0 = 1000``
   periods (about 2.7 years of days for the MPFM stream) gives ``h = 5.75``; with the
   well-test stream (one to a few dozen periods a year) a well's false alarms stay below
   the goal of one per well-year with room for data that are less Gaussian than assumed.
5. **Active span**: while an alarm is active the statistic is capped at ``h`` and the
   scale is frozen; the alarm clears when both sums are back at 0 (the residuals have been
   in control for at least ``h / k`` periods), and a new alarm needs ``h`` again.
6. **Accepted new level** (``accept_periods``, 0: never, the rule before s46; the residual
   alarm's default 30): an alarm still active after ``accept_periods`` periods closes as
   ``accepted``, and the test restarts as in classic CUSUM practice after a signal: both
   sums at 0, the reference re-estimated from the period means since the signal (the new
   level; self-starting again if they are fewer than ``min_periods``). Without it the
   frozen reference of an alarm whose level never comes back (the learner settled on a new
   bias) keeps the alarm active for good, and a second change inside it raises nothing.
7. **A quiet way back** (``alarm_on_return`` False, the default since s47): after an
   accepted alarm, a return toward the level before it is no alarm. A learner that follows
   a change slowly (``mm`` after a sand event) is often still on its way when its alarm is
   accepted; the way back to the old level then looked like a change in the other
   direction. Until the reference's centre is back at the level before the alarm, or for
   ``window`` periods at most, the side pointing back is tested against that old level
   instead of the new centre: going back is quiet, going beyond it is an alarm. The side
   pointing away from the old level is tested as before.

The detector follows the small river-like protocol of the project's detectors:
``update(residual, time_ns)``, the ``alarm`` property, ``reset()``, ``state_dict()`` and
``load_state_dict()``. :func:`alarms_from_predictions` runs it over a prequential study's
predictions (:func:`vfm_core.jobs.study.run_prequential`) in time order, which is what
the service does live.
"""

from __future__ import annotations

import functools
import math
from array import array
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import brentq

from vfm_core.errors import ConfigError

__all__ = [
    "ResidualCusum",
    "AlarmEvent",
    "AlarmSize",
    "cusum_threshold",
    "cusum_arl0",
    "standardised_residual",
    "alarms_from_predictions",
    "DEFAULT_PERIODS_S",
    "SCALES",
]

#: aggregation period per meter, s: MPFM readings come every few hours (a day's mean);
#: well tests days to months apart (each is its own period)
DEFAULT_PERIODS_S: dict[str, float] = {"mpfm": 86_400.0, "well_test": 0.0}

_SIEGMUND_SHIFT = 1.166  # Siegmund's correction of the boundary for the overshoot
_MAD_TO_SD = 1.4826  # the MAD of a Gaussian times this is its standard deviation
_WINSOR = 3.0  # the "winsorised" scale clips the reference at median +- this many robust sd
# the sd of N(0, 1) winsorised at +-3: sqrt(erf(3/sqrt 2) - 6 phi(3) + 18 (1 - Phi(3)))
_WINSOR_SD = 0.997498
#: the reference's centre and scale: ``winsorised`` (the mean and sd of the reference clipped
#: at median +- 3 robust sd: the residual alarm's default) or ``mad`` (median and 1.4826 MAD)
SCALES = ("winsorised", "mad")


def cusum_arl0(h: float, k: float = 0.5) -> float:
    """Siegmund's in-control average run length (periods) of a two-sided CUSUM on N(0, 1)."""
    if k <= 0:
        raise ConfigError(f"The CUSUM reference k must be positive, got {k}.")
    x = 2.0 * k * (h + _SIEGMUND_SHIFT)
    one_sided = (math.exp(x) - x - 1.0) / (2.0 * k * k)
    return one_sided / 2.0


def cusum_threshold(arl0: float, k: float = 0.5) -> float:
    """The decision threshold h whose two-sided in-control run length is ``arl0`` periods.

    >>> round(cusum_threshold(1000.0, 0.5), 2)
    5.75
    """
    return _threshold(float(arl0), float(k))


@functools.lru_cache(maxsize=64)
def _threshold(arl0: float, k: float) -> float:
    if not (math.isfinite(arl0) and arl0 >= 2.0):
        raise ConfigError(f"The in-control run length arl0 must be at least 2 periods, got {arl0}.")
    if not (math.isfinite(k) and 0.0 < k <= 3.0):
        raise ConfigError(f"The CUSUM reference k must lie in (0, 3], got {k}.")
    if cusum_arl0(0.0, k) >= arl0:
        return 0.0
    return float(brentq(lambda h: cusum_arl0(h, k) - arl0, 0.0, 200.0, xtol=1e-9))


_KERNELS: list[Any] = []


def robust_kernels() -> Any:
    """The compiled order statistics and sums of :mod:`vfm_core._robust_kernels` (the same
    numbers as the numpy expressions they replace, a fraction of their call cost), loaded
    once a process, or None (numba missing: numpy then). The detectors of this module,
    :mod:`vfm_core.rate_witness` and :mod:`vfm_core.sensor_faults` share them."""
    if not _KERNELS:
        try:
            from vfm_core import _robust_kernels

            _KERNELS.append(_robust_kernels.load())
        except ImportError:  # pragma: no cover - numba missing
            _KERNELS.append(None)
    return _KERNELS[0]


def _median_and_mad(ref: np.ndarray) -> tuple[float, float]:
    """``np.median(ref)`` and the median of ``|ref - it|`` (the raw MAD), compiled
    (:mod:`vfm_core._robust_kernels`) or by partial sorts: the same numbers either way."""
    kern = robust_kernels()
    if kern is not None:
        centre, mad = kern.median_mad(ref)
        if math.isfinite(centre):  # (else a value is not: numpy's rules below)
            return float(centre), float(mad)
    if np.isfinite(ref).all():
        centre = _median(ref)
        return centre, _median(np.abs(ref - centre), own=True)
    centre = float(np.median(ref))  # np.median's own handling of NaN
    return centre, float(np.median(np.abs(ref - centre)))


def _median(r: np.ndarray, own: bool = False) -> float:
    """The median of a non-empty 1-d array of finite values, as ``np.median`` gives it, by
    one partial sort (``np.median``'s own checks cost more than the sort at a few hundred
    values). ``own``: ``r`` is a temporary of the caller's, sorted in place (no copy)."""
    n = len(r)
    k = n // 2
    kth = k if n % 2 else (k - 1, k)
    if own:
        r.partition(kth)
        p = r
    else:
        p = np.partition(r, kth)
    return float(p[k]) if n % 2 else float((p[k - 1] + p[k]) / 2.0)


def _winsorised(ref: np.ndarray, centre: float, scale: float) -> tuple[float, float]:
    """The mean and the standard deviation (over that of a Gaussian winsorised alike) of
    ``ref`` clipped at ``centre +- 3 scale`` (its median and robust sd).

    Why not the median and MAD themselves: the period means are a scale mixture (a day of
    one MPFM reading scatters about twice as much as a day of four), so their tails are
    heavier than a Gaussian's and 1.4826 MAD falls short of their standard deviation by 5
    to 15 % on simulated fields; and the median of a skewed reference is not its mean. The
    CUSUM's run length depends on the mean and standard deviation of what it sums, and a
    scale 10 % short cuts it to 40 % (Siegmund). Clipping at 3 robust sd keeps a wild day
    from setting the scale."""
    lo, hi = centre - _WINSOR * scale, centre + _WINSOR * scale
    w = np.clip(ref, lo, hi)
    mean = float(w.sum()) / len(w)
    w -= mean
    sd = math.sqrt(float(w @ w) / max(1, len(w) - 1)) / _WINSOR_SD
    return mean, sd


def _long_run_factor(ref: np.ndarray, centre: float, scale: float, lags: int) -> float:
    """sqrt(1 + 2 sum_j (1 - j/(L+1)) rho_j), at least 1: the long-run standard deviation of
    autocorrelated period means over their plain one (Bartlett weights, Newey-West),
    from the reference in time order (winsorised at 4 sd, so a spike does not set it)."""
    if lags <= 0 or len(ref) < 3 * lags + 3:
        return 1.0
    # (np.clip and z.mean() as their ufuncs, in place: the same values, a fraction of the
    # call cost; compiled in one call when it can be, the same numbers again)
    kern = robust_kernels()
    z = kern.clipped_deviations(ref, centre, scale) if kern is not None else ref[:0]
    if len(z) != len(ref):  # (no kernel, or a value not finite: numpy's rules for it)
        z = ref - centre
        z /= scale
        np.maximum(z, -4.0, out=z)
        np.minimum(z, 4.0, out=z)
        z -= z.sum() / len(z)
    var = float(z @ z)
    if not var > 0:
        return 1.0
    total = 1.0
    for j in range(1, lags + 1):
        rho = float(z[:-j] @ z[j:]) / var
        total += 2.0 * (1.0 - j / (lags + 1.0)) * rho
    return math.sqrt(max(1.0, total))


def standardised_residual(measured: float, predicted: float, sd: float | None = None) -> float:
    """One measurement's residual: ``(measured - predicted) / sd`` with a predictive sd
    (Sm3/h, same unit as the rates), else ``ln(measured / predicted)``; NaN when there is
    no usable prediction (not finite, not positive)."""
    if not (math.isfinite(measured) and math.isfinite(predicted)):
        return float("nan")
    if sd is not None and math.isfinite(sd) and sd > 0:
        return (measured - predicted) / sd
    if measured <= 0 or predicted <= 0:
        return float("nan")
    return math.log(measured / predicted)


@dataclass
class AlarmEvent:
    """One alarm: when it began and ended (epoch ns, data time; ``end_ns`` None while
    active), its direction (``high``: measured above the model) and the period mean's
    standardised value furthest out during it, and the CUSUM statistic that raised it."""

    start_ns: int
    direction: str
    end_ns: int | None = None
    peak: float = 0.0
    statistic: float = 0.0
    #: how it ended: ``cleared`` (the residuals came back to the reference), ``accepted``
    #: (held their new level for ``accept_periods``: the new reference), None while active
    closed: str | None = None
    #: the change's estimated onset (epoch ns): the first reading of the period from which
    #: the signalling side's statistic climbed from zero without a break (the CUSUM's own
    #: change-point estimate); None in states saved before s51
    onset_ns: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "start_ns": self.start_ns,
            "end_ns": self.end_ns,
            "direction": self.direction,
            "peak": self.peak,
            "statistic": self.statistic,
            "closed": self.closed,
            "onset_ns": self.onset_ns,
        }


class ResidualCusum:
    """Self-starting two-sided CUSUM on one stream of residuals (see the module docstring).

    Hyperparameters are exactly the ``__init__`` arguments: ``arl0`` (target in-control
    run length, periods), ``k`` (reference, in standard deviations of the period mean),
    ``period_s`` (aggregation period, s; 0: every reading its own period), ``window``
    (period means in the self-starting reference), ``min_periods`` (periods before the
    first test), ``clip`` (bound on a standardised period mean), ``lags`` (of the long-run
    factor), ``scale`` (``winsorised`` or ``mad``: the reference's centre and scale, see
    the module docstring), ``accept_periods`` (periods after which a lasting alarm closes
    as an accepted new level and the reference restarts from them; 0: never),
    ``alarm_on_return`` (whether a return toward the level before an accepted alarm may
    raise one; step 7 of the module docstring).

    >>> import numpy as np
    >>> det = ResidualCusum(period_s=0.0)
    >>> rng = np.random.default_rng(0)
    >>> day = 86_400 * 10**9
    >>> for i in range(100):
    ...     _ = det.update(float(rng.standard_normal()), i * day)
    >>> det.alarm
    False
    >>> for i in range(100, 120):
    ...     _ = det.update(float(rng.standard_normal()) + 2.0, i * day)
    >>> det.alarm, det.direction
    (True, 'high')
    """

    def __init__(
        self,
        arl0: float = 1000.0,
        k: float = 0.5,
        period_s: float = 86_400.0,
        window: int = 365,
        min_periods: int = 30,
        clip: float = 4.0,
        lags: int = 3,
        scale: str = "mad",
        accept_periods: int = 0,
        alarm_on_return: bool = False,
    ) -> None:
        if scale not in SCALES:
            raise ConfigError(f"scale must be one of {', '.join(SCALES)}, got {scale!r}.")
        if not (math.isfinite(period_s) and period_s >= 0):
            raise ConfigError(f"period_s must be a number of seconds >= 0, got {period_s}.")
        if window < 5:
            raise ConfigError(f"window must hold at least 5 periods, got {window}.")
        if not 5 <= min_periods <= window:
            raise ConfigError(
                f"min_periods must lie between 5 and window ({window}), got {min_periods}."
            )
        if not (math.isfinite(clip) and clip > k):
            raise ConfigError(f"clip must exceed k ({k}), got {clip}.")
        self.arl0 = float(arl0)
        self.k = float(k)
        self.threshold = cusum_threshold(self.arl0, self.k)
        self.period_s = float(period_s)
        self.window = int(window)
        self.min_periods = int(min_periods)
        self.clip = float(clip)
        if not 0 <= lags <= 30:
            raise ConfigError(f"lags must lie between 0 and 30 periods, got {lags}.")
        self.lags = int(lags)
        self.scale = scale
        if not (accept_periods == 0 or 5 <= accept_periods <= 100_000):
            raise ConfigError(
                f"accept_periods must be 0 (never) or 5 to 100000 periods, got {accept_periods}."
            )
        self.accept_periods = int(accept_periods)
        self.alarm_on_return = bool(alarm_on_return)
        self._period_ns = int(round(self.period_s * 1e9))
        self.reset()

    # -- the protocol -----------------------------------------------------------------------
    def reset(self) -> None:
        """Forget everything (after a model change: the residuals of a new model are a new
        stream)."""
        # the last ``window`` period means, oldest first (an array: numpy reads it in place)
        self._ref: array[float] = array("d")
        self._open: int | None = None  # the open period's index
        self._sum = 0.0
        self._n = 0
        self._last_ns: int | None = None
        self.pos = 0.0
        self.neg = 0.0
        # the open period's first reading (epoch ns), and when each side's statistic last
        # left zero (the first reading of that period): the change-point estimates
        self._first_ns: int | None = None
        self._pos_onset: int | None = None
        self._neg_onset: int | None = None
        self.last_x = float("nan")
        self.n_readings = 0
        self.n_periods = 0
        self.events: list[AlarmEvent] = []
        self._active: AlarmEvent | None = None
        self._post: array[float] = array("d")  # the period means since the active alarm's signal
        # the reference's robust centre and scale (long-run factor included), and the
        # periods added to the reference since they were computed (see _scale)
        self._robust: tuple[float, float] | None = None
        self._robust_added = 0
        # the centre when the active alarm was signalled, and after an accepted alarm the
        # quiet way back (step 7): (the accepted direction, the old centre, periods left)
        self._signal_centre: float | None = None
        self._back: tuple[str, float, int] | None = None

    @property
    def alarm(self) -> bool:
        """True while an alarm is active."""
        return self._active is not None

    @property
    def statistic(self) -> float:
        """The larger of the two sums (compare with :attr:`threshold`)."""
        return max(self.pos, self.neg)

    @property
    def direction(self) -> str | None:
        """``high`` (measured above the model), ``low``, or None without an alarm."""
        return None if self._active is None else self._active.direction

    @property
    def since_ns(self) -> int | None:
        """When the active alarm began (epoch ns, data time), or None."""
        return None if self._active is None else self._active.start_ns

    @property
    def ready(self) -> bool:
        """True once enough periods are in for the test to run."""
        return len(self._ref) >= self.min_periods

    def update(self, residual: float, time_ns: int) -> bool:
        """Feed one residual (see :func:`standardised_residual`) at ``time_ns`` (epoch ns,
        the measurement's time; a stream must come in time order). Returns :attr:`alarm`.
        A residual that is not finite is ignored."""
        if not math.isfinite(residual):
            return self.alarm
        t = int(time_ns)
        self.n_readings += 1
        if self._period_ns <= 0:
            self._first_ns = t
            self._close(residual, t)
            return self._active is not None  # (self.alarm)
        index = t // self._period_ns
        if self._open is not None and index != self._open and self._n:
            self._close(self._sum / self._n, t)
            self._sum, self._n = 0.0, 0
        if index != self._open or self._first_ns is None:
            self._first_ns = t
        self._open = index
        self._sum += residual
        self._n += 1
        return self.alarm

    def flush(self, time_ns: int) -> bool:
        """Close the open period now (e.g. at the end of a replay). Returns :attr:`alarm`."""
        if self._n:
            self._close(self._sum / self._n, int(time_ns))
            self._sum, self._n, self._open = 0.0, 0, None
        return self.alarm

    # -- the test ---------------------------------------------------------------------------
    def _scale(self) -> tuple[float, float]:
        """The reference's median and robust sd (1.4826 MAD times the long-run factor),
        recomputed once a twentieth of the reference is new (every 18 periods with a year's
        reference, every period while it is short): a median of n values moves by a small
        fraction of its spread when n/20 of them change, and the cost per period (two
        medians and the autocorrelations of up to 365 values) falls as much. The instrument
        -fault detectors run one of these per input and day, so it matters there."""
        new = len(self._ref) // 20
        if self._robust is None or self._robust_added >= (new if new > 1 else 1):
            ref = np.frombuffer(self._ref)  # read-only here: the window's own memory
            centre, scale = _median_and_mad(ref)
            scale *= _MAD_TO_SD
            if scale > 0 and self.scale == "winsorised":
                centre, scale = _winsorised(ref, centre, scale)
            if scale > 0:
                scale *= _long_run_factor(ref, centre, scale, self.lags)
            self._robust, self._robust_added = (centre, scale), 0
        return self._robust

    def add_reference(self, mean: float) -> None:
        """Add one period mean to the reference, as :meth:`update` would, without testing
        it (no sums move, no alarm): a period another test has explained (a step of the
        level, not a trend) still tells the stream's spread. Ignored while an alarm is
        active (the reference is then frozen) and when not finite."""
        if self._active is None and math.isfinite(mean):
            self.n_periods += 1
            self._append(float(mean))

    def _append(self, mean: float) -> None:
        if len(self._ref) >= self.window:
            del self._ref[0]
        self._ref.append(mean)
        self._robust_added += 1

    def _close(self, mean: float, time_ns: int) -> None:
        self.n_periods += 1
        if len(self._ref) < self.min_periods:
            self._append(mean)
            return
        centre, scale = self._scale()
        if not scale > 0:
            # residuals that never vary (a model that repeats the meter): nothing to test
            self._append(mean)
            return
        # max(-clip, min(clip, .)) and max(0, .) as comparisons: the same values (NaN too)
        clip, x = self.clip, (mean - centre) / scale
        x = x if x < clip else clip
        x = x if x > -clip else -clip
        self.last_x = x
        xp, xn = (x, x) if self._back is None else self._way_back(mean, centre, scale, x)
        pos, neg = self.pos + xp - self.k, self.neg - xn - self.k
        if pos > 0.0 and self.pos == 0.0:
            self._pos_onset = self._first_ns
        if neg > 0.0 and self.neg == 0.0:
            self._neg_onset = self._first_ns
        self.pos = pos if pos > 0.0 else 0.0
        self.neg = neg if neg > 0.0 else 0.0
        h = self.threshold
        if self._active is None:
            if self.pos > h or self.neg > h:
                direction = "high" if self.pos >= self.neg else "low"
                onset = self._pos_onset if direction == "high" else self._neg_onset
                self._active = AlarmEvent(
                    time_ns, direction, peak=x, statistic=self.statistic, onset_ns=onset
                )
                self._signal_centre, self._back = centre, None
                self.events.append(self._active)
                self.pos, self.neg = min(self.pos, h), min(self.neg, h)
            else:
                self._append(mean)
            return
        self.pos, self.neg = min(self.pos, h), min(self.neg, h)
        if abs(x) > abs(self._active.peak):
            self._active.peak = x
        if self.accept_periods:
            self._post.append(mean)
        if self.pos == 0.0 and self.neg == 0.0:
            self._end(time_ns, "cleared")
        elif 0 < self.accept_periods <= len(self._post):
            self._accept(time_ns)

    def _way_back(self, mean: float, centre: float, scale: float, x: float) -> tuple[float, float]:
        """The two sides' standardised period means after an accepted alarm (step 7): the
        side pointing back to the old centre is measured from it while the centre has not
        reached it again; the bracket ends there, or after ``window`` periods."""
        assert self._back is not None
        accepted, old, left = self._back
        back = (old - centre) if accepted == "low" else (centre - old)
        if left <= 0 or back <= 0.0:
            self._back = None
            return x, x
        self._back = (accepted, old, left - 1)
        clip = self.clip
        y = (mean - old) / scale
        y = y if y < clip else clip
        y = y if y > -clip else -clip
        # an accepted low level: the way up is quiet below the old centre (pos side);
        # an accepted high level: the way down above it (neg side)
        return (min(x, y), x) if accepted == "low" else (x, max(x, y))

    def _end(self, time_ns: int, closed: str) -> None:
        assert self._active is not None
        self._active.end_ns = time_ns
        self._active.closed = closed
        self._active = None
        self._post = array("d")

    def _accept(self, time_ns: int) -> None:
        """The alarm has held for ``accept_periods``: its level is the new reference (the
        period means since the signal, the last ``window`` of them), the sums restart at 0."""
        post = self._post
        assert self._active is not None
        if not self.alarm_on_return and self._signal_centre is not None:
            self._back = (self._active.direction, self._signal_centre, self.window)
        self._end(time_ns, "accepted")
        self._ref = array("d", post[-self.window :])
        self._robust, self._robust_added = None, 0
        self.pos = self.neg = 0.0

    # -- state ------------------------------------------------------------------------------
    def state_dict(self) -> dict[str, Any]:
        """Plain values (JSON-safe) to resume the detector."""
        return {
            "arl0": self.arl0,
            "k": self.k,
            "period_s": self.period_s,
            "window": self.window,
            "min_periods": self.min_periods,
            "clip": self.clip,
            "lags": self.lags,
            "scale": self.scale,
            "accept_periods": self.accept_periods,
            "alarm_on_return": self.alarm_on_return,
            "reference": list(self._ref),
            "open": self._open,
            "sum": self._sum,
            "n": self._n,
            "pos": self.pos,
            "neg": self.neg,
            "n_readings": self.n_readings,
            "n_periods": self.n_periods,
            "events": [e.as_dict() for e in self.events[-20:]],
            "active": self._active is not None,
            "robust": None if self._robust is None else list(self._robust),
            "robust_added": self._robust_added,
            "post": list(self._post),
            "signal_centre": self._signal_centre,
            "first_ns": self._first_ns,
            "pos_onset": self._pos_onset,
            "neg_onset": self._neg_onset,
            "back": None if self._back is None else list(self._back),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resume from :meth:`state_dict`. A state saved before s46 (no ``accept_periods``,
        no ``post``) keeps this detector's ``accept_periods``; an alarm active in it counts
        its periods toward acceptance from the load."""
        self.__init__(  # type: ignore[misc]
            float(state["arl0"]),
            float(state["k"]),
            float(state["period_s"]),
            int(state["window"]),
            int(state["min_periods"]),
            float(state["clip"]),
            int(state.get("lags", 3)),
            str(state.get("scale", "mad")),
            int(state.get("accept_periods", self.accept_periods)),
            bool(state.get("alarm_on_return", self.alarm_on_return)),
        )
        self._ref.extend(float(v) for v in state.get("reference", []))
        del self._ref[: max(0, len(self._ref) - self.window)]  # the last window, as saved
        self._open = None if state.get("open") is None else int(state["open"])
        self._sum, self._n = float(state.get("sum", 0.0)), int(state.get("n", 0))
        self.pos, self.neg = float(state.get("pos", 0.0)), float(state.get("neg", 0.0))
        self.n_readings = int(state.get("n_readings", 0))
        self.n_periods = int(state.get("n_periods", 0))
        robust = state.get("robust")
        self._robust = None if robust is None else (float(robust[0]), float(robust[1]))
        self._robust_added = int(state.get("robust_added", 0))
        # (a state saved before s51 has none: the next climb from zero sets them)
        for name in ("first_ns", "pos_onset", "neg_onset"):
            v = state.get(name)
            setattr(self, "_" + name, None if v is None else int(v))
        # (a state saved before s47 has none: an alarm active in it is accepted as before)
        centre = state.get("signal_centre")
        self._signal_centre = None if centre is None else float(centre)
        back = state.get("back")
        self._back = None if back is None else (str(back[0]), float(back[1]), int(back[2]))
        self.events = [
            AlarmEvent(
                int(e["start_ns"]),
                str(e["direction"]),
                e.get("end_ns"),
                float(e["peak"]),
                float(e.get("statistic", 0.0)),
                e.get("closed"),
                None if e.get("onset_ns") is None else int(e["onset_ns"]),
            )
            for e in state.get("events", [])
        ]
        if state.get("active") and self.events and self.events[-1].end_ns is None:
            self._active = self.events[-1]
            self._post.extend(float(v) for v in state.get("post", []))


def alarm_size(shift: float | None, typical: float | None) -> dict[str, Any]:
    """How large an alarm is beside the error the operator already reads: ``small`` is True
    when its size at the raise, ``|shift|`` (a relative change: 0.005 = 0.5 %), is under
    ``typical``, the meter's usual relative error before the change (the reference
    readings' MAPE as a ratio, :meth:`AlarmSize.at_raise`). The detector found a real move
    (its false-alarm rate is set by ``arl0``), but no single reading shows it: the page
    lists it as "small" in the warning colour, ``/metrics`` as
    ``vfm_well_residual_alarm_small`` (alert ``VfmResidualAlarmSmall``, severity info). The
    usual error is read before the change, not from the rolling MAPE, which the shift's own
    errors raise while the model has not followed it. ``small`` is None when either figure
    is unknown (the alarm counts as a full one then). ``typical_error_percent`` is
    ``typical`` in %.

    >>> alarm_size(0.005, 0.022)
    {'small': True, 'typical_error_percent': 2.2}
    >>> alarm_size(-0.063, 0.022)["small"], alarm_size(None, 0.022)["small"]
    (False, None)
    """
    small: bool | None = None
    pct = None if typical is None or not math.isfinite(typical) else round(100.0 * typical, 6)
    if shift is not None and math.isfinite(shift) and pct is not None and pct > 0:
        small = 100.0 * abs(shift) < pct
    return {"small": small, "typical_error_percent": pct}


class AlarmSize:
    """The size of an alarm in the measurement's own terms: how far the measured rate moved
    from the model's prediction when the alarm was raised, as a relative change (0.05: the
    meter reads 5 % further above the model than it did before). The CUSUM runs on
    standardised residuals (``bayes``), which say that something moved, not by how much;
    :func:`vfm_core.meter_check.which_moved` needs the size to tell a meter that moved
    from a well that moved when the shift is small beside the well-test pairs' spread.

    Keeps each reading's log ratio ``ln(measured / predicted)`` (the last ``keep``, with
    their times). At an alarm: the median of the readings from its onset (the CUSUM's own
    change-point estimate, :attr:`AlarmEvent.onset_ns`) up to the reading that raised it,
    less the median of the last ``REFERENCE`` readings before the onset (at least
    ``MIN_REFERENCE``; None with fewer). Medians, because MPFM readings have heavy tails
    (slugs); the readings before the raise, because a learner then absorbs the shift
    (after it the residual says how much is left, not how much moved).

    >>> size = AlarmSize()
    >>> day = 86_400 * 10**9
    >>> for i in range(40):
    ...     size.add(i * day, 100.0 * (1.06 if i >= 30 else 1.0), 100.0)
    >>> round(size.at_raise(30 * day, 39 * day)["shift"], 3)
    0.06
    """

    REFERENCE = 30
    MIN_REFERENCE = 8

    def __init__(self, keep: int = 200) -> None:
        self.keep = int(keep)
        self._t: deque[int] = deque(maxlen=self.keep)
        self._r: deque[float] = deque(maxlen=self.keep)

    def add(self, time_ns: int, measured: float, predicted: float | None) -> None:
        """One reading (Sm3/h) and the prediction made at its sample (Sm3/h)."""
        if predicted is None or not (measured > 0 and predicted > 0):
            return
        r = math.log(measured / predicted)
        if not math.isfinite(r):
            return
        self._t.append(int(time_ns))
        self._r.append(r)

    def at_raise(self, onset_ns: int, raised_ns: int) -> dict[str, Any] | None:
        """``{"shift", "se", "readings", "reference", "onset_ns", "typical"}`` of an alarm that began at
        ``onset_ns`` (:attr:`AlarmEvent.onset_ns`) and was raised at ``raised_ns`` (epoch
        ns; the event's ``start_ns``): the relative shift, its
        standard error in log terms, the readings in the alarm it rests on and the readings
        before it, and the change's time that the shift rests on (the first of those readings,
        epoch ns: the onset narrowed by the scan below); None without enough of either. A fast alarm rests on few readings: at
        3 % meter noise and three readings the se is about 2 %."""
        t = np.asarray(self._t, dtype=np.int64)
        r = np.asarray(self._r, dtype=float)
        before = r[t < onset_ns][-self.REFERENCE :]
        within = (t >= onset_ns) & (t <= raised_ns)
        inside, times = r[within], t[within]
        if len(before) < self.MIN_REFERENCE or len(inside) == 0:
            return None
        centre = float(np.median(before))
        # the CUSUM's onset is where its statistic last left zero, often some readings
        # before the change (k lets chance climbs start): the change within the run is
        # the reading from which the mean excess is largest in standard terms (the
        # scan statistic of a step, sum / sqrt(n))
        excess = (inside - centre)[::-1].cumsum()[::-1]
        scan = np.abs(excess) / np.sqrt(np.arange(len(inside), 0, -1))
        change = int(np.argmax(scan))
        inside = inside[change:]
        shift = float(np.median(inside)) - centre
        # the two medians' standard error: the readings' robust sd (the reference's MAD),
        # times sqrt(pi / 2) for a median's efficiency, over both counts
        sd = _MAD_TO_SD * float(np.median(np.abs(before - centre)))
        se = 1.2533 * sd * math.sqrt(1.0 / len(inside) + 1.0 / len(before))
        return {
            "shift": math.expm1(shift),
            "se": se,
            "readings": len(inside),
            "reference": len(before),
            "onset_ns": int(times[change]),
            # the meter's usual error before the change: the mean absolute relative error
            # |predicted - measured| / measured of the reference readings (a MAPE, as a
            # ratio), which the alarm's size is read against (:func:`alarm_size`)
            "typical": float(np.mean(np.abs(np.expm1(-before)))),
        }

    def state(self) -> dict[str, Any]:
        return {"t": list(self._t), "r": list(self._r)}

    def restore(self, data: dict[str, Any]) -> None:
        t, r = list(data.get("t") or []), list(data.get("r") or [])
        if len(t) == len(r):
            self._t = deque((int(v) for v in t), maxlen=self.keep)
            self._r = deque((float(v) for v in r), maxlen=self.keep)


def _feed_sized(
    det: ResidualCusum, times: Any, measured: Any, predicted: Any, sds: Iterable[float | None]
) -> dict[int, dict[str, Any] | None]:
    """Feed one stream's readings (Sm3/h) to ``det`` in order; each new alarm's size
    (:meth:`AlarmSize.at_raise`, by the event's index)."""
    size, sizes = AlarmSize(), {}
    for t, m, q, s in zip(
        times,
        measured.to_numpy(dtype=float),
        predicted.to_numpy(dtype=float),
        sds,
        strict=True,
    ):
        size.add(int(t), float(m), float(q))
        before = len(det.events)
        det.update(standardised_residual(float(m), float(q), s), int(t))
        if len(det.events) > before:
            new = det.events[-1]
            onset = new.start_ns if new.onset_ns is None else new.onset_ns
            sizes[len(det.events) - 1] = size.at_raise(onset, new.start_ns)
    return sizes


def alarms_from_predictions(
    predictions: Any,
    *,
    arl0: float = 1000.0,
    k: float = 0.5,
    periods_s: dict[str, float] | None = None,
    window: int = 365,
    min_periods: int = 30,
    clip: float = 4.0,
    lags: int = 3,
    scale: str = "winsorised",
    accept_periods: int = 30,
    alarm_on_return: bool = False,
    use_sd: bool = True,
    flush: bool = True,
) -> list[dict[str, Any]]:
    """Run one detector per well and meter over a prequential study's predictions
    (columns ``time``, ``well``, ``source``, ``predicted``, ``measured`` (Sm3/h) and, for
    methods with intervals, ``predicted_std``), in time order, as the service does live.

    Returns the alarms: ``[{shift, shift_se, well, source, start, end, direction, peak, closed}]``
    with times as pandas Timestamps (UTC; ``end`` and ``closed`` None while still active at
    the end of the data; ``closed`` ``cleared`` or ``accepted``, see the module docstring;
    ``shift`` the relative size at the raise and ``shift_se`` its standard error in log
    terms, :class:`AlarmSize`, or None).
    """
    import pandas as pd

    periods = {**DEFAULT_PERIODS_S, **(periods_s or {})}
    p = predictions.sort_values("time", kind="stable")
    has_sd = use_sd and "predicted_std" in p.columns
    out: list[dict[str, Any]] = []
    for (well, source), g in p.groupby(["well", "source"], sort=True):
        det = ResidualCusum(
            arl0,
            k,
            periods.get(str(source), 0.0),
            window,
            min_periods,
            clip,
            lags,
            scale,
            accept_periods,
            alarm_on_return,
        )
        times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64").to_numpy()
        sds: Iterable[float | None] = (
            g["predicted_std"].to_numpy(dtype=float) if has_sd else [None] * len(g)
        )
        sizes = _feed_sized(det, times, g["measured"], g["predicted"], sds)
        if flush and len(times):
            det.flush(int(times[-1]))
        for i, e in enumerate(det.events):
            found = sizes.get(i)
            out.append(
                {
                    "shift": None if found is None else found["shift"],
                    "shift_se": None if found is None else found["se"],
                    **alarm_size(
                        None if found is None else found["shift"],
                        None if found is None else found["typical"],
                    ),
                    "well": str(well),
                    "source": str(source),
                    "start": pd.Timestamp(e.start_ns, tz="UTC"),
                    "end": None if e.end_ns is None else pd.Timestamp(e.end_ns, tz="UTC"),
                    "direction": e.direction,
                    "peak": e.peak,
                    "closed": e.closed,
                }
            )
    return out
