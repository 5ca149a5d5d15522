"""Prequential evaluation: every observation after the split is predicted before the model learns from it.

:func:`run_prequential` runs one model with one learning method on one target case and
returns every scored prediction; :func:`mape` and :func:`metrics_records` turn those into
the numbers of the paper's tables.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import TARGET_CASES, Batch, make_batch, target_mask
from vfm_core.errors import ConfigError, DataError
from vfm_core.learning import (
    DEFAULT_TRAIN,
    NEVER,
    FrameMemory,
    LearningMethod,
    OnlineSettings,
    TrainSettings,
    parse_method,
)
from vfm_core.models import ChokeModel, make_model
from vfm_core.schema import SOURCE, TARGET, TIME, WELL

__all__ = ["RunResult", "run_prequential", "mape", "metrics_records", "resolve_split", "wells_of"]

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


def wells_of(frame: pd.DataFrame) -> list[str]:
    """Wells in order of first appearance."""
    return list(dict.fromkeys(frame[WELL].astype(str)))


def resolve_split(targets: str, split: str | pd.Timestamp | None) -> pd.Timestamp:
    """The split date (UTC): the given one or the target case's default."""
    if targets not in TARGET_CASES:
        raise ConfigError(f"Unknown target case '{targets}'; choose one of {sorted(TARGET_CASES)}.")
    value = TARGET_CASES[targets][1] if split is None else split
    try:
        ts = pd.Timestamp(value)
    except (ValueError, TypeError):
        raise ConfigError(f"The split '{value}' is not a date; write it like 2019-01-01.") from None
    return ts.tz_localize("UTC") if ts.tzinfo is None else ts.tz_convert("UTC")


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
    """
    started = time.perf_counter()
    meth = parse_method(method)
    split_ts = resolve_split(targets, split)
    torch.manual_seed(seed)
    is_target = target_mask(frame, targets)
    times = frame[TIME]
    before = (times < split_ts).to_numpy()
    test_rows = np.flatnonzero(is_target & ~before)
    if len(test_rows) == 0:
        raise DataError(
            f"No '{targets}' measurements on or after the split {split_ts.date()}; "
            "choose an earlier --split."
        )
    wells = wells_of(frame.iloc[np.flatnonzero(is_target)])
    model = make_model(model_name, wells, seed=seed, effects=effects, **(model_kwargs or {}))
    train_settings = train or DEFAULT_TRAIN.get(model_name, TrainSettings())
    meth.bind(model, train=train_settings, online=online)
    memory = FrameMemory(frame, is_target, wells, model.extra_columns)
    window = None if meth.window is None else int(meth.window.value)
    initial = memory.batch(split_ts.value, window)

    cache_key = (
        model.name,
        repr(model.hyper),
        targets,
        split_ts,
        meth.window,
        seed,
        repr(train_settings),
    )
    if initial_fits is not None and cache_key in initial_fits:
        # the initial fit is the same for every method with the same window: reuse it
        fitted, iterations = initial_fits[cache_key]
        model.load_state_dict(fitted)
        meth.adopt(initial, iterations)
    else:
        meth.fit(initial)
        if initial_fits is not None:
            initial_fits[cache_key] = (copy.deepcopy(model.state_dict()), meth.iterations.clone())
    meth.start(split_ts.value)
    param_rows = _param_rows(model, split_ts, model.ready) if track_parameters else []
    predicted = np.full(len(frame), np.nan)
    spread = np.full(len(frame), np.nan)
    low = np.full(len(frame), np.nan)
    high = np.full(len(frame), np.nan)
    test = make_batch(frame, wells, extra_columns=model.extra_columns, rows=test_rows)
    total = len(test_rows)
    done = 0

    def record(batch: Batch, where: torch.Tensor) -> None:
        forecast = meth.predict(batch)
        rows = batch.row[where].numpy()
        predicted[rows] = forecast.mean[where].numpy()
        if forecast.std is not None:
            spread[rows] = forecast.std[where].numpy()
        if forecast.p05 is not None and forecast.p95 is not None:
            low[rows] = forecast.p05[where].numpy()
            high[rows] = forecast.p95[where].numpy()

    if meth.per_measurement or model.gradient_free:
        rounds: list[Batch]
        if model.shared:
            # Shared parameters must see the field in time order: one round per day,
            # holding every well's measurements of that day.
            day = torch.div(test.time_ns, 86_400 * 10**9, rounding_mode="floor")
            days = torch.unique(day[test.mask])
            rounds = [test.select(day == d) for d in days]
        else:
            rounds = [test.column(k) for k in range(test.x.shape[1])]
        for rb in rounds:
            has = rb.mask.any(1)
            now = torch.where(rb.mask, rb.time_ns, torch.full_like(rb.time_ns, NEVER))
            now = now.min(dim=1).values
            if model.shared:  # the field moves together: every well is at the round's start
                now = torch.full_like(now, int(now.min()))
            meth.retrain_due(memory, now)
            record(rb, rb.mask)
            meth.on_measurement(rb, memory)
            if track_parameters:
                param_rows += _param_rows(
                    model,
                    [
                        pd.Timestamp(int(t), tz="UTC") if bool(has[j]) else split_ts
                        for j, t in enumerate(now.tolist())
                    ],
                    has,
                )
            done += int(rb.mask.sum())
            if progress is not None:
                progress(done, total)
    else:
        t_last = int(test.time_ns[test.mask].max())
        start = int(split_ts.value)
        while start <= t_last:
            due = meth.next_due()
            end = NEVER if due is None else max(int(due), start + 1)
            in_period = (test.time_ns >= start) & (test.time_ns < end) & test.mask
            if bool(in_period.any()):
                record(test, in_period)
                done += int(in_period.sum())
                if progress is not None:
                    progress(done, total)
            if end > t_last:
                break
            meth.retrain_due(memory, torch.full((len(wells),), end, dtype=torch.int64))
            if track_parameters:
                param_rows += _param_rows(model, pd.Timestamp(end, tz="UTC"), model.ready)
            start = end

    scored = frame.iloc[test_rows]
    predictions = pd.DataFrame(
        {
            "time": scored[TIME].to_numpy(),
            "well": scored[WELL].astype(str).to_numpy(),
            "model": model.name,
            "method": meth.text,
            "source": scored[SOURCE].to_numpy(),
            "predicted": predicted[test_rows],
            "measured": scored[TARGET].to_numpy(),
        }
    )
    if meth.intervals:
        predictions["predicted_std"] = spread[test_rows]
        predictions["predicted_p05"] = low[test_rows]
        predictions["predicted_p95"] = high[test_rows]
    predictions["time"] = pd.to_datetime(predictions["time"], utc=True)
    return RunResult(
        model=model.name,
        method=meth.text,
        predictions=predictions,
        updates=[pd.Timestamp(t, tz="UTC") for t in sorted(meth.retrains)],
        parameters=pd.DataFrame(param_rows, columns=["time", "well", "name", "value"]),
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


def metrics_records(predictions: pd.DataFrame) -> list[dict[str, Any]]:
    """MAPE per model, method and well: ``[{model, method, well, mape, n}]``.

    ``n`` counts the scored observations (finite prediction); observations predicted
    before a well had any model (no data yet) are not scored.
    """
    records = []
    for (model, method, well), g in predictions.groupby(["model", "method", "well"], sort=False):
        ok = np.isfinite(g["predicted"].to_numpy())
        records.append(
            {
                "model": model,
                "method": method,
                "well": well,
                "mape": mape(g["predicted"], g["measured"]),
                "n": int(ok.sum()),
            }
        )
    return records
