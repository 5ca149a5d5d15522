"""Prequential evaluation: every observation after the split is predicted before the model learns from it.

:func:`run_prequential` runs one model with one learning method on one target case and
returns every scored prediction; :func:`mape` and :func:`metrics_records` turn those into
the numbers of the paper's tables.

Two extensions of the ordinary protocol:

- **Outages** (:func:`plan_outages`, ``run_prequential(..., outage=plan)``): windows of a
  given length in the test period in which the well's measurements are hidden, as when its
  multiphase meter has failed. Inside a window every measurement is predicted (and scored)
  but nothing learns from it: no online step, no retrain reads it, and ``last`` keeps the
  value from before the window. Since a failed MPFM gives no phase fractions either, the
  inputs ``eta_gas`` and ``eta_oil`` are by default held at the well's last measured row
  before the window (``fractions="held"``); ``"measured"`` keeps the file's values.
- **Phases** (``run_prequential(..., phases=True)``): the predicted total at standard
  conditions split into gas, oil and water by the sample's mass fractions and the model's
  densities (:func:`vfm_core.learning.streaming.phase_split`: learned ``rho_oil``, ``rho_wat``,
  ``m_gas`` of a physics model at the time of the prediction, else the prior means),
  scored against the file's ``q_gas``, ``q_oil``, ``q_water``.
"""

from __future__ import annotations

import copy
import math
import re
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import torch
from scipy.special import ndtr

from vfm_core.data import TARGET_CASES, Batch, make_batch, target_mask
from vfm_core.errors import ConfigError, DataError
from vfm_core.jobs.study_faults import FaultPlan, StandInTracks, fallback_rates
from vfm_core.learning import (
    DEFAULT_TRAIN,
    NEVER,
    FrameMemory,
    LearningMethod,
    OnlineSettings,
    TrainSettings,
    parse_method,
)
from vfm_core.learning.streaming import phase_split
from vfm_core.models import ChokeModel, make_model
from vfm_core.schema import INPUT_COLUMNS, OPTIONAL_RATE_COLUMNS, SOURCE, TARGET, TIME, WELL

__all__ = [
    "PHASES",
    "OUTAGE_FRACTIONS",
    "Outage",
    "RunResult",
    "run_prequential",
    "mape",
    "metrics_records",
    "interval_scores",
    "interval_score",
    "crps_normal",
    "crps_lognormal",
    "lognormal_from_interval",
    "probabilistic_scores",
    "ALPHA90",
    "parse_outages",
    "plan_outages",
    "has_phases",
    "resolve_split",
    "DEFAULT_TRAIN_SHARE",
    "wells_of",
]

#: The phase rates scored beside the total (optional columns of the observation format), Sm3/h.
PHASES: tuple[str, ...] = OPTIONAL_RATE_COLUMNS
#: How the phase-fraction inputs are taken inside an outage window (see the module docstring).
OUTAGE_FRACTIONS: tuple[str, ...] = ("held", "measured")
#: Nominal level of the central predictive interval whose coverage the records give.
_Z95 = 1.6448536269514722

Progress = Callable[[int, int], None]


@dataclass
class RunResult:
    """What one prequential run produced.

    ``predictions``: one row per scored observation (time, well, model, method, source,
    predicted, measured; rates in Sm3/h). ``updates``: times of periodic retrains.
    ``parameters``: physical parameters after each update (time, well, name, value; SI).
    """

    model: str
    method: str
    predictions: pd.DataFrame
    updates: list[pd.Timestamp] = field(default_factory=list)
    parameters: pd.DataFrame = field(default_factory=pd.DataFrame)
    final_model: ChokeModel | None = None
    runtime_s: float = 0.0


def _start_fresh(
    model: ChokeModel, fresh: list[str], one_well: Callable[[str], ChokeModel]
) -> None:
    """Put each well of ``fresh`` back at the state ``one_well(well)`` starts in (its per-well
    tensors: a one-well model's leading dimension is 1, the field's is its wells)."""
    if not fresh:
        return
    n = len(model.wells)
    tensors = dict(model.named_parameters()) | dict(model.named_buffers())
    with torch.no_grad():
        for well in fresh:
            j = model.wells.index(well)
            own = one_well(well)
            for name, t in (dict(own.named_parameters()) | dict(own.named_buffers())).items():
                full = tensors.get(name)
                if full is not None and t.dim() >= 1 and t.shape[0] == 1 and full.shape[0] == n:
                    full[j].copy_(t[0])


def wells_of(frame: pd.DataFrame) -> list[str]:
    """Wells in order of first appearance."""
    return list(dict.fromkeys(frame[WELL].astype(str)))


#: Share of a case's measurements before the data-derived default split (see resolve_split).
DEFAULT_TRAIN_SHARE = 2.0 / 3.0


def resolve_split(
    targets: str, split: str | pd.Timestamp | None, frame: pd.DataFrame | None = None
) -> pd.Timestamp:
    """The split date (UTC): the given one or the target case's default.

    The case's default (2019-01-01 for ``all``, 2020-01-01 for ``well_test``, the paper's)
    is kept whenever it has measurements of the case on both sides. Given the ``frame``, a
    default that does not (data from other years, such as Volve's 2008-2016) is replaced by
    the first day of the month in which two thirds of the case's measurements have been
    taken, so that every command runs on any field without a ``--split``.
    """
    if targets not in TARGET_CASES:
        raise ConfigError(f"Unknown target case '{targets}'; choose one of {sorted(TARGET_CASES)}.")
    value = TARGET_CASES[targets][1] if split is None else split
    try:
        ts = pd.Timestamp(value)
    except (ValueError, TypeError):
        raise ConfigError(f"The split '{value}' is not a date; write it like 2019-01-01.") from None
    ts = ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")
    if split is not None or frame is None:
        return ts
    times = pd.DatetimeIndex(pd.to_datetime(frame[TIME], utc=True))[target_mask(frame, targets)]
    if len(times) < 2 or ((times < ts).any() and (times >= ts).any()):
        return ts
    at = times.sort_values()[int(DEFAULT_TRAIN_SHARE * (len(times) - 1))]
    month = pd.Timestamp(year=at.year, month=at.month, day=1, tz="UTC")
    return month if month > times.min() else ts


