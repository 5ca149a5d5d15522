"""Does the measured rate follow the pressure readings? A witness for a slow pressure drift.

A transmitter that drifts a few percent a week looks, from its own history, like the
well's own slow wander: the input-only ``drift`` test of :mod:`vfm_core.sensor_faults`
finds a ``p_up`` drift of 20 % a month within a week in a few wells in a hundred. The
well's measured rate can tell them apart: when ``p_up`` really rises, the rate rises with
it; when only its reading rises, the rate stays. :class:`PressureWitness` watches one
well's daily mean log MPFM rate against the daily mean logs of its inputs and raises a
``drift`` of a pressure whose reading ramps one way while the rate ramps the other.

The model, per well and free of any rate model or learning method (like
:mod:`vfm_core.rate_witness`, so ``vfm evaluate`` can plan it once for every model):

* **Daily means** of ``log q`` (the MPFM readings of a UTC day) and, over the same paired
  samples, of ``log choke``, ``log p_up`` and ``log(p_up - p_down)``
  (:data:`LOG_INPUTS`; ``log p_down`` follows from the last two). Logs because near a
  working point every choke law is a product of powers of these: critical flow
  ``q ~ C(u) p_up^a``, subcritical ``q ~ C(u) sqrt(rho dp)``; the exponents are
  elasticities. ``t_up`` is left out: the rate answers it by at most ``T^-1/2`` in kelvin
  (a 10 % drift of 60 degC moves it under 1 %), below a week's noise, and ``t_up``
  answers the rate (its pull on the flowing temperature), which would teach a regression
  the wrong way round. The fractions are left out for the same reason.
* **The rate's series**: ``r = log q - b_u log u - b_p log p_up - b_pd log p_down - c t``.
  ``b_p`` is *not* learned: it is :data:`P_UP_ELASTICITY` (1/2), the least elasticity to
  ``p_up`` (``p_down`` held) of every choke law (critical flow ``a`` from 1/2, liquid, to
  1, gas; subcritical at least ``(p_up / dp) / 2``). The data cannot learn it: beside the
  choke a well's ``p_up`` changes from day to day by about as much as its reading's
  noise, so a regression on its changes is pulled towards zero (errors in the
  variables), and a value taken too large would make every real ``p_up`` change the rate
  follows look like a drift. ``b_u``, ``b_pd`` and the trend ``c`` (the well's decline:
  not news) are learned by a Huber regression (``c = 1.345``) of the day-to-day changes
  of ``log q - b_p log p_up`` on those of ``log u`` and ``log p_down`` over the last
  ``history_days`` (changes between days at most 3 days apart, none from inside an
  open finding), refitted every ``refit_days``; ``b_pd`` is then moved towards zero by
  two standard errors and kept at most 0 (the smallest answer to ``p_down`` the data
  allow, for the same reason). Changes, not levels: the rate's level wanders (the choke's
  wear, the gas-oil ratio, the meter's own drift) and changes are free of it.
* **Each pressure's own series**: ``log p_up`` (and ``log p_down``) less its answer to
  the choke (the drawdown; Huber on the changes, with a trend): what the reading does
  that the operator did not do.
* **The spread of each series**: a random walk (the wander, sd ``sigma_w`` per
  square-root day) plus the daily mean's noise (``sigma_e``), calibrated on the well's own
  series by the variogram: the robust variance (1.4826 MAD, squared) of the ``k``-day
  differences is ``2 sigma_e^2 + k sigma_w^2`` (``k`` = 1 to the days a test spans,
  reference and window: the wander is a small part of a few days' differences and shows
  over the lags it acts on; least squares, each part at least 0).
* **The ramp statistic** of a series, each closed day once ``min_days`` changes are in:
  a ramp starting ``n`` days ago (``n`` = 3..``window_days``) against the series' level
  over the ``reference_days`` before it, ``Z_n = sum_j j (y_(t-n+j) - mean y_ref) / sd``,
  with ``sd`` exact under the random walk plus noise (the days' real spacing counted),
  divided by ``kappa``: the robust sd of the past days' ``Z`` (at ``n`` = 4, 7 and
  ``window_days``), at least 1 (as the choke witness's ``kappa``).
* **The test** (a pair): a drift of a pressure's reading moves its own series one way
  and the rate's series the way the rate's elasticity asks (``-b_p`` or ``-b_pd`` times
  it): a ``p_up`` reading drifting up raises ``Z`` of ``p_up`` and lowers the rate's. A
  real ``p_up`` change moves both up (the rate follows by at least ``b_p``): never the
  pair of a drift. A finding when, for some ``n``, both statistics pass ``z_lim`` in a
  drift's directions. Under no drift the meter's noise and the input's own wander are
  independent, so the pair's probability is the product of the two; ``z_lim`` is the
  one-sided Gaussian quantile of the square root of ``share / 2 / 365.25 / (2 (N - 2))``:
  half the share for each pressure, per day, split (Bonferroni, conservative: the looks
  share their days) over both signs and the ``N - 2`` onsets.
* **Which input**: the pressure of the pair with the largest smaller statistic, if its
  reading's ramp times its elasticity explains at least half of the rate's ramp (the
  contrast's slopes): a rate that moved on its own (the meter, the well) with a small move
  of the reading beside it is not named.
* **The finding** is a ``drift`` of that input from the ramp's first day. While it is
  open the witness does not learn (its days carry the drift) and does not test; it
  closes when the rate's series, over the last 3 days, is back within half the deviation
  it had when raised (a transmitter set right), or when the caller accepts it
  (:meth:`PressureWitness.accept`: the new level is taken as real).

What it cannot see: a drift of an input the rate does not answer (``p_down`` in critical
flow, where ``b_pd`` is 0; ``t_up``); one slower than the rate's residual noise and
wander allow: taking the least elasticity to ``p_up`` halves the rate's answer to a
``p_up`` drift of a well in critical gas flow, and on the simulated fields the rate's
series wanders 0.2-0.6 % a square-root day beside 1.2-3.7 % of a day's noise, so a
20 %-a-month drift needs weeks (the detection table in ``docs/guide/sensor-faults.md``);
and any well without a frequent meter.

The entry points: :meth:`PressureWitness.rate` takes each MPFM reading with its paired
sample's inputs and closes a day when a later day's reading arrives;
:meth:`PressureWitness.day` takes a closed day's means directly. Both return a
:class:`PressureFinding` or None. :meth:`~PressureWitness.state` /
:meth:`~PressureWitness.restore` give and take plain JSON values.

>>> import numpy as np
>>> rng = np.random.default_rng(3)
>>> w = PressureWitness(share=0.01)
>>> found = []
>>> for d in range(400):
...     lu = np.log(0.5) + 0.2 * np.sin(d / 9.0)  # the choke moves
...     lp = np.log(100.0) - 0.0003 * d + 0.004 * rng.standard_normal()
...     ldp = lp + np.log(0.7)
...     lq = np.log(500.0) + 0.9 * (lu - np.log(0.5)) + (lp - np.log(100.0))
...     lq += 0.02 * rng.standard_normal()
...     if d >= 350:
...         lp += 0.2 * (d - 350) / 30  # the reading drifts up 20 % a month
...         ldp = lp + np.log(1.0 - 0.3 * 100.0 / np.exp(lp))
...     f = w.day(d, lq, (lu, lp, ldp))
...     if f is not None:
...         found.append((f.action, f.sensor, d - 350))
>>> found[0][:2], found[0][2] <= 14
(('raise', 'p_up'), True)
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

__all__ = [
    "LOG_INPUTS",
    "P_UP_ELASTICITY",
    "PressureFinding",
    "PressureWitness",
]

#: the daily mean logs the rate is regressed on, in this order
LOG_INPUTS: tuple[str, ...] = ("log choke", "log p_up", "log(p_up - p_down)")
_NS_PER_DAY = 86_400 * 10**9
_MAD_TO_SD = 1.4826
_HUBER_C = 1.345  # 95 % efficiency at the Gaussian
_MAX_GAP_DAYS = 3  # a change across a longer gap is not a day-to-day change
_MIN_PAIRS = 20  # k-day differences a variogram point needs
_MIN_DP = 1e-3  # the pressure drop's floor, a share of p_up (a log needs it positive)
_CLOSED_CHOKE = 1e-3
_CLOSE_DAYS = 3  # days whose mean residual must be back for a finding to close
_MIN_REFERENCE = 7  # observed days the reference level needs
_KAPPA_N = (4, 7)  # ramp lengths whose past values calibrate kappa (with window_days)
_SENSORS = ("p_up", "p_down")
#: the rate's least elasticity to p_up with p_down held, in every regime of a choke law:
#: critical flow q ~ p_up^a with a from 1/2 (liquid) to 1 (gas); subcritical
#: q ~ sqrt(rho dp), at least (dp)^(1/2) with d log dp / d log p_up = p_up / dp > 1
P_UP_ELASTICITY = 0.5


@dataclass
class PressureFinding:
    """What the witness found on a closed day: ``"raise"`` a ``drift`` of ``sensor`` that
    began on ``start_day`` (days since the epoch, UTC), or ``"close"`` the open one;
    ``day`` is the day that decided it, ``z`` the ramp statistic over its limit (in sd)
    and ``evidence`` a sentence with the numbers."""

    action: str
    sensor: str
    start_day: int
    day: int
    z: float
    evidence: str

    @property
    def start_ns(self) -> int:
        """The first day of the drift, epoch ns (midnight UTC)."""
        return self.start_day * _NS_PER_DAY

    @property
    def time_ns(self) -> int:
        """The end of the day that decided it, epoch ns."""
        return (self.day + 1) * _NS_PER_DAY


@dataclass
class _Fit:
    """One series' model: its coefficients (``rate``: trend per day, ``b_u``, ``b_p``,
    ``b_dp``; a pressure: trend per day, answer to log choke), the variance of a day's
    noise ``var_e`` and of its wander per day ``var_w`` (log units squared), and ``kappa``."""

    coef: np.ndarray
    var_e: float
    var_w: float
    kappa: float


def _log_p_down(vals: np.ndarray) -> np.ndarray:
    """log p_down from the daily mean log p_up and log(p_up - p_down) (columns 2, 3)."""
    return np.log(np.maximum(np.exp(vals[:, 2]) - np.exp(vals[:, 3]), 1e-9))


def _slope_se(x: np.ndarray, resid: np.ndarray, j: int) -> float:
    """The standard error of coefficient ``j`` of a regression on ``x``: the residuals'
    robust sd times ``sqrt((X'X)^-1_jj)``."""
    try:
        inv = np.linalg.inv(x.T @ x)
    except np.linalg.LinAlgError:
        return math.inf
    return _robust_sd(resid) * math.sqrt(max(float(inv[j, j]), 0.0))


def _with_p_down(vals: np.ndarray) -> np.ndarray:
    """The daily values with log p_down as a fifth column."""
    return np.column_stack([vals, _log_p_down(vals)])


@lru_cache(maxsize=256)
def _quantile(p: float) -> float:
    return NormalDist().inv_cdf(p)


def _robust_sd(x: np.ndarray) -> float:
    med = float(np.median(x))
    return _MAD_TO_SD * float(np.median(np.abs(x - med)))


def _huber(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Coefficients of ``y = x beta`` by iteratively reweighted least squares with Huber's
    weights (a day that met another change of the well weighs less)."""
    w = np.ones(len(y))
    beta = np.zeros(x.shape[1])
    for _ in range(30):
        sw = np.sqrt(w)
        new, *_ = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)
        done = bool(np.max(np.abs(new - beta)) < 1e-7)
        beta = new
        if done:
            break
        r = y - x @ beta
        scale = max(_robust_sd(r), 1e-9)
        w = np.minimum(1.0, _HUBER_C * scale / np.maximum(np.abs(r), 1e-12))
    return beta


class PressureWitness:
    """One well's test of whether the measured rate follows its pressure readings (see the
    module docstring). ``share``: false findings per well-year this test may raise;
    ``window_days``: the longest ramp tested (days); ``reference_days``: the days before a
    ramp whose mean residual is its reference; ``history_days``: the days of changes the
    elasticities and the spread are learned from; ``min_days``: changes before the test
    runs; ``refit_days``: days between refits of the elasticities and the spread."""

    def __init__(
        self,
        share: float,
        window_days: int = 14,
        reference_days: int = 28,
        history_days: int = 365,
        min_days: int = 60,
        refit_days: int = 28,
    ) -> None:
        if not (math.isfinite(share) and share > 0):
            raise ConfigError(f"share must be a positive number per well-year, got {share}.")
        if not 4 <= int(window_days) <= 60:
            raise ConfigError(f"window_days must lie in 4..60 days, got {window_days}.")
        if not _MIN_REFERENCE <= int(reference_days) <= 180:
            raise ConfigError(
                f"reference_days must lie in {_MIN_REFERENCE}..180 days, got {reference_days}."
            )
        if not 60 <= int(history_days) <= 1000:
            raise ConfigError(f"history_days must lie in 60..1000 days, got {history_days}.")
        if not 30 <= int(min_days) <= int(history_days):
            raise ConfigError(
                f"min_days must lie in 30..history_days ({history_days}), got {min_days}."
            )
        if not 1 <= int(refit_days) <= 90:
            raise ConfigError(f"refit_days must lie in 1..90 days, got {refit_days}.")
        self.share = float(share)
        self.window_days = int(window_days)
        self.reference_days = int(reference_days)
        self.history_days = int(history_days)
        self.min_days = int(min_days)
        self.refit_days = int(refit_days)
        onsets = self.window_days - 2
        #: each of the pair's limit (|Z| / kappa): their joint probability per day, for each
        #: pressure (half the share), sign and onset (Bonferroni), is its square
        alpha = self.share / 2.0 / 365.25 / (2 * onsets)
        self.z_lim = _quantile(round(1.0 - math.sqrt(alpha), 15))
        self._reset()

    def _reset(self) -> None:
        keep = self.history_days + self.reference_days + self.window_days + 1
        #: closed days: (day, mean log q, mean log choke, log p_up, log dp, in a finding)
        self.days: deque[tuple[int, float, float, float, float, bool]] = deque(maxlen=keep)
        #: the open day's sums: [day, n, log q, log choke, log p_up, log dp]
        self.today: list[float] | None = None
        #: the open finding: sensor, first day, reference level, deviation when raised
        self.open: tuple[str, int, float, float] | None = None
        self.last_fit_day: int | None = None
        #: per series (``rate``, ``p_up``, ``p_down``) its fit, once learned
        self.fit: dict[str, _Fit] | None = None

    # -- the protocol -----------------------------------------------------------------------
    def rate(
        self, time_ns: int, q: float, choke: float, p_up: float, p_down: float
    ) -> PressureFinding | None:
        """Feed one MPFM rate (Sm3/h, in time order) with its paired sample's ``choke``
        (fraction open), ``p_up`` and ``p_down`` (bar a). The readings of a UTC day are
        averaged (in logs); the first reading of a later day closes it and tests it
        (:meth:`day`). A reading with a closed choke, a non-positive rate or pressure, or
        out of time order is not taken."""
        if not all(math.isfinite(v) for v in (q, choke, p_up, p_down)):
            return None
        if q <= 0 or choke <= _CLOSED_CHOKE or p_up <= 0:
            return None
        day = int(time_ns) // _NS_PER_DAY
        found = None
        t = self.today
        if t is not None and day < t[0]:
            return None
        if t is not None and day != t[0]:
            n = t[1]
            found = self.day(int(t[0]), t[2] / n, (t[3] / n, t[4] / n, t[5] / n))
            t = None
        if t is None:
            t = self.today = [float(day), 0.0, 0.0, 0.0, 0.0, 0.0]
        dp = max(p_up - p_down, _MIN_DP * p_up) if math.isfinite(p_down) else math.nan
        row = (math.log(q), math.log(choke), math.log(p_up), math.log(dp))
        t[1] += 1
        for i, v in enumerate(row):
            t[2 + i] += v
        return found

    def day(
        self, day_index: int, mean_log_q: float, mean_log_inputs: Sequence[float]
    ) -> PressureFinding | None:
        """Feed one closed day (``day_index``: days since the epoch, UTC, increasing): the
        mean of its MPFM readings' ``log q`` (q in Sm3/h) and the means of the paired
        samples' :data:`LOG_INPUTS` (choke as a fraction, pressures in bar a). Returns a
        finding raised or closed by it, or None."""
        d = int(day_index)
        x = [float(v) for v in mean_log_inputs]
        if len(x) != len(LOG_INPUTS) or not all(map(math.isfinite, [mean_log_q, *x])):
            return None
        if self.days and d <= self.days[-1][0]:
            return None
        self.days.append((d, float(mean_log_q), x[0], x[1], x[2], self.open is not None))
        if self.last_fit_day is None or d - self.last_fit_day >= self.refit_days:
            if self.open is None:
                self._refit(d)
        if self.fit is None:
            return None
        if self.open is not None:
            return self._check_close(d)
        return self._test(d)

    def accept(self) -> None:
        """The caller closed the open finding (after its accept time): the new level is
        taken as real and the witness learns again from the next day."""
        self.open = None
        self.last_fit_day = None

    # -- the model --------------------------------------------------------------------------
    def _arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        arr = np.asarray(self.days, dtype=float)
        return arr[:, 0], arr[:, 1:5], arr[:, 5] > 0

    def _refit(self, d: int) -> None:
        """Learn the rate's elasticities and each series' spread from the history."""
        days, vals, flagged = self._arrays()
        keep = (days > d - self.history_days) & ~flagged
        days, vals = days[keep], vals[keep]
        if len(days) < 2:
            return
        gap = np.diff(days)
        ok = gap <= _MAX_GAP_DAYS
        if ok.sum() < self.min_days:
            return
        dv = np.diff(_with_p_down(vals), axis=0)[ok]
        g = gap[ok]
        # the rate less its least answer to p_up (see P_UP_ELASTICITY: the data cannot
        # tell more, p_up's own changes beside the choke are mostly its reading's noise),
        # on the choke and p_down, with an intercept per day between the two days (the
        # well's own trend)
        target = dv[:, 0] - P_UP_ELASTICITY * dv[:, 2]
        design = np.column_stack([g, dv[:, 1], dv[:, 4]])
        c, b_u, b_pd = _huber(design, target)
        # the smallest answer to p_down the data allow (one-sided 97.7 %), never a rise:
        # an answer taken too large would make a real p_down change look like a drift
        b_pd = min(0.0, b_pd + 2.0 * _slope_se(design, target - design @ [c, b_u, b_pd], 2))
        c, b_u = _huber(design[:, :2], target - b_pd * dv[:, 4])
        coefs = {"rate": np.array([c, b_u, P_UP_ELASTICITY, b_pd])}
        # each pressure's own level, less its answer to the choke (the drawdown) and its
        # trend: what the reading does that the operator did not do
        for col, name in ((2, "p_up"), (4, "p_down")):
            coefs[name] = _huber(np.column_stack([g, dv[:, 1]]), dv[:, col])
        fits: dict[str, _Fit] = {}
        levels: dict[str, np.ndarray] = {}
        for name, coef in coefs.items():
            levels[name] = self._levels(name, coef, days, vals)
            spread = self._spread(days, levels[name])
            if spread is None:
                return
            fits[name] = _Fit(coef, spread[0], spread[1], 1.0)
        for name, kappa in self._kappas(days, levels, fits).items():
            fits[name].kappa = kappa
        self.fit = fits
        self.last_fit_day = d

    @staticmethod
    def _levels(name: str, coef: np.ndarray, days: np.ndarray, vals: np.ndarray) -> np.ndarray:
        """The residual levels of series ``name`` (``rate``, ``p_up``, ``p_down``) on
        ``days`` from the daily values ``vals`` (columns: log q, log choke, log p_up,
        log dp)."""
        if name == "rate":
            x = np.column_stack([vals[:, 1:3], _log_p_down(vals)])
            return vals[:, 0] - x @ coef[1:] - coef[0] * days
        own = vals[:, 2] if name == "p_up" else _log_p_down(vals)
        return own - coef[1] * vals[:, 1] - coef[0] * days

    def _spread(self, days: np.ndarray, r: np.ndarray) -> tuple[float, float] | None:
        """``(sigma_e^2, sigma_w^2)`` of residual levels ``r`` by their variogram."""
        lags, v = [], []
        # every lag a test's contrast spans: the wander's slope is a small part of the
        # variance at a few days' lag, and shows only over the lags it acts on
        for k in range(1, self.reference_days + self.window_days + 1):
            pos = np.minimum(np.searchsorted(days, days + k), len(days) - 1)
            i = np.flatnonzero(days[pos] == days + k)
            if len(i) >= _MIN_PAIRS:
                lags.append(k)
                v.append(_robust_sd(r[pos[i]] - r[i]) ** 2)
        if len(lags) < 3:
            return None
        lag, var = np.asarray(lags, float), np.asarray(v)
        slope = max(0.0, float(np.polyfit(lag, var, 1)[0]))
        nugget = max(float(np.mean(var - slope * lag)), 1e-12)
        return nugget / 2.0, slope

    def _contrast(
        self, days: np.ndarray, end: int, n: int
    ) -> tuple[np.ndarray, float, float] | None:
        """The ramp contrast of a ramp of ``n`` days ending at index ``end`` (inclusive):
        weights on the last ``len(weights)`` days up to ``end`` (the reference's days
        first), and the factors of ``sigma_e^2`` and ``sigma_w^2`` in its variance under
        the random walk plus noise (the days' real spacing counted), or None without
        enough reference days."""
        t = days[end]
        first = t - n + 1
        lo_w = int(np.searchsorted(days[: end + 1], first))
        win = days[lo_w : end + 1]
        if len(win) < 2:
            return None
        ref_lo = int(np.searchsorted(days[:lo_w], first - self.reference_days))
        ref = days[ref_lo:lo_w]
        if len(ref) < _MIN_REFERENCE or (first - ref[-1]) > _MAX_GAP_DAYS + 1:
            return None
        j = win - first + 1
        c = np.concatenate([np.full(len(ref), -j.sum() / len(ref)), j])
        tail = np.cumsum(c[::-1])[::-1][1:]  # the sum of the weights after each step
        return c, float((c * c).sum()), float((np.diff(days[ref_lo : end + 1]) * tail**2).sum())

    @staticmethod
    def _z(contrast: tuple[np.ndarray, float, float], r: np.ndarray, end: int, f: _Fit) -> float:
        """The standardised ramp statistic of residual levels ``r`` (before ``kappa``)."""
        c, s_e, s_w = contrast
        var = f.var_e * s_e + f.var_w * s_w
        if var <= 0:
            return math.nan
        return float(c @ r[end + 1 - len(c) : end + 1]) / math.sqrt(var)

    def _kappas(
        self, days: np.ndarray, levels: dict[str, np.ndarray], fits: dict[str, _Fit]
    ) -> dict[str, float]:
        """Each series' robust sd of its past days' ramp statistics (at least 1)."""
        zs: dict[str, list[float]] = {name: [] for name in fits}
        for end in range(0, len(days), 3):  # every third day: neighbours share their days
            for n in (*_KAPPA_N, self.window_days):
                got = self._contrast(days, end, n)
                if got is None:
                    continue
                for name, f in fits.items():
                    z = self._z(got, levels[name], end, f)
                    if math.isfinite(z):
                        zs[name].append(z)
        return {
            name: 1.0 if len(v) < 30 else max(1.0, _robust_sd(np.asarray(v)))
            for name, v in zs.items()
        }

    # -- the test ---------------------------------------------------------------------------
    def _recent(self) -> tuple[np.ndarray, np.ndarray]:
        """The days a test reads (the last reference, window and one) and their values."""
        need = self.reference_days + self.window_days + 1
        arr = np.asarray(list(self.days)[-need:], dtype=float)
        return arr[:, 0], arr[:, 1:5]

    def gains(self) -> dict[str, float]:
        """How the rate the inputs predict answers a drift of each pressure's reading (log
        per log): :data:`P_UP_ELASTICITY` for ``p_up``, the learned ``b_pd`` for
        ``p_down``."""
        assert self.fit is not None
        b_p, b_pd = (float(v) for v in self.fit["rate"].coef[2:4])
        return {"p_up": b_p, "p_down": b_pd}

    def _test(self, d: int) -> PressureFinding | None:
        """Each ramp length: the rate's residual and a pressure's own level both beyond
        ``z_lim``, in the directions a drift of that reading gives; the pair with the
        largest smaller statistic is the finding."""
        assert self.fit is not None
        days, vals = self._recent()
        end = len(days) - 1
        levels = {k: self._levels(k, f.coef, days, vals) for k, f in self.fit.items()}
        gains = self.gains()
        best: tuple[float, int, str, float, float] | None = None
        for n in range(3, self.window_days + 1):
            got = self._contrast(days, end, n)
            if got is None:
                continue
            z = {k: self._z(got, levels[k], end, f) / f.kappa for k, f in self.fit.items()}
            for name in _SENSORS:
                # the reading moved one way, the rate's residual the way that drift asks
                want = -math.copysign(1.0, gains[name] * z[name])
                weaker = min(abs(z[name]), want * z["rate"]) if gains[name] else -math.inf
                if weaker > self.z_lim and (best is None or weaker > best[0]):
                    best = (weaker, n, name, z["rate"], z[name])
        if best is None:
            return None
        return self._locate(days, vals, levels["rate"], best, gains)

    def _slope(self, days: np.ndarray, y: np.ndarray, n: int) -> float:
        """The ramp's slope (per day) of ``y`` over the last ``n`` days against its level
        over the reference days before them: ``sum j (y - ref) / sum j^2``."""
        got = self._contrast(days, len(days) - 1, n)
        if got is None:
            return math.nan
        c = got[0]
        j = c[c > 0]
        return float(c @ y[len(y) - len(c) :]) / float((j * j).sum())

    def _locate(
        self,
        days: np.ndarray,
        vals: np.ndarray,
        r: np.ndarray,
        best: tuple[float, int, str, float, float],
        gains: dict[str, float],
    ) -> PressureFinding | None:
        """The finding, if the reading's trend explains at least half the residual's."""
        _, n, name, z_rate, z_own = best
        s = self._slope(days, r, n)
        own = vals[:, 2] if name == "p_up" else _log_p_down(vals)
        trend = self._slope(days, own, n)
        explained = gains[name] * trend
        if not (explained * s < 0 and abs(explained) >= abs(s) / 2):
            return None
        d = int(days[-1])
        first = d - n + 1
        c = self._contrast(days, len(days) - 1, n)[0]  # type: ignore[index]
        n_ref = int((c < 0).sum())
        ref_mean = float(np.mean(r[len(r) - len(c) : len(r) - len(c) + n_ref]))
        deviation = float(np.mean(r[-_CLOSE_DAYS:])) - ref_mean
        self.open = (name, first, ref_mean, deviation)
        self.days[-1] = (*self.days[-1][:5], True)
        text = (
            f"The measured rate did not follow {name}'s reading: over the {n} days from day "
            f"{first} the reading moved {100 * trend * n:+.1f} % ({abs(z_own):.1f} sd of its "
            f"own wander beside the choke), which by the well's elasticity "
            f"({gains[name]:.2f}) asks the rate for {100 * explained * n:+.1f} %, while the "
            f"rate's residual moved {100 * s * n:+.1f} % ({abs(z_rate):.1f} sd; each beyond "
            f"the threshold {self.z_lim:.1f}). The reading, not the well, seems to drift."
        )
        return PressureFinding("raise", name, first, d, min(abs(z_rate), abs(z_own)), text)

    def _check_close(self, d: int) -> PressureFinding | None:
        assert self.open is not None and self.fit is not None
        name, first, ref_mean, deviation = self.open
        days, vals = self._recent()
        r = self._levels("rate", self.fit["rate"].coef, days, vals)
        now = float(np.mean(r[-_CLOSE_DAYS:]))
        if abs(now - ref_mean) >= 0.5 * abs(deviation):
            return None
        self.open = None
        text = (
            f"The measured rate agrees with {name}'s reading again: the residual's mean over "
            f"the last {_CLOSE_DAYS} days is {100 * (now - ref_mean):+.1f} % from its level "
            f"before the drift (it was {100 * deviation:+.1f} % when raised)."
        )
        return PressureFinding("close", name, first, d, 0.0, text)

    # -- state ------------------------------------------------------------------------------
    def hyperparameters(self) -> dict[str, Any]:
        """The ``__init__`` arguments."""
        return {
            "share": self.share,
            "window_days": self.window_days,
            "reference_days": self.reference_days,
            "history_days": self.history_days,
            "min_days": self.min_days,
            "refit_days": self.refit_days,
        }

    def state(self) -> dict[str, Any]:
        """Plain JSON values to resume from (the fit is made again from the days)."""
        return {
            "days": [[int(d), q, u, p, dp, bool(f)] for d, q, u, p, dp, f in self.days],
            "today": None if self.today is None else list(self.today),
            "open": None if self.open is None else list(self.open),
            "last_fit_day": self.last_fit_day,
        }

    def restore(self, data: Mapping[str, Any]) -> None:
        """Resume from :meth:`state`."""
        self._reset()
        for row in data.get("days", []):
            d, q, u, p, dp, f = row
            self.days.append((int(d), float(q), float(u), float(p), float(dp), bool(f)))
        today = data.get("today")
        self.today = None if today is None else [float(v) for v in today]
        op = data.get("open")
        if op is not None:
            self.open = (str(op[0]), int(op[1]), float(op[2]), float(op[3]))
        if self.days:
            # the fit the saved witness used: made from the same days at the same refit day
            last = data.get("last_fit_day")
            if last is not None:
                saved_open, self.open = self.open, None
                days = self.days
                self.days = deque((r for r in days if r[0] <= int(last)), maxlen=days.maxlen)
                self._refit(int(last))
                self.days, self.open = days, saved_open
                self.last_fit_day = int(last)
