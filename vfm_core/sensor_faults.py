"""Instrument faults per well: frozen, spiking, drifting, offset and out-of-range inputs.

A VFM reads its rate from a handful of transmitters, and they fail in familiar ways (see
``docs/guide/sensor-faults.md``). :class:`WellSensorFaults` watches one well's sensor
samples as they come (streaming, pure: no clock, no I/O) and says which input is suspect,
how, since when and why, as :class:`SensorFault` events. The service keeps one per well
(``GET /wells/{well}`` ``sensor_faults``); ``vfm evaluate`` runs one per well over the whole
study (``sensor_faults.json``); :func:`faults_of_frame` runs it over a frame.

Inputs (units as in :mod:`vfm_core.schema`): ``choke`` (fraction), ``p_up``, ``p_down``
(bar a), ``t_up`` (degC), ``eta_gas``, ``eta_oil`` (mass fractions).

The tests and their thresholds
------------------------------

Every statistical test gets a share of one false-alarm budget: ``false_per_well_year``
(default 0.1, at most one false fault per ten well-years) is split evenly over the
``22`` tests that run per well (frozen on 6 inputs, spike on 5, drift on 5, offset on 5,
and the choke-rate witness).
A test that looks at every sample gets a per-sample false-alarm probability
``alpha = share / samples_per_year``, with the samples per year taken from the well's own
median interval between samples (so the thresholds hold whether a sample comes every
minute or every half day). A test on daily means gets ``share / 365.25`` per day.

* ``out_of_range`` (no statistics): a value outside its physical span (``ranges``;
  choke 0..1, pressures 0..1500 bar a, temperature -60..250 degC, fractions 0..1).
  The event lasts while the value is outside; such a sample feeds no other test.
* ``frozen``: a live transmitter carries noise, so a run of unchanged values (a change of
  at most ``1e-9`` relative) longer than the input's own history makes plausible is a
  stuck transmitter or link. The model is a two-state Markov chain of "unchanged" steps
  fitted to the input's history (exponential memory of ``frozen_memory`` steps, Jeffreys
  priors): ``p0`` = P(unchanged | changed before), ``q`` = P(unchanged | unchanged
  before). A run reaches length ``L`` with probability ``p0 q^(L-1)``; the threshold is the
  smallest ``L >= 3`` with ``p0 q^(L-1) <= alpha``. An input that never repeats (a
  pressure) is frozen after a handful of equal values; one that is constant for weeks by
  nature (a choke between moves, fractions set from a PVT table) needs a run far longer
  than its usual ones. A choke at a bound (0 or 1) and a fraction at 0 are not tested
  (fully open is stuck by design), nor is an input before 50 steps of history. The steps
  of a run that raised an event are not learned.
* ``spike``: one sample that jumps away from both neighbours and comes back. The model is
  the robust spread of the input's one-step changes (``s = 1.4826 MAD`` over the last
  ``spike_window`` changes, none at a choke move, none flagged). Sample ``t`` is a spike
  when ``|x_t - x_(t-1)|`` and ``|x_t - x_(t+1)|`` both exceed ``z s`` on the same side and
  ``x_(t+1)`` came back at least halfway, with ``z`` the two-sided Gaussian quantile of
  ``alpha``, and neither interval is a gap (longer than both 3 median intervals and two
  days: a shut-in or an outage may hide a real change). It is decided when sample ``t+1``
  arrives (and ends there). A jump at a choke
  move is the process answering the operator, not a fault; the choke itself (a set point:
  a manual change of a few hours is one sample up and back) is not tested for spikes.
* ``offset`` (a step of one input): the daily means of each input and two changes of
  them (divided by the square root of the days between, since a process wanders so): one
  day's (against the last day) and two days' (against the day before the last: a
  transmitter that steps in the middle of a day puts half its step into each of two
  one-day changes and the whole into the two days'). The one day's is robust-scaled
  (median, 1.4826 MAD) by the last year's day-to-day changes, the two days' by the last
  year's quiet two-day changes; each is tested at half the daily share. A
  change is a candidate when it is beyond its limit and every day it spans was quiet:
  the choke did not move and no other input's daily mean moved beyond 3 robust sd of its
  own changes (several inputs moving at once is the process changing, not one
  transmitter: the other inputs are the witnesses). The limit is where the tail of the
  input's own quiet changes reaches the share (:meth:`WellSensorFaults._tail_limit`: an
  exponential tail fitted beyond their 90 % quantile, peaks over threshold), never below
  the Gaussian quantile: a process's daily means have heavier tails than a Gaussian of
  their robust sd, and a Gaussian limit on them raised false steps far above the budget.
  A candidate is an offset when the level holds (at least halfway) for two more days.
  The event ends when the level comes back (halfway). A step of ``p_down`` alone is also
  what a separator set-point change looks like from one well's inputs, so a confirmed
  ``p_down`` step is raised only when it is of consequence and the rate says it is the
  transmitter (:meth:`WellSensorFaults._set_point`): not where ``p_down / p_up`` stays
  below the lowest critical ratio of the models' choke laws on both levels
  (:func:`critical_floor`; the rate does not depend on ``p_down`` there, an offset changes
  no predicted rate and nothing tells it from the set point), nor where no choke law with a
  critical ratio at or above that floor lets the step move the rate beyond the noise of
  the meter's means (:func:`p_down_consequence`: just above a critical ratio the rate is
  flat in ``p_down``), nor where the MPFM's rate moved against the step beyond its noise
  (a real change of the back pressure in subcritical flow). Such steps are counted in
  ``set_points``, not raised.
* ``drift``: a self-starting two-sided CUSUM (:class:`vfm_core.residual_alarm.ResidualCusum`:
  robust centre and scale of the last year, Bartlett long-run factor over ``lags`` days,
  ``k = 0.5``) on the same scaled day-to-day changes, with an in-control run length of
  ``365.25 / share`` days: a ramp shifts their mean. Centring on the recent median means
  a well's own slow trend (depletion) is not news; a change of trend is. A ``p_down``
  drift in critical flow (``p_down / p_up`` below :func:`critical_floor` on every day
  since the CUSUM last stood at zero) is counted in ``drifts_set_aside``, not raised: as
  for a step, the rate does not depend on ``p_down`` there
  (:meth:`WellSensorFaults._critical_drift`).
* Drift and offset are not tested on the choke's own readings (its steps are the
  operator's). A choke ``offset`` is found by its witness, the measured rate
  (:mod:`vfm_core.rate_witness`, fed by :meth:`WellSensorFaults.measure`): a move of the
  reading that the MPFM's rate does not follow. It is closed when the rate says the
  reading is right again (a move back with no response, or the well's rate level, also
  after a shut-in when a transmitter is usually set right, matching the reading better
  than the reading less the offset: :mod:`vfm_core.rate_witness`), or after 180 days
  from when it was found (:data:`_CHOKE_ACCEPT_DAYS`): held longer, the model would grow
  stale, so the
  reading is then taken as the choke's and learned from (a later move of it back that the
  rate does not follow is that offset's end, not a new one). While open it is stood in
  for (:meth:`WellSensorFaults.fallbacks`). Until the witness decides a move (it needs three
  readings after it), a measurement whose rate has so far not followed the move is held
  too (:meth:`WellSensorFaults.suspect`): a learner fast enough to follow the measured
  rate learned a 20 % offset's error within the day it took to find it. An input's
  offset or drift open for ``accept_days`` is closed and the new level taken as real (a
  set point that moved; the evidence says so). While one input has an active fault, the others' daily tests pause:
  one fault at a time is located.

What this does not do (yet): use the rate model's residual and its sensitivity to each
input to locate a slow drift that only the measured rate reveals (a ``p_up`` drift that
looks like the well's own decline), or a field-wide comparison of the wells on one
manifold (a separator set-point change moves every well's ``p_down``; a transmitter
offset moves one): in subcritical flow a set-point step the rate's noise hides is still
raised as an offset.

The fallback (keep predicting while an input is flagged)
--------------------------------------------------------

:meth:`WellSensorFaults.fallbacks` gives, for a sample, a :class:`Fallback` per input with
an open fault of :data:`FALLBACK_KINDS` (frozen, out of range): a value to use in its place
(its last live reading moved by the input's own trend, shrunk towards none when the trend
is lost in its noise) and a spread (the sd of the input's day-to-day changes times the
square root of the days since, a random walk's growth, bounded by the physical range).
A choke offset (:data:`FALLBACK_FAULTS`) stands in with the reading less the shift its
witness estimated (where the rate says the choke is), with that estimate's sd.
:func:`fallback_points` and :func:`widened_rates` turn a model's answers at the value and
at the ends of its 90 % span into the rates and a widened interval; the service uses them
(``service/engine/learning.py``, ``Learning.fallback``). While the well's rate is still
measured, each MPFM rate at a stood-in sample is a witness of the input
(:meth:`WellSensorFaults.follow_rate`, :func:`witness_track`): with the model held, one
Kalman step moves the stand-in toward the value at which the model's rate matches the
measured one less the meter's usual bias, by as much as the rate's sensitivity to the
input and its noise allow (nothing where the rate does not depend on it). The rules and their reasons are in
:meth:`WellSensorFaults._anchor` and :meth:`WellSensorFaults.fallbacks`.

Cost: ``benchmarks/bench_detector_cost.py`` measures :meth:`WellSensorFaults.update`
against a prediction's cost, per sample (at 1-3 samples a day nearly every sample closes a
day and runs the daily tests of five inputs; at one a minute the per-sample tests are
most of it). The reference windows are arrays that numpy reads in place, and their
medians, MADs and tail excesses are compiled (:mod:`vfm_core._robust_kernels`: the same
numbers as numpy's, which run instead with ``VFM_KERNELS=0``).

The object follows the project's small protocol: ``update(time_ns, values)`` returns the
events that began or ended at that sample (``measure(time_ns, q_total, values)`` those of
a paired MPFM rate); ``active`` lists the open ones; ``state()`` /
``restore()`` give and take plain JSON values for a checkpoint.

>>> det = WellSensorFaults()
>>> import numpy as np
>>> rng = np.random.default_rng(1)
>>> hour = 3_600 * 10**9
>>> found = []
>>> for i in range(400):
...     x = [0.5, 100 + rng.normal(0, 0.3), 30 + rng.normal(0, 0.2), 60 + rng.normal(0, 0.2),
...          0.1 + rng.normal(0, 1e-3), 0.6 + rng.normal(0, 1e-3)]
...     if i >= 300:
...         x[2] = last_p_down  # p_down stuck at its last reading
...     last_p_down = x[2]
...     found += det.update(i * 12 * hour, x)
>>> [(e.sensor, e.kind) for e in found]
[('p_down', 'frozen')]
"""

from __future__ import annotations

import math
import operator
from array import array
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from statistics import NormalDist
from typing import Any

import numpy as np

from vfm_core import physics
from vfm_core.errors import ConfigError
from vfm_core.rate_witness import MIN_READINGS, ChokeRateWitness
from vfm_core.residual_alarm import ResidualCusum, robust_kernels
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.timeutil import iso

__all__ = [
    "SENSORS",
    "KINDS",
    "HOLD_KINDS",
    "FALLBACK_KINDS",
    "FALLBACK_FAULTS",
    "ALARM_KINDS",
    "ALARM_FAULTS",
    "raises_alarm",
    "HOLD_FAULTS",
    "DEFAULT_RANGES",
    "SensorFault",
    "Fallback",
    "fallback_points",
    "widened_rates",
    "Track",
    "tracked",
    "track_variance",
    "witness_track",
    "residual_noise",
    "WellSensorFaults",
    "faults_of_frame",
    "feed_frame",
    "mpfm_rates",
    "write_sensor_faults",
    "critical_floor",
    "p_down_consequence",
]

#: the sensors watched, in the order of :data:`vfm_core.schema.INPUT_COLUMNS`
SENSORS: tuple[str, ...] = INPUT_COLUMNS
KINDS: tuple[str, ...] = ("frozen", "spike", "drift", "offset", "out_of_range")
#: the kinds whose samples are not learned from (their false-alarm rate was measured within
#: the budget, see docs/guide/sensor-faults.md; an out-of-range value has none: a reading
#: outside the input's physical span is never real); drift and offset are shown, not acted on
HOLD_KINDS: tuple[str, ...] = ("frozen", "spike", "out_of_range")
#: the kinds whose input is replaced by its fallback in predictions while the fault is open:
#: the lasting kinds of :data:`HOLD_KINDS` (a spike is one sample, decided only when the
#: next one arrives)
FALLBACK_KINDS: tuple[str, ...] = ("frozen", "out_of_range")
#: single faults (sensor, kind) that hold learning and stand in though their kind does not:
#: a choke offset, found by the measured rate (vfm_core.rate_witness) with a false rate
#: measured within its share of the budget (docs/guide/sensor-faults.md), and whose size
#: the witness estimates (the stand-in: the reading less that shift). Learning from it
#: would teach the model the transmitter's offset (bayes pulled c_d 0.81 -> 0.73 in two
#: weeks on a 20 % offset).
HOLD_FAULTS: tuple[tuple[str, str], ...] = (("choke", "offset"),)
FALLBACK_FAULTS: tuple[tuple[str, str], ...] = HOLD_FAULTS
#: the kinds that raise an alarm (the page's alarm line, the ``VfmSensorFault`` alert in
#: docker/alerts.yml, a warning in the log), and single (sensor, kind) faults that do though
#: their kind does not: a choke offset, whose false rate was measured within the budget. The
#: others are shown, counted and logged at info, not raised: a spike is one sample, and an
#: input's own offset was raised 0.2-0.5 times a well-year on clean fields (nearly all
#: separator set-point steps of p_down), above the budget of 0.1; with the steps of no
#: consequence and those the rate followed set aside (WellSensorFaults._set_point) it is
#: 0.04-0.06, all kinds together 0.05-0.10 (docs/guide/sensor-faults.md): not decided yet.
ALARM_KINDS: tuple[str, ...] = ("frozen", "out_of_range", "drift")
ALARM_FAULTS: tuple[tuple[str, str], ...] = (("choke", "offset"),)