def has_phases(frame: pd.DataFrame, rows: np.ndarray | None = None) -> bool:
    """True when ``frame`` has every phase column (:data:`PHASES`) with some measured value
    (on ``rows``, positional, when given)."""
    if not all(c in frame.columns for c in PHASES):
        return False
    sub = frame[list(PHASES)] if rows is None else frame[list(PHASES)].iloc[rows]
    return bool(np.isfinite(sub.to_numpy(dtype=float)).any())


def parse_outages(text: str | Sequence[str]) -> list[tuple[str, pd.Timedelta]]:
    """Outage lengths from ``7d,30d,90d`` (or a list of such texts): ``[(label, span)]``.

    A label is kept as written (``30d``); a length must be a positive span of at least a
    day (the meters behind this protocol read at most daily). Duplicates are dropped.
    """
    parts = [text] if isinstance(text, str) else list(text)
    labels = [x.strip() for part in parts for x in str(part).split(",") if x.strip()]
    out: dict[str, pd.Timedelta] = {}
    for label in labels:
        # pandas deprecates the lower-case day and week units; accept them as users write them
        normalised = re.sub(r"(?<=\d)([dw])\b", lambda m: m[1].upper(), label)
        try:
            span = pd.Timedelta(normalised)
        except ValueError:
            span = None
        if span is None or pd.isna(span) or span < pd.Timedelta(days=1):
            raise ConfigError(
                f"The outage length '{label}' is not a span of a day or more; "
                "write the lengths like 7d,30d,90d."
            )
        out.setdefault(label, span)
    if not out:
        raise ConfigError("No outage length given; write the lengths like 7d,30d,90d.")
    return list(out.items())


@dataclass(frozen=True)
class Outage:
    """Where the hidden measurement windows of one outage length fall (see :func:`plan_outages`).

    ``windows``: one row per window (``outage``, ``well``, ``start``, ``end`` UTC, ``rows``:
    target measurements inside). ``hidden``: [len(frame)] True on the target rows inside a
    window (predicted and scored, never learned from). ``fractions``: ``held`` or ``measured``
    (how the phase-fraction inputs are taken inside a window).
    """

    label: str
    length: pd.Timedelta
    windows: pd.DataFrame
    hidden: np.ndarray
    fractions: str = "held"
    seed: int = 0


