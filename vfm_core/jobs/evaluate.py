"""The study as a command: every model with every learning method, prequentially, with outputs.

``vfm evaluate DATA --out DIR`` writes, all at once at the end (an interrupted run leaves
nothing half-written):

- ``DIR/metrics.json``: ``{"split", "targets", "records": [{model, method, well, mape, n}],
  "summary": [{model, method, mean_mape, median_mape, wells}], "runtime_s", ...}``. MAPE in
  percent. This schema is a public contract.
- ``DIR/predictions.parquet``: every scored observation (time, well, model, method, source,
  predicted, measured; Sm3/h).
- ``DIR/report.html``: one self-contained page with the paper's tables and figures.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

from vfm_core.data import target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.study import metrics_records, resolve_split, run_prequential
from vfm_core.learning import parse_method
from vfm_core.models import MODELS
from vfm_core.schema import SOURCE, TIME, WELL, WELL_TEST

__all__ = ["StudyResult", "run_study", "write_study", "summarise", "DEFAULT_METHODS"]

DEFAULT_METHODS: tuple[str, ...] = ("ol", "pbl:14d", "pbl:182d")


@dataclass
class StudyResult:
    """Everything one study produced; :func:`write_study` turns it into files."""

    split: pd.Timestamp
    targets: str
    records: list[dict[str, Any]]
    summary: list[dict[str, Any]]
    predictions: pd.DataFrame
    #: times of periodic retrains per method (the same for every model)
    updates: dict[str, list[pd.Timestamp]]
    #: well-test times per well, from the data (for the days-between-tests view)
    well_tests: dict[str, list[pd.Timestamp]]
    runtime_s: float
    #: physical parameter traces (time, well, model, method, name, value), may be empty
    parameters: pd.DataFrame = field(default_factory=pd.DataFrame)
    data_path: str = ""

    def metrics(self) -> dict[str, Any]:
        return {
            "data": self.data_path,
            "split": self.split.isoformat(),
            "targets": self.targets,
            "records": self.records,
            "summary": self.summary,
            "runtime_s": round(self.runtime_s, 3),
        }


def summarise(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean (and median) MAPE across wells per model and method (the paper's Tables 2 and 3)."""
    df = pd.DataFrame(records)
    if df.empty:
        return []
    out = []
    for (model, method), g in df.groupby(["model", "method"], sort=False):
        values = g["mape"].dropna()
        out.append(
            {
                "model": model,
                "method": method,
                "mean_mape": float(values.mean()) if len(values) else float("nan"),
                "median_mape": float(values.median()) if len(values) else float("nan"),
                "wells": int(len(values)),
            }
        )
    return out


def _check_names(models: Sequence[str], methods: Sequence[str]) -> None:
    unknown = [m for m in models if m not in MODELS]
    if unknown:
        raise ConfigError(f"Unknown model(s) {unknown}; choose from {', '.join(MODELS)}.")
    for m in methods:
        parse_method(m)