def raises_alarm(sensor: str, kind: str) -> bool:
    """Whether a fault of ``sensor`` and ``kind`` raises an alarm (:data:`ALARM_KINDS`,
    :data:`ALARM_FAULTS`) rather than being shown only."""
    return kind in ALARM_KINDS or (sensor, kind) in ALARM_FAULTS


#: the kinds whose last trusted level is kept when they are raised (:meth:`fallbacks` can
#: stand in for any of them; the service uses :data:`FALLBACK_KINDS`)
_ANCHOR_KINDS: tuple[str, ...] = ("frozen", "drift", "offset", "out_of_range")

#: physical span of each input (units of the observation format)
DEFAULT_RANGES: dict[str, tuple[float, float]] = {
    "choke": (0.0, 1.0),
    "p_up": (0.0, 1500.0),
    "p_down": (0.0, 1500.0),
    "t_up": (-60.0, 250.0),
    "eta_gas": (0.0, 1.0),
    "eta_oil": (0.0, 1.0),
}
_UNITS = {
    "choke": "",
    "p_up": " bar",
    "p_down": " bar",
    "t_up": " degC",
    "eta_gas": "",
    "eta_oil": "",
}
_CHOKE = 0
_NS_PER_DAY = 86_400 * 10**9
_DEFAULT_INTERVAL_NS = 12 * 3_600 * 10**9  # before the well's own interval is known
_MAD_TO_SD = 1.4826
_SAME = 1e-9  # relative change below which two readings are the same value
_SPIKE_MIN_CHANGES = 30
_FROZEN_MIN_STEPS = 50
# frozen x6, spike x5, drift x5, offset x5 (two changes at half a share each), and the
# choke-rate witness (vfm_core.rate_witness: a choke offset the measured rate reveals)
_N_TESTS = 22
_MIN_DAYS = 30  # day-to-day changes before the drift and offset tests run
_GAP_NS = 2 * 86_400 * 10**9  # an interval above this and 3 median intervals is a gap
_MAX_DAY_GAP = 3  # days; a longer gap starts the day-to-day changes afresh
_CONFIRM_DAYS = 2  # days a step must hold after its day before it is an offset
# days a choke offset stays open (learning held, the reading stood in for) unless the rate
# says the reading is right again: long enough for a transmitter to be set right at a
# planned maintenance, short enough that the held model does not miss a season of the
# well's own change. Taken as real after 30 days (accept_days, as an input's offset),
# offsets of 60 days left mm + bayes 2.1x worse in the 60 days after them than held
# (docs/guide/sensor-faults.md): the model learned the offset, then had to unlearn it.
_CHOKE_ACCEPT_DAYS = 180.0
_CO_MOVE = 3.0  # robust sd of a raw daily change: another input moving with a step excuses it
_LEVEL_DAYS = 64  # closed daily means kept per input: the last trusted level before a fault
_REF_DAYS = 365  # daily changes kept per input: the references of the daily tests
# the step test's tail fit begins at this quantile of the scaled changes: the usual start of
# a peaks-over-threshold fit, far enough out for the tail's law, ~36 excesses in a year
_TAIL_QUANTILE = 0.9
_Z90 = NormalDist().inv_cdf(0.95)  # the half-width of a central 90 % interval, in sd
_MEDIAN_SE = 1.2533  # the standard error of a median of n normal values, in sd / sqrt(n)
# the measured rate as a witness of a stood-in input (:func:`witness_track`): a rate further
# than this many sd of its innovation from the stand-in's is not taken (a bad reading, or a
# model wrong there: one measurement must not move the stand-in across its whole span)
_WITNESS_GATE = 4.0
_WITNESS_MIN_RESIDUALS = 10  # learned log residuals for their spread, else the default
_WITNESS_LOG_SD = 0.05  # an MPFM reading's noise at its worst (5 %): no residuals yet
_WITNESS_MIN_LOG_SD = 0.01  # floor: a reading is seldom better than 1 % (as the review's)
_WANDER_LAG = 30  # days: the lag of the input's variogram that its wander is read at
# A p_down step and the rate (:meth:`WellSensorFaults._set_point`): below the lowest
# critical ratio the models' choke laws give, the rate does not depend on p_down. The
# constant law's p_cr prior (0.55 +- 0.05) at -2 sd; Sachdeva's solved ratio at the well's
# fluid with the fluid priors at +-2 sd in the direction that lowers it.
_P_CR_LOW = physics.PRIORS["p_cr"].mean - 2.0 * physics.PRIORS["p_cr"].std
_FOLLOW_P = 0.01  # a true offset taken for a set-point change by the rate's noise alone
_FOLLOW_DAYS = 7  # days of MPFM readings before a p_down step, at the choke of the step
_P_DOWN = 2


@lru_cache(maxsize=256)
def _z_two_sided(alpha: float) -> float:
    """The two-sided standard normal quantile of a false-alarm probability ``alpha``."""
    return NormalDist().inv_cdf(1.0 - alpha / 2.0)


@dataclass
class SensorFault:
    """One instrument fault: which ``sensor``, what ``kind``, when it began (``start_ns``,
    epoch ns data time; for drift and offset the estimated onset) and ended (``end_ns``,
    None while active), when it was detected (``detected_ns``) and ``evidence`` (a sentence
    with the numbers)."""

    sensor: str
    kind: str
    start_ns: int
    detected_ns: int
    evidence: str
    end_ns: int | None = None

    def as_dict(self) -> dict[str, Any]:
        """The event as the API and ``sensor_faults.json`` show it (ISO 8601 UTC times)."""
        return {
            "sensor": self.sensor,
            "kind": self.kind,
            "start": iso(self.start_ns),
            "end": iso(self.end_ns),
            "evidence": self.evidence,
            "detected": iso(self.detected_ns),
            "alarm": raises_alarm(self.sensor, self.kind),
        }

    def state(self) -> dict[str, Any]:
        return {
            "sensor": self.sensor,
            "kind": self.kind,
            "start_ns": self.start_ns,
            "detected_ns": self.detected_ns,
            "evidence": self.evidence,
            "end_ns": self.end_ns,
        }

    @classmethod
    def from_state(cls, d: Mapping[str, Any]) -> SensorFault:
        end = d.get("end_ns")
        return cls(
            str(d["sensor"]),
            str(d["kind"]),
            int(d["start_ns"]),
            int(d["detected_ns"]),
            str(d["evidence"]),
            None if end is None else int(end),
        )


def _median(r: np.ndarray) -> float:
    """The median of a non-empty 1-d array, as ``np.median`` gives it, by one partial sort
    (``np.median``'s own checks cost more than the sort at a few hundred values, and the
    daily tests take thousands of medians a well-year)."""
    n = len(r)
    k = n // 2
    if n % 2:
        return float(np.partition(r, k)[k])
    p = np.partition(r, (k - 1, k))
    return float((p[k - 1] + p[k]) / 2.0)


def _median_inplace(r: np.ndarray) -> float:
    """:func:`_median` of an array of one's own, partly sorted in place (no copy): for a
    temporary that is not read again in its order."""
    n = len(r)
    k = n // 2
    if n % 2:
        r.partition(k)
        return float(r[k])
    r.partition((k - 1, k))
    return float((r[k - 1] + r[k]) / 2.0)


def _centre_mad(r: np.ndarray) -> tuple[float, float]:
    """The median of ``r`` (non-empty; not changed) and the median of its absolute
    deviations from it (the raw MAD)."""
    k = robust_kernels()
    if k is not None:
        centre, mad = k.median_mad(r)
        if math.isfinite(centre):  # (else a value is not: numpy's rules for it)
            return float(centre), float(mad)
    centre = _median(r)  # (a copy: r may be a window's own memory)
    return centre, _median_inplace(np.abs(r - centre))


def _excesses(r: np.ndarray, centre: float, scale: float, k: int) -> tuple[float, np.ndarray]:
    """With ``z = |r - centre| / scale``: its ``k``-th smallest value ``u`` and the excesses
    ``z - u`` of the values beyond it, in the order of ``r`` (their sum is then numpy's)."""
    kern = robust_kernels()
    if kern is not None:
        u, over = kern.tail_excesses(r, centre, scale, k)
        if math.isfinite(u):  # (else a value is not: numpy's rules for it)
            return float(u), over
    z = np.abs(r - centre) / scale
    u = float(np.partition(z, k)[k])
    return u, z[z > u] - u


def _median_mad(values: array[float]) -> tuple[float, float]:
    """The median and 1.4826 MAD (a robust sd) of ``values``."""
    centre, mad = _centre_mad(np.frombuffer(values))
    return centre, _MAD_TO_SD * mad


def _window() -> array[float]:
    """An empty window of floats (see :func:`_push`): numpy reads it without a copy
    (``np.frombuffer``), where a deque would be copied value by value."""
    return array("d")


def _push(window: array[float], value: float, maxlen: int) -> None:
    """Append ``value`` to ``window``, dropping its oldest value beyond ``maxlen`` (as a
    ``deque(maxlen=...)`` does)."""
    if len(window) >= maxlen:
        del window[0]
    window.append(value)


def _refill(window: array[float], saved: Any, maxlen: int) -> None:
    """Put a checkpoint's values (oldest first) into an empty ``window``: the last
    ``maxlen`` of them."""
    window.extend(float(v) for v in saved)
    if len(window) > maxlen:
        del window[: len(window) - maxlen]


def _num(v: Any) -> float:
    """A saved number (null for NaN)."""
    return math.nan if v is None else float(v)


@dataclass(frozen=True)
class Fallback:
    """The stand-in for one flagged input at one sample (see :meth:`WellSensorFaults.fallbacks`).

    ``value``: the value to use in place of the input (units of the observation format:
    fraction, bar a, degC); ``spread``: the standard deviation of how far the true value
    may have moved since the last trusted level; ``low`` / ``high``: ``value -/+ 1.645
    spread`` (a central 90 % span) clipped to the input's physical range; ``measured``:
    what the transmitter reads; ``start_ns``: when the fault began (epoch ns). For the
    measured rate's witness (:func:`witness_track`): ``wander``, the variance per day of how
    the input itself wanders (its daily means' variogram, without their noise, unit^2 / day;
    NaN: unknown, no witness), and ``prior``, the variance of where it is now from that
    wander (a day's change of its daily means, then ``wander`` a day; unit^2)."""

    sensor: str
    kind: str
    index: int
    value: float
    spread: float
    low: float
    high: float
    measured: float
    start_ns: int
    wander: float = math.nan
    prior: float = math.nan

    def as_dict(self) -> dict[str, Any]:
        """As the prediction message and ``GET /wells/{well}`` show it (``since``: ISO 8601
        UTC; ``measured`` null when not a finite number)."""
        return {
            "sensor": self.sensor,
            "kind": self.kind,
            "value": float(self.value),
            "measured": float(self.measured) if math.isfinite(self.measured) else None,
            "spread": float(self.spread),
            "low": float(self.low),
            "high": float(self.high),
            "since": iso(self.start_ns),
        }


def fallback_points(inputs: Sequence[float], used: Sequence[Fallback]) -> list[list[float]]:
    """The inputs a model is asked at while inputs are flagged: first every flagged input at
    its fallback value, then, per flagged input, at the low and at the high end of its span
    (the other flagged inputs at their fallback values)."""
    centre = [float(v) for v in inputs]
    for f in used:
        centre[f.index] = f.value
    points = [centre]
    for f in used:
        for end in (f.low, f.high):
            p = list(centre)
            p[f.index] = end
            points.append(p)
    return points


def widened_rates(answers: Sequence[Mapping[str, float | None]]) -> dict[str, float | None]:
    """The rates of :func:`fallback_points`' first point with their interval widened to the
    union of every point's (Sm3/h): ``q_total_p05`` the lowest of their 5 % quantiles (their
    ``q_total`` for a method without intervals), ``q_total_p95`` the highest 95 % quantile.
    ``q_total_std`` (only when the method gives one) adds the input's share in quadrature:
    per flagged input, the difference of the rates at its span's ends over 2 x 1.645.
    Points whose model answer is not finite (an input pair the model refuses) are left out.
    """
    centre = dict(answers[0])
    q = centre.get("q_total")
    if q is None or not math.isfinite(q):
        return centre

    def finite(v: float | None) -> float | None:
        return v if v is not None and math.isfinite(v) else None

    lows, highs = [], []
    for a in answers:
        qa = finite(a.get("q_total"))
        if qa is None:
            continue
        lows.append(finite(a.get("q_total_p05")) or qa)
        highs.append(finite(a.get("q_total_p95")) or qa)
    centre["q_total_p05"], centre["q_total_p95"] = min(lows), max(highs)
    std = finite(centre.get("q_total_std"))
    if std is not None:
        var = std * std
        for k in range(1, len(answers) - 1, 2):
            lo, hi = finite(answers[k].get("q_total")), finite(answers[k + 1].get("q_total"))
            if lo is not None and hi is not None:
                var += ((hi - lo) / (2.0 * _Z90)) ** 2
        centre["q_total_std"] = math.sqrt(var)
    return centre


#: the measured rate's correction of one stand-in (:func:`tracked`, :func:`witness_track`):
#: (shift of its value, the variance of where the input is at the last measurement taken,
#: that measurement's time ns, the meter's bias and noise about the model in log space,
#: :func:`residual_noise`, fixed at the first witness, then what the rates said of that
#: bias: its correction, the correction's variance and its covariance with the input's;
#: a checkpoint of before them restores with zeros, a bias taken as exact)
Track = tuple[float, float, int, float, float, float, float, float]
#: residuals whose median is a witness's meter bias (the service and the study keep 50):
#: that median's own variance, (1.2533 sd)^2 / 50, is the bias's prior in the witness
_WITNESS_RESIDUALS = 50


