"""The study as a command: every model with every learning method, prequentially, with outputs.

``vfm evaluate DATA --out DIR`` writes, all at once at the end (an interrupted run leaves
nothing half-written):

- ``DIR/metrics.json``: ``{"split", "targets", "records": [{model, method, well, mape, n}],
  "summary": [{model, method, mean_mape, median_mape, wells}], "runtime_s", ...}``. MAPE in
  percent. This schema is a public contract.
- ``DIR/predictions.parquet``: every scored observation (time, well, model, method, source,
  predicted, measured; Sm3/h). Where the data have ``q_gas``, ``q_oil`` and ``q_water``,
  also ``predicted_q_gas`` ... ``measured_q_water`` (Sm3/h); for methods with intervals,
  ``predicted_std``, ``predicted_p05``, ``predicted_p95``.
- ``DIR/outage_predictions.parquet`` (with ``outages``): the same columns for the rows
  inside the outage windows, plus ``outage`` (the length, e.g. ``30d``) and ``days_since``
  (days since the well's last measurement learned from).
- ``DIR/report.html``: one self-contained page with the paper's tables and figures.
- ``DIR/allocation.parquet`` (with separator readings in the data; :func:`run_separator_study`
  and ``write_study(separators=...)``): each reading split to its wells (time, separator,
  well, q_alloc, lo90, hi90, q_pred, residual, model, method; Sm3/h). ``metrics.json`` then
  has ``"separators"``: per run (model, bayes method) the readings learned from, refused and
  unusable, the sum's mean error (%) with and without learning from the readings, and the
  well tests' MAPE (%) with and without them (the second is the study's own case 2 run),
  overall and per well; the report a section with a figure.

Records of ``metrics.json`` beyond ``{model, method, well, mape, n}`` (extensions, never
renames): ``"target": "q_oil"`` (etc.) for a phase's score (absent for the total, which
stays the default record), ``"outage": "30d"`` for the outage protocol's score (absent for
the ordinary one), and ``coverage90`` (fraction 0..1), ``width90`` (%),
``interval_score90`` and ``crps`` (both % of the measured rate, mean over the scored
measurements; smaller is better) on the total's records of methods with predictive intervals.
``interval_score90`` is the interval score of [p05, p95] (Gneiting and Raftery 2007, eq. 43,
alpha 0.1: the width plus 20 times any miss), ``crps`` the continuous ranked probability score
of the log-normal predictive distribution those quantiles give (closed form of Baran and Lerch
2015); both judge width and coverage together, and ``crps`` reduces to MAPE for a point
forecast. The summary carries the same keys.

``metrics.json`` also has ``"runs"``: one entry per model and method run, ``{model, method,
runtime_s, retrains}`` (plus ``outage`` for a run of the outage protocol), so the cost of
each run can be seen and compared; :func:`slow_runs` names the runs that took more than
three times the median run and says why, and ``vfm evaluate`` prints it.

At an instrument fault the study does what the service does (:mod:`vfm_core.jobs.study_faults`,
``run_study(sensor_faults=True)``, the default): ``metrics.json`` has ``"held_at_fault"`` and
``"fallback_at_fault"`` (per well: the scored measurements not learned from, and those
predicted with a stand-in; zeros without a fault), and ``predictions.parquet`` has ``held``
(bool) and ``fallback`` (the sensors stood in for, "" for none) when any row is either.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

from vfm_core.data import target_mask
from vfm_core.errors import ConfigError
from vfm_core.jobs.results import StudyResult
from vfm_core.jobs.study import (
    OUTAGE_FRACTIONS,
    PHASES,
    Outage,
    RunResult,
    has_phases,
    metrics_records,
    parse_outages,
    plan_outages,
    resolve_split,
    run_prequential,
)
from vfm_core.jobs.study_faults import FaultPlan, fault_counts, plan_sensor_faults
from vfm_core.jobs.workers import StudyWorkers
from vfm_core.learning import parse_method
from vfm_core.models import MODELS
from vfm_core.schema import SOURCE, TIME, WELL, WELL_TEST

__all__ = [
    "StudyResult",
    "run_study",
    "write_study",
    "summarise",
    "slow_runs",
    "DEFAULT_METHODS",
    "run_separator_study",
    "SeparatorStudy",
]

DEFAULT_METHODS: tuple[str, ...] = ("ol", "pbl:14d", "pbl:182d")
#: what a study worker imports before it takes a model (see vfm_core.jobs.workers)
PRELOAD: tuple[str, ...] = (__name__,)


#: record keys that tell apart scores of the same model and method (absent = the default)
_SCORE_KEYS: tuple[str, ...] = ("target", "outage")


def summarise(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Mean (and median) MAPE across wells per model and method (the paper's Tables 2 and 3).

    Records with a ``target`` (phase) or ``outage`` key are summarised apart and their
    summary rows carry the same keys; the default rows (total, ordinary protocol) are exactly
    as before. With intervals, ``coverage90`` is the mean across wells (fraction),
    ``width90`` the median across wells (%), and ``interval_score90`` and ``crps`` the mean
    across wells (%, like ``mean_mape``).
    """
    df = pd.DataFrame(records)
    if df.empty:
        return []
    extra = [k for k in _SCORE_KEYS if k in df.columns]
    # "" stands for an absent key while grouping (NaN would drop the rows)
    filled = df.assign(**{k: df[k].fillna("").astype(str) for k in extra})
    out = []
    for key, g in filled.groupby(["model", "method", *extra], sort=False):
        model, method = key[0], key[1]
        values = g["mape"].dropna()
        row: dict[str, Any] = {
            "model": model,
            "method": method,
            "mean_mape": float(values.mean()) if len(values) else float("nan"),
            "median_mape": float(values.median()) if len(values) else float("nan"),
            "wells": int(len(values)),
        }
        for name, value in zip(extra, key[2:], strict=True):
            if value:
                row[name] = value
        if "coverage90" in g.columns and g["coverage90"].notna().any():
            row["coverage90"] = float(g["coverage90"].dropna().mean())
            row["width90"] = float(g["width90"].dropna().median())
            for score in ("interval_score90", "crps"):
                if score in g.columns and g[score].notna().any():
                    row[score] = float(g[score].dropna().mean())
        out.append(row)
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
    outages: str | Sequence[str] = (),
    outage_fractions: str = "held",
    jobs: int = 1,
    workers: StudyWorkers | None = None,
    sensor_faults: bool = True,
) -> StudyResult:
    """Run every model with every method prequentially on one target case.

    ``params`` (from ``vfm tune``'s params.json) overrides the default settings per model
    and method. ``effects`` adds, for each of ``mm``, ``hem`` and ``ham``, a run of the model
    extended with those physical effects, labelled e.g. ``mm+erosion``, beside the plain one.

    ``outages`` (``"7d,30d,90d"`` or a list) adds the outage protocol: for each length, the
    windows of :func:`vfm_core.jobs.study.plan_outages` (seeded by ``seed``), and one more
    prequential run per model and method in which they are hidden from learning (one run
    per length, whatever the number of windows; the initial fit is shared with the ordinary
    run). ``outage_fractions``: ``held`` (the phase fractions inside a window are those of
    the last measurement before it, as with a failed MPFM) or ``measured`` (the file's).
    Where the data have the phase rates, every run also scores them.

    ``jobs``: processes that run the study's model groups at once (this one and ``jobs - 1``
    spawned workers, see :mod:`vfm_core.jobs.workers`); ``workers``, already started, are
    used instead (and kept open: ``vfm evaluate`` shares them between its cases). The
    results are the same as with one process: each run is seeded and independent.

    ``sensor_faults``: do what the service does at an instrument fault (hold, stand in:
    :mod:`vfm_core.jobs.study_faults`; the detectors run once over the whole frame); False
    takes every input as read. Without a fault flagged the results are the same.
    """
    _check_names(models, methods)
    split_ts = resolve_split(targets, split, frame)
    lengths = _outage_lengths(outages, outage_fractions)
    started = time.perf_counter()
    plan = _plan_runs(
        frame,
        targets=targets,
        split=split_ts,
        models=models,
        methods=methods,
        effects=effects,
        lengths=lengths,
        seed=seed,
        fractions=outage_fractions,
        sensor_faults=sensor_faults,
    )
    common = {
        "targets": targets,
        "split": split_ts,
        "seed": seed,
        "track_parameters": track_parameters,
        "params": params,
        "effects": list(effects),
        "phases": plan.phases,
        "run_kwargs": dict(run_kwargs or {}),
        "n_test": plan.n_test,
        "faults": plan.faults,
    }
    tasks = [
        {"frame": plan.frame, "runs": runs, "plans": plan.outages, "common": common}
        for runs in plan.groups.values()
    ]
    results = _run_groups(tasks, jobs, workers, _progress_bar(plan, targets, progress))
    gathered = _gather(plan.order, results, plan.outages, track_parameters)
    return _study_result(plan, gathered, split_ts, targets, started, data_path, outage_fractions)


