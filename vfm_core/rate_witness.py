"""Does the measured rate follow the choke's position reading? A witness for a choke offset.

The choke's position reading is a set point that the operator moves, so the input-only
tests of :mod:`vfm_core.sensor_faults` cannot test it for an offset: every step of it is
a step of the process. The well's rate can: when the choke really moves, the rate moves
with it; when only its reading moves (a transmitter re-zeroed wrongly after maintenance,
a position sensor that slipped, an actuator that no longer moves the choke), the rate
stays where it was. :class:`ChokeRateWitness` watches one well's choke readings and its
frequent rate readings (an MPFM's; well tests are too sparse for it) and raises a choke
``offset`` when a move of the reading is not followed by the rate.

The model, per well and free of any rate model or learning method (so ``vfm evaluate``
plans it once for every model, as the input tests):

* **A move** is a change of the reading (relative change above ``1e-9``). Its response is
  ``d = mean(log q after) - mean(log q before)``: the rate readings of the new level in the
  ``window_days`` after it against those of the old level in the ``window_days`` before it
  (each at least :data:`MIN_READINGS`). A reading at a choke of zero (shut in) starts
  afresh. The window before is taken from the rate's latest level: a step of the rate
  in it against the move's response (an operator who closes in after a sand event raised
  C_D) is found by :func:`_latest_level`, and only the readings after it count; before a
  raise the window after is scanned the same way, and a step there leaves the move
  undecided.
* **The well's elasticity** ``beta``: the median of ``d / dlog u`` over its last
  :data:`MOVES_KEPT` complete moves of at least 1 % (a median, since a move now and then
  meets another change of the well). A linear valve in critical flow gives about 1.
* **The spread of a real move's response**: ``sigma^2 = se^2 + tau^2 dlog u^2``, where
  ``se = s sqrt(1/n_before + 1/n_after)`` is the noise of the two means (``s``: the median
  within-window sd of the past moves' readings) and ``tau`` the scatter of the elasticity
  between moves, chosen so that the past moves' standardised residuals
  ``(d - beta dlog u) / sigma`` have a robust sd (1.4826 MAD) of one (bisection; ``tau = 0``
  when they are already narrower, and then the residuals' own robust sd, at least one,
  scales ``sigma``).
* **The test**, at every rate reading in the ``window_days`` after a move, once the well
  has :data:`MIN_MOVES` complete moves and ``beta > 0.2``: the shortfall
  ``z = (beta dlog u - d) sign(dlog u) / sigma`` (how far the rate fell short of the
  response the reading asks for) beyond ``z_lim``, and the response closer to none than to
  the expected (``|d| < |d - beta dlog u|``). ``z_lim`` is the one-sided Gaussian quantile of
  ``share / moves_per_year / looks``: ``share`` is this test's part of the detectors'
  false-alarm budget (:class:`vfm_core.sensor_faults.WellSensorFaults` gives it), the moves
  per year are the well's own (at least 12), and ``looks`` (the readings a window holds,
  at most 12) divides it among the repeated looks at one move (Bonferroni, conservative:
  the looks share their readings).
* **The fault** starts at the move and is an ``offset`` of the ``choke``. A move of the
  reading back by the same amount with no response again closes it (the reading came back);
  the caller closes it after its acceptance time otherwise, and a later move of the reading
  back that the rate does not follow is then that offset's end, not a new one (the
  transmitter set right after the model learned the offset). Moves while it is open teach
  nothing (their readings carry the offset).
* **Where the choke is** while the offset is open: at the old opening, ``u_where =
  u_before`` (the test found the response within chance of none), with sd ``u_where kappa
  sqrt(noise) / beta`` (how far the choke could have moved unseen: the response's noise
  over the elasticity). The reading is then off by ``shift = u_after - u_where``,
  taken as additive (a transmitter re-zeroed wrongly: a later move of the reading is a move
  of the choke), which :meth:`vfm_core.sensor_faults.WellSensorFaults.fallbacks` subtracts
  from every reading until the offset closes. A transmitter whose span, not its zero, is
  wrong makes the stand-in off by the span error times the later moves.

What it cannot see: an offset that appears without a change of the reading (a choke
re-zeroed during a shut-in, where the move is hidden in the gap), one smaller than the
MPFM's noise over a week allows (about 5 % of the opening at 3 % noise: see the detection
table in ``docs/guide/sensor-faults.md``), and any well without a frequent meter.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from statistics import NormalDist
from typing import Any

import numpy as np

from vfm_core.errors import ConfigError
from vfm_core.residual_alarm import robust_kernels
from vfm_core.timeutil import iso

__all__ = ["ChokeFinding", "ChokeRateWitness", "MIN_MOVES", "MIN_READINGS", "MOVES_KEPT"]

#: complete moves (both windows with readings) before the test runs
MIN_MOVES = 8
#: rate readings each side of a move for its response
MIN_READINGS = 3
#: complete moves kept for the elasticity and the spread
MOVES_KEPT = 100
_NS_PER_DAY = 86_400 * 10**9
_SAME = 1e-9
_MIN_MOVE = 0.01  # |dlog u| of the moves the elasticity is taken from
_MIN_BETA = 0.2  # below it the rate barely answers the choke: no power
_MAD_TO_SD = 1.4826
_MAX_LOOKS = 12
_MIN_MOVES_PER_YEAR = 12.0
_CLOSED_CHOKE = 1e-3  # a reading at or below it is a closed choke (shut in)
_MIN_DP = 1e-3  # the pressure drop's floor, a share of p_up (a log needs it positive)
_GAP_NS = 2 * _NS_PER_DAY  # samples further apart: a break (a shut-in, an outage)
_Z_NONE = NormalDist().inv_cdf(0.995)  # |d| within it: no response (two-sided 99 %)
_BISECTIONS = 24  # of omega in [0, 1]: to 1e-7 (log rate)
_HUBER_STEPS = 20  # reweightings of the elasticity's Huber fit at most
_LEVEL_ALPHA = 0.01  # a step of the rate before a move: one-sided, over all its splits


@dataclass
class ChokeFinding:
    """What the witness found at a rate reading: ``"raise"`` a choke offset that began at
    ``start_ns`` (the move), or ``"close"`` the open one; ``time_ns`` is the reading's time
    and ``evidence`` a sentence with the numbers."""

    action: str
    start_ns: int
    time_ns: int
    evidence: str
    #: for a raised offset: how far the reading moved beyond the choke (reading units,
    #: fraction open; the reading after the move less the opening before it, where the
    #: rate says the choke stayed), and that estimate's standard deviation
    shift: float = 0.0
    shift_sd: float = math.nan


@dataclass
class _Move:
    """A change of the choke reading: when, from and to which reading, its segment."""

    time_ns: int
    u_before: float
    u_after: float
    segment: int
    decided: bool = False  # raised (or closed) a fault: not learned, not tested again
    recorded: bool = False  # its response was taken (or refused) for the elasticity
    #: the rate's response so far is nearer none than the expected one, by a move the
    #: readings can tell (:meth:`ChokeRateWitness.doubted`): not yet decided
    doubt: bool = False
    #: where the rate's latest level before the move began (ns; 0: the whole window),
    #: when the rate stepped against the move's response before it (:func:`_latest_level`)
    level_ns: int = 0
    #: the window before it, once made: (elasticity, adjusted log rates, largest
    #: adjustment, mean log p_up and log(p_up - p_down), mean adjusted log rate (NaN when
    #: empty))
    before: tuple[float, np.ndarray, float, tuple[float, float], float] | None = None
    #: the window after it so far, kept up reading by reading: [elasticity, time of the
    #: last reading in it, n, sum of adjusted log rates, largest adjustment, sums of log
    #: p_up and log(p_up - p_down) (NaN once one is unknown)]
    after: list[float] | None = None

    @property
    def dlu(self) -> float:
        return math.log(self.u_after) - math.log(self.u_before)


class _Readings:
    """The rate readings of the last three windows as rows of a growing array (time ns,
    log q, segment, and at the paired sample log u, log p_up, log(p_up - p_down)): a test
    slices it instead of converting a list every reading."""

    def __init__(self) -> None:
        self.buf = np.empty((64, 6))
        self.n = 0
        #: changes with every append or clear (what is cached of the rows is keyed by it)
        self.version = 0

    def __len__(self) -> int:
        return self.n

    def append(self, row: Sequence[float], oldest_ns: float) -> None:
        """Add a row; rows before ``oldest_ns`` are dropped when the array is full."""
        if self.n == len(self.buf):
            keep = self.buf[: self.n][self.buf[: self.n, 0] >= oldest_ns]
            if len(keep) > len(self.buf) // 2:
                self.buf = np.empty((2 * len(self.buf), 6))
            self.n = len(keep)
            self.buf[: self.n] = keep
        self.buf[self.n] = row
        self.n += 1
        self.version += 1

    def since(self, oldest_ns: float) -> np.ndarray:
        """The rows at or after ``oldest_ns`` (a view)."""
        arr = self.buf[: self.n]
        return arr[int(arr[:, 0].searchsorted(oldest_ns)) :]

    def clear(self) -> None:
        self.n = 0
        self.version += 1


@dataclass
class _Windows:
    """A move's two windows: their numbers of readings and the change of the mean
    adjusted log rate between them, the largest adjustment, and the change of the mean
    log p_up and log(p_up - p_down)."""

    n_before: int
    n_after: int
    d: float
    other: float
    d_log_p_up: float
    d_log_dp: float


@lru_cache(maxsize=512)
def _quantile(p: float) -> float:
    """The standard normal quantile of ``p`` (cached: a well's limits repeat)."""
    return NormalDist().inv_cdf(p)


def _median(x: np.ndarray) -> float:
    """The median of a non-empty 1-d array by a partial sort (``np.median``'s checks cost
    more than the sort at a hundred values)."""
    n = len(x)
    k = n // 2
    part = np.partition(x, [k - 1, k] if n % 2 == 0 else k)
    return float(part[k]) if n % 2 else 0.5 * float(part[k - 1] + part[k])


def _robust_sd(x: np.ndarray) -> float:
    k = robust_kernels()
    if k is not None:
        centre, mad = k.median_mad(x)
        if math.isfinite(centre):  # (else a value is not: numpy's rules for it)
            return _MAD_TO_SD * float(mad)
    return _MAD_TO_SD * _median(np.abs(x - _median(x)))


def _median_of_any(x: np.ndarray) -> float:
    """``np.median(x)`` (``x`` non-empty, any layout; compiled when its values are finite)."""
    k = robust_kernels()
    if k is not None:
        centre = k.median_mad(x)[0]
        if math.isfinite(centre):
            return float(centre)
    return float(np.median(x))


def _omega_kappa(e: np.ndarray, base: np.ndarray) -> tuple[float, float]:
    """The scatter ``omega`` of the elasticity between moves and the spread's factor
    ``kappa`` (see the module docstring): bisection of [0, 1] for the ``omega`` at which
    the robust sd of ``e / sqrt(base + omega^2)`` is one (0 when it is one or less
    already), and ``kappa`` that robust sd at it, at least one. Compiled when it can be
    (:func:`vfm_core._robust_kernels.scaled_spread_root`, the same numbers)."""
    k = robust_kernels()
    if k is not None:
        omega, kappa = k.scaled_spread_root(e, base, _BISECTIONS)
        if math.isfinite(omega):  # (else a value is not: numpy's rules for it)
            return float(omega), float(kappa)

    def spread(omega: float) -> float:
        return _robust_sd(e / np.sqrt(base + omega * omega))

    omega, kappa = 0.0, max(1.0, spread(0.0))
    if spread(0.0) > 1.0:
        lo, hi = 0.0, 1.0
        for _ in range(_BISECTIONS):  # omega to 1e-7 (log rate)
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if spread(mid) > 1.0 else (lo, mid)
        omega, kappa = hi, max(1.0, spread(hi))
    return omega, kappa


def _latest_level(values: np.ndarray, s: float, sign: float) -> int:
    """Where the rate's latest level in a move's window before it begins (an index into
    ``values``, the window's adjusted log rates in time order; 0: one level). The rate
    stepped (a sand event that raised C_D, a change of the reservoir) when the mean of the
    readings from some index on differs from the mean of those before it, in the direction
    ``sign`` (against the move's expected response: the step an operator's corrective move
    answers, which otherwise shrinks the response measured over the whole window), by more
    than the one-sided 99 % Gaussian quantile, Bonferroni over the splits, of the means'
    noise (``s``: one reading's sd of the log rate)."""
    n = len(values)
    if n < 2 or not (math.isfinite(s) and s > 0):
        return 0
    k = np.arange(1, n, dtype=float)
    cs = np.cumsum(values)
    early = cs[:-1] / k
    late = (cs[-1] - cs[:-1]) / (n - k)
    z = sign * (late - early) / (s * np.sqrt(1.0 / k + 1.0 / (n - k)))
    best = int(np.argmax(z))
    return best + 1 if z[best] > _quantile(1.0 - _LEVEL_ALPHA / (n - 1)) else 0


def _num(v: Any) -> float:
    return math.nan if v is None else float(v)


def _huber_slope(x: np.ndarray, y: np.ndarray, var: np.ndarray) -> tuple[float, float]:
    """The slope of ``y = beta x`` (through the origin) by weighted least squares with
    Huber's weights (``c = 1.345``, 95 % efficiency at the Gaussian; a move that met another
    change of the well weighs less), and its standard error: the standardised residuals'
    robust sd over ``sqrt(sum x^2 / var)``. Compiled when it can be
    (:func:`vfm_core._robust_kernels.huber_slope`, the same numbers)."""
    k = robust_kernels()
    if k is not None:
        beta, se = k.huber_slope(x, y, var, _HUBER_STEPS)
        if math.isfinite(beta):  # (else a value is not finite: numpy's rules for it)
            return float(beta), float(se)
    w0 = 1.0 / var
    w = w0.copy()
    beta = 0.0
    for _ in range(_HUBER_STEPS):
        last, beta = beta, float((w * x * y).sum() / (w * x * x).sum())
        if abs(beta - last) < 1e-6:
            break
        r = (y - beta * x) * np.sqrt(w0)
        scale = max(_robust_sd(r), 1e-9)
        u = np.abs(r) / scale
        w = w0 * np.minimum(1.0, 1.345 / np.maximum(u, 1e-12))
    scale = max(_robust_sd((y - beta * x) * np.sqrt(w0)), 1.0)
    return beta, scale / math.sqrt(float((w0 * x * x).sum()))


class ChokeRateWitness:
    """One well's test of whether the measured rate follows the choke reading (see the
    module docstring). ``share``: false faults per well-year this test may raise;
    ``window_days``: the days each side of a move its response is taken over."""

    def __init__(self, share: float, window_days: float = 7.0) -> None:
        if not (math.isfinite(share) and share > 0):
            raise ConfigError(f"share must be a positive number per well-year, got {share}.")
        if not (math.isfinite(window_days) and 1.0 <= window_days <= 60.0):
            raise ConfigError(f"window_days must lie in 1..60 days, got {window_days}.")
        self.share = float(share)
        self.window_ns = int(window_days * _NS_PER_DAY)
        self.u: float | None = None
        self.last_ns: int | None = None
        self.segment = 0
        #: the first segment after the latest break (a shut-in, a gap): nothing before it
        #: is compared with anything after it
        self.closed_segment = 0
        #: the moves whose window after them is still open, oldest first
        self.pending: deque[_Move] = deque(maxlen=64)
        #: rate readings: (time ns, log q, segment, and at the paired sample the log of the
        #: choke reading, of p_up and of p_up - p_down)
        self.readings = _Readings()
        #: complete moves: (dlog u, response d, n_before, n_after, pooled within sd)
        self.moves: deque[tuple[float, float, int, int, float]] = deque(maxlen=MOVES_KEPT)
        self.move_times: deque[int] = deque(maxlen=400)
        self.open: _Move | None = None
        #: while an offset is open: its shift (reading units), the well's rate constant
        #: under it (``log q - beta log(reading - shift)``) at the readings that confirmed
        #: it, and the current level's readings (segment, that constant, and the one under
        #: the reading taken as right): :meth:`_level_check`
        self.open_shift = 0.0
        self.open_ref: deque[float] = deque(maxlen=60)
        self.open_level: list[tuple[int, float, float]] = []
        #: the log move of the latest offset taken as real (:meth:`accept`), until its end
        self.accepted: float | None = None
        self._fit: tuple[float, float, float, float, float] | None = None  # see fit()
        self._no_fit = False  # fit() found too few moves since the last complete one
        self._looks_at = (-1, _MAX_LOOKS)  # (readings.version, _looks() at it)

    # -- the protocol ---------------------------------------------------------------------
    def choke(self, time_ns: int, u: float) -> None:
        """Feed one sample's choke reading (fraction open, in time order). A closed choke
        (shut in) or a gap of more than two days between samples is a break: no move across
        it is tested or learned."""
        t = int(time_ns)
        if not math.isfinite(u):
            return
        gap = self.last_ns is not None and t - self.last_ns > _GAP_NS
        self.last_ns = t
        if u <= _CLOSED_CHOKE or gap:
            self._record_latest(t)
            self.pending.clear()
            self.segment += 1
            self.closed_segment = self.segment
            self.u = None if u <= _CLOSED_CHOKE else u
            return
        if self.u is None:
            self.u = u
            return
        if abs(u - self.u) <= _SAME * max(1.0, abs(self.u)):
            return
        self._record_latest(t)
        self.segment += 1
        self.pending.append(_Move(t, self.u, u, self.segment))
        self.move_times.append(t)
        self.u = u

    def rate(
        self, time_ns: int, q: float, p_up: float = math.nan, p_down: float = math.nan
    ) -> ChokeFinding | None:
        """Feed one rate reading (Sm3/h, the well's frequent meter, in time order) with its
        paired sample's ``p_up`` and ``p_down`` (bar a; NaN if unknown) and test the moves of
        the last ``window_days`` with it (the first finding is returned)."""
        t = int(time_ns)
        if not (math.isfinite(q) and q > 0) or self.u is None:
            return None
        lp, ldp = math.nan, math.nan
        if math.isfinite(p_up) and math.isfinite(p_down) and p_up > 0:
            lp = math.log(p_up)
            ldp = math.log(max(p_up - p_down, _MIN_DP * p_up))
        if len(self.readings) and t < self.readings.buf[self.readings.n - 1, 0]:
            return None  # out of time order: the windows need it in order
        lq, lu = math.log(q), math.log(self.u)
        self.readings.append((t, lq, self.segment, lu, lp, ldp), t - 3 * self.window_ns)
        while self.pending and t >= self.pending[0].time_ns + self.window_ns:
            self._record(self.pending.popleft(), t)
        self._extend(t, lq, lu, lp, ldp)
        if self.open is not None:
            found = self._level_check(t, lq)
            if found is not None:
                return found
        for m in self.pending:
            if not m.decided:
                found = self._test(m, t)
                if found is not None:
                    return found
        return None

    def _level_check(self, t: int, lq: float) -> ChokeFinding | None:
        """While an offset is open: does the rate still say so? At each reading the
        well's rate constant is taken both ways, ``log q - beta log(reading - shift)`` (the
        offset stays) and ``log q - beta log(reading)`` (the reading is right again); once
        the current level (since the latest move or break) has :data:`MIN_READINGS`
        readings, its mean under each is compared with the constant the offset's own
        readings gave. Nearer under the reading, by a separation of the two beyond three
        sd of the means' noise, the offset is closed (the transmitter was set right, also
        across a shut-in, or the reading moved back); nearer under the offset, the level's
        readings join the reference (a slow change of the well is followed)."""
        fit = self.fit()
        u = self.u
        if fit is None or u is None or u - self.open_shift <= _CLOSED_CHOKE:
            return None
        beta, s = fit[0], fit[1]
        level = self.open_level
        if level and level[0][0] != self.segment:
            level.clear()
        level.append((self.segment, lq - beta * math.log(u - self.open_shift),
                      lq - beta * math.log(u)))  # fmt: skip
        n, n_ref = len(level), len(self.open_ref)
        if n < MIN_READINGS or n_ref < MIN_READINGS:
            return None
        ref = float(np.mean(self.open_ref))
        stays = float(np.mean([v[1] for v in level]))
        right = float(np.mean([v[2] for v in level]))
        noise = s * math.sqrt(1.0 / n + 1.0 / n_ref)
        if abs(right - ref) < abs(stays - ref) and abs(stays - right) > 3.0 * noise:
            m = self.open
            assert m is not None
            self.open = None
            for later in self.pending:  # a move back among them is the offset's end
                later.decided = later.decided or later.time_ns > m.time_ns
            since = int(self.readings.buf[self.readings.n - n, 0])  # the level's first
            return ChokeFinding(
                "close",
                since,
                t,
                f"The rate says the choke's reading is right again: over the {n} meter "
                f"readings since {iso(since)} the "
                f"well's rate constant is {100 * (right - ref):+.1f} % off the offset's "
                f"own with the reading as it is, against {100 * (stays - ref):+.1f} % with "
                f"the offset's shift of {self.open_shift:.3g} taken off.",
            )
        if abs(stays - ref) <= abs(right - ref):  # the offset stays: the level joins
            self.open_ref.extend(v[1] for v in (level if n == MIN_READINGS else level[-1:]))
        return None

    # -- the response of a move ---------------------------------------------------------------
    def _windows(self, m: _Move, until: int) -> tuple[np.ndarray, np.ndarray]:
        """The log rates of the old level in the window before ``m`` and of the new one
        from ``m`` up to ``until``."""
        lo = m.time_ns - self.window_ns
        arr = self.readings.since(lo)
        t, seg = arr[:, 0], arr[:, 2]
        before = arr[(seg == m.segment - 1) & (t < m.time_ns), 1]
        after = arr[(seg == m.segment) & (t >= m.time_ns) & (t <= until), 1]
        return before, after

    def _adjusted(self, m: _Move, until: int, beta: float) -> _Windows:
        """The log rates in the window before ``m`` and from ``m`` up to ``until`` (the
        latest reading), each moved to the choke reading next to ``m`` on its side by the
        elasticity (``log q - beta (log u - log u_m)``), so other moves inside the windows do
        not count; the largest such adjustment (its error enters the spread); and the change
        of the mean log ``p_up`` and log ``p_up - p_down`` between the windows (0 where
        unknown). The side before the move is made once per elasticity (its readings are
        all in), the side after it is kept up reading by reading (:meth:`_extend`)."""
        if m.before is None or m.before[0] != beta:
            arr = self.readings.since(m.time_ns - self.window_ns)
            arr = arr[(arr[:, 2] >= self.closed_segment) & (arr[:, 0] < m.time_ns)]
            values, worst, b_p = self._side(arr, math.log(m.u_before), beta)
            fit = self._fit
            cut = _latest_level(values, fit[1] if fit else math.nan, -math.copysign(1.0, m.dlu))
            m.level_ns = int(arr[cut, 0]) if cut else 0
            if cut:  # the rate stepped before the move: its response is from the new level
                values, worst, b_p = self._side(arr[cut:], math.log(m.u_before), beta)
            mean = float(values.mean()) if len(values) else math.nan
            m.before = (beta, values, worst, b_p, mean)
        _, b_values, b_worst, b_p, b_mean = m.before
        if m.after is None or m.after[0] != beta or m.after[1] != until:
            arr = self.readings.since(m.time_ns)
            arr = arr[arr[:, 0] <= until]
            values, worst, a_p = self._side(arr, math.log(m.u_after), beta)
            m.after = [beta, until, len(values), float(values.sum()), worst]
            m.after += [a_p[0] * len(values), a_p[1] * len(values)]
        _, _, n_a, total, a_worst, p_sum, dp_sum = m.after
        n_b = len(b_values)
        if not (n_a and n_b):
            return _Windows(n_b, int(n_a), 0.0, 0.0, 0.0, 0.0)
        d_p = p_sum / n_a - b_p[0]
        d_dp = dp_sum / n_a - b_p[1]
        d = total / n_a - b_mean
        return _Windows(
            n_b,
            int(n_a),
            d,
            max(b_worst, a_worst),
            d_p if math.isfinite(d_p) else 0.0,
            d_dp if math.isfinite(d_dp) else 0.0,
        )

    def _extend(self, t: int, lq: float, lu: float, lp: float, ldp: float) -> None:
        """Add the reading at ``t`` to the window after each pending move whose window is
        kept at the elasticity in use (the others are made afresh when tested)."""
        fit = self._fit
        for m in self.pending:
            a = m.after
            if fit is None or a is None or a[0] != fit[0] or m.decided:
                continue
            moved = lu - math.log(m.u_after)
            a[1] = t
            a[2] += 1
            a[3] += lq - a[0] * moved
            a[4] = max(a[4], abs(moved))
            a[5] += lp
            a[6] += ldp

    @staticmethod
    def _side(
        arr: np.ndarray, ref: float, beta: float
    ) -> tuple[np.ndarray, float, tuple[float, float]]:
        """One window's log rates moved to the reading ``ref`` (log), the largest move, and
        its mean log p_up and log(p_up - p_down) (NaN where one is unknown)."""
        if not len(arr):
            return arr[:, 1], 0.0, (math.nan, math.nan)
        moved = arr[:, 3] - ref
        means = arr[:, 4:6].mean(axis=0)
        return (
            arr[:, 1] - beta * moved,
            float(np.abs(moved).max()),
            (float(means[0]), float(means[1])),
        )

    def _record_latest(self, t: int) -> None:
        """The latest move's level ends at ``t`` (another move, a break): its response is
        complete."""
        if self.pending:
            self._record(self.pending[-1], t)

    def _record(self, m: _Move, t: int) -> None:
        """Keep the response of move ``m`` (its level up to ``t`` or its window's end) for
        the well's elasticity and spread, once; not while an offset is open or for a move
        that raised one."""
        if m.recorded:
            return
        m.recorded = True
        if m.decided or self.open is not None:
            return
        b, a = self._windows(m, min(t, m.time_ns + self.window_ns))
        if len(b) < MIN_READINGS or len(a) < MIN_READINGS:
            return
        ss = float(((b - b.mean()) ** 2).sum() + ((a - a.mean()) ** 2).sum())
        s = math.sqrt(ss / (len(b) + len(a) - 2))
        self.moves.append((m.dlu, float(a.mean() - b.mean()), len(b), len(a), s))
        self._fit, self._no_fit = None, False

    # -- the well's elasticity and spread -------------------------------------------------------
    def fit(self) -> tuple[float, float, float, float, float] | None:
        """``(beta, s, omega, kappa, se_beta)`` from the complete moves (None before
        :data:`MIN_MOVES` of them, or with fewer than half that many of 1 % or more)."""
        if self._fit is not None or self._no_fit:
            return self._fit
        self._no_fit = True  # until the next complete move
        if len(self.moves) < MIN_MOVES:
            return None
        arr = np.asarray(self.moves, dtype=float)
        dlu, d, nb, na, s_each = arr.T
        big = np.abs(dlu) >= _MIN_MOVE
        if big.sum() < MIN_MOVES // 2:
            return None
        s = _median_of_any(s_each)
        se2 = s * s * (1.0 / nb + 1.0 / na)
        beta, se_beta = _huber_slope(dlu, d, se2)
        base = se2 + (se_beta * dlu) ** 2
        omega, kappa = _omega_kappa(d - beta * dlu, base)
        self._fit = (beta, s, omega, kappa, se_beta)
        return self._fit

    def moves_per_year(self) -> float:
        """The well's choke moves per year over its last 400 moves (at least 12)."""
        if len(self.move_times) < 2:
            return _MIN_MOVES_PER_YEAR
        span = (self.move_times[-1] - self.move_times[0]) / _NS_PER_DAY / 365.25
        return max(_MIN_MOVES_PER_YEAR, (len(self.move_times) - 1) / max(span, 1.0 / 12))

    def limit(self, looks: int) -> float:
        """The shortfall a move must reach: the one-sided Gaussian quantile of this test's
        share per move and look."""
        alpha = self.share / self.moves_per_year() / max(1, min(looks, _MAX_LOOKS))
        return _quantile(round(1.0 - alpha, 12))

    def _looks(self) -> int:
        """The looks at one move: the rate readings its window holds at the well's own rate
        of readings, from the :data:`MIN_READINGS`-th on (kept until the next reading)."""
        if self._looks_at[0] == self.readings.version:
            return self._looks_at[1]
        looks = self._count_looks()
        self._looks_at = (self.readings.version, looks)
        return looks

    def _count_looks(self) -> int:
        arr = self.readings.since(
            self.readings.buf[max(self.readings.n - 1, 0), 0] - 3 * self.window_ns
        )
        if len(arr) < 2:
            return _MAX_LOOKS
        span = max(float(arr[-1, 0] - arr[0, 0]), 1.0)
        per_window = (len(arr) - 1) * self.window_ns / span
        return int(per_window) - MIN_READINGS + 1

    # -- the test -------------------------------------------------------------------------------
    def _test(self, m: _Move, t: int) -> ChokeFinding | None:
        fit = self.fit()
        if fit is None or fit[0] <= _MIN_BETA:
            return None
        beta, s, omega, kappa, se_beta = fit
        win = self._adjusted(m, t, beta)
        n_b, n_a = win.n_before, win.n_after
        d = win.d
        dlu = m.dlu
        expected = beta * dlu
        # in doubt from the first reading after the move: its response is nearer none than
        # the expected one, and the move is one the readings can tell (the expected response
        # beyond three sd of the means' noise)
        m.doubt = (
            n_b >= MIN_READINGS
            and n_a >= 1
            and abs(d) < abs(d - expected)
            and abs(expected) > 3.0 * s * math.sqrt(1 / n_b + 1 / n_a)
        )
        if n_b < MIN_READINGS or n_a < MIN_READINGS:
            return None
        sign = math.copysign(1.0, dlu)
        noise = s * s * (1 / n_b + 1 / n_a) + omega * omega + (se_beta * win.other) ** 2
        sigma = kappa * math.sqrt(noise + (se_beta * dlu) ** 2)
        # the most of the shortfall the pressures' own change could explain: the rate
        # follows p_up with an exponent of at most one (critical flow) and the pressure
        # drop with at most a half (Bernoulli, subcritical); the regime is not known here
        explained = min(0.0, sign * win.d_log_p_up) + 0.5 * min(0.0, sign * win.d_log_dp)
        z = ((expected - d) * sign + explained) / sigma
        z_lim = self.limit(self._looks())
        # short of the response beyond chance, and no change beyond chance itself: the rate
        # did what it does when nothing moved (a rate that fell for another reason is not it)
        if not (z > z_lim and abs(d) <= _Z_NONE * kappa * math.sqrt(noise)):
            return None
        if self._stepped_after(m, t, beta, s):
            return None  # the rate stepped after the move: its response is not measurable
        m.decided = True
        text = (
            f"the choke's reading moved {m.u_before:.4g} -> {m.u_after:.4g} "
            f"({100 * (math.exp(dlu) - 1):+.1f} %) at {iso(m.time_ns)}, but the measured rate "
            f"did not follow: {100 * (math.exp(d) - 1):+.1f} % over {n_a} meter readings "
            f"after it against {n_b} before"
            + (f" (the rate's level since {iso(m.level_ns)})" if m.level_ns else "")
            + f", where the well's last {len(self.moves)} "
            f"choke moves (elasticity {beta:.2f}) say {100 * (math.exp(expected) - 1):+.1f} % "
            f"(short by {z:.1f} sd, threshold {z_lim:.1f})."
        )
        if self.open is not None and dlu * self.open.dlu < 0:
            self.open = None
            return ChokeFinding(
                "close", m.time_ns, t, f"The reading came back without the rate: {text}"
            )
        if self.accepted is not None and dlu * self.accepted < 0:
            # the end of an offset taken as real (its transmitter set right): not a new one
            self.accepted = None
            return ChokeFinding(
                "close", m.time_ns, t, f"An accepted offset ended, the reading back: {text}"
            )
        self.open = m
        # where the choke is: at the old opening (the test found the response within chance
        # of none; taking d / beta as a move instead put the stand-in off by that noise over
        # the elasticity, 7.5 % on a well of elasticity 0.71 whose rate dipped 5.4 %)
        where = m.u_before
        self.open_shift = m.u_after - where
        after = self.readings.since(m.time_ns)
        after = after[after[:, 2] == m.segment]
        self.open_ref.clear()
        self.open_ref.extend((after[:, 1] - beta * math.log(where)).tolist())
        self.open_level = []
        return ChokeFinding(
            "raise",
            m.time_ns,
            t,
            text[0].upper() + text[1:] + " The position reading, not the choke, seems to "
            "have moved: an offset of the choke's transmitter, or a choke that no longer "
            "answers its actuator.",
            shift=m.u_after - where,
            shift_sd=where * kappa * math.sqrt(noise) / beta,
        )

    def _stepped_after(self, m: _Move, until: int, beta: float, s: float) -> bool:
        """Did the rate step against the move's expected response within its window after
        it (up to ``until``, ns), with the choke reading still (a sand event that raised
        C_D a day after the operator closed in)? Then the window mixes two levels and the
        response looks short though the choke moved (:func:`_latest_level`). Asked only
        before a raise."""
        arr = self.readings.since(m.time_ns)
        arr = arr[(arr[:, 0] <= until) & (arr[:, 2] == m.segment)]
        values = self._side(arr, math.log(m.u_after), beta)[0]
        return _latest_level(values, s, -math.copysign(1.0, m.dlu)) > 0

    def doubted(self, time_ns: int) -> _Move | None:
        """The latest undecided move at or before ``time_ns`` (epoch ns) whose rate has so
        far answered nearer none than the response its reading asks for: a reading paired
        with a sample after it may carry an offset that the test has not decided yet (it
        needs :data:`MIN_READINGS` readings). None when no move is in doubt."""
        t = int(time_ns)
        for m in reversed(self.pending):
            if m.time_ns <= t and m.doubt and not m.decided:
                return m
        return None

    def accept(self) -> None:
        """The caller closed the open offset after its acceptance time: the reading is
        taken as the choke's. Its direction is kept: a later move of the reading back that
        the rate does not follow is that offset's end (the transmitter set right), not a
        new offset."""
        if self.open is not None:
            self.accepted = self.open.dlu
        self.open = None

    # -- state ----------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Plain JSON values to resume from."""

        def mv(m: _Move | None) -> list[Any] | None:
            if m is None:
                return None
            return [m.time_ns, m.u_before, m.u_after, m.segment, m.decided, m.recorded, m.doubt]

        return {
            "u": self.u,
            "last_ns": self.last_ns,
            "segment": self.segment,
            "closed_segment": self.closed_segment,
            "pending": [mv(m) for m in self.pending],
            "open": mv(self.open),
            "open_shift": self.open_shift,
            "accepted": self.accepted,
            "open_ref": list(self.open_ref),
            "open_level": [list(v) for v in self.open_level],
            "readings": [  # NaN (no pressure) as null: plain JSON
                [int(r[0]), float(r[1]), int(r[2]), float(r[3])]
                + [float(x) if math.isfinite(x) else None for x in r[4:]]
                for r in self.readings.since(-math.inf).tolist()
            ],
            "moves": [list(r) for r in self.moves],
            "move_times": list(self.move_times),
        }

    def restore(self, data: Mapping[str, Any]) -> None:
        """Resume from :meth:`state`."""

        def mv(v: Any) -> _Move | None:
            if v is None:
                return None
            m = _Move(int(v[0]), float(v[1]), float(v[2]), int(v[3]), bool(v[4]), bool(v[5]))
            m.doubt = bool(v[6]) if len(v) > 6 else False  # absent from older checkpoints
            return m

        self.u = None if data.get("u") is None else float(data["u"])
        self.last_ns = None if data.get("last_ns") is None else int(data["last_ns"])
        self.segment = int(data.get("segment", 0))
        self.closed_segment = int(data.get("closed_segment", 0))
        self.pending.clear()
        self.pending.extend(m for m in (mv(v) for v in data.get("pending", [])) if m is not None)
        self.open = mv(data.get("open"))
        self.open_shift = float(data.get("open_shift", 0.0))  # absent from older checkpoints
        accepted = data.get("accepted")
        self.accepted = None if accepted is None else float(accepted)
        self.open_ref.clear()
        self.open_ref.extend(float(v) for v in data.get("open_ref", []))
        self.open_level = [(int(a), float(b), float(c)) for a, b, c in data.get("open_level", [])]
        self.readings.clear()
        for r in data.get("readings", []):
            row = (int(r[0]), float(r[1]), int(r[2]), float(r[3]), _num(r[4]), _num(r[5]))
            self.readings.append(row, -math.inf)
        self.moves.clear()
        self.moves.extend(
            (float(a), float(b), int(c), int(d), float(e))
            for a, b, c, d, e in data.get("moves", [])
        )
        self.move_times.clear()
        self.move_times.extend(int(t) for t in data.get("move_times", []))
        self._fit, self._no_fit = None, False