def residual_noise(log_residuals: Sequence[float]) -> tuple[float, float]:
    """The bias and the noise of a meter's rate about the model, in log space: the median
    and the robust sd (1.4826 MAD about it, at least 0.01) of the well's latest learned log
    residuals of that meter ``r = log(measured / predicted)``. An MPFM reads its own bias
    (a slow drift of its factor, which the model, weighing the well tests, does not
    follow): taken as news of the input, it would move the stand-in to fit it. With fewer
    than 10 residuals: no bias, 0.05 (an MPFM reading's noise at its worst)."""
    r = np.array([float(v) for v in log_residuals if math.isfinite(v)])
    if len(r) < _WITNESS_MIN_RESIDUALS:
        return 0.0, _WITNESS_LOG_SD
    bias = float(np.median(r))
    return bias, max(_MAD_TO_SD * float(np.median(np.abs(r - bias))), _WITNESS_MIN_LOG_SD)


def tracked(
    base: Fallback, track: Track | None, bounds: tuple[float, float], time_ns: int
) -> Fallback:
    """The stand-in ``base`` (:meth:`WellSensorFaults.fallbacks`, from the input's history)
    at a sample (epoch ns) corrected by what the measured rates said of the input so far
    (``track``, see :func:`witness_track`; None: ``base`` as it is): its value shifted (the
    trend since is ``base``'s), clipped to ``bounds`` (the input's physical range). Its
    spread stays ``base``'s, the span is moved with the value: the witness's own variance
    (:func:`track_variance`) assumes the input wanders as it did before the fault, and an
    input that does something else (a new trend) would leave a span that narrow behind."""
    if track is None:
        return base
    low, high = bounds
    value = min(max(base.value + track[0], low), high)
    spread = base.spread
    lo, hi = max(value - _Z90 * spread, low), min(value + _Z90 * spread, high)
    return replace(base, value=value, low=lo, high=hi)


def track_variance(used: Fallback, track: Track | None, time_ns: int) -> float:
    """The variance (unit^2) of where the stood-in input is at a sample (epoch ns), as the
    witness sees it: at the first witness ``used.prior``, later the track's variance grown
    by the input's ``wander`` since its last measurement; never above ``used``'s spread^2."""
    cap = used.spread * used.spread
    if track is None:
        return min(used.prior, cap)
    days = max(int(time_ns) - track[2], 0) / _NS_PER_DAY
    return min(track[1] + used.wander * days, cap)


def witness_track(
    used: Fallback,
    track: Track | None,
    answers: Sequence[Mapping[str, float | None]],
    q_measured: float,
    noise: tuple[float, float],
    time_ns: int,
    bounds: tuple[float, float],
) -> Track | None:
    """The measured rate as a witness of the stood-in input: one Kalman step.

    ``used``: the stand-in the sample was predicted with (``track`` applied, :func:`tracked`);
    ``answers``: the model's at :func:`fallback_points` of that one stand-in (at its value,
    at the low and at the high end of its span), the model's parameters held (learning
    is); the rate measured at that sample ``q_measured`` (Sm3/h) by a meter whose bias and
    noise about the model are ``noise`` (log space, :func:`residual_noise`; the track keeps
    those of its first witness). The state is the input and the meter's bias. The input's
    prior is the stand-in's value with the variance :func:`track_variance` (from the
    input's own wander, not the history's random walk of its noisy daily means); the
    bias's is ``noise``'s, with the variance of a median of the 50 residuals it is taken
    from, ``(1.2533 sd)^2 / 50``: a bias read off a few weeks of a noisy meter is itself
    uncertain, and a rate that keeps missing the model by that much is as likely the meter's
    bias as the input. The measurement is the log rate, linear in the input with the slope
    of the model's log rates across the span (the secant: no extra model call), plus the
    bias. A rate that could shrink the input's variance by less than 0.1 % (the rate
    hardly depends on it: ``p_down`` at critical flow) is not taken, so the stand-in stays
    the history's; nor a rate beyond 4 sd of its innovation, nor one before the track's last
    (out of order). Returns the new track (for :func:`tracked`)."""
    if track is not None and int(time_ns) < track[2]:
        return track
    bias, log_sd = noise if track is None else track[3:5]
    if len(answers) != 3 or not (q_measured > 0 and log_sd > 0):
        return track
    q = [answers[k].get("q_total") for k in range(3)]
    if not all(v is not None and math.isfinite(v) and v > 0 for v in q):
        return track
    qc, ql, qh = (float(v) for v in q)  # type: ignore[arg-type]
    width = used.high - used.low
    slope = (math.log(qh) - math.log(ql)) / width if width > 0 else 0.0
    prior = track_variance(used, track, time_ns)
    r = log_sd * log_sd
    if not (math.isfinite(prior) and prior > 0) or slope * slope * prior < 1e-3 * r:
        return track
    if track is None:
        shift, b, vb, cov = 0.0, 0.0, (_MEDIAN_SE * log_sd) ** 2 / _WITNESS_RESIDUALS, 0.0
    else:
        shift, b, vb, cov = track[0], track[5], track[6], track[7]
        cov = max(min(cov, math.sqrt(prior * vb)), -math.sqrt(prior * vb))
    innovation = math.log(q_measured) - math.log(qc) - bias - b
    s = slope * slope * prior + 2.0 * slope * cov + vb + r
    if abs(innovation) > _WITNESS_GATE * math.sqrt(s):
        return track
    gain, gain_b = (prior * slope + cov) / s, (cov * slope + vb) / s
    value = min(max(used.value + gain * innovation, bounds[0]), bounds[1])
    return (
        shift + value - used.value,
        prior - gain * (slope * prior + cov),
        int(time_ns),
        bias,
        log_sd,
        b + gain_b * innovation,
        vb - gain_b * (slope * cov + vb),
        cov - gain * (slope * cov + vb),
    )


def _saved_track(v: Sequence[Any]) -> Track:
    """A checkpoint's track (:data:`Track`); one of before the meter's bias was a state (five
    values) restores with that bias taken as exact (zero correction and variance)."""
    b = (float(v[5]), float(v[6]), float(v[7])) if len(v) >= 8 else (0.0, 0.0, 0.0)
    return (float(v[0]), float(v[1]), int(v[2]), float(v[3]), float(v[4]), *b)


def critical_floor(p_up: float, t_up: float, eta_gas: float, eta_oil: float) -> float:
    """The lowest critical pressure ratio ``p_down / p_up`` (-) that the models' choke laws
    give for a well's fluid at ``p_up`` (bar a), ``t_up`` (degC) and the mass fractions:
    the constant law's ``p_cr`` prior at -2 sd (0.45), or Sachdeva's solved ratio
    (:func:`vfm_core.physics.sachdeva_critical_ratio`, ideal gas) with the fluid priors at
    2 sd in the direction that lowers it (a denser gas, a lighter liquid, a larger heat-
    capacity ratio), whichever is lower. Below it the flow is critical under every such
    law: the rate does not depend on ``p_down``."""
    pr = physics.PRIORS
    eg = min(max(float(eta_gas), 1e-6), 1.0)
    eo = min(max(float(eta_oil), 0.0), 1.0 - eg)
    m_gas = pr["m_gas"].mean + 2.0 * pr["m_gas"].std
    rho_g1 = physics.gas_density(p_up * 1e5, t_up + 273.15, m_gas)
    v_liq = physics.liquid_specific_volume(
        eg,
        eo,
        pr["rho_oil"].mean - 2.0 * pr["rho_oil"].std,
        pr["rho_wat"].mean - 2.0 * pr["rho_wat"].std,
    )
    kappa = pr["kappa"].mean + 2.0 * pr["kappa"].std
    y_c = float(physics.sachdeva_critical_ratio(eg, rho_g1, v_liq, kappa, iterations=40))
    return min(_P_CR_LOW, y_c)


def p_down_consequence(ratio_before: float, ratio_after: float, floor: float) -> float:
    """The largest change of the log rate (-) that a step of ``p_down / p_up`` from
    ``ratio_before`` to ``ratio_after`` can make under a choke law whose critical ratio is
    at or above ``floor`` (:func:`critical_floor`).

    An incompressible liquid's rate goes as ``sqrt(p_up - p_down)``: its log rate changes
    by ``0.5 ln((1 - y2) / (1 - y1))``, with the ratios clamped at the critical ratio
    (below it the flow is critical, the rate flat in ``p_down``). A compressible phase
    makes the subcritical curve flatter, down to a slope of zero at its own critical ratio
    (the flux is largest there): Sachdeva's law's log slope in ``y`` is at most the
    liquid's at every ratio above its critical one (checked on a grid of gas fractions
    0.001-0.8, heat-capacity ratios 1.2-1.35, oil densities 700-850 kg/m3, gas molar masses
    16-25 g/mol: at most 0.9998 of it), and so is the constant law's (Sachdeva's flux
    clamped at its ``p_cr``, 0.45 or more: at most 0.983 of it for gas fractions 0.05-0.9,
    also where that ``p_cr`` lies below the fluid's own critical ratio). A higher critical
    ratio clamps more of the step. So the liquid law clamped at the floor bounds them all.

    >>> round(p_down_consequence(0.43, 0.47, 0.45), 4)  # mostly below the floor
    0.0185
    >>> p_down_consequence(0.30, 0.40, 0.45)  # critical on both levels
    0.0
    """
    y1 = min(max(ratio_before, floor), 0.999)
    y2 = min(max(ratio_after, floor), 0.999)
    return 0.5 * abs(math.log((1.0 - y2) / (1.0 - y1)))


@lru_cache(maxsize=4096)
def _rounded_floor(p_up: float, t_up: float, eta_gas: float, eta_oil: float) -> float:
    """:func:`critical_floor` of inputs rounded by the caller (0.1 bar, 0.5 K, 0.001 of a
    fraction: the floor moves by far less than its own -2 sd margin across such a step),
    remembered: a frozen input's samples ask it again and again at nearly the same point."""
    return critical_floor(p_up, t_up, eta_gas, eta_oil)


@dataclass
class _Frozen:
    """Markov counts of unchanged steps of one input (exponentially forgotten)."""

    n_c: float = 0.0  # steps after a changed step
    n_cu: float = 0.0  # ... that were unchanged
    n_u: float = 0.0  # steps after an unchanged step
    n_uu: float = 0.0  # ... that were unchanged
    run: int = 1  # samples in the current run of one value
    run_start_ns: int = 0
    # the current run's transitions, learned only when it ends without an event
    pend_c: float = 0.0
    pend_cu: float = 0.0
    pend_u: float = 0.0
    pend_uu: float = 0.0
    prev_unchanged: bool = False
    steps: int = 0


@dataclass
class _Pending:
    """The previous sample, waiting for the next one to decide whether it was a spike."""

    time_ns: int
    values: list[float]
    choke_moved: bool
    gap_ok: bool


