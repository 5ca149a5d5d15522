"""Instrument faults in the study: what the service does at a faulty input, offline.

The service (``service/engine``) feeds every sample of a well to its instrument-fault
detectors (:class:`vfm_core.sensor_faults.WellSensorFaults`) before it predicts it. While an
input has an open fault of :data:`~vfm_core.sensor_faults.FALLBACK_KINDS` (frozen, out of
range) it predicts the sample with a stand-in for that input and a widened interval
(:meth:`~vfm_core.sensor_faults.WellSensorFaults.fallbacks`,
:func:`~vfm_core.sensor_faults.fallback_points`, :func:`~vfm_core.sensor_faults.widened_rates`),
and a measurement whose paired sample lies in a fault of
:data:`~vfm_core.sensor_faults.HOLD_KINDS` is held (stored, not learned from).

:func:`plan_sensor_faults` runs the same detectors over a study's frame, every well's
samples in time order as the service receives them (one sample per well and time: a second
row at the same time carries only its measurement, as the replay sends it), and notes per
row what the service would do: ``held`` (a measurement there is not learned) and the
stand-ins its prediction uses. A row's MPFM rate is fed after its sample, as the service
feeds a paired rate (the choke-rate witness, :mod:`vfm_core.rate_witness`). The detectors
see the inputs and the MPFM's rates, never a model, so the plan is the same for every
model and method and is made once per study.
:func:`fallback_rates` asks a study's learning method for a row's rates at the stand-ins,
as ``Learning.fallback`` asks the service's learner, and widens them with the same
function. The hold is checked right after the paired sample is fed to the detectors, as
in the service when a measurement comes after its sample: a spike, decided only when the
next sample arrives, is then learned (it would be held if the measurement came later).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import Batch
from vfm_core.learning.method import Forecast
from vfm_core.learning.streaming import phase_split
from vfm_core.schema import MPFM, SOURCE, TARGET, TIME, WELL
from vfm_core.sensor_faults import (
    DEFAULT_RANGES,
    SENSORS,
    Fallback,
    Track,
    WellSensorFaults,
    fallback_points,
    mpfm_rates,
    residual_noise,
    tracked,
    widened_rates,
    witness_track,
)

__all__ = ["FaultPlan", "StandInTracks", "plan_sensor_faults", "fallback_rates", "fault_counts"]

#: learned residuals per well whose spread is a witness's noise (the service keeps as many:
#: ``well_test_review.residuals``)
_RESIDUALS = 50


@dataclass
class FaultPlan:
    """What the service's instrument-fault handling does at each row of one frame.

    ``held`` [len(frame)]: True where a measurement is not learned from (its sample lies in
    a fault of :data:`~vfm_core.sensor_faults.HOLD_KINDS` once the sample is seen);
    ``stand_ins``: by row position, the stand-ins (one per flagged input) its prediction
    uses; rows absent use every input as read; ``out_of_span``: the rows that are never
    learned from, whatever the split (an impossible reading teaches nothing; the loader
    keeps them only for ``vfm evaluate``, ``keep_out_of_range``)."""

    held: np.ndarray
    stand_ins: dict[int, tuple[Fallback, ...]] = field(default_factory=dict)
    #: [len(frame)] rows whose sample has an input outside its physical span (an
    #: ``out_of_range`` fault): never learned from, before the split either (None: none)
    out_of_span: np.ndarray | None = None

    def acts_on(self, rows: np.ndarray) -> bool:
        """True when any of ``rows`` (positions) is held or predicted with a stand-in."""
        return bool(self.held[rows].any()) or any(int(r) in self.stand_ins for r in rows)

    def replaced(self, rows: np.ndarray) -> list[str]:
        """For each of ``rows``, the sensors its prediction stands in for ("p_up", or
        "p_up,t_up"; "" for none)."""
        return [",".join(f.sensor for f in self.stand_ins.get(int(r), ())) for r in rows]


def plan_sensor_faults(frame: pd.DataFrame, **hyperparameters: Any) -> FaultPlan:
    """Run one :class:`WellSensorFaults` (``hyperparameters``: its ``__init__`` arguments)
    per well over ``frame`` (columns ``time``, ``well`` and the six inputs), each well's
    distinct sample times in order, and note per row what the service would do there (see
    :class:`FaultPlan`). Rows of one well at one time share its sample's answer."""
    n = len(frame)
    held = np.zeros(n, dtype=bool)
    stand_ins: dict[int, tuple[Fallback, ...]] = {}
    times = pd.to_datetime(frame[TIME], utc=True).dt.as_unit("ns").astype("int64").to_numpy()
    values = frame[list(SENSORS)].to_numpy(dtype=float)
    wells = frame[WELL].astype(str).to_numpy()
    mpfm = np.asarray(mpfm_rates(frame), dtype=float)
    spans = {**DEFAULT_RANGES, **(hyperparameters.get("ranges") or {})}
    low = np.array([spans[name][0] for name in SENSORS])
    high = np.array([spans[name][1] for name in SENSORS])
    with np.errstate(invalid="ignore"):
        out_of_span = np.isfinite(values).all(axis=1) & ((values < low) | (values > high)).any(
            axis=1
        )
    for well in dict.fromkeys(wells.tolist()):
        rows = np.flatnonzero(wells == well)
        rows = rows[np.argsort(times[rows], kind="stable")]
        det = WellSensorFaults(**hyperparameters)
        last_t: int | None = None
        used: tuple[Fallback, ...] = ()
        in_fault = False
        for pos in rows.tolist():
            t = int(times[pos])
            if t != last_t:  # a new sample: fed to the detectors, then predicted
                row = values[pos].tolist()
                det.update(t, row)
                used = tuple(det.fallbacks(t, row)) if det.stands_in() else ()
                in_fault = det.suspect(t, values=row) is not None
                last_t = t
            if math.isfinite(mpfm[pos]):  # the choke-rate witness (vfm_core.rate_witness)
                det.measure(t, float(mpfm[pos]), values[pos].tolist())
                # as the service: the rate fed first, then the hold asked (a choke offset
                # found, or in doubt, with this very reading)
                in_fault = det.suspect(t, values=values[pos].tolist()) is not None
            held[pos] = in_fault
            if used:
                stand_ins[pos] = used
    return FaultPlan(held, stand_ins, out_of_span if out_of_span.any() else None)