def _progress_bar(plan: _Plan, targets: str, progress: bool) -> tqdm:
    """The study's progress bar: every run's scored observations (hidden unless ``progress``)."""
    return tqdm(
        total=plan.n_test * len(plan.order),
        disable=not progress,
        unit="obs",
        desc=f"evaluate [{targets}]",
        dynamic_ncols=True,
        mininterval=0.5,
    )


@dataclass
class _Plan:
    """The runs of a study: the frame (with the effects' features), the (model, method,
    label, outage plan or -1) runs in serial order and their groups (see
    :func:`_serial_order`), the outage plans, the rows scored, whether phases are scored."""

    frame: pd.DataFrame
    order: list[tuple[str, str, str, int]]
    groups: dict[str, list[tuple[int, str, str, str, int]]]
    outages: list[Outage]
    lengths: list[tuple[str, pd.Timedelta]]
    n_test: int
    phases: bool
    #: what the service does at instrument faults, per row (None: inputs taken as read)
    faults: FaultPlan | None = None


def _plan_runs(
    frame: pd.DataFrame,
    *,
    targets: str,
    split: pd.Timestamp,
    models: Sequence[str],
    methods: Sequence[str],
    effects: Sequence[str],
    lengths: list[tuple[str, pd.Timedelta]],
    seed: int,
    fractions: str,
    sensor_faults: bool = True,
) -> _Plan:
    """Every run of the study, its outage windows (seeded), what it scores and what its
    instrument faults change (:func:`plan_sensor_faults`, with ``sensor_faults``)."""
    test_mask = target_mask(frame, targets) & (frame[TIME] >= split).to_numpy()
    phases = has_phases(frame, np.flatnonzero(test_mask))
    frame, combos = _combinations(frame, models, methods, effects)
    plans = [
        plan_outages(
            frame, span, targets=targets, split=split, seed=seed, fractions=fractions, label=label
        )
        for label, span in lengths
    ]
    order, groups = _serial_order(combos, len(plans))
    faults = plan_sensor_faults(frame) if sensor_faults else None
    return _Plan(frame, order, groups, plans, lengths, int(test_mask.sum()), phases, faults)