class WellSensorFaults:
    """The sensor-fault detectors of one well (see the module docstring for the rules).

    Hyperparameters are exactly the ``__init__`` arguments: ``false_per_well_year``
    (false faults per well-year the thresholds allow, all tests together), ``ranges``
    (physical span per sensor), ``frozen_memory`` (steps of history of the frozen test),
    ``spike_window`` (one-step changes in the spike test's scale), ``lags`` (days in the
    long-run factor of the drift CUSUM), ``accept_days`` (days after which a drift or
    input offset is closed and the new level taken as real; a choke offset after
    :data:`_CHOKE_ACCEPT_DAYS`, see the module docstring).
    """

    def __init__(
        self,
        false_per_well_year: float = 0.1,
        ranges: Mapping[str, tuple[float, float]] | None = None,
        frozen_memory: int = 2000,
        spike_window: int = 200,
        lags: int = 3,
        accept_days: float = 30.0,
    ) -> None:
        if not (math.isfinite(false_per_well_year) and 0 < false_per_well_year <= 10):
            raise ConfigError(
                "false_per_well_year must lie in (0, 10] false faults per well-year, "
                f"got {false_per_well_year}."
            )
        merged = {**DEFAULT_RANGES, **(ranges or {})}
        unknown = sorted(set(merged) - set(SENSORS))
        if unknown:
            raise ConfigError(f"Unknown sensors {unknown} in ranges; valid: {list(SENSORS)}.")
        for name, (low, high) in merged.items():
            if not (math.isfinite(low) and math.isfinite(high) and low < high):
                raise ConfigError(
                    f"The range of {name} must be finite low < high, got {low, high}."
                )
        if frozen_memory < 100 or spike_window < 50:
            raise ConfigError("frozen_memory must be >= 100 and spike_window >= 50 samples.")
        if not accept_days > 0:
            raise ConfigError(f"accept_days must be a positive number of days, got {accept_days}.")
        self.false_per_well_year = float(false_per_well_year)
        self.ranges = {k: (float(v[0]), float(v[1])) for k, v in merged.items()}
        #: the lower and the upper ends of the ranges, in the order of SENSORS
        self._bounds = tuple(zip(*(self.ranges[name] for name in SENSORS), strict=True))
        self.frozen_memory = int(frozen_memory)
        self.spike_window = int(spike_window)
        self.lags = int(lags)
        self.accept_days = float(accept_days)
        #: false alarms per well-year allowed to one test
        self.budget = self.false_per_well_year / _N_TESTS
        self.arl0_days = 365.25 / self.budget
        # a day's change beyond this many robust sd is a step candidate (two-sided, per day)
        self._step_alpha = self.budget / 365.25 / 2.0  # per day, each of two changes
        self._z_day = NormalDist().inv_cdf(1.0 - self._step_alpha / 2.0)
        self._reset()

    # -- the protocol -------------------------------------------------------------------------
    def _reset(self) -> None:
        n = len(SENSORS)
        self.samples = 0
        self.intervals: deque[int] = deque(maxlen=64)
        self.last_ns: int | None = None
        self.last_values: list[float] | None = None
        self.frozen = [_Frozen() for _ in SENSORS]
        self.changes = [_window() for _ in SENSORS]  # the last spike_window one-step changes
        self.changes_added = [0] * n
        self.scale = [0.0] * n
        self.scale_at = [-1] * n  # changes_added when the scale was computed (-1: never)
        self.pending: _Pending | None = None
        self._interval_cache = (-1, float(_DEFAULT_INTERVAL_NS))
        #: samples a day at the current sample's median interval (set by :meth:`update`)
        self._spd = max(1.0, _NS_PER_DAY / _DEFAULT_INTERVAL_NS)
        #: the median interval (ns) of the last sample, its alpha and samples a day
        self._rates = (math.nan, math.nan, self._spd)
        self._robust_cache: dict[tuple[str, int], tuple[int, float, float]] = {}
        #: the cache's keys per input: the day-to-day, quiet two-day and raw daily changes
        self._keys = tuple(tuple((what, i) for i in range(n)) for what in ("diff", "two", "raw"))
        #: per input, the step test's limit in robust sd (:meth:`_tail_limit`)
        self._limits = [self._z_day] * n
        self._limits2 = [self._z_day] * n  # the two-day change's
        self.last_values_before: list[float] | None = None  # the sample before the pending
        self.cusums = [self._new_cusum() for _ in SENSORS]
        self.cusum_zero_ns: list[int | None] = [None] * n
        # the open day of each input, the last closed one, a step candidate
        self.day_index = [0] * n
        self.day_start_ns = [0] * n
        self.day_sum = [0.0] * n
        self.day_n = [0] * n
        self.day_prev: list[tuple[int, float, int] | None] = [None] * n
        self.diffs = [_window() for _ in SENSORS]  # the last _REF_DAYS day-to-day changes
        #: the day-to-day changes of the days the step test runs on (the choke still, no
        #: other input moving): the tail its limit is fitted to (:meth:`_tail_limit`)
        self.quiet = [_window() for _ in SENSORS]
        #: the quiet two-day changes (per square-root day), the day before the last closed
        #: one, whether the last closed day was quiet, and each candidate's span in days
        self.quiet2 = [_window() for _ in SENSORS]
        self.day_prev2: list[tuple[int, float, int] | None] = [None] * n
        self.prev_alone = [False] * n
        self.cand_days = [1] * n
        self.cand: list[tuple[float, float, int, float, int] | None] = [None] * n
        self.offset_level: list[tuple[float, float] | None] = [None] * n
        #: per input, the day-to-day changes (per square-root day, with their ns) of an
        #: open step candidate's days, held from the drift CUSUM until it is decided
        self.drift_wait: list[list[tuple[float, int]]] = [[] for _ in SENSORS]
        # raw daily means (the co-movement check of the step test)
        self.raw_day, self.raw_n, self.raw_sum = 0, 0, [0.0] * n
        self.raw_choke = self.prev_raw_choke = False
        self.raw_prev: tuple[int, list[float]] | None = None
        self.raw_diffs = [_window() for _ in SENSORS]
        self.day_moved: tuple[set[int], bool] = (set(), False)
        self.open: dict[tuple[str, str], SensorFault] = {}
        self.events: deque[SensorFault] = deque(maxlen=50)
        #: the choke's offset, from the measured rate (vfm_core.rate_witness)
        self.witness = ChokeRateWitness(self.budget)
        #: faults raised per "sensor/kind" (kept across restarts through the state)
        self.raised: dict[str, int] = {}
        #: closed daily means per input, (day index, mean), the latest _LEVEL_DAYS days
        self.levels: list[deque[tuple[int, float]]] = [deque(maxlen=_LEVEL_DAYS) for _ in SENSORS]
        #: per open fault "sensor/kind": the last trusted level, its trend per day, the
        #: robust sd of the day-to-day changes per square-root day, and the level's time (ns)
        self.anchors: dict[str, tuple[float, float, float, int]] = {}
        #: per open fault "sensor/kind" of :data:`FALLBACK_KINDS`: what the measured rates
        #: said of the input so far (:meth:`follow_rate`), the correction of its stand-in
        self.tracks: dict[str, Track] = {}
        #: per open fault "sensor/kind" of :data:`_ANCHOR_KINDS`: the input's own wander
        #: before it (variance per day, :meth:`_wander`), fixed when it is raised
        self.wanders: dict[str, float] = {}
        #: p_down steps not raised as offsets, per reason (:meth:`_set_point`): "critical"
        #: (the rate does not depend on p_down on either level), "slight" (no choke law
        #: above the floor lets the step move the rate beyond the noise of the meter's
        #: means), "followed" (the measured
        #: rate answered the step as a real change of the back pressure does)
        self.set_points: dict[str, int] = {}
        #: p_down drift alarms not raised: in critical flow (:meth:`_critical_drift`)
        self.drifts_set_aside = 0

    def _new_cusum(self) -> ResidualCusum:
        # each day's change is its own period (period_s 0): the daily means are made here
        return ResidualCusum(
            arl0=self.arl0_days,
            k=0.5,
            period_s=0.0,
            window=365,
            min_periods=_MIN_DAYS,
            lags=self.lags,
        )

    @property
    def active(self) -> list[SensorFault]:
        """The faults open now."""
        return list(self.open.values())

    def flagged_kinds(self) -> set[tuple[str, str]]:
        """The (sensor, kind) pairs with an open fault."""
        return set(list(self.open))

    def suspect(
        self,
        time_ns: int,
        kinds: Sequence[str] = HOLD_KINDS,
        faults: Sequence[tuple[str, str]] = HOLD_FAULTS,
        values: Sequence[float] | None = None,
    ) -> SensorFault | None:
        """The fault of one of ``kinds``, or one of the (sensor, kind) ``faults`` (active or
        recent), whose span covers the sample at ``time_ns`` (epoch ns), if any: a
        measurement paired with that sample would teach the model the fault. By default only
        those whose false-alarm rate is measured within the budget (:data:`HOLD_KINDS`,
        :data:`HOLD_FAULTS`): a false offset would hold a month of learning.

        With the sample's six ``values`` given, a frozen ``p_down`` does not count where it
        cannot matter to the rate (:meth:`p_down_moot`: the flow is critical under every
        choke law over the stand-in's 90 % span): a measurement there teaches the model
        nothing about ``p_down``, and holding it would only cost learning."""
        t = int(time_ns)
        for e in reversed(list(self.events)):
            if e.kind not in kinds and (e.sensor, e.kind) not in faults:
                continue
            if e.start_ns <= t and (e.end_ns is None or t < e.end_ns):
                if (e.sensor, e.kind) == ("p_down", "frozen") and values is not None:
                    if self.p_down_moot(t, values):
                        continue
                return e
            if e.kind == "spike" and e.start_ns == t:
                return e
        if ("choke", "offset") in faults:
            return self._choke_doubt(t)
        return None

    def p_down_moot(self, time_ns: int, values: Sequence[float]) -> bool:
        """True when a frozen ``p_down`` cannot matter to the rate of the sample at
        ``time_ns`` (epoch ns; ``values``: its six inputs, observation units): the other
        inputs it needs have no open fault, and ``p_down / p_up`` stays below the lowest
        critical ratio of the models' choke laws (:func:`critical_floor`) both at the
        reading and at the top of its stand-in's 90 % span (:meth:`fallbacks`). The flow
        is then critical under every law: the rate does not depend on ``p_down``, and a
        measurement there cannot teach the model its fault."""
        if any(sensor not in ("p_down", "choke") for sensor, _ in self.open):
            return False
        p_up, t_up, eta_gas, eta_oil = (float(values[i]) for i in (1, 3, 4, 5))
        high = float(values[2])
        if not all(map(math.isfinite, (p_up, t_up, eta_gas, eta_oil, high))) or p_up <= 0:
            return False
        for f in self.fallbacks(time_ns, values):
            if f.sensor == "p_down":
                high = max(high, f.high)
        return high / p_up < _rounded_floor(
            round(p_up, 1), round(t_up * 2.0) / 2.0, round(eta_gas, 3), round(eta_oil, 3)
        )

    def _choke_doubt(self, t: int) -> SensorFault | None:
        """A provisional choke offset (not an event: no alarm, no count of faults) while
        the choke-rate witness is in doubt about a move before ``t``: the rate has so far
        answered it nearer none than the response the reading asks for, and the test has
        not decided yet (:meth:`vfm_core.rate_witness.ChokeRateWitness.doubted`)."""
        m = self.witness.doubted(t)
        if m is None:
            return None
        return SensorFault(
            "choke",
            "offset",
            m.time_ns,
            t,
            f"Provisional: the choke's reading moved {m.u_before:.4g} -> {m.u_after:.4g} at "
            f"{iso(m.time_ns)} and the measured rate has not followed it so far; a "
            "measurement is not learned while the choke-rate witness cannot yet tell a "
            "transmitter's offset from a real move.",
        )

    def flagged(self) -> set[str]:
        """The sensors with an open fault."""
        return {sensor for sensor, _ in self.open}

    # -- the fallback ---------------------------------------------------------------------------
    def _anchor(self, i: int, kind: str, start_ns: int) -> tuple[float, float, float, int]:
        """What input ``i`` was before a fault of ``kind`` that began at ``start_ns``:
        (level, trend per day, sd of its day-to-day changes per square-root day, the
        level's time ns).

        The level: for a frozen or out-of-range input, its last live reading (the value it
        froze at, or the last one within its range): an input wanders, so the latest reading
        is a better guess of where it is than an older average. For a drift or offset, whose
        onset is an estimate, the mean of the last closed day before the fault's day (else
        the last reading). The trend is the robust centre ``c`` of the input's day-to-day
        changes (the well's own decline), shrunk by ``max(0, 1 - (se / c)^2)`` with ``se =
        1.2533 sd / sqrt(n)`` the standard error of a median: the factor that minimises the
        squared error of extrapolating a noisy trend (a trend lost in its noise counts for
        nothing). The sd is the changes' 1.4826 MAD; without 30 days of them, the sd of
        one-step changes times sqrt(samples a day) (a random walk at the sample scale:
        wider, not narrower); without those either, NaN (see :meth:`fallbacks`).
        """
        last = self.last_values
        level = float(last[i]) if last is not None else math.nan
        at_ns = start_ns if kind == "frozen" else (self.last_ns or start_ns)
        if kind not in ("frozen", "out_of_range"):
            start_day = start_ns // _NS_PER_DAY
            for day, mean in reversed(self.levels[i]):
                if day < start_day:
                    level, at_ns = mean, day * _NS_PER_DAY + _NS_PER_DAY // 2
                    break
        trend, scale = 0.0, math.nan
        ref = self.diffs[i]
        if len(ref) >= _MIN_DAYS:  # computed afresh: the tests' cached scales stay theirs
            centre, scale = _median_mad(ref)
            se = _MEDIAN_SE * scale / math.sqrt(len(ref))
            if abs(centre) > se:
                trend = centre * (1.0 - (se / centre) ** 2)
        if not scale > 0 and len(self.changes[i]) >= 2:
            scale = _median_mad(self.changes[i])[1] * math.sqrt(self._samples_per_day())
        return float(level), float(trend), float(scale), int(at_ns)

    def _wander(self, i: int, start_ns: int) -> float:
        """How input ``i`` itself wanders (variance per day, its unit^2 / day) before the day
        of ``start_ns``: the growth of the variance of its daily means' changes from one day
        apart to 30, ``(v30 - v1) / 29`` (robust: 1.4826 MAD about the median, so the trend
        drops out). The noise of a daily mean is in both and cancels: the day-to-day changes
        (the history's spread) are mostly that noise, and a random walk of them overstates
        where the input goes in a month (seed 4711's three wells with a frozen ``p_up``: a
        90 % span of 4-6 bar either side after 60 days, while the true daily means stayed
        within 0.8-0.9 bar sd of their mean).

        The changes are the last year's day-to-day changes (:attr:`diffs`, those the drift
        test watches, less the days since the fault's), a 30-day change the sum of 30 in a
        row: some 300 of them. The last 64 daily means gave 34, mostly over the same days,
        whose spread is too small: below 0.005 bar^2 a day on 5 of 17 wells with a frozen
        ``p_up`` (seeds 5101-5104, 5121-5124; a year's: 0.04-0.24), which stopped the
        witness's stand-in after its first steps. A change across a gap of two or three
        days is per square-root day (as the drift test keeps it); one across a longer gap,
        or a step held as an offset candidate, is not among them (nor in the sums). NaN
        without 40 changes."""
        ref = np.asarray(self.diffs[i], dtype=float)
        start_day = start_ns // _NS_PER_DAY
        since = sum(1 for d, _ in self.levels[i] if d >= start_day)  # the fault's own days
        d = ref[: len(ref) - since] if since else ref
        if len(d) < _WANDER_LAG + 10:
            return math.nan
        sums = np.convolve(d, np.ones(_WANDER_LAG), mode="valid")
        var = [(_MAD_TO_SD * float(np.median(np.abs(r - np.median(r))))) ** 2 for r in (d, sums)]
        return max(var[1] - var[0], 0.0) / (_WANDER_LAG - 1)

    def stands_in(
        self,
        kinds: Sequence[str] = FALLBACK_KINDS,
        faults: Sequence[tuple[str, str]] = FALLBACK_FAULTS,
    ) -> bool:
        """True while an input has an open fault of one of ``kinds`` or one of the (sensor,
        kind) ``faults`` (its samples are then predicted with its fallback, one by one)."""
        return any(k in kinds or (s, k) in faults for s, k in self.open)

    def fallbacks(
        self,
        time_ns: int,
        values: Sequence[float],
        kinds: Sequence[str] = FALLBACK_KINDS,
        faults: Sequence[tuple[str, str]] = FALLBACK_FAULTS,
    ) -> list[Fallback]:
        """The stand-ins for the inputs of a sample (epoch ns, the six values) that have an
        open fault of one of ``kinds`` or one of the (sensor, kind) ``faults``; empty when
        none (the usual case: one dict test).

        Asked before or after :meth:`update` of the sample, the answer is the same: a frozen
        input that reads another value now, or an out-of-range one back in its range, is no
        longer replaced (the fault ends at this sample).

        The value is the last trusted level (:meth:`_anchor`) moved by its trend over the
        days since, clipped to the physical range; the spread is the sd of the day-to-day
        changes times sqrt(days since the level, at least one: a daily mean is known to a
        day), a random walk's growth, capped so that its 90 % span is at most the range.
        With no history to scale it (NaN), the span is the whole range: nothing is known
        of where the input went. The choke (set by the operator in steps, no daily test)
        falls in that case, except at a choke offset (:meth:`_choke_shift`).
        """
        if not self.open:
            return []
        out: list[Fallback] = []
        done: set[str] = set()
        for (sensor, kind), fault in list(self.open.items()):
            if (kind not in kinds and (sensor, kind) not in faults) or sensor in done:
                continue
            i = SENSORS.index(sensor)
            v = float(values[i])
            low, high = self.ranges[sensor]
            if (sensor, kind) == ("choke", "offset"):
                out.append(self._choke_shift(fault, v))
                done.add(sensor)
                continue
            last = self.last_values
            if kind == "frozen" and last is not None:
                if abs(v - last[i]) > _SAME * max(1.0, abs(last[i])):
                    continue  # it reads again
            if kind == "out_of_range" and math.isfinite(v) and low <= v <= high:
                continue
            key = f"{sensor}/{kind}"
            if key not in self.anchors:  # a checkpoint of before the fallback existed
                self.anchors[key] = self._anchor(i, kind, fault.start_ns)
            level, trend, scale, at_ns = self.anchors[key]
            if key not in self.wanders:  # a checkpoint of before the witness existed
                self.wanders[key] = self._wander(i, fault.start_ns)
            days = max((int(time_ns) - at_ns) / _NS_PER_DAY, 0.0)
            value = level + trend * days if math.isfinite(level) else (low + high) / 2.0
            value = min(max(value, low), high)
            widest = (high - low) / (2.0 * _Z90)
            spread = scale * math.sqrt(max(days, 1.0)) if scale > 0 else widest
            spread = min(spread, widest)
            lo, hi = max(value - _Z90 * spread, low), min(value + _Z90 * spread, high)
            wander = self.wanders[key]
            prior = min(scale * scale + wander * max(days - 1.0, 0.0), spread * spread)
            base = Fallback(
                sensor, kind, i, value, spread, lo, hi, v, fault.start_ns, wander, prior
            )
            out.append(tracked(base, self.tracks.get(key), (low, high), time_ns))
            done.add(sensor)
        return out

    def follow_rate(
        self,
        time_ns: int,
        used: Sequence[Fallback],
        answers: Sequence[Mapping[str, float | None]],
        q_measured: float,
        noise: tuple[float, float],
    ) -> bool:
        """A rate (Sm3/h) measured at the sample at ``time_ns`` (epoch ns) that was predicted
        with the stand-ins ``used`` (from :meth:`fallbacks`) and the model's ``answers`` at
        their :func:`fallback_points`: with one stood-in input of :data:`FALLBACK_KINDS`
        whose fault is still open, a Kalman step of its stand-in
        (:func:`witness_track`; ``noise``: the meter's bias and noise about the model in
        log space, :func:`residual_noise`, used from the fault's first witness on). The later
        samples' :meth:`fallbacks` follow it. Several inputs stood in for at once are left
        as they are (the rate cannot tell which one moved). True when the stand-in moved."""
        if len(used) != 1 or used[0].kind not in FALLBACK_KINDS:
            return False
        f = used[0]
        fault = self.open.get((f.sensor, f.kind))
        if fault is None or fault.start_ns != f.start_ns:
            return False
        key = f"{f.sensor}/{f.kind}"
        before = self.tracks.get(key)
        after = witness_track(f, before, answers, q_measured, noise, time_ns, self.ranges[f.sensor])
        if after is None or after == before:
            return False
        self.tracks[key] = after
        return after[:2] != (before[:2] if before is not None else (0.0, 0.0))

    def _choke_shift(self, fault: SensorFault, v: float) -> Fallback:
        """The stand-in for a choke reading ``v`` (fraction open) at an open choke offset:
        the reading less the shift the witness estimated (where the measured rate says the
        choke is; :mod:`vfm_core.rate_witness`), with that estimate's sd (constant: a
        transmitter's offset does not wander), clipped to the range. Absent (a checkpoint of
        before the shift was kept): the whole move of the reading, with a quarter of it as
        its sd."""
        low, high = self.ranges["choke"]
        key = "choke/offset"
        if key not in self.anchors:
            m = self.witness.open
            move = 0.0 if m is None else m.u_after - m.u_before
            self.anchors[key] = (move, 0.0, 0.25 * abs(move), fault.start_ns)
        shift, _, sd, _ = self.anchors[key]
        value = min(max(v - shift, low), high)
        sd = sd if math.isfinite(sd) and sd > 0 else 0.25 * abs(shift)
        lo, hi = max(value - _Z90 * sd, low), min(value + _Z90 * sd, high)
        return Fallback("choke", "offset", _CHOKE, value, sd, lo, hi, v, fault.start_ns)

    def update(self, time_ns: int, values: Sequence[float]) -> list[SensorFault]:
        """Feed one sample (epoch ns, data time, in time order; ``values`` in the order of
        :data:`SENSORS`, units of the observation format). Returns the events that began or
        ended at it (an ended one has ``end_ns`` set)."""
        t = int(time_ns)
        x = [float(v) for v in values]
        if len(x) != len(SENSORS):
            raise ConfigError(f"A sample has {len(SENSORS)} values ({', '.join(SENSORS)}).")
        if self.last_ns is not None and t <= self.last_ns:
            return []  # not after the previous sample: the caller refuses it
        out: list[SensorFault] = []
        bad = self._range(t, x, out)
        if bad:  # nothing else learns from a sample with an impossible value
            return out
        if self.last_ns is not None:
            self.intervals.append(t - self.last_ns)
        self.witness.choke(t, x[_CHOKE])
        if self.open:  # (a choke offset to accept: none without an open fault)
            self._accept_choke(t, out)
        at, interval = self._interval_cache  # (:meth:`_interval_ns`'s cached answer, inline)
        if at < 0 or self.samples - at >= 16 or not self.intervals:
            interval = self._interval_ns()
        if interval != self._rates[0]:  # (it changes every 16 samples at most)
            # the per-sample false-alarm probability of one per-sample test: its share of
            # the budget over the samples a year (:meth:`samples_per_year`)
            alpha = self.budget / (365.25 * _NS_PER_DAY / max(interval, 1e9))
            self._rates = (interval, alpha, max(1.0, _NS_PER_DAY / max(interval, 1.0)))
        alpha = self._rates[1]
        self._spd = self._rates[2]  # samples a day, for this sample's tests
        prev = self.last_values
        choke_moved = prev is not None and abs(x[_CHOKE] - prev[_CHOKE]) > _SAME
        # a gap (a shut-in, a historian outage) may hide a real change: no spike across it
        gap_ok = prev is not None and (t - (self.last_ns or t)) <= max(3 * interval, _GAP_NS)
        if prev is not None:
            self._frozen(t, x, prev, alpha, out)
        # the previous sample is decided now that its successor is known
        if self.pending is not None:
            spiked = self._spike(t, x, gap_ok, alpha, out)
            self._daily(self.pending, spiked, out)
            self._learn_changes(self.pending, spiked)
        self.pending = _Pending(t, x, choke_moved, gap_ok)
        self.last_ns, self.last_values = t, x
        self.samples += 1
        return out

    def measure(self, time_ns: int, q_total: float, values: Sequence[float]) -> list[SensorFault]:
        """Feed one MPFM rate (Sm3/h) paired with the sample at ``time_ns`` (epoch ns) whose
        inputs were ``values`` (the order of :data:`SENSORS`), after that sample's
        :meth:`update`: the choke-rate witness (:mod:`vfm_core.rate_witness`) tests the
        choke's latest moves with it. Returns the choke offset raised or ended by it. A rate
        paired with an older sample (another choke reading than the latest, or before the
        latest rate) is not taken."""
        out: list[SensorFault] = []
        w = self.witness
        t = int(time_ns)
        choke, p_up, p_down = (float(values[i]) for i in range(3))
        if w.u is None or abs(choke - w.u) > _SAME * max(1.0, abs(w.u)):
            return out
        found = w.rate(t, float(q_total), p_up, p_down)
        if found is None:
            return out
        if found.action == "close":
            if ("choke", "offset") in self.open:
                self.open[("choke", "offset")].evidence += " " + found.evidence
                self._close("choke", "offset", t, out)
        elif ("choke", "offset") not in self.open:
            self._raise(SensorFault("choke", "offset", found.start_ns, t, found.evidence), out)
            self.anchors["choke/offset"] = (found.shift, 0.0, found.shift_sd, found.start_ns)
        return out

    def _accept_choke(self, t: int, out: list[SensorFault]) -> None:
        """A choke offset open for :data:`_CHOKE_ACCEPT_DAYS` since it was found is closed:
        its reading is taken as the choke's. Held longer, the model would grow stale (no
        wear, no depletion learned); from then on it learns the reading as it is."""
        fault = self.open.get(("choke", "offset"))
        if fault is not None and (t - fault.detected_ns) / _NS_PER_DAY >= _CHOKE_ACCEPT_DAYS:
            fault.evidence += (
                f" After {_CHOKE_ACCEPT_DAYS:g} days the reading is taken as the choke's: the "
                "model learns from it again (held longer it would grow stale); a move of the "
                "reading back that the rate does not follow is the offset's end."
            )
            self._close("choke", "offset", t, out)
            self.witness.accept()

    # -- helpers ------------------------------------------------------------------------------
    def _interval_ns(self) -> float:
        """The median of the last 64 intervals between samples, ns (recomputed every 16)."""
        if not self.intervals:
            return float(_DEFAULT_INTERVAL_NS)
        at, value = self._interval_cache
        if at < 0 or self.samples - at >= 16:
            value = _median_inplace(np.fromiter(self.intervals, dtype=float))
            self._interval_cache = (self.samples, value)
        return value

    def samples_per_year(self) -> float:
        """Samples per year at the well's median interval between samples."""
        return 365.25 * _NS_PER_DAY / max(self._interval_ns(), 1e9)

    def _raise(self, fault: SensorFault, out: list[SensorFault]) -> None:
        if fault.kind in _ANCHOR_KINDS:  # the level to stand in for it, before it changes
            i = SENSORS.index(fault.sensor)
            self.anchors[f"{fault.sensor}/{fault.kind}"] = self._anchor(
                i, fault.kind, fault.start_ns
            )
            self.wanders[f"{fault.sensor}/{fault.kind}"] = self._wander(i, fault.start_ns)
        self.open[(fault.sensor, fault.kind)] = fault
        self.events.append(fault)
        key = f"{fault.sensor}/{fault.kind}"
        self.raised[key] = self.raised.get(key, 0) + 1
        out.append(fault)

    def _close(self, sensor: str, kind: str, t: int, out: list[SensorFault]) -> None:
        fault = self.open.pop((sensor, kind), None)
        self.anchors.pop(f"{sensor}/{kind}", None)
        self.tracks.pop(f"{sensor}/{kind}", None)
        self.wanders.pop(f"{sensor}/{kind}", None)
        if fault is not None:
            fault.end_ns = t
            out.append(fault)

    def _range(self, t: int, x: list[float], out: list[SensorFault]) -> bool:
        """Raise or close the ``out_of_range`` faults of sample ``x``; True when a value is
        outside its physical span (NaN and infinities are: the spans are finite)."""
        lows, highs = self._bounds
        if not self.open and all(map(operator.le, lows, x)) and all(map(operator.le, x, highs)):
            return False  # the usual case: every value inside, nothing open to close
        bad = False
        for i, name in enumerate(SENSORS):
            low, high = self.ranges[name]
            v = x[i]
            outside = not (math.isfinite(v) and low <= v <= high)
            key = (name, "out_of_range")
            if outside:
                bad = True
                if key not in self.open:
                    unit = _UNITS[name]
                    self._raise(
                        SensorFault(
                            name,
                            "out_of_range",
                            t,
                            t,
                            f"{name} read {v:.6g}{unit}, outside its physical span "
                            f"{low:g}..{high:g}{unit}.",
                        ),
                        out,
                    )
            elif key in self.open:
                self._close(name, "out_of_range", t, out)
        return bad

    # -- frozen ---------------------------------------------------------------------------------
    def _frozen(
        self, t: int, x: list[float], prev: list[float], alpha: float, out: list[SensorFault]
    ) -> None:
        """The frozen test of every input at sample ``x`` (``prev``: the sample before)."""
        decay = 1.0 - 1.0 / self.frozen_memory
        is_open = self.open
        for i, f in enumerate(self.frozen):
            p = prev[i]
            a = abs(p)
            unchanged = abs(x[i] - p) <= _SAME * (a if a > 1.0 else 1.0)  # max(1, |p|)
            if not (unchanged or f.prev_unchanged or f.pend_c or f.pend_u):
                # the usual step of a live input: changed after a changed one, nothing
                # pending (the general rule below with pend_c = 1, the rest 0: decay**1 is
                # decay, and a count plus 0.0 is the count; a fault closed now resets the
                # pending counts first, and the counts stay)
                f.steps += 1
                f.run = 1
                if is_open and (SENSORS[i], "frozen") in is_open:
                    self._close(SENSORS[i], "frozen", t, out)
                    continue
                f.n_c = f.n_c * decay + 1.0
                f.n_cu = f.n_cu * decay
                continue
            if f.prev_unchanged:
                f.pend_u += 1.0
                if unchanged:
                    f.pend_uu += 1.0
            else:
                f.pend_c += 1.0
                if unchanged:
                    f.pend_cu += 1.0
            f.prev_unchanged = unchanged
            f.steps += 1
            if unchanged:
                self._frozen_run(i, f, t, x, alpha, out)
                continue
            # the value changed: the run ends
            if is_open and (SENSORS[i], "frozen") in is_open:
                self._close(SENSORS[i], "frozen", t, out)
                f.pend_c = f.pend_cu = f.pend_u = f.pend_uu = 0.0
            f.run = 1
            f.n_c = f.n_c * decay**f.pend_c + f.pend_c
            f.n_cu = f.n_cu * decay**f.pend_c + f.pend_cu
            if f.pend_u:  # (else decay**0 = 1 and nothing to add: the counts as they are)
                f.n_u = f.n_u * decay**f.pend_u + f.pend_u
                f.n_uu = f.n_uu * decay**f.pend_u + f.pend_uu
            f.pend_c = f.pend_cu = f.pend_u = f.pend_uu = 0.0

    def _frozen_run(
        self, i: int, f: _Frozen, t: int, x: list[float], alpha: float, out: list[SensorFault]
    ) -> None:
        """Input ``i`` read the same value again: its run grows; raise a frozen fault when
        the run is longer than its history makes plausible (see the module docstring)."""
        name = SENSORS[i]
        if f.run == 1:
            f.run_start_ns = self.last_ns if self.last_ns is not None else t
        f.run += 1
        if (name, "frozen") in self.open or f.n_c + f.n_u < _FROZEN_MIN_STEPS:
            return
        if self._at_bound(i, x[i]):
            return
        p0 = (f.n_cu + 0.5) / (f.n_c + 1.0)
        q = min((f.n_uu + 0.5) / (f.n_u + 1.0), 1.0 - 1e-12)
        limit = max(3, 1 + math.ceil(math.log(alpha / p0) / math.log(q)))
        if f.run >= limit:
            days = (t - f.run_start_ns) / _NS_PER_DAY
            self._raise(
                SensorFault(
                    name,
                    "frozen",
                    f.run_start_ns,
                    t,
                    f"{name} has read {x[i]:.6g}{_UNITS[name]} for {f.run} samples "
                    f"({days:.1f} days); its history makes a run of {limit} unchanged "
                    f"values less likely than {alpha:.2g} per sample (P(repeat) "
                    f"{p0:.3g}, P(repeat again) {q:.3g}).",
                ),
                out,
            )
            f.pend_c = f.pend_cu = f.pend_u = f.pend_uu = 0.0  # the fault is not history

    def _at_bound(self, i: int, v: float) -> bool:
        name = SENSORS[i]
        if name == "choke":
            return v <= 0.0 or v >= 1.0
        if name in ("eta_gas", "eta_oil"):
            return v <= 0.0
        return False

    # -- spike ------------------------------------------------------------------------------
    def _spike(
        self, t: int, x: list[float], gap_ok: bool, alpha: float, out: list[SensorFault]
    ) -> set[int]:
        """Was the pending sample a spike on some input? Decided with its successor ``x``."""
        p = self.pending
        before = self.last_values_before
        spiked: set[int] = set()
        if p is None or before is None or not (p.gap_ok and gap_ok):
            return spiked
        if p.choke_moved or abs(x[_CHOKE] - p.values[_CHOKE]) > _SAME:
            return spiked  # the process answers the operator
        z = _z_two_sided(alpha)
        values, changes, scale_at, added = p.values, self.changes, self.scale_at, self.changes_added
        for i in range(len(SENSORS)):
            if i == _CHOKE or len(changes[i]) < _SPIKE_MIN_CHANGES:
                continue
            if scale_at[i] < 0 or added[i] - scale_at[i] >= 16:
                self._spike_scale(i)
            s = self.scale[i]
            if not s > 0:
                continue
            up = values[i] - before[i]
            back = values[i] - x[i]
            zs = z * s
            if (
                abs(up) > zs
                and abs(back) > zs
                and up * back > 0
                and abs(x[i] - before[i]) < 0.5 * min(abs(up), abs(back))
            ):
                spiked.add(i)
                self._spike_event(i, (p.time_ns, t), up, back, s, z, out)
        return spiked

    def _spike_event(
        self,
        i: int,
        span: tuple[int, int],
        up: float,
        back: float,
        s: float,
        z: float,
        out: list[SensorFault],
    ) -> None:
        """Record a spike of input ``i`` (``span``: the spiked sample's time and its
        successor's, ns; ``up``, ``back``: the jump and the return; ``s``: the robust spread
        of its one-step changes; ``z``: the threshold in those)."""
        name = SENSORS[i]
        fault = SensorFault(
            name,
            "spike",
            span[0],
            span[1],
            f"{name} jumped by {up:+.4g}{_UNITS[name]} and came back by {-back:+.4g} "
            f"at the next sample, {abs(up) / s:.1f} times the robust spread of its "
            f"one-step changes ({s:.3g}{_UNITS[name]}; threshold {z:.2f}), with the "
            "choke unmoved.",
            end_ns=span[1],
        )
        self.events.append(fault)
        self.raised[f"{name}/spike"] = self.raised.get(f"{name}/spike", 0) + 1
        out.append(fault)

    def _spike_scale(self, i: int) -> float:
        """1.4826 MAD of input ``i``'s recent one-step changes (recomputed every 16 new ones:
        the median of a few hundred values is the costliest step per sample; :meth:`_spike`
        asks only when it is due)."""
        n = self.changes_added[i]
        if self.scale_at[i] < 0 or n - self.scale_at[i] >= 16:
            self.scale[i] = _MAD_TO_SD * _centre_mad(np.frombuffer(self.changes[i]))[1]
            self.scale_at[i] = n
        return self.scale[i]

    def _learn_changes(self, p: _Pending, spiked: set[int]) -> None:
        before = self.last_values_before
        if before is not None and p.gap_ok and not p.choke_moved:
            flagged = self.flagged() if self.open else ()
            added, values, full = self.changes_added, p.values, self.spike_window
            if not (spiked or flagged):  # the usual sample: every input learns its change
                for ch, v, b in zip(self.changes, values, before, strict=True):
                    if len(ch) >= full:
                        del ch[0]
                    ch.append(v - b)
                self.changes_added = [a + 1 for a in added]
                self.last_values_before = p.values
                return
            for i, (name, ch) in enumerate(zip(SENSORS, self.changes, strict=True)):
                if (spiked and i in spiked) or (flagged and name in flagged):
                    continue
                if len(ch) >= full:  # (_push, inline: six a sample)
                    del ch[0]
                ch.append(values[i] - before[i])
                added[i] += 1
        self.last_values_before = p.values

    # -- drift and offset (daily) -------------------------------------------------------------------
    def _daily(self, p: _Pending, spiked: set[int], out: list[SensorFault]) -> None:
        """The daily drift and offset tests, fed the decided sample ``p``."""
        if spiked:
            return  # a spiked sample is not part of any day's mean
        x = p.values
        t = p.time_ns
        day = t // _NS_PER_DAY
        self._day_context(day, x, p.choke_moved)
        day_n, day_sum, day_index, is_open = self.day_n, self.day_sum, self.day_index, self.open
        if not is_open:  # the usual sample: no input set aside (a day's close may raise a
            # drift or an offset, which sets none aside for the inputs after it)
            day_n[_CHOKE], day_sum[_CHOKE], self.cand[_CHOKE] = 0, 0.0, None  # no daily tests
            for i in range(1, len(SENSORS)):
                if day_n[i] and day != day_index[i]:
                    self._close_day(i, SENSORS[i], t, out)
                if not day_n[i]:
                    day_index[i], self.day_start_ns[i] = day, t
                day_sum[i] += x[i]
                day_n[i] += 1
            return
        flagged = self.flagged()
        for i, name in enumerate(SENSORS):
            # a frozen input is the frozen test's; another's fault would only repeat it
            if (
                i == _CHOKE
                or (flagged and any(s != name for s in flagged))
                or (is_open and (name, "frozen") in is_open)
            ):
                day_n[i], day_sum[i], self.cand[i] = 0, 0.0, None
                continue
            if day_n[i] and day != day_index[i]:
                self._close_day(i, name, t, out)
            if not day_n[i]:
                day_index[i], self.day_start_ns[i] = day, t
            day_sum[i] += x[i]
            day_n[i] += 1

    def _robust(self, key: tuple[str, int], ref: array[float]) -> tuple[float, float]:
        """Median and 1.4826 MAD of a reference of daily values, recomputed once about a
        twentieth of the reference is new (every 18 days with a year's, every day while it
        is under 40 days): n/20 new values barely move the median of n, and the cost per
        sample falls as much."""
        hit = self._robust_cache.get(key)
        if hit is not None:
            new = len(ref) // 20
            if self.samples - hit[0] < (new if new > 1 else 1) * self._spd:  # max(1, n // 20)
                return hit[1], hit[2]
        r = np.frombuffer(ref)
        centre, mad = _centre_mad(r)
        scale = _MAD_TO_SD * mad
        self._robust_cache[key] = (self.samples, centre, scale)
        if key[0] == "diff":  # the step test's limit follows the tail of its quiet days
            quiet = self.quiet[key[1]]
            tail = np.frombuffer(quiet) if len(quiet) >= _MIN_DAYS else r
            self._limits[key[1]] = self._tail_limit(tail, centre, scale)
        elif key[0] == "two":
            self._limits2[key[1]] = self._tail_limit(r, centre, scale)
        return centre, scale

    def _tail_limit(self, r: np.ndarray, centre: float, scale: float) -> float:
        """The step test's limit for one input, in robust sd: where the tail of its own
        scaled day-to-day changes ``|r - centre| / scale`` reaches the daily share
        ``a = budget / 365.25 / 2`` (two-sided; the one-day and the two-day change share the
        offset test's), and never below the Gaussian quantile of it.

        The tail is a peaks-over-threshold fit: beyond ``u``, the 90 % quantile of the
        scaled changes, the excesses are taken as exponential (a generalised Pareto of
        shape 0, the limit law of the Gaussian's, a mixture of Gaussians' and every
        light or moderate tail; the shape itself is too noisy to fit from the ~36
        excesses of a year), with their mean ``b`` as scale. Then ``P(|z| > T) =
        p_u exp(-(T - u) / b)`` with ``p_u`` the share beyond ``u``, and ``T = u + b
        ln(p_u / a)``. Why: a process's daily means are not Gaussian in their tails (a
        day of one sample against one of three, a wander with bursts), and a Gaussian
        limit on a heavier tail raises its false steps far above the budget; the
        exponential tail lies above the Gaussian's beyond ``u``, so for a Gaussian
        input the limit is conservative (median 5.7 sd over a year of changes, 10-90 %
        4.96-6.5, against the Gaussian 4.5)."""
        if not scale > 0:
            return self._z_day
        n = len(r)
        k = int(_TAIL_QUANTILE * (n - 1))  # the order statistic at the quantile
        kern = robust_kernels()
        u, count, total = (
            kern.tail_sum(r, centre, scale, k) if kern is not None else (math.nan, 0, math.nan)
        )
        if not math.isfinite(u):  # (no kernel, a value not finite, or many excesses)
            u, over = _excesses(r, centre, scale, k)
            count, total = len(over), float(over.sum())
        if count < 2:
            return self._z_day
        share = count / n
        mean = total / count  # np.mean's arithmetic, without its call cost
        limit = u + mean * math.log(share / self._step_alpha)
        return max(self._z_day, limit)

    def _samples_per_day(self) -> float:
        return max(1.0, _NS_PER_DAY / max(self._interval_ns(), 1.0))

    def _day_context(self, day: int, x: list[float], choke_moved: bool) -> None:
        """Raw daily means of all inputs: when a day closes, which inputs moved beyond
        ``_CO_MOVE`` robust sd of their own day-to-day changes (several moving at once is
        the process changing, not one transmitter), and whether the choke moved."""
        if self.raw_n and day != self.raw_day:
            self._close_raw_day(day)
        if not self.raw_n:
            self.raw_day = day
        self.raw_sum = list(map(operator.add, self.raw_sum, x))
        self.raw_n += 1
        self.raw_choke = self.raw_choke or choke_moved

    def _close_raw_day(self, day: int) -> None:
        """The raw daily means of the day before ``day`` are complete: which inputs moved
        (see :meth:`_day_context`)."""
        n = self.raw_n
        mean = [v / n for v in self.raw_sum]
        moved: set[int] = set()
        prev = self.raw_prev
        if prev is not None and day - prev[0] <= _MAX_DAY_GAP + 1:
            keys, cache, samples, spd = self._keys[2], self._robust_cache, self.samples, self._spd
            for j, (m, before, ref) in enumerate(zip(mean, prev[1], self.raw_diffs, strict=True)):
                diff = m - before
                n_ref = len(ref)
                if n_ref >= _MIN_DAYS:
                    hit = cache.get(keys[j])  # (:meth:`_robust`'s cached answer, inline)
                    if hit is not None and samples - hit[0] < max(1, n_ref // 20) * spd:
                        c, sc = hit[1], hit[2]
                    else:
                        c, sc = self._robust(keys[j], ref)
                    if sc > 0 and abs(diff - c) > _CO_MOVE * sc:
                        moved.add(j)
                if n_ref >= _REF_DAYS:  # (_push, inline)
                    del ref[0]
                ref.append(diff)
        self.day_moved = (moved, self.raw_choke or self.prev_raw_choke)
        self.prev_raw_choke = self.raw_choke
        self.raw_prev = (self.raw_day, mean)
        self.raw_sum, self.raw_n, self.raw_choke = [0.0] * len(SENSORS), 0, False

    def _confirm_step(
        self, i: int, name: str, mean: float, t: int, open_kind: str | None, out: list[SensorFault]
    ) -> bool:
        """A step candidate (a day when no other input moved and the choke stayed) is an
        offset once the level has held (at least halfway) for _CONFIRM_DAYS more days.
        True when it was raised now."""
        cand = self.cand[i]
        self.cand[i] = None
        if cand is None or open_kind is not None:
            return False
        step, level_before, c_start, z, held = cand
        level = mean - level_before
        if not (level * step > 0 and abs(level) > 0.5 * abs(step)):
            return False
        held += 1
        if held < _CONFIRM_DAYS:
            self.cand[i] = (step, level_before, c_start, z, held)
            return False
        unit = _UNITS[name]
        why = ""
        if i == _P_DOWN:
            reason, why = self._set_point(level_before, mean, step, c_start)
            if reason:
                self.set_points[reason] = self.set_points.get(reason, 0) + 1
                # the new level is the process's: no two-day change across the step again
                self.prev_alone[i] = False
                return False
        two = self.cand_days[i] == 2
        span, what, limit = (
            ("two days", "quiet two-day", self._limits2[i])
            if two
            else ("a day", "day-to-day", self._limits[i])
        )
        self._raise(
            SensorFault(
                name,
                "offset",
                c_start,
                t,
                f"{name} stepped by {step:+.4g}{unit} in {span} ({z:.1f} times the "
                f"robust spread of its {what} changes, threshold {limit:.2f} from "
                f"their own tail) and held there for {held} more days "
                f"({level:+.4g}{unit}); on the {'days' if two else 'day'} of the step "
                f"no other input moved beyond {_CO_MOVE:g} sd of its own and the choke "
                f"stayed.{why}",
            ),
            out,
        )
        self.offset_level[i] = (level_before, step)
        return True

    def _set_point(
        self, level_before: float, level: float, step: float, start_ns: int
    ) -> tuple[str, str]:
        """Whether a confirmed step of ``p_down`` (daily means ``level_before`` ->
        ``level``, bar a, from ``start_ns``) is a set-point change rather than an offset of
        consequence: ``(reason, "")`` with reason ``"critical"``, ``"slight"`` or
        ``"followed"`` when it
        is not raised, else ``("", sentence)`` for the offset's evidence.

        - ``critical``: ``p_down / p_up`` stays below the lowest critical ratio of the
          models' choke laws (:func:`critical_floor`) on both levels. The rate does not
          depend on ``p_down`` there: a transmitter offset changes no predicted rate, and
          nothing the well measures tells it from the separator's set point moving.
        - ``slight``: the flow may be subcritical, but under no choke law whose critical
          ratio is at or above that floor can the step move the mean log rate by more
          than the noise ``se`` of the change of the two means the ``followed`` test
          compares (:func:`p_down_consequence`: at most the liquid law's
          ``0.5 |ln((1 - y2) / (1 - y1))|``, the ratios clamped at the floor; ``se =
          s sqrt(1/n_before + 1/n_after)``, ``s`` the pooled sd below; 1 % when there are
          too few readings or none). Just above the critical ratio the rate is flat in
          ``p_down`` (its derivative is zero there). With the largest possible answer
          within one ``se``, that test has no power to tell a set point from a
          transmitter (a real answer would pass its 1 % limit in under 1 case of 10),
          and an offset of that size moves a week's predicted mean rate by less than
          the meter's noise of that mean.
        - ``followed``: the flow may be subcritical, and the MPFM's rate moved against
          the step (a higher back pressure, a lower rate) beyond its noise: the mean log
          rate of the readings since the step's day against those of the ``_FOLLOW_DAYS``
          days before, at the same choke (one-sided Student t at ``_FOLLOW_P``). A
          transmitter's offset moves the reading only, and the rate stays.
        """
        lv = self.levels
        if not (lv[1] and lv[3] and lv[4] and lv[5]) or not lv[1][-1][1] > 0:
            return "", ""  # nothing to judge the flow by: raised as before
        p_up = lv[1][-1][1]
        floor = critical_floor(p_up, lv[3][-1][1], lv[4][-1][1], lv[5][-1][1])
        ratio = max(level_before, level) / p_up
        if ratio < floor:
            return "critical", ""
        why = (
            f" p_down / p_up reached {ratio:.2f}, at or above the lowest critical ratio "
            f"{floor:.2f}: the rate may depend on p_down"
        )
        most = p_down_consequence(level_before / p_up, level / p_up, floor)
        rows = self.witness.readings.since(start_ns - _FOLLOW_DAYS * _NS_PER_DAY)
        after = rows[rows[:, 0] >= start_ns]
        if not len(after):
            if most < _WITNESS_MIN_LOG_SD:
                return "slight", ""
            return "", why + "; no meter reading since the step."
        before = rows[(rows[:, 0] < start_ns) & (rows[:, 2] == after[0, 2])]
        after = after[after[:, 2] == after[0, 2]]
        n_b, n_a = len(before), len(after)
        if n_b < MIN_READINGS or n_a < MIN_READINGS:
            if most < _WITNESS_MIN_LOG_SD:
                return "slight", ""
            return "", why + f"; too few meter readings at the step's choke ({n_b}, {n_a})."
        d = float(after[:, 1].mean() - before[:, 1].mean())
        dev = np.concatenate([before[:, 1] - before[:, 1].mean(), after[:, 1] - after[:, 1].mean()])
        sd = max(math.sqrt(float(dev @ dev) / (n_b + n_a - 2)), _WITNESS_MIN_LOG_SD)
        se = sd * math.sqrt(1.0 / n_b + 1.0 / n_a)  # the noise of the two means' change
        if most < se:
            return "slight", ""
        why += f" (by at most {100 * most:.1f} % of the rate; noise of the meter's means {100 * se:.1f} %)"
        from scipy.stats import t as student  # (rare: a confirmed p_down step)

        z = -math.copysign(1.0, step) * d / (sd * math.sqrt(1.0 / n_b + 1.0 / n_a))
        limit = float(student.ppf(1.0 - _FOLLOW_P, n_b + n_a - 2))
        if z > limit:
            return "followed", ""
        return "", why + (
            f", and the measured rate did not answer the step as a real change would: "
            f"{100 * d:+.1f} % over {n_a} meter readings against {n_b} before "
            f"({z:.1f} sd against it, a set-point change needs {limit:.1f})."
        )

    def _step_test(
        self,
        i: int,
        today: tuple[int, float, int],
        prev: tuple[int, float, int],
        diff: float,
        alone: bool,
        open_kind: str | None,
    ) -> None:
        """The step candidates of input ``i`` on a closed day (``today``: day, mean, start
        ns; ``prev``: the last closed day; ``diff``: their change per square-root day).

        Two changes are tested, each at half the offset test's daily share: one day's
        (today against the last day), robust-scaled by the last year's changes, and two
        days' (today against the day before the last), robust-scaled by the last year's
        quiet two-day changes: a transmitter that steps in the middle of a day puts half
        its step into each of two one-day changes and the whole of it into the two days'.
        A change is a candidate when it is beyond its limit (:meth:`_tail_limit`) and every
        day it spans was quiet (the choke still, no other input moving). The changes of
        days that are no candidate and carry no open fault join the references."""
        day, mean, start = today
        prev2, was_alone = self.day_prev2[i], self.prev_alone[i]
        self.day_prev2[i], self.prev_alone[i] = prev, alone
        fresh = self.cand[i] is None and open_kind is None
        ref = self.diffs[i]
        cache, spd, samples = self._robust_cache, self._spd, self.samples
        n = len(ref)
        if n >= _MIN_DAYS:
            # (:meth:`_robust`'s cached answer, inline: twice per input and day)
            hit = cache.get(self._keys[0][i])
            if hit is not None and samples - hit[0] < max(1, n // 20) * spd:
                centre, scale = hit[1], hit[2]
            else:
                centre, scale = self._robust(self._keys[0][i], ref)
            z = (diff - centre) / scale if scale > 0 else 0.0
            if fresh and alone and abs(z) > self._limits[i]:
                self.cand[i] = (mean - prev[1], prev[1], start, abs(z), 0)
                self.cand_days[i] = 1
        two = None
        if prev2 is not None and prev[0] - prev2[0] <= _MAX_DAY_GAP and was_alone and alone:
            two = (mean - prev2[1]) / math.sqrt(day - prev2[0])
        ref2 = self.quiet2[i]
        n2 = len(ref2)
        if two is not None and n2 >= _MIN_DAYS and prev2 is not None:
            hit = cache.get(self._keys[1][i])
            if hit is not None and samples - hit[0] < max(1, n2 // 20) * spd:
                centre, scale = hit[1], hit[2]
            else:
                centre, scale = self._robust(self._keys[1][i], ref2)
            z = (two - centre) / scale if scale > 0 else 0.0
            if fresh and self.cand[i] is None and abs(z) > self._limits2[i]:
                self.cand[i] = (mean - prev2[1], prev2[1], prev[2], abs(z), 0)
                self.cand_days[i] = 2
        if self.cand[i] is None and open_kind is None:  # (_push, inline)
            if n >= _REF_DAYS:
                del ref[0]
            ref.append(diff)
            if alone:  # the days the step test runs on: the null its limits are set from
                quiet = self.quiet[i]
                if len(quiet) >= _REF_DAYS:
                    del quiet[0]
                quiet.append(diff)
            if two is not None:
                if n2 >= _REF_DAYS:
                    del ref2[0]
                ref2.append(two)

    def _close_day(self, i: int, name: str, t: int, out: list[SensorFault]) -> None:
        """A day of input ``i`` is complete: test its mean against the day before."""
        mean = self.day_sum[i] / self.day_n[i]
        day, start = self.day_index[i], self.day_start_ns[i]
        self.levels[i].append((day, mean))
        self.day_sum[i], self.day_n[i] = 0.0, 0
        prev = self.day_prev[i]
        self.day_prev[i] = today = (day, mean, start)
        if prev is None or day - prev[0] > _MAX_DAY_GAP:
            self.cand[i], self.day_prev2[i] = None, None
            return
        # per square-root day between the two: the wander of a process grows so with time,
        # and a day-to-day change across a gap of two or three days must not look bigger
        diff = (mean - prev[1]) / math.sqrt(day - prev[0])
        cus = self.cusums[i]
        was = cus.alarm
        open_kind = (
            next((k for (s, k) in self.open if s == name and k in ("drift", "offset")), None)
            if self.open
            else None
        )
        moved, choke = self.day_moved
        alone = not choke and (not moved or (len(moved) == 1 and i in moved))  # none but i
        set_aside = False
        if self.cand[i] is not None:
            aside = sum(self.set_points.values())
            if self._confirm_step(i, name, mean, t, open_kind, out):
                open_kind = "offset"
            set_aside = sum(self.set_points.values()) > aside
        self._step_test(i, today, prev, diff, alone, open_kind)
        # a drift: a CUSUM on the day-to-day changes (a ramp shifts their mean). The
        # changes of a step candidate's days wait for the step test's verdict: a step
        # (raised, or set aside as a set point) is no trend, and its one or two days of
        # change would otherwise raise a drift after a little wander (each counts up to the
        # CUSUM's clip): they join only its reference (the spread, as before); a
        # candidate whose level did not hold feeds them late
        wait = self.drift_wait[i]
        if open_kind == "offset" or set_aside:
            for late, _ in wait:
                cus.add_reference(late)
            wait.clear()
        if self.cand[i] is not None:
            wait.append((diff, t))
        elif open_kind != "offset":
            for late, t_late in wait:
                cus.update(late, t_late)
            wait.clear()
            cus.update(diff, t)
        if open_kind is None and not was and not cus.alarm:  # the usual day: nothing happens
            if cus.statistic == 0.0:
                self.cusum_zero_ns[i] = t
            return
        self._drift_and_ends(i, name, t, (mean, start), was, open_kind, out)

    def _critical_drift(self, i: int, mean: float) -> bool:
        """Whether a drift alarm of input ``i`` (today's daily mean ``mean``) is a ``p_down``
        drift in critical flow: ``p_down / p_up`` below the lowest critical ratio of the
        models' choke laws (:func:`critical_floor`) on every day since the CUSUM last stood
        at zero and today. The rate does not depend on ``p_down`` there: a drifting
        transmitter changes no predicted rate, and a set point's wander is the same to one
        well's inputs; the rule of the ``p_down`` steps (:meth:`_set_point`)."""
        lv = self.levels
        if i != _P_DOWN or not (lv[1] and lv[3] and lv[4] and lv[5]) or not lv[1][-1][1] > 0:
            return False
        p_up = lv[1][-1][1]
        floor = critical_floor(p_up, lv[3][-1][1], lv[4][-1][1], lv[5][-1][1])
        zero = self.cusum_zero_ns[i]
        since = -1 if zero is None else zero // _NS_PER_DAY
        highest = max([mean] + [m for d, m in lv[i] if d >= since])
        return highest / p_up < floor

    def _drift_and_ends(
        self,
        i: int,
        name: str,
        t: int,
        today: tuple[float, int],
        was: bool,
        open_kind: str | None,
        out: list[SensorFault],
    ) -> None:
        """After input ``i``'s CUSUM took a closed day (``today``: its mean and start ns;
        ``was``: the CUSUM's alarm before it; ``open_kind``: the input's open drift or
        offset): raise a drift, close a drift or offset that ended, accept a level that
        held ``accept_days``."""
        mean, start = today
        cus = self.cusums[i]
        if cus.alarm and not was and open_kind is None and self._critical_drift(i, mean):
            # of no consequence (the rate does not depend on p_down): counted, not raised;
            # the CUSUM keeps its alarm, so the same drift is not asked again
            self.drifts_set_aside += 1
        elif cus.alarm and not was and open_kind is None:
            self._raise(
                SensorFault(
                    name,
                    "drift",
                    self.cusum_zero_ns[i] or start,
                    t,
                    f"{name} has moved {'up' if cus.direction == 'high' else 'down'} day after "
                    f"day beyond its own history (CUSUM of its daily changes "
                    f"{cus.statistic:.2f} > threshold {cus.threshold:.2f}, "
                    f"{self.arl0_days:.0f} days between false alarms).",
                ),
                out,
            )
        elif open_kind == "drift" and not cus.alarm:
            self._close(name, "drift", t, out)
        elif open_kind == "offset":
            level_before, step = self.offset_level[i] or (0.0, 0.0)
            if abs(mean - level_before) < 0.5 * abs(step):
                self._close(name, "offset", t, out)
        if cus.statistic == 0.0:
            self.cusum_zero_ns[i] = t
        fault = self.open.get((name, open_kind)) if open_kind else None
        if fault is not None and (t - fault.detected_ns) / _NS_PER_DAY >= self.accept_days:
            fault.evidence += (
                f" After {self.accept_days:g} days the new level is taken as real "
                "(a set point moved, or the fault stays): the tests start again from it."
            )
            self._close(name, str(open_kind), t, out)
            self.cusums[i] = self._new_cusum()
            self.cusum_zero_ns[i] = t

    # -- state --------------------------------------------------------------------------------
    def hyperparameters(self) -> dict[str, Any]:
        return {
            "false_per_well_year": self.false_per_well_year,
            "ranges": {k: list(v) for k, v in self.ranges.items()},
            "frozen_memory": self.frozen_memory,
            "spike_window": self.spike_window,
            "lags": self.lags,
            "accept_days": self.accept_days,
        }

    def state(self) -> dict[str, Any]:
        """Plain values (JSON) to resume the detectors where they were after a restart."""
        p = self.pending
        return {
            "hyperparameters": self.hyperparameters(),
            "samples": self.samples,
            "intervals": list(self.intervals),
            "last_ns": self.last_ns,
            "last_values": self.last_values,
            "last_values_before": self.last_values_before,
            "frozen": [vars(f).copy() for f in self.frozen],
            "changes": [list(c) for c in self.changes],
            "pending": None
            if p is None
            else {"time_ns": p.time_ns, "values": p.values, "moved": p.choke_moved, "ok": p.gap_ok},
            "cusums": [c.state_dict() for c in self.cusums],
            "cusum_zero_ns": self.cusum_zero_ns,
            "day": [self.day_index, self.day_start_ns, self.day_sum, self.day_n],
            "day_prev": [None if d is None else list(d) for d in self.day_prev],
            "diffs": [list(d) for d in self.diffs],
            "quiet": [list(d) for d in self.quiet],
            "quiet2": [list(d) for d in self.quiet2],
            "day_prev2": [None if d is None else list(d) for d in self.day_prev2],
            "prev_alone": list(self.prev_alone),
            "cand_days": list(self.cand_days),
            "cand": [None if c is None else list(c) for c in self.cand],
            "offset_level": [None if c is None else list(c) for c in self.offset_level],
            "drift_wait": [[list(p) for p in w] for w in self.drift_wait],
            "raw": [
                self.raw_day,
                self.raw_n,
                list(self.raw_sum),
                self.raw_choke,
                self.prev_raw_choke,
            ],
            "raw_prev": None
            if self.raw_prev is None
            else [self.raw_prev[0], list(self.raw_prev[1])],
            "raw_diffs": [list(d) for d in self.raw_diffs],
            "day_moved": [sorted(self.day_moved[0]), self.day_moved[1]],
            "events": [e.state() for e in self.events],
            "open": [[s, k] for (s, k) in self.open],
            "raised": dict(self.raised),
            "levels": [[list(d) for d in q] for q in self.levels],
            "witness": self.witness.state(),
            "anchors": {  # NaN (no level or scale yet) as null: plain JSON
                k: [x if math.isfinite(x) else None for x in v] for k, v in self.anchors.items()
            },
            "tracks": {k: list(v) for k, v in self.tracks.items()},
            "wanders": {k: v if math.isfinite(v) else None for k, v in self.wanders.items()},
            "set_points": dict(self.set_points),
            "drifts_set_aside": self.drifts_set_aside,
        }

    def restore(self, data: Mapping[str, Any]) -> bool:
        """Resume from :meth:`state`. Returns False (and starts afresh) when the state was
        saved under other hyperparameters: its thresholds would mean something else."""
        if data.get("hyperparameters") != self.hyperparameters():
            self._reset()
            return False
        self._reset()
        self.samples = int(data["samples"])
        self.intervals.extend(int(v) for v in data["intervals"])
        self.last_ns = data["last_ns"]
        self.last_values = data["last_values"]
        self.last_values_before = data["last_values_before"]
        self.frozen = [_Frozen(**f) for f in data["frozen"]]
        for w, saved in zip(self.changes, data["changes"], strict=True):
            _refill(w, saved, self.spike_window)
        p = data.get("pending")
        self.pending = (
            None
            if p is None
            else _Pending(int(p["time_ns"]), list(p["values"]), bool(p["moved"]), bool(p["ok"]))
        )
        for cus, saved in zip(self.cusums, data["cusums"], strict=True):
            cus.load_state_dict(saved)
        self.cusum_zero_ns = list(data["cusum_zero_ns"])
        index, start, total, count = data["day"]
        self.day_index, self.day_start_ns = [int(v) for v in index], [int(v) for v in start]
        self.day_sum, self.day_n = [float(v) for v in total], [int(v) for v in count]
        self.day_prev = [
            None if d is None else (int(d[0]), float(d[1]), int(d[2])) for d in data["day_prev"]
        ]
        for w, saved in zip(self.diffs, data["diffs"], strict=True):
            _refill(w, saved, _REF_DAYS)
        # absent from older checkpoints: the step test's tail is then the diffs' own
        n = len(SENSORS)
        for w, saved in zip(self.quiet, data.get("quiet") or [[]] * n, strict=True):
            _refill(w, saved, _REF_DAYS)
        for w, saved in zip(self.quiet2, data.get("quiet2") or [[]] * n, strict=True):
            _refill(w, saved, _REF_DAYS)
        self.day_prev2 = [
            None if d is None else (int(d[0]), float(d[1]), int(d[2]))
            for d in data.get("day_prev2") or [None] * n
        ]
        self.prev_alone = [bool(v) for v in data.get("prev_alone") or [False] * n]
        self.cand_days = [int(v) for v in data.get("cand_days") or [1] * n]
        self.cand = [
            None if c is None else (float(c[0]), float(c[1]), int(c[2]), float(c[3]), int(c[4]))
            for c in data["cand"]
        ]
        self.offset_level = [
            None if c is None else (float(c[0]), float(c[1])) for c in data["offset_level"]
        ]
        self.drift_wait = [  # (absent in a state saved before it: nothing waits)
            [(float(d), int(t)) for d, t in w] for w in data.get("drift_wait") or [[]] * n
        ]
        self.events.extend(SensorFault.from_state(e) for e in data["events"])
        by_key = {(e.sensor, e.kind): e for e in self.events if e.end_ns is None}
        for s, k in data["open"]:
            if (s, k) in by_key:
                self.open[(s, k)] = by_key[(s, k)]
        self.raised = {str(k): int(v) for k, v in data["raised"].items()}
        self.set_points = {str(k): int(v) for k, v in (data.get("set_points") or {}).items()}
        self.drifts_set_aside = int(data.get("drifts_set_aside", 0))  # absent: older state
        raw_day, raw_n, raw_sum, self.raw_choke, self.prev_raw_choke = data["raw"]
        self.raw_day, self.raw_n = int(raw_day), int(raw_n)
        self.raw_sum = [float(v) for v in raw_sum]
        rp = data["raw_prev"]
        self.raw_prev = None if rp is None else (int(rp[0]), [float(v) for v in rp[1]])
        for w, saved in zip(self.raw_diffs, data["raw_diffs"], strict=True):
            _refill(w, saved, _REF_DAYS)
        self.day_moved = ({int(j) for j in data["day_moved"][0]}, bool(data["day_moved"][1]))
        self._restore_fallback(data)
        if data.get("witness"):  # absent from older checkpoints: it starts afresh
            self.witness.restore(data["witness"])
        for i in range(len(SENSORS)):
            self.scale_at[i] = -1
        return True

    def _restore_fallback(self, data: Mapping[str, Any]) -> None:
        """The stand-ins' state from :meth:`state`: the levels, the open faults' anchors,
        wanders and witness tracks (each absent from older checkpoints)."""
        # the fallback's levels and anchors (absent from older checkpoints: an anchor is then
        # made when first asked for, from what the detectors hold)
        for q, saved in zip(self.levels, data.get("levels") or [[]] * len(SENSORS), strict=True):
            q.extend((int(d), float(m)) for d, m in saved)
        self.anchors = {
            str(k): (_num(v[0]), _num(v[1]), _num(v[2]), int(v[3]))
            for k, v in (data.get("anchors") or {}).items()
            if (str(k).split("/")[0], str(k).split("/")[-1]) in self.open
        }
        self.tracks = {  # absent from older checkpoints: the stand-in starts uncorrected
            str(k): _saved_track(v)
            for k, v in (data.get("tracks") or {}).items()
            if (str(k).split("/")[0], str(k).split("/")[-1]) in self.open
        }
        self.wanders = {
            str(k): _num(v)
            for k, v in (data.get("wanders") or {}).items()
            if (str(k).split("/")[0], str(k).split("/")[-1]) in self.open
        }

    def view(self) -> list[dict[str, Any]]:
        """The recent events, newest last, as ``GET /wells/{well}`` shows ``sensor_faults``."""
        return [e.as_dict() for e in list(self.events)]  # a copy: the worker appends


def mpfm_rates(g: Any) -> list[float]:
    """Per row of a frame, its MPFM rate (Sm3/h; NaN on other rows, or without the
    ``source`` and ``q_total`` columns)."""
    import pandas as pd

    if "q_total" not in g.columns or "source" not in g.columns:
        return [math.nan] * len(g)
    q = pd.to_numeric(g["q_total"], errors="coerce").to_numpy(dtype=float)
    return np.where(g["source"].astype(str).to_numpy() == "mpfm", q, np.nan).tolist()


def feed_frame(det: WellSensorFaults, g: Any) -> list[SensorFault]:
    """Feed one well's rows (a frame with ``time`` and the six inputs, in time order;
    ``source`` and ``q_total`` give the MPFM's rates) to ``det`` as the service feeds them
    live: each distinct sample time once, then a row's MPFM rate to the choke-rate witness.
    Returns the faults that began or ended (each once, in the order first seen)."""
    import pandas as pd

    times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64").to_numpy()
    values = g[list(SENSORS)].to_numpy(dtype=float)
    seen: dict[int, SensorFault] = {}
    last: int | None = None
    for t, row, q in zip(times.tolist(), values.tolist(), mpfm_rates(g), strict=True):
        if t != last:  # a second row at one time carries only its measurement
            for e in det.update(t, row):
                seen[id(e)] = e
            last = t
        if math.isfinite(q):
            for e in det.measure(t, q, row):
                seen[id(e)] = e
    return list(seen.values())


def faults_of_frame(frame: Any, **hyperparameters: Any) -> list[dict[str, Any]]:
    """Run one :class:`WellSensorFaults` per well over an observation frame (columns
    ``time``, ``well`` and the six inputs; ``source`` and ``q_total`` feed the MPFM's rates
    to the choke-rate witness) in time order, as the service does live.
    Returns every event as a dict (:meth:`SensorFault.as_dict` plus ``well``)."""

    out: list[dict[str, Any]] = []
    f = frame.sort_values(["well", "time"], kind="stable")
    for well, g in f.groupby("well", sort=True):
        for e in feed_frame(WellSensorFaults(**hyperparameters), g):
            out.append({"well": str(well), **e.as_dict()})
    out.sort(key=lambda d: (d["well"], d["start"] or "", d["sensor"], d["kind"]))
    return out


def write_sensor_faults(frame: Any, out_dir: Any, **hyperparameters: Any) -> Any:
    """Write ``out_dir/sensor_faults.json``: ``{"sensor_faults": [{well, sensor, kind,
    start, end, evidence, detected}], "hyperparameters", "wells", "well_years"}`` over the
    whole frame (every well, every row in time order). Returns the path."""
    import json
    import os
    import tempfile
    from pathlib import Path

    import pandas as pd

    faults = faults_of_frame(frame, **hyperparameters)
    times = pd.to_datetime(frame["time"], utc=True)
    spans = times.groupby(frame["well"]).agg(["min", "max"])
    well_years = float(((spans["max"] - spans["min"]).dt.total_seconds() / 86_400 / 365.25).sum())
    doc = {
        "sensor_faults": faults,
        "hyperparameters": WellSensorFaults(**hyperparameters).hyperparameters(),
        "wells": int(len(spans)),
        "well_years": well_years,
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "sensor_faults.json"
    fd, temp = tempfile.mkstemp(prefix=".sensor_faults-", dir=out)
    with os.fdopen(fd, "w") as fh:
        json.dump(doc, fh, indent=2)
    os.replace(temp, path)
    return path
