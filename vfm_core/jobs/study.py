"""Prequential evaluation: every observation after the split is predicted before the model learns from it.

:func:`run_prequential` runs one model with one learning method on one target case and
returns every scored prediction; :func:`mape` and :func:`metrics_records` turn those into
the numbers of the paper's tables.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd
import torch

from vfm_core.data import TARGET_CASES, Batch, make_batch, target_mask
from vfm_core.errors import ConfigError, DataError
from vfm_core.learners import (
    DEFAULT_ONLINE,
    DEFAULT_TRAIN,
    Method,
    OnlineLearner,
    OnlineSettings,
    TrainSettings,
    fit_batch,
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
    method: str | Method,
    *,
    targets: str = "all",
    split: str | pd.Timestamp | None = None,
    train: TrainSettings | None = None,
    online: OnlineSettings | None = None,
    model_kwargs: dict[str, Any] | None = None,
    seed: int = 0,
    progress: Progress | None = None,
    track_parameters: bool = False,
    model_factory: Callable[[list[str]], ChokeModel] | None = None,
    initial_fits: dict[Any, Any] | None = None,
) -> RunResult:
    """Fit on data before ``split``, then predict-then-learn every target observation after it.

    ``frame`` is a loaded observation frame (time-sorted). ``targets`` chooses which
    measurements count (``all``: MPFM and well tests; ``well_test``). ``progress(done, total)``
    is called as observations are processed. ``initial_fits``, a dict shared between
    calls, caches the initial fit so that methods with the same window reuse it.
    """
    import time as _time

    started = _time.perf_counter()
    meth = parse_method(method) if isinstance(method, str) else method
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
    model = (
        model_factory(wells)
        if model_factory is not None
        else make_model(model_name, wells, seed=seed, **(model_kwargs or {}))
    )
    train_settings = train or DEFAULT_TRAIN.get(model_name, TrainSettings())
    online_settings = online or DEFAULT_ONLINE.get(model_name, OnlineSettings())

    def rows_until(t_end: pd.Timestamp) -> np.ndarray:
        keep = is_target & (times < t_end).to_numpy()
        if meth.window is not None:
            keep &= (times >= t_end - meth.window).to_numpy()
        return np.flatnonzero(keep)

    cache_key = (
        model_name,
        targets,
        split_ts,
        meth.window,
        seed,
        repr(train_settings),
        repr(model_kwargs),
    )
    if initial_fits is not None and model_factory is None and cache_key in initial_fits:
        # the initial fit is the same for every method with the same window: reuse it
        model, iterations = (copy.deepcopy(v) for v in initial_fits[cache_key])
    else:
        initial = fit_batch(
            model,
            make_batch(frame, wells, extra_columns=model.extra_columns, rows=rows_until(split_ts)),
            train_settings,
        )
        iterations = initial["iterations"]
        if initial_fits is not None and model_factory is None:
            initial_fits[cache_key] = (copy.deepcopy(model), iterations.clone())
    param_rows = _param_rows(model, split_ts, model.ready) if track_parameters else []
    predicted = np.full(len(frame), np.nan)
    test = make_batch(frame, wells, extra_columns=model.extra_columns, rows=test_rows)
    total = len(test_rows)
    done = 0
    updates: list[pd.Timestamp] = []

    if meth.kind == "ol" or model.gradient_free:
        # The benchmark `last` always predicts the previous measurement, whatever the
        # method (the paper's benchmark), so it runs the per-observation loop.
        learner = OnlineLearner(model, online_settings)
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
            q = model.predict_batch(rb)
            predicted[rb.row[rb.mask].numpy()] = q[rb.mask].numpy()
            learner.learn(rb)
            if track_parameters:
                last_t = [
                    pd.Timestamp(int(t), tz="UTC") for t in rb.time_ns.min(dim=1).values.tolist()
                ]
                param_rows += _param_rows(
                    model,
                    [t if rb.mask[j].any() else split_ts for j, t in enumerate(last_t)],
                    rb.mask.any(1),
                )
            done += int(rb.mask.sum())
            if progress is not None:
                progress(done, total)
    elif meth.kind == "auto":
        updates = _run_auto(
            frame,
            model,
            meth,
            test,
            wells,
            is_target,
            times,
            predicted,
            lambda end, mask: fit_batch(
                model,
                make_batch(frame, wells, extra_columns=model.extra_columns, rows=rows_until(end)),
                train_settings,
                iterations,
                wells=mask,
            ),
        )
        done = total
        if progress is not None:
            progress(done, total)
    else:
        assert meth.period is not None
        t_last = times.iloc[test_rows].max()
        start = split_ts
        while start <= t_last:
            end = start + meth.period
            in_period = (test.time_ns >= start.value) & (test.time_ns < end.value) & test.mask
            if bool(in_period.any()):
                q = model.predict_batch(test)
                predicted[test.row[in_period].numpy()] = q[in_period].numpy()
                done += int(in_period.sum())
                if progress is not None:
                    progress(done, total)
            if end <= t_last:
                fit_batch(
                    model,
                    make_batch(
                        frame, wells, extra_columns=model.extra_columns, rows=rows_until(end)
                    ),
                    train_settings,
                    iterations,
                )
                updates.append(end)
                if track_parameters:
                    param_rows += _param_rows(model, end, model.ready)
            start = end

    scored = frame.iloc[test_rows]
    predictions = pd.DataFrame(
        {
            "time": scored[TIME].to_numpy(),
            "well": scored[WELL].astype(str).to_numpy(),
            "model": model_name,
            "method": meth.text,
            "source": scored[SOURCE].to_numpy(),
            "predicted": predicted[test_rows],
            "measured": scored[TARGET].to_numpy(),
        }
    )
    predictions["time"] = pd.to_datetime(predictions["time"], utc=True)
    return RunResult(
        model=model_name,
        method=meth.text,
        predictions=predictions,
        updates=updates,
        parameters=pd.DataFrame(param_rows, columns=["time", "well", "name", "value"]),
        final_model=model,
        runtime_s=_time.perf_counter() - started,
    )


def _run_auto(
    frame: pd.DataFrame,
    model: ChokeModel,
    meth: Method,
    test: Batch,
    wells: list[str],
    is_target: np.ndarray,
    times: pd.Series,
    predicted: np.ndarray,
    retrain: Callable[[pd.Timestamp, torch.Tensor], Any],
) -> list[pd.Timestamp]:
    """``pbl:auto``: retrain a well when a streaming Hotelling test confirms a shift in its inputs.

    Each well's detector starts with its latest ``reference`` training inputs; after a
    confirmed shift at time t the well is retrained on data before t and the detector
    restarts from the latest ``reference`` inputs up to t. Detection needs only the
    inputs, so the retrain times are found first, then the model runs through them.
    """
    from vfm_core.drift import StreamingHotelling
    from vfm_core.schema import INPUT_COLUMNS

    x_all = frame[list(INPUT_COLUMNS)].to_numpy(dtype=float)
    events: dict[int, list[int]] = {}
    for j, well in enumerate(wells):
        own = np.flatnonzero(is_target & (frame[WELL].astype(str) == well).to_numpy())
        test_pos = test.row[j][test.mask[j]].numpy()
        history = own[own < (test_pos[0] if len(test_pos) else len(frame))]
        history = (
            history[times.iloc[history].to_numpy() < times.iloc[test_pos[0]]]
            if len(test_pos)
            else history
        )
        det = StreamingHotelling(meth.reference, meth.alpha, meth.confirm)
        seen = list(x_all[history[-meth.reference :]]) if len(history) else []
        det.reset(np.asarray(seen) if len(seen) >= meth.reference else None)
        recent = seen[-meth.reference :]
        for k, pos in enumerate(test_pos):
            det.update(x_all[pos])
            recent = (recent + [x_all[pos]])[-meth.reference :]
            if det.drift_detected and k + 1 < len(test_pos):
                t_ns = int(test.time_ns[j][k + 1])  # retrain before the next observation
                events.setdefault(t_ns, []).append(j)
                det.reset(np.asarray(recent) if len(recent) >= meth.reference else None)
    updates: list[pd.Timestamp] = []
    done_mask = torch.zeros_like(test.mask)
    for t_ns in sorted(events):
        due = test.mask & ~done_mask & (test.time_ns < t_ns)
        if bool(due.any()):
            q = model.predict_batch(test)
            predicted[test.row[due].numpy()] = q[due].numpy()
            done_mask |= due
        mask = torch.zeros(len(wells), dtype=torch.bool)
        mask[events[t_ns]] = True
        when = pd.Timestamp(t_ns, tz="UTC")
        retrain(when, mask)
        updates.append(when)
    rest = test.mask & ~done_mask
    if bool(rest.any()):
        q = model.predict_batch(test)
        predicted[test.row[rest].numpy()] = q[rest].numpy()
    return updates


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