def _study_result(
    plan: _Plan,
    gathered: _Gathered,
    split: pd.Timestamp,
    targets: str,
    started: float,
    data_path: str,
    outage_fractions: str,
) -> StudyResult:
    """The study's result from its runs' outputs: the scores of both protocols, the
    summary, the well tests' times, the runtime since ``started`` (perf_counter, s)."""
    preds = pd.concat(gathered.predictions, ignore_index=True)
    records = metrics_records(preds)
    outage_preds = _concat(gathered.outage_predictions)
    if not outage_preds.empty:
        records += metrics_records(outage_preds)
    tests = plan.frame[plan.frame[SOURCE] == WELL_TEST]
    well_tests = {str(w): list(g[TIME]) for w, g in tests.groupby(WELL, sort=False)}
    return StudyResult(
        split=split,
        targets=targets,
        records=records,
        summary=summarise(records),
        predictions=preds,
        updates=gathered.updates,
        well_tests=well_tests,
        runtime_s=time.perf_counter() - started,
        parameters=_concat(gathered.parameters),
        data_path=data_path,
        outage_predictions=outage_preds,
        outage_windows=_concat([p.windows for p in plan.outages]),
        outages=[label for label, _ in plan.lengths],
        outage_fractions=outage_fractions,
        phases=list(PHASES) if plan.phases else [],
        runs=gathered.runs,
    )