def plan_outages(
    frame: pd.DataFrame,
    length: str | pd.Timedelta,
    *,
    targets: str = "all",
    split: str | pd.Timestamp | None = None,
    seed: int = 0,
    fractions: str = "held",
    label: str | None = None,
) -> Outage:
    """Seeded, non-overlapping windows of ``length`` in each well's test period.

    A well's test period runs from its first to its last ``targets`` measurement on or after
    the split. It is cut into ``n = floor(span / (3 length))`` equal slots, and one window
    is placed in each slot at a random offset such that at least ``length`` of the slot
    lies before the window: windows never overlap, the first starts at least one ``length``
    after the well's first test measurement, and between two windows the meter reads for
    at least one ``length``, so the models relearn before the next outage. A well whose test
    period is shorter than ``3 length`` gets no window. The offsets come from ``seed``, the
    well's name and the length alone: the same inputs give the same windows, and adding a
    well or another length moves nobody else's.
    """
    if fractions not in OUTAGE_FRACTIONS:
        raise ConfigError(
            f"Unknown outage fractions '{fractions}'; choose one of {', '.join(OUTAGE_FRACTIONS)}."
        )
    if isinstance(length, str):
        ((label_parsed, span),) = parse_outages(length)
        label = label or label_parsed
    else:
        span = pd.Timedelta(length)
        if span < pd.Timedelta(days=1):
            raise ConfigError(f"The outage length {span} is shorter than a day; use 1d or more.")
        label = label or f"{span / pd.Timedelta(days=1):g}d"
    split_ts = resolve_split(targets, split, frame)
    is_target = target_mask(frame, targets)
    time_ns = pd.DatetimeIndex(frame[TIME]).as_unit("ns").asi8
    test = is_target & (time_ns >= split_ts.value)
    hidden = np.zeros(len(frame), dtype=bool)
    wells = frame[WELL].astype(str).to_numpy()
    step = int(span.value)
    step_s = step // 10**9
    rows: list[dict[str, Any]] = []
    for well in wells_of(frame.iloc[np.flatnonzero(test)]):
        mine = test & (wells == well)
        t = time_ns[mine]
        # whole seconds, so that the windows read the same in metrics.json as here
        first, last = -(-int(t.min()) // 10**9), int(t.max()) // 10**9
        n = (last - first) // (3 * step_s)
        if n < 1:
            continue
        rng = np.random.default_rng([seed, zlib.crc32(well.encode()), step_s])
        slot = (last - first) // n
        for k in range(n):
            lo = first + k * slot + step_s
            hi = first + (k + 1) * slot - step_s
            start = (lo + int(rng.integers(0, hi - lo + 1))) * 10**9
            end = start + step
            inside = mine & (time_ns >= start) & (time_ns < end)
            hidden |= inside
            rows.append(
                {
                    "outage": label,
                    "well": well,
                    "start": pd.Timestamp(start, tz="UTC"),
                    "end": pd.Timestamp(end, tz="UTC"),
                    "rows": int(inside.sum()),
                }
            )
    windows = pd.DataFrame(rows, columns=["outage", "well", "start", "end", "rows"])
    return Outage(label, span, windows, hidden, fractions, seed)


def _held_fractions(frame: pd.DataFrame, learned: np.ndarray, hidden: np.ndarray) -> pd.DataFrame:
    """``frame`` with ``eta_gas`` and ``eta_oil`` of every ``hidden`` row replaced by those of
    the same well's latest ``learned`` row before it (unchanged where the well has none)."""
    eta = list(INPUT_COLUMNS[4:6])
    held = frame[eta].where(pd.Series(learned, index=frame.index))
    held = held.groupby(frame[WELL].astype(str).to_numpy(), sort=False).ffill()
    out = frame.copy()
    take = hidden & held.notna().all(axis=1).to_numpy()
    out.loc[take, eta] = held.loc[take, eta].to_numpy()
    return out


def _days_since(frame: pd.DataFrame, learned: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Days from each of ``rows`` back to the same well's latest ``learned`` row strictly
    before it (NaN where there is none)."""
    time_ns = pd.DatetimeIndex(frame[TIME]).as_unit("ns").asi8
    wells = frame[WELL].astype(str).to_numpy()
    out = np.full(len(rows), np.nan)
    for well in dict.fromkeys(wells[rows]):
        seen = np.sort(time_ns[learned & (wells == well)])
        here = np.flatnonzero(wells[rows] == well)
        t = time_ns[rows[here]]
        k = np.searchsorted(seen, t, side="left") - 1
        ok = k >= 0
        out[here[ok]] = (t[ok] - seen[k[ok]]) / 86_400e9
    return out


class _StudyMemory(FrameMemory):
    """:class:`FrameMemory` that packs the frame's rows once and answers each retrain by
    selecting from them (the same samples in the same order as packing them anew; only
    the masked padding may differ), and that answers an empty batch when nothing was
    measured in the span asked for (a retrain window inside a long outage or shut-in),
    instead of failing in :func:`vfm_core.data.make_batch`, which needs at least one row."""

    _packed: Batch | None = None

    def batch(self, until_ns: int, window_ns: int | None = None) -> Batch:
        keep = self._rows & (self._time_ns < until_ns)
        if window_ns is not None:
            keep &= self._time_ns >= until_ns - window_ns
        if keep.any():
            # packing a pandas frame costs tens of milliseconds, a retrain every 14 days
            # of a study runs a hundred times: select from the rows packed once
            if self._packed is None:
                self._packed = make_batch(
                    self.frame,
                    self.wells,
                    rows=np.flatnonzero(self._rows),
                    extra_columns=self.extra_columns,
                )
            packed = self._packed
            take = packed.mask & (packed.time_ns < until_ns)
            if window_ns is not None:
                take &= packed.time_ns >= until_ns - window_ns
            return packed.select(take)
        w, k = len(self.wells), len(self.extra_columns)
        return Batch(
            list(self.wells),
            torch.zeros(w, 0, len(INPUT_COLUMNS), dtype=torch.float64),
            torch.zeros(w, 0, dtype=torch.float64),
            torch.zeros(w, 0, dtype=torch.bool),
            torch.zeros(w, 0, dtype=torch.int64),
            torch.zeros(w, 0, dtype=torch.int64),
            torch.zeros(w, 0, dtype=torch.bool),
            torch.zeros(w, 0, k, dtype=torch.float64),
            self.extra_columns,
        )


def _day_rounds(test: Batch, span_ns: int = 86_400 * 10**9) -> list[Batch]:
    """One batch per calendar day (UTC) of ``test``, holding every well's samples of that
    day in time order: what ``test.select(day == d)`` gives for each day, cut by index
    ranges (each well's samples are in time order, so a day is a contiguous run), so the
    cost grows with the samples and not with days x samples. ``span_ns`` = 1: one batch
    per distinct time instead."""
    key = torch.div(test.time_ns, span_ns, rounding_mode="floor")
    return [batch for _, batch in _keyed_rounds(test, key)]


def _coupled_rounds(test: Batch, events: torch.Tensor) -> list[Batch]:
    """The rounds of a method that couples the wells only through the samples ``events``
    [W, N] (``bayes:cal_pool=on``: the well tests, whose errors set the other wells'
    interval factors; :meth:`~vfm_core.learning.method.LearningMethod.coupling_samples`):
    the forecasts of one round per distinct time (:func:`_day_rounds` with ``span_ns`` 1)
    in far fewer rounds. Each distinct time of an event is a round of its own (every
    well's samples at that time); between two of them, where nothing couples the wells,
    each well's k-th sample of the span is one round, as for a method that does not."""
    times = torch.unique(test.time_ns[events & test.mask])  # sorted
    if len(times) == 0:
        return [test.column(k) for k in range(test.x.shape[1])]
    t = test.time_ns.contiguous()
    before = torch.searchsorted(times, t)  # the events strictly earlier than each sample
    at = times[before.clamp(max=len(times) - 1)]
    is_event = (before < len(times)) & (at == t)
    # the span before event j -> key 2 j, the event j itself -> 2 j + 1
    rounds: list[Batch] = []
    for key, batch in _keyed_rounds(test, 2 * before + is_event.to(before.dtype)):
        if key % 2:
            rounds.append(batch)
        else:
            rounds += [batch.column(k) for k in range(batch.x.shape[1])]
    return rounds


def _keyed_rounds(test: Batch, key: torch.Tensor) -> list[tuple[int, Batch]]:
    """``test`` grouped by ``key`` [W, N] (int64, non-decreasing along each well's
    samples, as time is): each group's key and batch (every well's samples of the group,
    in time order), in key order. Cut by index ranges (a group is a contiguous run of each
    well's samples), so the cost grows with the samples, not groups x samples."""
    key = torch.where(test.mask, key, torch.full_like(key, NEVER))
    keys = torch.unique(key[test.mask])
    if len(keys) == 0:
        return []
    wide = keys.unsqueeze(0).expand(test.n_wells, -1).contiguous()
    lo = torch.searchsorted(key, wide)
    counts = torch.searchsorted(key, wide, right=True) - lo
    n_max = test.x.shape[1]
    rounds = []
    for k, n in enumerate(counts.max(dim=0).values.tolist()):
        steps = torch.arange(n)
        keep = steps < counts[:, k : k + 1]
        idx = (lo[:, k : k + 1] + steps).clamp(max=n_max - 1)
        rounds.append((int(keys[k]), _gathered(test, idx, keep & torch.gather(test.mask, 1, idx))))
    return rounds


def _gathered(test: Batch, idx: torch.Tensor, keep: torch.Tensor) -> Batch:
    """The samples ``idx`` [W, n] of ``test`` where ``keep`` [W, n], as a batch (the
    others masked, with the well's first sample's inputs as filler)."""
    assert test.well_test is not None and test.extra is not None
    x = torch.gather(test.x, 1, idx.unsqueeze(-1).expand(-1, -1, test.x.shape[-1]))
    ex = torch.gather(test.extra, 1, idx.unsqueeze(-1).expand(-1, -1, test.extra.shape[-1]))
    t = torch.gather(test.time_ns, 1, idx)
    r = torch.gather(test.row, 1, idx)
    return Batch(
        test.wells,
        torch.where(keep.unsqueeze(-1), x, test.x[:, :1].expand_as(x)),
        torch.where(keep, torch.gather(test.y, 1, idx), torch.zeros(idx.shape, dtype=test.y.dtype)),
        keep,
        torch.where(keep, t, torch.full_like(t, NEVER)),
        torch.where(keep, r, torch.full_like(r, -1)),
        torch.gather(test.well_test, 1, idx) & keep,
        torch.where(keep.unsqueeze(-1), ex, test.extra[:, :1].expand_as(ex)),
        test.extra_names,
    )


def _param_rows(
    model: ChokeModel, when: pd.Timestamp | Sequence[pd.Timestamp], active: torch.Tensor
) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    params = model.physical_parameters()
    if not params:
        return rows
    times = [when] * len(model.wells) if isinstance(when, pd.Timestamp) else list(when)
    for j, well in enumerate(model.wells):
        if not bool(active[j]):
            continue
        for name, values in params.items():
            rows.append({"time": times[j], "well": well, "name": name, "value": float(values[j])})
    return rows


@dataclass
class _Case:
    """The rows of one prequential run: the frame, its target rows, the split, the test rows
    (targets on or after the split: predicted and scored), the wells and the rows an outage
    hides from learning (``learned``: the target rows that are not hidden)."""

    frame: pd.DataFrame
    targets: str
    split_ts: pd.Timestamp
    is_target: np.ndarray
    before: np.ndarray
    test_rows: np.ndarray
    wells: list[str]
    hidden: np.ndarray
    #: [len(frame)] test rows whose measurement the service holds at an instrument fault, and
    #: the rows before the split with an input outside its physical span (never learned)
    held: np.ndarray | None = None

    @property
    def kept_out(self) -> np.ndarray:
        """[len(frame)] True on the rows not learned from: hidden by an outage, or held at
        an instrument fault."""
        return self.hidden if self.held is None else self.hidden | self.held

    @property
    def learned(self) -> np.ndarray:
        """[len(frame)] True on the target rows that may be learned from."""
        return self.is_target & ~self.kept_out


@dataclass(frozen=True)
class _ModelSpec:
    """How the run makes its model (for the field, or for one well starting fresh)."""

    name: str
    seed: int
    effects: Sequence[Any]
    kwargs: dict[str, Any]

    def make(self, wells: list[str]) -> ChokeModel:
        """The model for ``wells`` at its prior."""
        return make_model(self.name, wells, seed=self.seed, effects=self.effects, **self.kwargs)


@dataclass
class _Replay:
    """What the parts of one prequential run share once the model is fitted: the method, the
    test observations (``test``), the parameter rows kept so far, and the arrays the
    predictions are written into (one entry per frame row; Sm3/h; ``phases`` those split)."""

    case: _Case
    meth: LearningMethod
    model: ChokeModel
    memory: _StudyMemory
    test: Batch
    progress: Progress | None
    track_parameters: bool
    param_rows: list[dict[str, Any]]
    phases: tuple[str, ...]
    done: int = 0
    #: what the service does at instrument faults (:mod:`vfm_core.jobs.study_faults`)
    faults: FaultPlan | None = None

    def __post_init__(self) -> None:
        n = len(self.case.frame)
        self.total = len(self.case.test_rows)
        self.hidden_t = torch.from_numpy(self.case.kept_out)
        self.predicted = np.full(n, np.nan)
        self.spread = np.full(n, np.nan)
        self.low = np.full(n, np.nan)
        self.high = np.full(n, np.nan)
        self.split_rates = {p: np.full(n, np.nan) for p in self.phases}
        #: the measured rates as witnesses of the stood-in inputs (as the service's)
        self.tracks = (
            StandInTracks(self.case.frame, self.case.learned, self.case.hidden, self.predicted)
            if self.faults is not None and self.faults.stand_ins
            else None
        )

    def record(self, batch: Batch, where: torch.Tensor) -> None:
        """Predict ``batch`` and keep the forecasts of its ``where`` samples."""
        forecast = self.meth.predict(batch)
        rows = batch.row[where].numpy()
        self.predicted[rows] = forecast.mean[where].numpy()
        if forecast.std is not None:
            self.spread[rows] = forecast.std[where].numpy()
        if forecast.p05 is not None and forecast.p95 is not None:
            self.low[rows] = forecast.p05[where].numpy()
            self.high[rows] = forecast.p95[where].numpy()
        if self.split_rates:
            # at the fluid densities the mass fractions are given in (the priors' means), not
            # a physics model's learned ones: those trade off against C_D and, measured, add
            # error (Volve: oil 13.9 -> 19.1 % for mm bayes; see streaming.phase_split)
            for name, q in phase_split(forecast.mean, batch.x).items():
                self.split_rates[name][rows] = q[where].numpy()
        if self.faults is not None and self.faults.stand_ins:
            self.stand_in(batch, where)

    def stand_in(self, batch: Batch, where: torch.Tensor) -> None:
        """The ``where`` samples with a flagged input predicted again with its stand-in and
        a widened interval, as the service predicts them (:func:`fallback_rates`)."""
        assert self.faults is not None
        for row, rates in fallback_rates(
            self.meth.predict, batch, where, self.faults.stand_ins, self.tracks
        ).items():
            self.predicted[row] = _number(rates.get("q_total"))
            self.spread[row] = _number(rates.get("q_total_std"))
            self.low[row] = _number(rates.get("q_total_p05"))
            self.high[row] = _number(rates.get("q_total_p95"))
            for name, values in self.split_rates.items():
                values[row] = _number(rates.get(name))

    def learn(self, batch: Batch) -> None:
        """Let the method learn from ``batch``'s measurements that are not hidden (nor
        held at an instrument fault)."""
        if self.case.kept_out.any():
            keep = batch.mask & ~self.hidden_t[batch.row.clamp(min=0)]
            if not bool(keep.any()):
                return  # every measurement of this round is hidden: nothing arrives
            if not bool(keep.eq(batch.mask).all()):
                batch = batch.select(keep)
        self.meth.on_measurement(batch, self.memory)

    def advance(self, processed: int) -> None:
        """Count ``processed`` more observations done and tell ``progress``."""
        self.done += processed
        if self.progress is not None:
            self.progress(self.done, self.total)


def _number(value: float | None) -> float:
    """A rate of an answer, NaN for none."""
    return math.nan if value is None else float(value)


def _case(
    frame: pd.DataFrame,
    targets: str,
    split: str | pd.Timestamp | None,
    outage: Outage | None,
    faults: FaultPlan | None = None,
) -> _Case:
    """The rows of a run on ``frame``: its ``targets`` after ``split``, ``outage``'s hidden,
    those ``faults`` holds."""
    split_ts = resolve_split(targets, split, frame)
    is_target = target_mask(frame, targets)
    before = (frame[TIME] < split_ts).to_numpy()
    test_rows = np.flatnonzero(is_target & ~before)
    if len(test_rows) == 0:
        raise DataError(
            f"No '{targets}' measurements on or after the split {split_ts.date()}; "
            "choose an earlier --split."
        )
    wells = wells_of(frame.iloc[np.flatnonzero(is_target)])
    hidden = np.zeros(len(frame), dtype=bool)
    if outage is not None:
        if len(outage.hidden) != len(frame):
            raise ValueError("The outage plan belongs to another frame; plan it on this one.")
        hidden = np.asarray(outage.hidden, dtype=bool) & is_target & ~before
    held = None
    if faults is not None:
        if len(faults.held) != len(frame):
            raise ValueError("The fault plan belongs to another frame; plan it on this one.")
        held = faults.held & is_target & ~before
        if faults.out_of_span is not None:  # an impossible reading: never learned
            held |= faults.out_of_span & is_target
    return _Case(frame, targets, split_ts, is_target, before, test_rows, wells, hidden, held)


def _fit_before_split(
    case: _Case,
    meth: LearningMethod,
    spec: _ModelSpec,
    train: TrainSettings | None,
    online: OnlineSettings | None,
    initial_fits: dict[Any, Any] | None,
) -> tuple[ChokeModel, _StudyMemory]:
    """The model fitted through ``meth`` on what was measured before the split (or the
    cached fit from ``initial_fits``), wells unseen before it at their own prior, and the
    memory retrains read; ``meth`` started at the split."""
    model = spec.make(case.wells)
    train_settings = train or DEFAULT_TRAIN.get(spec.name, TrainSettings())
    meth.bind(model, train=train_settings, online=online)
    # retrains read only what was learned from: hidden measurements never enter the memory
    memory = _StudyMemory(case.frame, case.learned, case.wells, model.extra_columns)
    window = None if meth.window is None else int(meth.window.value)
    initial = memory.batch(case.split_ts.value, window)
    cache_key = (
        model.name,
        repr(model.hyper),
        case.targets,
        case.split_ts,
        meth.window,
        spec.seed,
        repr(train_settings),
    )
    _initial_fit(meth, model, initial, cache_key, initial_fits)
    if not model.shared:
        # a well with no measurement before the split starts as the service starts a new
        # well: its own one-well model at its prior, not the field fit's slice of it
        frame = case.frame
        had = set(frame.loc[case.is_target & case.before, WELL].astype(str))
        _start_fresh(model, [w for w in case.wells if w not in had], lambda w: spec.make([w]))
    meth.start(case.split_ts.value)
    return model, memory


def _initial_fit(
    meth: LearningMethod,
    model: ChokeModel,
    initial: Batch,
    cache_key: tuple[Any, ...],
    initial_fits: dict[Any, Any] | None,
) -> None:
    """Fit ``model`` on ``initial`` through ``meth``, or adopt the fit ``initial_fits`` holds
    for ``cache_key`` (the initial fit is the same for every method with the same window)."""
    if initial_fits is not None and cache_key in initial_fits:
        fitted, iterations = initial_fits[cache_key]
        model.load_state_dict(fitted)
        meth.adopt(initial, iterations)
    else:
        meth.fit(initial)
        if initial_fits is not None:
            # the MAP fit, before the method's own start moved it (a filter's Kalman pass
            # over the history): the methods that adopt it start where this one did
            fitted = getattr(meth, "fit_state", None) or copy.deepcopy(model.state_dict())
            initial_fits[cache_key] = (fitted, meth.iterations.clone())
        meth.fit_state = None  # held for this only


def _replay_in_rounds(run: _Replay) -> None:
    """The test observations one round at a time, each predicted, then learned from: one
    round per well's sample (per day of the field for a shared model, per distinct time for
    a method that couples the wells,
    :attr:`~vfm_core.learning.method.LearningMethod.couples_wells`)."""
    model, test = run.model, run.test
    rounds: list[Batch]
    if model.shared:
        # Shared parameters must see the field in time order: one round per day,
        # holding every well's measurements of that day.
        rounds = _day_rounds(test)
    elif run.meth.couples_wells:
        # A method's statistics shared by the wells: in time order around the samples that
        # couple them (rounds of each well's k-th sample would let a well's forecast use
        # another well's later measurements; a day's round would predict a well's second
        # sample of the day before learning its first).
        events = run.meth.coupling_samples(test)
        rounds = _day_rounds(test, 1) if events is None else _coupled_rounds(test, events)
    else:
        rounds = [test.column(k) for k in range(test.x.shape[1])]
    for rb in rounds:
        has = rb.mask.any(1)
        now = torch.where(rb.mask, rb.time_ns, torch.full_like(rb.time_ns, NEVER))
        now = now.min(dim=1).values
        if model.shared:  # the field moves together: every well is at the round's start
            now = torch.full_like(now, int(now.min()))
        run.meth.retrain_due(run.memory, now)
        run.record(rb, rb.mask)
        run.learn(rb)
        if run.track_parameters:
            run.param_rows += _param_rows(
                model,
                [
                    pd.Timestamp(int(t), tz="UTC") if bool(has[j]) else run.case.split_ts
                    for j, t in enumerate(now.tolist())
                ],
                has,
            )
        run.advance(int(rb.mask.sum()))


def _replay_between_retrains(run: _Replay) -> None:
    """The test observations between two scheduled retrains predicted in one call; a well
    without a model yet learns from its first measurement when it arrives."""
    meth, model, test = run.meth, run.model, run.test
    t_last = int(test.time_ns[test.mask].max())
    start = int(run.case.split_ts.value)
    # a well with no model yet starts at its first measurement learned from, as the
    # method starts it when measurements come one by one (the service): fitted on what
    # it has, its retrains counted from then (PeriodicBatch._learn)
    arrives = test.mask & ~run.hidden_t[test.row.clamp(min=0)]
    first = torch.where(arrives, test.time_ns, torch.full_like(test.time_ns, NEVER))
    starts = torch.where(model.ready, NEVER, first.min(dim=1).values)
    while start <= t_last:
        due = meth.next_due()
        end = NEVER if due is None else max(int(due), start + 1)
        waiting = (starts >= start) & (starts < end) & (starts != NEVER)
        new_at = int(starts[waiting].min()) if bool(waiting.any()) else None
        if new_at is not None:  # up to that measurement, predicted before it is learned
            end = new_at + 1
        in_period = (test.time_ns >= start) & (test.time_ns < end) & test.mask
        if bool(in_period.any()):
            # only the period's samples: predicting the whole test span at every
            # retrain made a run's predictions cost (retrains x test samples)
            period = test.select(in_period)
            run.record(period, period.mask)
            run.advance(int(in_period.sum()))
        if new_at is not None:
            wells_now = starts == new_at
            run.learn(test.select(arrives & (test.time_ns == new_at) & wells_now.unsqueeze(1)))
            starts[wells_now] = NEVER
            start = end
            continue
        if end > t_last:
            break
        meth.retrain_due(run.memory, torch.full((len(model.wells),), end, dtype=torch.int64))
        if run.track_parameters:
            run.param_rows += _param_rows(model, pd.Timestamp(end, tz="UTC"), model.ready)
        start = end


def _predictions_frame(run: _Replay, outage: Outage | None) -> pd.DataFrame:
    """One row per scored observation (see :class:`RunResult`), with the interval, phase
    and outage columns where the run has them."""
    frame, test_rows = run.case.frame, run.case.test_rows
    scored = frame.iloc[test_rows]
    predictions = pd.DataFrame(
        {
            "time": scored[TIME].to_numpy(),
            "well": scored[WELL].astype(str).to_numpy(),
            "model": run.model.name,
            "method": run.meth.text,
            "source": scored[SOURCE].to_numpy(),
            "predicted": run.predicted[test_rows],
            "measured": scored[TARGET].to_numpy(),
        }
    )
    if run.meth.intervals:
        predictions["predicted_std"] = run.spread[test_rows]
        predictions["predicted_p05"] = run.low[test_rows]
        predictions["predicted_p95"] = run.high[test_rows]
    for name, values in run.split_rates.items():
        predictions[f"predicted_{name}"] = values[test_rows]
        predictions[f"measured_{name}"] = scored[name].to_numpy(dtype=float)
    if outage is not None:
        predictions["outage"] = outage.label
        predictions["in_outage"] = run.case.hidden[test_rows]
        predictions["days_since"] = _days_since(frame, run.case.learned, test_rows)
    if run.faults is not None and run.faults.acts_on(test_rows):
        assert run.case.held is not None
        predictions["held"] = run.case.held[test_rows]
        predictions["fallback"] = run.faults.replaced(test_rows)
    predictions["time"] = pd.to_datetime(predictions["time"], utc=True)
    return predictions


def run_prequential(
    frame: pd.DataFrame,
    model_name: str,
    method: str | LearningMethod,
    *,
    targets: str = "all",
    split: str | pd.Timestamp | None = None,
    train: TrainSettings | None = None,
    online: OnlineSettings | None = None,
    model_kwargs: dict[str, Any] | None = None,
    effects: Sequence[Any] = (),
    seed: int = 0,
    progress: Progress | None = None,
    track_parameters: bool = False,
    initial_fits: dict[Any, Any] | None = None,
    outage: Outage | None = None,
    phases: bool = False,
    sensor_faults: FaultPlan | None = None,
) -> RunResult:
    """Fit on data before ``split``, then predict-then-learn every target observation after it.

    ``frame`` is a loaded observation frame (time-sorted). ``targets`` chooses which
    measurements count (``all``: MPFM and well tests; ``well_test``). ``effects`` extend a
    physics model (the frame must hold their feature columns: see
    :func:`vfm_core.effects.add_features`). ``progress(done, total)`` is called as
    observations are processed. ``initial_fits``, a dict shared between calls, caches the
    initial fit so that methods with the same window reuse it.

    Any learning method runs through its protocol (:mod:`vfm_core.learning.method`):
    methods that learn per measurement see the test observations in rounds, one per well
    (one day of the field for a shared model); the others have their predictions between
    two scheduled retrains made in one call.

    ``outage`` (from :func:`plan_outages` on the same frame, targets and split) hides its
    windows' measurements from learning; the predictions then carry ``outage`` (the
    label), ``in_outage`` (True inside a window: the rows the outage protocol scores) and
    ``days_since`` (days since the well's latest measurement learned from). ``phases``
    adds ``predicted_q_gas`` ... ``measured_q_water`` (Sm3/h) when the frame has the phase
    columns.

    ``sensor_faults`` (:func:`vfm_core.jobs.study_faults.plan_sensor_faults` of ``frame``):
    what the service does at an instrument fault: the measurements it holds are not learned
    (nor read by a retrain), a flagged input's rows are predicted with its stand-in and a
    widened interval; the predictions then carry ``held`` and ``fallback`` (sensors, "").
    """
    started = time.perf_counter()
    meth = parse_method(method)
    case = _case(frame, targets, split, outage, sensor_faults)
    torch.manual_seed(seed)
    spec = _ModelSpec(model_name, seed, effects, model_kwargs or {})
    model, memory = _fit_before_split(case, meth, spec, train, online, initial_fits)
    seen = frame
    if outage is not None and outage.fractions == "held" and case.hidden.any():
        seen = _held_fractions(frame, case.learned, case.hidden)
    run = _Replay(
        case,
        meth,
        model,
        memory,
        test=make_batch(seen, case.wells, extra_columns=model.extra_columns, rows=case.test_rows),
        progress=progress,
        track_parameters=track_parameters,
        param_rows=_param_rows(model, case.split_ts, model.ready) if track_parameters else [],
        phases=PHASES if phases and has_phases(frame, case.test_rows) else (),
        faults=sensor_faults,
    )
    if meth.per_measurement or model.gradient_free:
        _replay_in_rounds(run)
    else:
        _replay_between_retrains(run)
    return RunResult(
        model=model.name,
        method=meth.text,
        predictions=_predictions_frame(run, outage),
        updates=[pd.Timestamp(t, tz="UTC") for t in sorted(meth.retrains)],
        parameters=pd.DataFrame(run.param_rows, columns=["time", "well", "name", "value"]),
        final_model=model,
        runtime_s=time.perf_counter() - started,
    )


def mape(predicted: np.ndarray | pd.Series, measured: np.ndarray | pd.Series) -> float:
    """Mean absolute percentage error, percent, over finite predictions with nonzero measurement."""
    p = np.asarray(predicted, dtype=float)
    m = np.asarray(measured, dtype=float)
    ok = np.isfinite(p) & np.isfinite(m) & (m != 0)
    if not ok.any():
        return float("nan")
    return float(np.mean(np.abs(p[ok] - m[ok]) / np.abs(m[ok])) * 100.0)


def interval_scores(
    predicted: np.ndarray | pd.Series,
    measured: np.ndarray | pd.Series,
    p05: np.ndarray | pd.Series,
    p95: np.ndarray | pd.Series,
) -> tuple[float, float]:
    """How well a central 90 % predictive interval does: ``(coverage90, width90)``.

    ``coverage90``: the fraction (0..1) of measurements inside [p05, p95]; ``width90``: the
    median of (p95 - p05) / predicted, in percent. Over rows where all four are finite
    (and the prediction positive, for the width); NaN when there are none.
    """
    q = np.asarray(predicted, dtype=float)
    m = np.asarray(measured, dtype=float)
    lo = np.asarray(p05, dtype=float)
    hi = np.asarray(p95, dtype=float)
    ok = np.isfinite(q) & np.isfinite(m) & np.isfinite(lo) & np.isfinite(hi)
    if not ok.any():
        return float("nan"), float("nan")
    coverage = float(np.mean((m[ok] >= lo[ok]) & (m[ok] <= hi[ok])))
    pos = ok & (q > 0)
    width = float(np.median((hi[pos] - lo[pos]) / q[pos]) * 100.0) if pos.any() else float("nan")
    return coverage, width


#: The two tails together of the central 90 % interval (the interval score's alpha).
ALPHA90 = 0.1


def interval_score(
    lower: np.ndarray | pd.Series,
    upper: np.ndarray | pd.Series,
    measured: np.ndarray | pd.Series,
    alpha: float = ALPHA90,
) -> np.ndarray:
    """The interval score of central (1 - alpha) intervals [lower, upper], per row, in the
    unit of the rates (Gneiting and Raftery 2007, eq. 43):

    (u - l) + (2 / alpha) (l - y) 1{y < l} + (2 / alpha) (y - u) 1{y > u}.

    The width plus a penalty for every measurement outside, so a narrow interval that misses
    and a wide one that always covers both score badly; smaller is better, and a forecaster
    scores best by giving its true alpha/2 and 1 - alpha/2 quantiles (a proper score).
    Example: [90, 110] Sm3/h at alpha 0.1 scores 20 for y = 100 and 20 + 20 x 5 = 120 for
    y = 115.
    """
    lo = np.asarray(lower, dtype=float)
    hi = np.asarray(upper, dtype=float)
    y = np.asarray(measured, dtype=float)
    below = np.where(y < lo, lo - y, 0.0)
    above = np.where(y > hi, y - hi, 0.0)
    return (hi - lo) + (2.0 / alpha) * (below + above)


def crps_normal(
    mean: np.ndarray | pd.Series | float,
    sd: np.ndarray | pd.Series | float,
    measured: np.ndarray | pd.Series | float,
) -> np.ndarray:
    """The continuous ranked probability score of a normal forecast N(mean, sd^2) for the
    measurement y, in the unit of y (Gneiting and Raftery 2007, Sect. 4.2):

    sd [z (2 Phi(z) - 1) + 2 phi(z) - 1 / sqrt(pi)],  z = (y - mean) / sd.

    At y = mean it is sd (sqrt(2) - 1) / sqrt(pi) = 0.2337 sd; with sd = 0 it is |y - mean|
    (the CRPS of a point forecast is its absolute error).
    """
    mu = np.asarray(mean, dtype=float)
    s = np.asarray(sd, dtype=float)
    y = np.asarray(measured, dtype=float)
    safe = np.where(s > 0, s, 1.0)
    z = (y - mu) / safe
    pdf = np.exp(-0.5 * z * z) / np.sqrt(2.0 * np.pi)
    spread = safe * (z * (2.0 * ndtr(z) - 1.0) + 2.0 * pdf - 1.0 / np.sqrt(np.pi))
    return np.where(s > 0, spread, np.abs(y - mu))


def crps_lognormal(
    mu_log: np.ndarray | pd.Series | float,
    sigma_log: np.ndarray | pd.Series | float,
    measured: np.ndarray | pd.Series | float,
) -> np.ndarray:
    """The CRPS of a log-normal forecast (log X ~ N(mu_log, sigma_log^2)) for a measurement
    y > 0, in the unit of y (closed form of Baran and Lerch 2015, Sect. 2.2):

    y (2 Phi(w) - 1) - 2 exp(mu_log + sigma_log^2 / 2) [Phi(w - sigma_log)
    + Phi(sigma_log / sqrt(2)) - 1],  w = (log y - mu_log) / sigma_log.

    With sigma_log = 0 it is |y - exp(mu_log)|. NaN where y <= 0.
    """
    mu = np.asarray(mu_log, dtype=float)
    s = np.asarray(sigma_log, dtype=float)
    y = np.asarray(measured, dtype=float)
    positive = y > 0
    log_y = np.log(np.where(positive, y, 1.0))
    safe = np.where(s > 0, s, 1.0)
    w = (log_y - mu) / safe
    mean = np.exp(mu + 0.5 * safe * safe)
    spread = y * (2.0 * ndtr(w) - 1.0) - 2.0 * mean * (
        ndtr(w - safe) + ndtr(safe / np.sqrt(2.0)) - 1.0
    )
    score = np.where(s > 0, spread, np.abs(y - np.exp(mu)))
    return np.where(positive, score, np.nan)


def lognormal_from_interval(
    p05: np.ndarray | pd.Series, p95: np.ndarray | pd.Series
) -> tuple[np.ndarray, np.ndarray]:
    """The log-normal whose 5 % and 95 % quantiles are ``p05`` and ``p95`` (both > 0):
    ``(mu_log, sigma_log)``, mu_log = (log p05 + log p95) / 2 and sigma_log =
    (log p95 - log p05) / (2 x 1.6449).

    This is the predictive distribution of ``bayes``: its rate is the median of a
    log-normal and its interval the rate x exp(+-1.6449 sd), sd the spread in log space
    (:mod:`vfm_core.learning.bayes`, "Prediction"), so the two quantiles give it back exactly.
    """
    log_lo = np.log(np.asarray(p05, dtype=float))
    log_hi = np.log(np.asarray(p95, dtype=float))
    return 0.5 * (log_lo + log_hi), (log_hi - log_lo) / (2.0 * _Z95)


def probabilistic_scores(
    measured: np.ndarray | pd.Series,
    p05: np.ndarray | pd.Series,
    p95: np.ndarray | pd.Series,
) -> tuple[float, float]:
    """Scores of the predictive distribution, each relative to the measured rate:
    ``(interval_score90, crps)``, both in percent.

    ``interval_score90``: mean over rows of 100 x IS / y, IS the :func:`interval_score` of
    [p05, p95] at alpha 0.1. ``crps``: mean of 100 x CRPS / y for the log-normal that has
    p05 and p95 as its 5 % and 95 % quantiles (:func:`lognormal_from_interval`,
    :func:`crps_lognormal`). Both judge width and coverage together (smaller is better); the
    CRPS of a point forecast is its absolute error, so ``crps`` can be read beside MAPE. Over
    rows with a finite positive measurement and 0 < p05 <= p95; NaN when there are none.
    """
    y = np.asarray(measured, dtype=float)
    lo = np.asarray(p05, dtype=float)
    hi = np.asarray(p95, dtype=float)
    ok = np.isfinite(y) & np.isfinite(lo) & np.isfinite(hi) & (y > 0) & (lo > 0) & (hi >= lo)
    if not ok.any():
        return float("nan"), float("nan")
    y, lo, hi = y[ok], lo[ok], hi[ok]
    mu_log, sigma_log = lognormal_from_interval(lo, hi)
    relative_is = interval_score(lo, hi, y) / y
    relative_crps = crps_lognormal(mu_log, sigma_log, y) / y
    return float(np.mean(relative_is) * 100.0), float(np.mean(relative_crps) * 100.0)


def metrics_records(predictions: pd.DataFrame) -> list[dict[str, Any]]:
    """MAPE per model, method and well: ``[{model, method, well, mape, n}]``.

    ``n`` counts the scored observations (finite prediction); observations predicted
    before a well had any model (no data yet) are not scored.

    Extensions, each only where the predictions carry what it needs (so the records of an
    ordinary run are exactly as before):

    - ``outage`` column (an outage run): every record gains ``"outage": "<label>"`` and is
      scored on the rows inside the windows only (``in_outage``).
    - interval columns ``predicted_p05``/``predicted_p95`` with values: the total's record
      gains ``coverage90`` (fraction 0..1) and ``width90`` (%), see :func:`interval_scores`,
      and ``interval_score90`` and ``crps`` (% of the measured rate, smaller is better), see
      :func:`probabilistic_scores`.
    - phase columns ``predicted_q_oil``/``measured_q_oil`` etc.: after each total record,
      one record per phase with ``"target": "q_oil"`` (MAPE against the measured phase
      rate; ``n`` counts rows with a finite prediction and a nonzero measured phase rate).
    """
    cols = set(predictions.columns)
    outage = "outage" in cols
    if outage and "in_outage" in cols:
        predictions = predictions[predictions["in_outage"].to_numpy(dtype=bool)]
    phases = [p for p in PHASES if f"predicted_{p}" in cols and f"measured_{p}" in cols]
    intervals = {"predicted_p05", "predicted_p95"} <= cols
    keys = ["model", "method", "well"] + (["outage"] if outage else [])
    records = []
    for key, g in predictions.groupby(keys, sort=False):
        model, method, well = key[:3]
        ok = np.isfinite(g["predicted"].to_numpy(dtype=float))
        base: dict[str, Any] = {"model": model, "method": method, "well": well}
        if outage:
            base["outage"] = key[3]
        total = {**base, "mape": mape(g["predicted"], g["measured"]), "n": int(ok.sum())}
        if intervals and np.isfinite(g["predicted_p05"].to_numpy(dtype=float)).any():
            coverage, width = interval_scores(
                g["predicted"], g["measured"], g["predicted_p05"], g["predicted_p95"]
            )
            total["coverage90"] = coverage
            total["width90"] = width
            score90, crps = probabilistic_scores(
                g["measured"], g["predicted_p05"], g["predicted_p95"]
            )
            total["interval_score90"] = score90
            total["crps"] = crps
        records.append(total)
        for phase in phases:
            q = g[f"predicted_{phase}"].to_numpy(dtype=float)
            m = g[f"measured_{phase}"].to_numpy(dtype=float)
            scored = np.isfinite(q) & np.isfinite(m) & (m != 0)
            if not (np.isfinite(m) & (m != 0)).any():
                continue
            records.append({**base, "target": phase, "mape": mape(q, m), "n": int(scored.sum())})
    return records
