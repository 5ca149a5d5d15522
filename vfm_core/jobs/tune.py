"""Hyperparameter search (paper section 4.2): ``vfm tune DATA --out DIR``.

For each model and learning method, every setting of a grid is scored by the mean MAPE
across wells on a time-ordered inner split of the data *before* the study's split: the
model is fitted on data before the inner split and run prequentially from the inner
split up to the split. The test period is never looked at.

Grids (``--grid``), what each learning method tries on them:

- ``paper``: online learning gamma in {5e-1, 1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-10},
  E in {1, 10, 20}, SGD or Adam; batch learning gamma in {1e-1, 1e-2, 1e-3, 1e-4, 1e-5}
  with E by early stopping; ``bayes`` a drift factor in {0.25, 0.5, 1, 2, 4} and a noise
  adaptation rate in {0, 0.02, 0.1}.
- ``small`` (default): gamma in {1e-1, 1e-2, 1e-3, 1e-4}, E in {1, 10}, SGD or Adam; batch
  gamma in {1e-1, 1e-2, 1e-3}; ``bayes`` the drift factor alone.

Results go line by line to ``DIR/trials.jsonl``, so an interrupted search resumes where it
stopped; the chosen settings go to ``DIR/params.json``, which ``vfm evaluate --params`` and
the service read. Settings are tried in parallel worker processes (spawned, not forked).
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

from vfm_core.errors import ConfigError
from vfm_core.fileio import write_text_atomic
from vfm_core.jobs.study import metrics_records, resolve_split, run_prequential
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, parse_method

__all__ = [
    "GRIDS",
    "trial_grid",
    "run_tuning",
    "load_params",
    "settings_for",
    "method_for",
    "register",
]

#: The grids by name; what each method tries on them is the method's (see
#: :meth:`vfm_core.learning.method.LearningMethod.tuning`).
GRIDS: dict[str, str] = {
    "paper": "the paper's grid (section 4.2, Table B.1)",
    "small": "a smaller grid, about a quarter of the paper's",
}


def trial_grid(models: Sequence[str], methods: Sequence[str], grid: str) -> list[dict[str, Any]]:
    """Every (model, method, setting) to try, as JSON-able dicts with a stable key.

    Each learning method says what it tries (:meth:`LearningMethod.tuning`): online steps
    for ``ol``, the batch learning rate for the retraining methods, the drift for ``bayes``.
    """
    if grid not in GRIDS:
        raise ConfigError(f"Unknown grid '{grid}'; choose one of {sorted(GRIDS)}.")
    trials = []
    for model, method in itertools.product(models, methods):
        if model == "last":
            continue  # the benchmark has nothing to tune
        for option in parse_method(method).tuning(grid):
            trials.append({"model": model, "method": method, **option})
    for t in trials:
        t["key"] = json.dumps(
            {k: t.get(k) for k in ("model", "method", "online", "train", "text")}, sort_keys=True
        )
    return trials


def _run_trial(args: tuple[str, dict[str, Any], str, str, str]) -> dict[str, Any]:
    data_path, trial, targets, inner_split, split = args
    from vfm_core.runtime import configure

    configure(1)
    from vfm_core.observations import load_observations

    frame = load_observations(data_path).frame
    frame = frame[frame["time"] < pd.Timestamp(split)].reset_index(drop=True)
    model = trial["model"]
    train = replace(DEFAULT_TRAIN[model], **trial.get("train", {}))
    online = replace(DEFAULT_ONLINE[model], **trial.get("online", {}))
    try:
        result = run_prequential(
            frame,
            model,
            trial.get("text", trial["method"]),
            targets=targets,
            split=inner_split,
            train=train,
            online=online,
        )
        mapes = [r["mape"] for r in metrics_records(result.predictions)]
        score = float(np.nanmean(mapes)) if mapes else float("nan")
    except Exception as exc:  # a setting that fails (diverges, no data) scores as failed
        return {**trial, "mean_mape": None, "error": str(exc)}
    if not np.isfinite(score):
        score = None  # type: ignore[assignment]
    return {**trial, "mean_mape": score}


def _inner_split(
    before: pd.DataFrame, targets: str, split_ts: pd.Timestamp, inner_split: str | None
) -> pd.Timestamp:
    """Start of the inner validation period: ``inner_split``, or two thirds of the way from
    the first pre-split row (``before``) to the split."""
    if inner_split is None:
        # the last third of the pre-split period is the inner validation period
        t0, t1 = before["time"].min(), split_ts
        return t0 + (t1 - t0) * (2 / 3)
    return resolve_split(targets, inner_split)


def _finished_trials(log: Path) -> dict[str, dict[str, Any]]:
    """The trials ``trials.jsonl`` already holds, by key (an interrupted search resumes)."""
    done: dict[str, dict[str, Any]] = {}
    if log.exists():
        for line in log.read_text().splitlines():
            if line.strip():
                rec = json.loads(line)
                done[rec["key"]] = rec
    return done


def _run_trials(
    jobs: list[tuple[str, dict[str, Any], str, str, str]],
    log: Path,
    done: dict[str, dict[str, Any]],
    workers: int,
    progress: bool,
) -> None:
    """Run ``jobs`` in spawned worker processes, each finished trial appended to ``log``
    and put in ``done``."""
    bar = tqdm(
        total=len(jobs) + len(done),
        initial=len(done),
        disable=not progress,
        desc="tune",
        unit="trial",
    )
    try:
        if jobs:
            import multiprocessing as mp

            with ProcessPoolExecutor(
                max_workers=max(1, workers), mp_context=mp.get_context("spawn")
            ) as pool:
                for rec in pool.map(_run_trial, jobs):
                    with log.open("a") as fh:  # one line per finished trial: resumable
                        fh.write(json.dumps(rec) + "\n")
                    done[rec["key"]] = rec
                    bar.update(1)
    finally:
        bar.close()


def _best_settings(
    done: dict[str, dict[str, Any]], models: Sequence[str], methods: Sequence[str]
) -> dict[str, dict[str, Any]]:
    """Per model and method, the finished trial's settings with the lowest inner mean MAPE."""
    chosen: dict[str, dict[str, Any]] = {}
    for rec in done.values():
        if (
            rec.get("mean_mape") is None
            or rec["model"] not in models
            or rec["method"] not in methods
        ):
            continue
        slot = chosen.setdefault(rec["model"], {}).get(rec["method"])
        if slot is None or rec["mean_mape"] < slot["inner_mean_mape"]:
            entry = {"inner_mean_mape": rec["mean_mape"]}
            if "online" in rec:
                entry["online"] = rec["online"]
            if "train" in rec:
                entry["train"] = rec["train"]
            if "text" in rec:
                entry["text"] = rec["text"]
            chosen[rec["model"]][rec["method"]] = entry
    return chosen