def _points_batch(batch: Batch, w: int, s: int, points: list[list[float]]) -> Batch:
    """Sample ``s`` of well ``w`` of ``batch`` once per point of ``points`` (its six inputs
    replaced by the point's; time, meter and features as they were), the other wells
    without samples: one model call answers every point."""
    k = len(points)
    assert batch.well_test is not None and batch.extra is not None
    mask = torch.zeros(batch.n_wells, k, dtype=torch.bool)
    mask[w] = True
    x = batch.x[:, s : s + 1].expand(-1, k, -1).clone()
    x[w] = torch.tensor(points, dtype=batch.x.dtype)
    return Batch(
        batch.wells,
        x,
        torch.zeros(batch.n_wells, k, dtype=batch.y.dtype),
        mask,
        batch.time_ns[:, s : s + 1].expand(-1, k).clone(),
        batch.row[:, s : s + 1].expand(-1, k).clone(),
        batch.well_test[:, s : s + 1].expand(-1, k) & mask,
        batch.extra[:, s : s + 1].expand(-1, k, -1).clone(),
        batch.extra_names,
    )


def _answers(forecast: Forecast, w: int, x: torch.Tensor) -> list[dict[str, float | None]]:
    """Well ``w``'s answers in ``forecast`` (one per point, inputs ``x`` [K, 6]) as the
    service's learner gives them: ``q_total``, its phase split, and ``q_total_std``,
    ``q_total_p05``, ``q_total_p95`` where the method gives them."""
    mean = forecast.mean[w : w + 1]
    phases = phase_split(mean, x.unsqueeze(0))
    out: list[dict[str, float | None]] = []
    for j in range(mean.shape[1]):
        a: dict[str, float | None] = {"q_total": float(mean[0, j])}
        a.update({name: float(q[0, j]) for name, q in phases.items()})
        a["q_total_std"] = None if forecast.std is None else float(forecast.std[w, j])
        if forecast.p05 is not None and forecast.p95 is not None:
            a["q_total_p05"] = float(forecast.p05[w, j])
            a["q_total_p95"] = float(forecast.p95[w, j])
        out.append(a)
    return out