def _concat(frames: list[pd.DataFrame]) -> pd.DataFrame:
    """The frames one after the other (a new index); an empty frame for none."""
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _serial_order(
    combos: list[tuple[str, str, str]], n_plans: int
) -> tuple[list[tuple[str, str, str, int]], dict[str, list[tuple[int, str, str, str, int]]]]:
    """The runs (model, method, label, outage plan or -1 for the ordinary protocol) in the
    order of a serial study, and the groups: one model label's runs (they share the
    initial fit), the unit that a worker takes, each run with its index in that order."""
    order = [(model, meth, label, k) for model, meth, label in combos for k in range(-1, n_plans)]
    groups: dict[str, list[tuple[int, str, str, str, int]]] = {}
    for index, (model, meth, label, k) in enumerate(order):
        groups.setdefault(label, []).append((index, model, meth, label, k))
    return order, groups


def _outage_lengths(
    outages: str | Sequence[str], outage_fractions: str
) -> list[tuple[str, pd.Timedelta]]:
    """The outage lengths asked for (label, span), none for an empty request; a
    :class:`ConfigError` for an unknown ``outage_fractions``."""
    asked = [outages] if isinstance(outages, str) else list(outages)
    lengths = parse_outages(asked) if any(str(a).strip() for a in asked) else []
    if outage_fractions not in OUTAGE_FRACTIONS:
        raise ConfigError(
            f"Unknown outage fractions '{outage_fractions}'; choose one of "
            f"{', '.join(OUTAGE_FRACTIONS)}."
        )
    return lengths


def _combinations(
    frame: pd.DataFrame, models: Sequence[str], methods: Sequence[str], effects: Sequence[str]
) -> tuple[pd.DataFrame, list[tuple[str, str, str]]]:
    """The (model, method, label) runs of the study, and the frame with the features the
    ``effects`` need: with effects, ``mm``, ``hem`` and ``ham`` also run extended (label
    e.g. ``mm+erosion``) beside the plain model."""
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
    return frame, combos


def _run_groups(
    tasks: list[dict[str, Any]], jobs: int, workers: StudyWorkers | None, bar: tqdm
) -> dict[int, RunResult]:
    """Every run of the study by its index in the serial order: in this process, or on
    ``workers`` (or ``jobs - 1`` workers started and closed here) a model group each."""
    own = workers is None and jobs > 1 and len(tasks) > 1
    pool = StudyWorkers(min(jobs, len(tasks)) - 1, preload=PRELOAD).start() if own else workers
    try:
        if pool is None or len(tasks) < 2:
            done = [_run_group(task, _BarReport(bar)) for task in tasks]
        else:
            bar.set_postfix_str(f"{1 + pool.workers} processes")
            done = pool.map(_run_group, tasks, bar.update)
    finally:
        bar.close()
        if own and pool is not None:
            pool.close()
    return {i: r for part in done for i, r in part.items()}


@dataclass
class _Gathered:
    """The runs' outputs in the serial order, apart by protocol (see :func:`_gather`)."""

    predictions: list[pd.DataFrame] = field(default_factory=list)
    outage_predictions: list[pd.DataFrame] = field(default_factory=list)
    parameters: list[pd.DataFrame] = field(default_factory=list)
    updates: dict[str, list[pd.Timestamp]] = field(default_factory=dict)
    runs: list[dict[str, Any]] = field(default_factory=list)


def _gather(
    order: list[tuple[str, str, str, int]],
    results: dict[int, RunResult],
    plans: list[Outage],
    track_parameters: bool,
) -> _Gathered:
    """The ordinary runs' predictions, updates and parameters, the outage runs' predictions
    inside their windows, and one ``runs`` entry per run (its cost)."""
    out = _Gathered()
    for index, (_, meth, label, k) in enumerate(order):
        result = results[index]
        plan = None if k < 0 else plans[k]
        out.runs.append(
            {
                "model": label,
                "method": meth,
                **({} if plan is None else {"outage": plan.label}),
                "runtime_s": result.runtime_s,
                "retrains": len(result.updates),
            }
        )
        if plan is not None:
            inside = result.predictions["in_outage"].to_numpy(dtype=bool)
            out.outage_predictions.append(result.predictions[inside].drop(columns="in_outage"))
            continue
        out.predictions.append(result.predictions)
        out.updates[meth] = result.updates
        if track_parameters and not result.parameters.empty:
            out.parameters.append(result.parameters.assign(model=label, method=meth))
    return out