def run_tuning(
    data: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    models: Sequence[str],
    methods: Sequence[str],
    targets: str = "all",
    split: str | None = None,
    inner_split: str | None = None,
    grid: str = "small",
    workers: int = 2,
    progress: bool = True,
) -> dict[str, Any]:
    """Run (or resume) the search and write ``params.json``; returns its content."""
    split_ts = resolve_split(targets, split)
    from vfm_core.observations import load_observations

    frame = load_observations(data).frame
    before = frame[frame["time"] < split_ts]
    if before.empty:
        raise ConfigError(f"No data before the split {split_ts.date()}: nothing to tune on.")
    inner_ts = _inner_split(before, targets, split_ts, inner_split)
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    log = out_dir / "trials.jsonl"
    done = _finished_trials(log)
    trials = [t for t in trial_grid(models, methods, grid) if t["key"] not in done]
    jobs = [(str(data), t, targets, inner_ts.isoformat(), split_ts.isoformat()) for t in trials]
    _run_trials(jobs, log, done, workers, progress)
    params = {
        "format": "vfm-params/1",
        "targets": targets,
        "split": split_ts.isoformat(),
        "inner_split": inner_ts.isoformat(),
        "grid": grid,
        "models": _best_settings(done, models, methods),
    }
    write_text_atomic(out_dir / "params.json", json.dumps(params, indent=2))
    return params


def load_params(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a ``params.json`` written by ``vfm tune`` (validated)."""
    try:
        params = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ConfigError(f"No parameter file at {path}; run `vfm tune` first.") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(f"{path} is not valid JSON: {exc}.") from None
    if params.get("format") != "vfm-params/1":
        raise ConfigError(f"{path} is not a vfm tune parameter file (format vfm-params/1).")
    return params


def method_for(params: dict[str, Any] | None, model: str, method: str) -> str:
    """The method's text with the options a params file chose for it (e.g. ``bayes:drift=2``
    for ``bayes``), or ``method`` itself."""
    entry = ((params or {}).get("models", {}).get(model, {}) or {}).get(method) or {}
    return str(entry.get("text", method))


def settings_for(params: dict[str, Any] | None, model: str, method: str) -> dict[str, Any]:
    """``train``/``online`` settings for run_prequential from a params file (defaults otherwise)."""
    out: dict[str, Any] = {}
    if not params:
        return out
    entry = params.get("models", {}).get(model, {}).get(method)
    if entry is None:
        return out
    if "online" in entry:
        out["online"] = replace(DEFAULT_ONLINE[model], **entry["online"])
    if "train" in entry:
        out["train"] = replace(DEFAULT_TRAIN[model], **entry["train"])
    return out


def _cmd_tune(args: argparse.Namespace) -> int:
    from vfm_core.models import MODELS

    models = [m for v in (args.models or []) for m in v.split(",") if m] or [
        m for m in MODELS if m != "last"
    ]
    methods = [m for v in (args.methods or []) for m in v.split(",") if m] or [
        "ol",
        "pbl:14d",
        "pbl:182d",
    ]
    params = run_tuning(
        args.data,
        args.out,
        models=models,
        methods=methods,
        targets=args.targets,
        split=args.split,
        inner_split=args.inner_split,
        grid=args.grid,
        workers=args.workers,
        progress=not args.quiet,
    )
    print(
        f"Inner validation {params['inner_split'][:10]} .. {params['split'][:10]} (targets {args.targets}):"
    )
    for model, per in params["models"].items():
        for method, entry in per.items():
            setting = entry.get("online") or entry.get("train")
            print(f"  {model:5s} {method:9s} {entry['inner_mean_mape']:7.2f} %  {setting}")
    print(f"Wrote {Path(args.out) / 'params.json'} (use: vfm evaluate ... --params that file).")
    return 0


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("tune", help="hyperparameter search on data before the split (resumable)")
    p.add_argument("data", help="observation file")
    p.add_argument("--out", required=True, help="output folder (trials.jsonl, params.json)")
    p.add_argument(
        "--models", action="append", help="comma-separated models (default: all but last)"
    )
    p.add_argument(
        "--methods", action="append", help="comma-separated methods (default ol,pbl:14d,pbl:182d)"
    )
    p.add_argument("--targets", default="all", help="all or well_test (default all)")
    p.add_argument("--split", default=None, help="the study's split; only data before it are used")
    p.add_argument(
        "--inner-split",
        default=None,
        help="start of the inner validation period (default: two thirds into the pre-split data)",
    )
    p.add_argument("--grid", default="small", choices=sorted(GRIDS))
    p.add_argument("--workers", type=int, default=2, help="parallel worker processes (default 2)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(handler=_cmd_tune)
