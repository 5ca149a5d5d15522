"""Benchmark: wall time and peak memory of the full study, and the cost of one online update.

Prints figures; asserts nothing (these machines are shared and noisy: compare ratios
within one run). Usage:

    .venv/bin/python benchmarks/bench_study.py [--wells 10] [--years 5] [--models ...] [--cases all,well_test]
        [--outages 7d,30d,90d] [--data field.parquet | --hidden erosion] [--per-run]
        [--jobs 1,2] [--matmul torch,numpy] [--fit-kernel 0,1]

With ``--jobs 1,2`` the whole study runs once per value, as ``vfm evaluate --jobs`` runs it
(this process and N - 1 workers taking the models in turn), and the ratios of the wall
times are printed.

With ``--matmul torch,numpy`` everything asked runs once per value of ``VFM_MATMUL``, each
in its own process: the networks' products in torch (MKL) or in numpy's OpenBLAS
(:mod:`vfm_core.models.linalg`), side by side. ``--fit-kernel 0,1`` does the same for the
compiled training steps of ``mm`` and the hybrids (``VFM_FIT_KERNEL``).

With ``--per-run`` the study is timed one model x method run at a time (as ``vfm evaluate``
runs them, the initial fit shared between methods with the same window), per case, with
the slowest run's time over the median run's: no model or method should crawl.

With ``--outages`` each case runs twice, without and with the outage protocol, and the
ratio of the wall times is printed: the protocol adds one prequential run per model,
method and outage length (the initial fit is shared), so the ratio should stay near
1 + the number of lengths, whatever the number of windows.

River (a benchmark-only extra: ``pip install -e '.[bench]'``) gives a reference: its
``LinearRegression.learn_one`` on the same stream.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from vfm_core.data import make_batch, target_mask
from vfm_core.jobs.evaluate import PRELOAD, format_summary, run_study
from vfm_core.jobs.study import run_prequential, wells_of
from vfm_core.jobs.workers import StudyWorkers
from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, fit_batch, parse_method
from vfm_core.models import MODELS, make_model
from vfm_core.models.linalg import numpy_enabled
from vfm_core.observations import load_observations, validate_frame
from vfm_core.runtime import configure, tune_malloc
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def ol_update_cost(frame, name: str, n: int = 200) -> float:
    """Microseconds per online update of one well (one observation, E steps)."""
    wells = wells_of(frame)[:1]
    rows = np.flatnonzero(target_mask(frame, "all") & (frame["well"] == wells[0]).to_numpy())
    batch = make_batch(frame, wells, rows)
    model = make_model(name, wells)
    fit_batch(model, batch.select(torch.cumsum(batch.mask.long(), 1) <= 200), DEFAULT_TRAIN[name])
    learner = parse_method("ol").bind(model)
    cols = [batch.select(torch.cumsum(batch.mask.long(), 1) == k + 201) for k in range(n)]
    started = time.perf_counter()
    for col in cols:
        learner.on_measurement(col)
    return (time.perf_counter() - started) / n * 1e6


def river_cost(frame, n: int = 2000) -> float | None:
    try:
        from river import linear_model, preprocessing
    except ImportError:
        return None
    well = wells_of(frame)[0]
    sub = frame[(frame["well"] == well) & frame["q_total"].notna()].head(n)
    model = preprocessing.StandardScaler() | linear_model.LinearRegression()
    xs = [dict(zip(INPUT_COLUMNS, row, strict=True)) for row in sub[list(INPUT_COLUMNS)].to_numpy()]
    ys = sub["q_total"].to_numpy()
    started = time.perf_counter()
    for x, y in zip(xs, ys, strict=True):
        model.predict_one(x)
        model.learn_one(x, y)
    return (time.perf_counter() - started) / len(xs) * 1e6


def warm_up(frame, models: list[str], methods: list[str]) -> None:
    """Run every model and method once on the field's first 300 days, untimed in the
    table: what a process pays once (numba's kernels compiled or loaded from its cache,
    torch's first optimiser) is then not charged to whichever run comes first."""
    first = frame[frame["time"] < frame["time"].min() + np.timedelta64(300, "D")]
    started = time.perf_counter()
    for model in models:
        for method in methods:
            run_prequential(first, model, method, targets="all", initial_fits={})
    print(f"warm-up (once per process, not in the table): {time.perf_counter() - started:.1f} s")


def per_run_times(frame, models: list[str], methods: list[str], case: str) -> None:
    """Seconds of each model x method run of one case, and the slowest over the median."""
    initial_fits: dict = {}
    times: dict[tuple[str, str], float] = {}
    for model in models:
        for method in methods:
            started = time.perf_counter()
            run_prequential(
                frame, model, method, targets=case, initial_fits=initial_fits, phases=True
            )
            times[model, method] = time.perf_counter() - started
            print(f"  {case:<9} {model:<5} {method:<10} {times[model, method]:8.1f} s", flush=True)
    values = sorted(times.values())
    median = float(np.median(values))
    slowest = max(times, key=times.__getitem__)
    print(
        f"case {case}: {sum(values):.1f} s in {len(values)} runs; median {median:.1f} s, "
        f"slowest {' '.join(slowest)} {times[slowest]:.1f} s = {times[slowest] / median:.1f} x median"
    )
    # per model, its methods together (a model's share of the study)
    per_model = {m: sum(times[m, k] for k in methods) for m in models}
    model_median = float(np.median(list(per_model.values())))
    heaviest = max(per_model, key=per_model.__getitem__)
    print(
        f"case {case} per model (its {len(methods)} methods): median {model_median:.1f} s, "
        f"slowest {heaviest} {per_model[heaviest]:.1f} s = "
        f"{per_model[heaviest] / max(model_median, 1e-9):.1f} x median"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--wells", type=int, default=10)
    parser.add_argument("--years", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--models", default=",".join(MODELS))
    parser.add_argument("--methods", default="ol,pbl:14d,pbl:182d")
    parser.add_argument("--cases", default="all,well_test")
    parser.add_argument("--outages", default="", help="e.g. 7d,30d,90d (also time the protocol)")
    parser.add_argument("--skip-study", action="store_true")
    parser.add_argument("--out", default=None, help="also write each case's outputs (report) here")
    parser.add_argument("--data", default=None, help="an observation file instead of simulating")
    parser.add_argument("--hidden", default="", help="hidden effects of the simulated field")
    parser.add_argument("--per-run", action="store_true", help="time each model x method run")
    parser.add_argument(
        "--jobs",
        default="1",
        help="processes for the whole study (as vfm evaluate --jobs); a list (1,2) runs "
        "it once per value and prints the ratios",
    )
    parser.add_argument(
        "--matmul",
        default="",
        help="the networks' products: torch, numpy or a list (torch,numpy), each value a "
        "run of everything asked, side by side (VFM_MATMUL; vfm_core.models.linalg)",
    )
    parser.add_argument(
        "--fit-kernel",
        default="",
        help="1: the mm and hybrids' training steps compiled (the default), 0: torch's loop, "
        "or a list (0,1), side by side (VFM_FIT_KERNEL; vfm_core.learning.kernels.FitSteps)",
    )
    args = parser.parse_args()
    for option, variable in (("--matmul", "VFM_MATMUL"), ("--fit-kernel", "VFM_FIT_KERNEL")):
        values = [v.strip() for v in getattr(args, option[2:].replace("-", "_")).split(",")]
        values = [v for v in values if v]
        if len(values) > 1:  # each value in its own process: nothing cached is shared
            for value in values:
                print(f"\n=== {variable}={value}", flush=True)
                argv = [sys.argv[0], *strip_option(sys.argv[1:], option)]
                env = {**os.environ, variable: value}
                subprocess.run([sys.executable, *argv], env=env, check=True)
            return
        if values:
            os.environ[variable] = values[0]
    models = args.models.split(",")
    configure(1)  # torch's threads, glibc's malloc: as the vfm command (vfm_core.runtime)
    print(
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"malloc kept for reuse: {tune_malloc()} (VFM_MALLOC=default: glibc's defaults), "
        f"matmul {'torch' if not numpy_enabled() else 'numpy where faster'} (VFM_MATMUL), "
        f"numpy's BLAS {blas_kernels()}, compiled training steps "
        f"{'off' if os.environ.get('VFM_FIT_KERNEL', '1') == '0' else 'on'} (VFM_FIT_KERNEL)"
    )
    started = time.perf_counter()
    if args.data:
        frame = load_observations(args.data).frame
    else:
        hidden = [h for h in args.hidden.split(",") if h]
        field = simulate_field(wells=args.wells, years=args.years, seed=args.seed, hidden=hidden)
        frame = validate_frame(field.observations).frame
    print(f"field: {len(frame):,} rows in {time.perf_counter() - started:.2f} s")
    if args.per_run:
        warm_up(frame, models, args.methods.split(","))
        for case in args.cases.split(","):
            per_run_times(frame, models, args.methods.split(","), case)
        print(
            f"\nall runs: {time.perf_counter() - started:.1f} s wall, peak RSS {peak_rss_mb():.0f} MB"
        )
        return

    print("\none online update (one well, one observation, E steps), microseconds:")
    for name in models:
        print(
            f"  {name:5s} {ol_update_cost(frame, name):10.0f} us  (E={DEFAULT_ONLINE[name].steps})"
        )
    ref = river_cost(frame)
    if ref is None:
        print("  river: not installed (pip install -e '.[bench]')")
    else:
        print(f"  river LinearRegression.learn_one (+predict_one, scaled): {ref:8.0f} us")

    if args.skip_study:
        return
    walls = {}
    for jobs in [int(j) for j in args.jobs.split(",")]:
        walls[jobs] = whole_study(frame, models, args, jobs)
    if len(walls) > 1:
        first = next(iter(walls))
        print(
            "\nwall time of the whole study by --jobs: "
            + ", ".join(f"{j}: {w:.1f} s ({walls[first] / w:.2f}x)" for j, w in walls.items())
        )


def blas_kernels() -> str:
    """numpy's BLAS, its kernels and threads (threadpoolctl), e.g. 'openblas Haswell x1'."""
    from threadpoolctl import threadpool_info

    pools = [p for p in threadpool_info() if p.get("user_api") == "blas"]
    return ", ".join(
        f"{p.get('internal_api')} {p.get('architecture', '?')} x{p.get('num_threads')}"
        for p in pools
    )


def strip_option(argv: list[str], name: str) -> list[str]:
    """``argv`` without ``name`` and its value (``--name value`` or ``--name=value``)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == name:
            skip = True
        elif not a.startswith(name + "="):
            out.append(a)
    return out


def whole_study(frame, models: list[str], args: argparse.Namespace, jobs: int) -> float:
    """The study of every case, as ``vfm evaluate --jobs`` runs it; returns its wall time."""
    print(f"\nthe whole study with --jobs {jobs}:")
    started = time.perf_counter()
    total = 0.0
    with StudyWorkers(max(jobs, 1) - 1, preload=PRELOAD) as workers:
        for case in args.cases.split(","):
            total += study_case(frame, models, args, case, workers if jobs > 1 else None)
    wall = time.perf_counter() - started
    print(f"full study (--jobs {jobs}): {wall:.1f} s wall, peak RSS {peak_rss_mb():.0f} MB")
    return wall


def study_case(frame, models: list[str], args: argparse.Namespace, case: str, workers) -> float:
    common = dict(models=models, methods=args.methods.split(","), targets=case, progress=False)
    result = run_study(frame, workers=workers, **common)
    total = result.runtime_s
    if args.out:
        from vfm_core.jobs.evaluate import write_study

        write_study(result, f"{args.out}/{case}")
    print()
    print(format_summary(result))
    per = result.predictions.groupby(["model", "method"]).size()
    print(f"case {case}: {result.runtime_s:.1f} s for {len(per)} model x method runs")
    if args.outages:
        with_outages = run_study(frame, outages=args.outages, workers=workers, **common)
        total += with_outages.runtime_s
        lengths = len(with_outages.outages)
        windows = len(with_outages.outage_windows)
        print(format_summary(with_outages))
        print(
            f"case {case} with outages {args.outages} ({windows} windows): "
            f"{with_outages.runtime_s:.1f} s, {with_outages.runtime_s / result.runtime_s:.2f} x "
            f"the ordinary study (1 + {lengths} lengths = {1 + lengths})"
        )
    return total


if __name__ == "__main__":
    main()