class _BarReport:
    """The progress of a study run in this process alone: observations done, and the run
    under way (shown beside the bar)."""

    def __init__(self, bar: Any) -> None:
        self.bar = bar

    def __call__(self, n: int) -> None:
        self.bar.update(n)

    def status(self, text: str) -> None:
        self.bar.set_postfix_str(text)


def _run_group(task: dict[str, Any], report: Callable[[int], None]) -> dict[int, RunResult]:
    """Run one group of the study (one model's methods, and their outage runs, sharing the
    initial fit), in this process or a worker's; ``report(n)``: n more observations done.
    Returns each run's result by its index in the serial order (without the final model)."""
    from vfm_core.jobs.tune import method_for, settings_for

    frame, plans, common = task["frame"], task["plans"], task["common"]
    params, n_test = common["params"], common["n_test"]
    initial_fits: dict[Any, Any] = {}
    out: dict[int, RunResult] = {}
    status = getattr(report, "status", None)
    for index, model, meth, label, k in task["runs"]:
        plan = None if k < 0 else plans[k]
        extended = label != model
        reported = [0]
        if status is not None:
            status(f"{label} {meth}" + ("" if plan is None else f" outage {plan.label}"))

        def progress(done: int, total: int, reported: list[int] = reported) -> None:
            if done > reported[0]:
                report(done - reported[0])
                reported[0] = done

        text = method_for(params, model, meth)  # with the options `vfm tune` chose
        result = run_prequential(
            frame,
            model,
            text,
            targets=common["targets"],
            split=common["split"],
            seed=common["seed"],
            progress=progress,
            track_parameters=common["track_parameters"] and plan is None,
            initial_fits=initial_fits,
            effects=common["effects"] if extended else (),
            outage=plan,
            phases=common["phases"],
            sensor_faults=common["faults"],
            **settings_for(params, model, meth),
            **common["run_kwargs"],
        )
        if n_test > reported[0]:
            report(n_test - reported[0])
        result.final_model = None  # not needed, and not sent back from a worker
        if extended:
            result.predictions["model"] = label
        if text != meth:
            result.predictions["method"] = meth
        out[index] = result
    return out


#: a run this many times the median run's time is named by :func:`slow_runs`
SLOW_FACTOR = 3.0
#: ... when it also took at least this long, s (a run of half a second is never worth a word)
SLOW_MIN_S = 5.0


def slow_runs(runs: Sequence[dict[str, Any]]) -> list[str]:
    """Sentences naming the runs that took more than :data:`SLOW_FACTOR` times the median
    run (and at least :data:`SLOW_MIN_S` s), slowest first, with what made them slow."""
    times = [float(r["runtime_s"]) for r in runs]
    if len(times) < 3:
        return []
    median = float(np.median(times))
    out = []
    for r in sorted(runs, key=lambda r: -float(r["runtime_s"])):
        took = float(r["runtime_s"])
        if took < SLOW_MIN_S or took <= SLOW_FACTOR * median:
            continue
        what = f"{r['model']} {r['method']}" + (
            f" (outage {r['outage']})" if r.get("outage") else ""
        )
        why = (
            f"it retrained {r['retrains']} times, each on all the measurements so far (or "
            "its window); a longer period (e.g. pbl:30d), a window (pbl:14d:window=365d) or "
            "pbl:auto (retrain on drift) costs less"
            if r.get("retrains")
            else "it learned from every measurement in turn"
        )
        out.append(
            f"{what} took {took:.1f} s, {took / median:.1f} times the median run "
            f"({median:.1f} s): {why}."
        )
    return out


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
    result: StudyResult,
    out_dir: str | os.PathLike[str],
    *,
    report: bool = True,
    separators: Sequence[SeparatorStudy] = (),
) -> list[Path]:
    """Write metrics.json, predictions.parquet and report.html into ``out_dir``; with
    ``separators`` (:func:`run_separator_study`) also allocation.parquet, their runs in
    metrics.json's ``separators`` and a section of the report.

    Files are first written into a staging folder beside ``out_dir`` and moved in at the
    end, so an interrupted run leaves no half-written output.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    try:
        metrics = _clean(result.metrics())
        metrics.update(fault_counts(result.predictions))  # held_at_fault, fallback_at_fault
        if separators:
            metrics["separators"] = _clean([sep.metrics() for sep in separators])
            _write_separators(separators, staging)
        (staging / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default))
        result.predictions.to_parquet(staging / "predictions.parquet", index=False)
        if not result.outage_predictions.empty:
            result.outage_predictions.to_parquet(
                staging / "outage_predictions.parquet", index=False
            )
        if not result.parameters.empty:
            result.parameters.to_parquet(staging / "parameters.parquet", index=False)
        if report:
            from vfm_core.reporting.study import build_report

            build_report(result, staging / "report.html", separators=separators)
        written = []
        for f in sorted(staging.iterdir()):
            os.replace(f, out / f.name)
            written.append(out / f.name)
        return written
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def format_summary(result: StudyResult) -> str:
    """The mean MAPE across wells as a model x method table (text); with phases or outages,
    a second table: per protocol and target, each model's best method."""
    df = pd.DataFrame(result.summary)
    if df.empty:
        return "(no scored observations)"
    extra = [k for k in _SCORE_KEYS if k in df.columns]
    default = df[df[extra].isna().all(axis=1)] if extra else df
    text = _format_default(result, default)
    if extra:
        text += "\n\n" + _format_protocols(df)
    return text