def run_study(
    frame: pd.DataFrame,
    *,
    models: Sequence[str] = tuple(MODELS),
    methods: Sequence[str] = DEFAULT_METHODS,
    targets: str = "all",
    split: str | None = None,
    seed: int = 0,
    progress: bool = True,
    track_parameters: bool = False,
    data_path: str = "",
    run_kwargs: dict[str, Any] | None = None,
    params: dict[str, Any] | None = None,
    effects: Sequence[str] = (),
) -> StudyResult:
    """Run every model with every method prequentially on one target case.

    ``params`` (from ``vfm tune``'s params.json) overrides the default settings per model
    and method. ``effects`` adds, for each of ``mm``, ``hem`` and ``ham``, a run of the model
    extended with those physical effects, labelled e.g. ``mm+erosion``, beside the plain one.
    """
    _check_names(models, methods)
    split_ts = resolve_split(targets, split)
    started = time.perf_counter()
    is_target = target_mask(frame, targets)
    n_test = int((is_target & (frame[TIME] >= split_ts).to_numpy()).sum())
    effect_label = ""
    if effects:
        from vfm_core.effects import add_features, resolve_effects

        frame = add_features(frame, list(effects))
        effect_label = "+".join(c.name for c in resolve_effects(list(effects)))
    combos: list[tuple[str, str, str]] = []
    for m in models:
        for meth in methods:
            combos.append((m, meth, m))
            if effects and m in ("mm", "hem", "ham"):
                combos.append((m, meth, f"{m}+{effect_label}"))
    bar = tqdm(
        total=n_test * len(combos),
        disable=not progress,
        unit="obs",
        desc=f"evaluate [{targets}]",
        dynamic_ncols=True,
        mininterval=0.5,
    )
    predictions = []
    parameters = []
    updates: dict[str, list[pd.Timestamp]] = {}
    initial_fits: dict[Any, Any] = {}
    try:
        for model, meth, label in combos:
            bar.set_postfix_str(f"{label} {meth}")
            base = bar.n

            def report(done: int, total: int, base: int = base) -> None:
                bar.update(base + done - bar.n)

            from vfm_core.jobs.tune import settings_for

            extended = label != model
            result = run_prequential(
                frame,
                model,
                meth,
                targets=targets,
                split=split_ts,
                seed=seed,
                progress=report,
                track_parameters=track_parameters,
                initial_fits=initial_fits,
                effects=list(effects) if extended else (),
                **settings_for(params, model, meth),
                **(run_kwargs or {}),
            )
            if extended:
                result.predictions["model"] = label
            bar.update(base + n_test - bar.n)
            predictions.append(result.predictions)
            updates[meth] = result.updates
            if track_parameters and not result.parameters.empty:
                parameters.append(result.parameters.assign(model=label, method=meth))
    finally:
        bar.close()
    preds = pd.concat(predictions, ignore_index=True)
    records = metrics_records(preds)
    tests = frame[frame[SOURCE] == WELL_TEST]
    well_tests = {str(w): list(g[TIME]) for w, g in tests.groupby(WELL, sort=False)}
    return StudyResult(
        split=split_ts,
        targets=targets,
        records=records,
        summary=summarise(records),
        predictions=preds,
        updates=updates,
        well_tests=well_tests,
        runtime_s=time.perf_counter() - started,
        parameters=pd.concat(parameters, ignore_index=True) if parameters else pd.DataFrame(),
        data_path=data_path,
    )


def _json_default(value: Any) -> Any:
    if isinstance(value, float | np.floating) and not np.isfinite(value):
        return None
    if isinstance(value, np.integer | np.floating):
        return value.item()
    if isinstance(value, pd.Timestamp):
        return value.isoformat()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _clean(obj: Any) -> Any:
    """NaN -> None recursively (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_clean(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def write_study(
    result: StudyResult, out_dir: str | os.PathLike[str], *, report: bool = True
) -> list[Path]:
    """Write metrics.json, predictions.parquet and report.html into ``out_dir``.

    Files are first written into a staging folder beside ``out_dir`` and moved in at the
    end, so an interrupted run leaves no half-written output.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        metrics = _clean(result.metrics())
        (staging / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default))
        result.predictions.to_parquet(staging / "predictions.parquet", index=False)
        if not result.parameters.empty:
            result.parameters.to_parquet(staging / "parameters.parquet", index=False)
        if report:
            from vfm_core.reporting.study import build_report

            build_report(result, staging / "report.html")
        written = []
        for f in sorted(staging.iterdir()):
            os.replace(f, out / f.name)
            written.append(out / f.name)
        return written
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def format_summary(result: StudyResult) -> str:
    """The mean MAPE across wells as a model x method table (text)."""
    df = pd.DataFrame(result.summary)
    if df.empty:
        return "(no scored observations)"
    table = df.pivot(index="method", columns="model", values="mean_mape")
    table = table.reindex(
        index=list(dict.fromkeys(df["method"])), columns=list(dict.fromkeys(df["model"]))
    )
    table["All"] = table.drop(columns=["last"], errors="ignore").mean(axis=1)
    lines = [f"Mean MAPE across wells (%), targets={result.targets}, split={result.split.date()}"]
    lines.append(table.to_string(float_format=lambda v: f"{v:6.1f}"))
    return "\n".join(lines)