class StandInTracks:
    """The measured rates as witnesses of the stood-in inputs in one run of a study, as the
    service's detectors keep them (:meth:`WellSensorFaults.follow_rate
    <vfm_core.sensor_faults.WellSensorFaults.follow_rate>`): per well and fault, the correction
    of the plan's stand-ins (:func:`~vfm_core.sensor_faults.tracked`), one Kalman step per
    measurement at a stood-in sample after its prediction
    (:func:`~vfm_core.sensor_faults.witness_track`). Only the MPFM's rates witness (the
    well's steady meter; a well test is rare); their bias and noise about the model are
    those of the well's last 50 learned MPFM log residuals before the fault's first
    witness (:func:`~vfm_core.sensor_faults.residual_noise`), as the service's.

    ``frame``: the study's rows; ``learned`` [len(frame)]: the rows learned from (their
    residuals count); ``hidden`` [len(frame)]: rows whose measurement never arrives (an
    outage: no witness); ``predicted``: the run's predictions by row (Sm3/h), filled as it
    goes."""

    def __init__(
        self,
        frame: pd.DataFrame,
        learned: np.ndarray,
        hidden: np.ndarray,
        predicted: np.ndarray,
    ) -> None:
        self.measured = frame[TARGET].to_numpy(dtype=float)
        self.times = pd.to_datetime(frame[TIME], utc=True).dt.as_unit("ns").astype("int64")
        self.times = self.times.to_numpy()
        self.wells = frame[WELL].astype(str).to_numpy()
        self.mpfm = (frame[SOURCE].astype(str) == MPFM).to_numpy()
        self.learned, self.hidden, self.predicted = learned, hidden, predicted
        self.tracks: dict[tuple[str, str, str, int], Track] = {}
        self._rows: dict[str, np.ndarray] = {}

    def _key(self, row: int, f: Fallback) -> tuple[str, str, str, int]:
        return (str(self.wells[row]), f.sensor, f.kind, f.start_ns)

    def apply(self, row: int, used: tuple[Fallback, ...]) -> tuple[Fallback, ...]:
        """The plan's stand-ins of ``row`` corrected by the witnesses so far."""
        t = int(self.times[row])
        return tuple(
            tracked(f, self.tracks.get(self._key(row, f)), DEFAULT_RANGES[f.sensor], t)
            for f in used
        )

    def noise(self, row: int) -> tuple[float, float]:
        """The bias and noise of the well's last learned MPFM log residuals before ``row``."""
        well = str(self.wells[row])
        if well not in self._rows:
            rows = np.flatnonzero((self.wells == well) & self.learned & self.mpfm)
            self._rows[well] = rows[np.argsort(self.times[rows], kind="stable")]
        rows = self._rows[well]
        rows = rows[self.times[rows] < self.times[row]]
        q, m = self.predicted[rows], self.measured[rows]
        ok = np.isfinite(q) & np.isfinite(m) & (q > 0) & (m > 0)
        return residual_noise(np.log(m[ok] / q[ok])[-_RESIDUALS:].tolist())

    def witness(
        self, row: int, used: tuple[Fallback, ...], answers: list[dict[str, float | None]]
    ) -> None:
        """The measurement at ``row`` (predicted with ``used`` and the model's ``answers``
        at their points) taken as a witness, as :meth:`WellSensorFaults.follow_rate` takes it."""
        q = float(self.measured[row])
        if len(used) != 1 or self.hidden[row] or not self.mpfm[row]:
            return
        if not (math.isfinite(q) and q > 0):
            return
        f = used[0]
        key = self._key(row, f)
        before = self.tracks.get(key)
        noise = before[3:5] if before is not None else self.noise(row)
        t = int(self.times[row])
        after = witness_track(f, before, answers, q, noise, t, DEFAULT_RANGES[f.sensor])
        if after is not None:
            self.tracks[key] = after


def fallback_rates(
    predict: Callable[[Batch], Forecast],
    batch: Batch,
    where: torch.Tensor,
    stand_ins: Mapping[int, tuple[Fallback, ...]],
    tracks: StandInTracks | None = None,
) -> dict[int, dict[str, float | None]]:
    """The rates (Sm3/h) of the ``where`` samples of ``batch`` that have stand-ins, by row
    position: the method (``predict``, at its state now: the sample's own prediction's)
    asked at :func:`fallback_points` and the answers widened by :func:`widened_rates`, as
    the service's ``Learning.fallback`` does. A row whose stand-in answer is not finite keeps
    its prediction at the readings (absent), as in the service. With ``tracks``, each
    well's samples in order: the stand-ins corrected by the measurements before, then the
    sample's own measurement taken as a witness (after its prediction: prequential)."""
    out: dict[int, dict[str, float | None]] = {}
    found = torch.nonzero(where & (batch.row >= 0)).tolist()
    for w, s in found:
        row = int(batch.row[w, s])
        used = stand_ins.get(row)
        if not used:
            continue
        if tracks is not None:
            used = tracks.apply(row, used)
        points = fallback_points(batch.x[w, s].tolist(), used)
        one = _points_batch(batch, w, s, points)
        with torch.no_grad():
            forecast = predict(one)
        answers = _answers(forecast, w, one.x[w])
        rates = widened_rates(answers)
        q = rates.get("q_total")
        if q is not None and math.isfinite(q):
            out[row] = rates
        if tracks is not None:
            tracks.witness(row, used, answers)
    return out


def fault_counts(predictions: pd.DataFrame) -> dict[str, dict[str, int]]:
    """Per well, the scored measurements held at a fault (``held_at_fault``) and those
    predicted with a stand-in (``fallback_at_fault``), from one run's ``predictions`` (the
    plan is the same for every model and method: the first run's rows are counted; zero
    where the predictions carry no ``held`` / ``fallback`` column)."""
    wells = list(dict.fromkeys(predictions["well"].astype(str))) if len(predictions) else []
    held = dict.fromkeys(wells, 0)
    fallback = dict.fromkeys(wells, 0)
    if len(predictions) and "held" in predictions.columns:
        first = predictions.iloc[0]
        one = predictions[
            (predictions["model"] == first["model"]) & (predictions["method"] == first["method"])
        ]
        for well, g in one.groupby(one["well"].astype(str), sort=False):
            held[well] = int(g["held"].fillna(False).astype(bool).sum())
            fallback[well] = int((g["fallback"].fillna("").astype(str) != "").sum())
    return {"held_at_fault": held, "fallback_at_fault": fallback}