def _format_protocols(df: pd.DataFrame) -> str:
    """Mean MAPE across wells (%) per protocol and target, each model at its best method."""
    df = df.assign(
        protocol=df["outage"].fillna("ordinary") if "outage" in df.columns else "ordinary",
        target=df["target"].fillna("q_total") if "target" in df.columns else "q_total",
    )
    df = df[np.isfinite(df["mean_mape"].to_numpy(dtype=float))]
    best = df.loc[df.groupby(["protocol", "target", "model"], sort=False)["mean_mape"].idxmin()]
    cells = [f"{v:6.1f} {m}" for v, m in zip(best["mean_mape"], best["method"], strict=True)]
    table = best.assign(cell=cells).pivot(
        index=["protocol", "target"], columns="model", values="cell"
    )
    table = table.reindex(columns=list(dict.fromkeys(df["model"])))
    index = pd.MultiIndex.from_product(
        [list(dict.fromkeys(df["protocol"])), list(dict.fromkeys(df["target"]))],
        names=["protocol", "target"],
    )
    table = table.reindex(index).dropna(how="all")
    lines = ["Mean MAPE across wells (%) at each model's best method, per protocol and target"]
    lines.append(table.fillna("-").to_string())
    return "\n".join(lines)


def _format_default(result: StudyResult, df: pd.DataFrame) -> str:
    table = df.pivot(index="method", columns="model", values="mean_mape")
    table = table.reindex(
        index=list(dict.fromkeys(df["method"])), columns=list(dict.fromkeys(df["model"]))
    )
    table["All"] = table.drop(columns=["last"], errors="ignore").mean(axis=1)
    lines = [f"Mean MAPE across wells (%), targets={result.targets}, split={result.split.date()}"]
    lines.append(table.to_string(float_format=lambda v: f"{v:6.1f}"))
    return "\n".join(lines)


#: the models whose separator runs ``vfm evaluate`` makes (physics and hybrids: their
#: filter states are small and their rates physical; see vfm_core.separator)
SEPARATOR_MODELS: tuple[str, ...] = ("mm", "hem", "ham")


@dataclass
class SeparatorStudy:
    """One separator run of ``vfm evaluate``: ``model`` with the ``bayes`` method ``method``
    on the case 2 protocol, learning from the separators' readings (``run``) and the same run
    without learning from them (``without``: the well tests alone; the readings allocated
    all the same), so that what the totals gave is read on the same well tests."""

    model: str
    method: str
    run: Any  # vfm_core.separator.SeparatorRun
    without: Any

    def well_tests(self) -> pd.DataFrame:
        """MAPE (%) on each well's well tests after the split: ``with`` and ``without`` the
        readings learned from, and the number of well tests ``n``, one row per well."""
        n = self.run.predictions.groupby("well").size()
        table = pd.DataFrame(
            {"with": self.run.well_mape(), "without": self.without.well_mape(), "n": n}
        )
        return table.rename_axis("well")

    def lower_percent(self) -> float:
        """How much lower the mean well-test MAPE is with the readings (%, of without)."""
        with_, without = self.run.well_mape().mean(), self.without.well_mape().mean()
        return float((1.0 - with_ / without) * 100.0) if without > 0 else float("nan")

    def sentence(self) -> str:
        """One line for the console."""
        c = self.run.counts
        with_, without = self.run.well_mape().mean(), self.without.well_mape().mean()
        lower = self.lower_percent()
        change = f"{lower:.0f} % lower" if lower >= 0 else f"{-lower:.0f} % higher"
        return (
            f"Separator ({self.model} {self.method}): {c.get('taken', 0)} readings learned from "
            f"({c.get('refused', 0)} refused, {c.get('incomplete', 0)} unusable); the wells' "
            f"predictions summed to within {self.run.sum_error():.2f} % of the totals on "
            f"average; well tests {with_:.2f} % MAPE ({without:.2f} % without the readings: "
            f"{change})."
        )

    def metrics(self) -> dict[str, Any]:
        """The run in ``metrics.json``'s ``separators`` list (MAPE and errors in %)."""
        c = self.run.counts
        wells = self.well_tests()
        return {
            "model": self.model,
            "method": self.method,
            "readings_learned": int(c.get("taken", 0)),
            "readings_downweighted": int(c.get("downweighted", 0)),
            "readings_refused": int(c.get("refused", 0)),
            "readings_unusable": int(c.get("incomplete", 0)),
            "sum_error_percent": self.run.sum_error(),
            "sum_error_without_percent": self.without.sum_error(),
            "well_test_mape_percent": float(wells["with"].mean()),
            "well_test_mape_without_percent": float(wells["without"].mean()),
            "lower_percent": self.lower_percent(),
            "wells": {
                str(w): {
                    "mape_percent": float(r["with"]),
                    "mape_without_percent": float(r["without"]),
                    "n": int(r["n"]),
                }
                for w, r in wells.iterrows()
            },
            "runtime_s": float(self.run.runtime_s + self.without.runtime_s),
        }


def run_separator_study(
    frame: pd.DataFrame,
    separators: Any,
    *,
    models: Sequence[str],
    methods: Sequence[str],
    split: str | None = None,
    seed: int = 0,
    progress: bool = False,
) -> tuple[list[SeparatorStudy], list[str]]:
    """With separator readings (``separators``: :class:`vfm_core.separator_format.SeparatorData`),
    run :func:`vfm_core.separator.run_separator` for each of ``models`` among
    :data:`SEPARATOR_MODELS` (``mm`` if none) with each ``bayes`` method of ``methods``
    (``bayes`` if none), with and without learning from the readings; the runs and the
    sentences to print (one per run, and why other methods were left out)."""
    from vfm_core.separator import check_method, run_separator

    chosen = [m for m in models if m in SEPARATOR_MODELS] or ["mm"]
    bayes = [m for m in methods if check_method(m) is None] or ["bayes"]
    pairs = [(model, meth) for model in chosen for meth in bayes]
    bar = tqdm(
        total=2 * len(pairs), desc="separator runs", unit="run", disable=not progress, leave=False
    )
    studies, lines = [], []
    try:
        for model, meth in pairs:
            runs = []
            for learn in (True, False):
                bar.set_postfix_str(f"{model} {meth}" + ("" if learn else ", without readings"))
                runs.append(
                    run_separator(
                        frame, separators, model, meth, split=split, seed=seed, learn=learn
                    )
                )
                bar.update()
            studies.append(SeparatorStudy(model, meth, runs[0], runs[1]))
            lines.append(studies[-1].sentence())
    finally:
        bar.close()
    ignored = [m for m in methods if check_method(m) is not None]
    if ignored:
        lines.append(check_method(ignored[0]) or "")
    return studies, lines


def _write_separators(studies: Sequence[SeparatorStudy], staging: Path) -> None:
    """``allocation.parquet`` (:data:`~vfm_core.separator.ALLOCATION_COLUMNS` plus ``model``
    and ``method``; Sm3/h) of the runs that learned from the readings."""
    table = pd.concat(
        [s.run.allocation.assign(model=s.model, method=s.method) for s in studies],
        ignore_index=True,
    )
    table.to_parquet(staging / "allocation.parquet", index=False)
