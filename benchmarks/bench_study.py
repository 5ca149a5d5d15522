"""Benchmark: wall time and peak memory of the full study, and the cost of one online update.

Prints figures; asserts nothing (these machines are shared and noisy: compare ratios
within one run). Usage:

    .venv/bin/python benchmarks/bench_study.py [--wells 10] [--years 5] [--models ...] [--cases all,well_test]
        [--outages 7d,30d,90d] [--data field.parquet | --hidden erosion] [--per-run]
        [--jobs 1,2] [--matmul torch,numpy] [--fit-kernel 0,1] [--markdown PATH]

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

With ``--markdown PATH`` the run measures what the documentation's page on the study's
speed shows and writes it there as a Markdown fragment (the command, the date, the
machine's CPUs and load, then the tables): the cost of one online update per model; every
model x method run of each case timed alone in this process (``--per-run``); the whole
study with ``--jobs`` (2 unless given) against the same runs in one process; and the
choices that make the study fast, each undone in a process of its own (``--variants``:
the compiled training loops, numpy's BLAS for the networks' products, glibc's malloc
settings, one torch thread) on a few runs, with their time and mean MAPE beside the
defaults'. About 6-10 minutes on a 2-core machine shared with other work::

    python benchmarks/bench_study.py --markdown docs/benchmarks/generated/study.md

River (a benchmark-only extra: ``pip install -e '.[bench]'``) gives a reference: its
``LinearRegression.learn_one`` on the same stream.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np
import torch

from vfm_core.data import make_batch, target_mask
from vfm_core.fileio import write_text_atomic
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


def per_run_times(
    frame, models: list[str], methods: list[str], case: str
) -> dict[tuple[str, str], float]:
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
    return times


#: the choices that make the study fast, each undone alone (``--variants``): a label, the
#: environment variable and its value (``threads`` is this script's own ``--threads``)
VARIANTS: dict[str, tuple[str, str]] = {
    "defaults": ("", ""),
    "training loops in torch": ("VFM_FIT_KERNEL", "0"),
    "no compiled kernel at all": ("VFM_KERNELS", "0"),
    "networks' products in torch (MKL)": ("VFM_MATMUL", "torch"),
    "glibc's malloc defaults": ("VFM_MALLOC", "default"),
    "two torch threads": ("threads", "2"),
}

#: what ``--markdown`` undoes, on ``--variant-runs``, when ``--variants`` is not given
MARKDOWN_VARIANTS = (
    "defaults,training loops in torch,networks' products in torch (MKL),"
    "glibc's malloc defaults,two torch threads"
)

#: marks the one line of JSON a variant's process prints for its parent
VARIANT_MARK = "VARIANT_JSON "


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
        default=None,
        help="processes for the whole study (as vfm evaluate --jobs); a list (1,2) runs "
        "it once per value and prints the ratios (default 1; 2 with --markdown)",
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
    parser.add_argument(
        "--markdown",
        metavar="PATH",
        default=None,
        help="measure what the docs' page shows (update costs, --per-run, the whole study, "
        "the variants) and write it as a Markdown fragment here",
    )
    parser.add_argument(
        "--variants",
        default=None,
        help=f"comma-separated labels of {sorted(VARIANTS)}: each in a process of its own on "
        f"--variant-runs (default with --markdown: {MARKDOWN_VARIANTS})",
    )
    parser.add_argument(
        "--variant-runs",
        default="nn:pbl:14d:all,mm:pbl:14d:all,mtl:pbl:14d:well_test",
        help="model:method:case runs the variants time",
    )
    parser.add_argument("--threads", type=int, default=1, help="torch threads (vfm's default 1)")
    parser.add_argument("--variant-json", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.jobs is None:
        args.jobs = "2" if args.markdown else "1"
    if args.variants is None:
        args.variants = MARKDOWN_VARIANTS if args.markdown else ""
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
    configure(args.threads)  # torch's threads, glibc's malloc: as the vfm command
    setting = (
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, "
        f"malloc kept for reuse: {tune_malloc()} (VFM_MALLOC=default: glibc's defaults), "
        f"matmul {'torch' if not numpy_enabled() else 'numpy where faster'} (VFM_MATMUL), "
        f"numpy's BLAS {blas_kernels()}, compiled training steps "
        f"{'off' if os.environ.get('VFM_FIT_KERNEL', '1') == '0' else 'on'} (VFM_FIT_KERNEL)"
    )
    print(setting, flush=not args.variant_json)
    started = time.perf_counter()
    frame = load_field(args)
    print(f"field: {len(frame):,} rows in {time.perf_counter() - started:.2f} s")
    if args.variant_json:  # a child of --variants: time the runs, one line of JSON
        print(VARIANT_MARK + json.dumps(time_runs(frame, args.variant_runs)), flush=True)
        return
    report: dict = {"rows": len(frame), "models": models, "methods": args.methods.split(",")}
    if args.per_run or args.markdown:
        warm_up(frame, models, args.methods.split(","))
        report["per_run"] = {
            case: per_run_times(frame, models, args.methods.split(","), case)
            for case in args.cases.split(",")
        }
        print(
            f"\nall runs: {time.perf_counter() - started:.1f} s wall, peak RSS {peak_rss_mb():.0f} MB"
        )
        if not args.markdown:
            return

    print("\none online update (one well, one observation, E steps), microseconds:")
    report["updates"] = {}
    for name in models:
        report["updates"][name] = ol_update_cost(frame, name)
        print(f"  {name:5s} {report['updates'][name]:10.0f} us  (E={DEFAULT_ONLINE[name].steps})")
    ref = river_cost(frame)
    report["river"] = ref
    if ref is None:
        print("  river: not installed (pip install -e '.[bench]')")
    else:
        print(f"  river LinearRegression.learn_one (+predict_one, scaled): {ref:8.0f} us")

    if not args.skip_study:
        walls = {}
        for jobs in [int(j) for j in args.jobs.split(",")]:
            walls[jobs] = whole_study(frame, models, args, jobs)
        report["walls"] = walls
        report["peak_rss_mb"] = peak_rss_mb()
        if len(walls) > 1:
            first = next(iter(walls))
            print(
                "\nwall time of the whole study by --jobs: "
                + ", ".join(f"{j}: {w:.1f} s ({walls[first] / w:.2f}x)" for j, w in walls.items())
            )
    labels = [v.strip() for v in args.variants.split(",") if v.strip()]
    if labels:
        report["variants"] = run_variants(args, labels)
    if args.markdown:
        report["wall_s"] = time.perf_counter() - started
        write_text_atomic(args.markdown, markdown_report(args, setting, report))
        print(f"\nwrote {args.markdown}")


def load_field(args: argparse.Namespace):
    """The observation frame the benchmark runs on: ``--data``, or a simulated field."""
    if args.data:
        return load_observations(args.data).frame
    hidden = [h for h in args.hidden.split(",") if h]
    field = simulate_field(wells=args.wells, years=args.years, seed=args.seed, hidden=hidden)
    return validate_frame(field.observations).frame


def mean_mape(predictions) -> float:
    """Mean over wells of each well's mean absolute percentage error (%) of its scored rows."""
    p = predictions[predictions["measured"].abs() > 0]
    err = ((p["predicted"] - p["measured"]).abs() / p["measured"].abs()).groupby(p["well"])
    return float(err.mean().mean() * 100.0)


def time_runs(frame, spec: str) -> list[dict]:
    """Each ``model:method:case`` of ``spec`` run once after a warm-up on the field's first
    300 days: seconds and mean MAPE (%)."""
    runs = [r.split(":") for r in spec.split(",") if r]
    runs = [(r[0], ":".join(r[1:-1]), r[-1]) for r in runs]
    warm_up(frame, sorted({m for m, _, _ in runs}), sorted({k for _, k, _ in runs}))
    out = []
    for model, method, case in runs:
        started, cpu = time.perf_counter(), time.process_time()
        result = run_prequential(frame, model, method, targets=case, initial_fits={})
        seconds, cpu = time.perf_counter() - started, time.process_time() - cpu
        out.append(
            {
                "model": model,
                "method": method,
                "case": case,
                "seconds": seconds,
                "cpu_s": cpu,
                "mape": mean_mape(result.predictions),
            }
        )
        print(f"  {case:<9} {model:<5} {method:<10} {seconds:8.1f} s, CPU {cpu:.1f} s", flush=True)
    return out


def run_variants(args: argparse.Namespace, labels: list[str]) -> dict[str, list[dict]]:
    """Each variant in a process of its own (nothing compiled, cached or allocated is
    shared), one after the other, the runs of ``--variant-runs`` timed in each."""
    unknown = [v for v in labels if v not in VARIANTS]
    if unknown:
        raise SystemExit(f"Unknown variants {unknown}; the variants are {sorted(VARIANTS)}.")
    out = {}
    for label in labels:
        variable, value = VARIANTS[label]
        env = {k: v for k, v in os.environ.items() if k not in {"VFM_FIT_KERNEL", "VFM_MATMUL"}}
        argv = [
            sys.argv[0],
            "--variant-json",
            f"--wells={args.wells}",
            f"--years={args.years}",
            f"--seed={args.seed}",
            f"--hidden={args.hidden}",
            f"--variant-runs={args.variant_runs}",
        ]
        if args.data:
            argv.append(f"--data={args.data}")
        if variable == "threads":
            argv.append(f"--threads={value}")
        elif variable:
            env[variable] = value
        print(f"\n=== variant: {label} ({variable}={value})" if variable else "\n=== defaults")
        done = subprocess.run(
            [sys.executable, *argv], env=env, check=True, capture_output=True, text=True
        )
        print(done.stdout, end="", flush=True)
        lines = [x for x in done.stdout.splitlines() if x.startswith(VARIANT_MARK)]
        out[label] = json.loads(lines[-1][len(VARIANT_MARK) :])
    return out


def markdown_report(args: argparse.Namespace, setting: str, report: dict) -> str:
    """The run's tables as a Markdown fragment, the command and the machine first."""
    import platform
    from datetime import UTC, datetime

    argv = " ".join(sys.argv[1:])
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    methods = report["methods"]
    lines = [
        f"Written by `python benchmarks/bench_study.py {argv}` on "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC in {report['wall_s'] / 60:.1f} min: "
        f"{os.cpu_count()} CPUs ({platform.machine()}), load average (1, 5, 15 min) "
        f"{load[0]:.1f}, {load[1]:.1f}, {load[2]:.1f} at the end; {setting}. The field: "
        + (
            f"`{args.data}`"
            if args.data
            else f"`simulate_field(wells={args.wells}, years={args.years:g}, seed={args.seed}"
            + (f", hidden={args.hidden!r}" if args.hidden else "")
            + ")`"
        )
        + f", {report['rows']:,} rows. Seconds of wall time unless named otherwise.",
        "",
    ]
    if "updates" in report:
        lines += [
            "**One online update** (`ol`, one well, one observation, E steps), microseconds:",
            "",
            "| model | E | µs per update |",
            "| --- | ---: | ---: |",
        ]
        for name, us in report["updates"].items():
            lines.append(f"| `{name}` | {DEFAULT_ONLINE[name].steps} | {us:,.0f} |")
        if report.get("river") is not None:
            lines.append(
                f"| river `LinearRegression` (`predict_one` + `learn_one`, scaled) |  | "
                f"{report['river']:,.1f} |"
            )
        lines.append("")
    for case, times in report.get("per_run", {}).items():
        values = sorted(times.values())
        median = float(np.median(values))
        slowest = max(times, key=times.__getitem__)
        per_model = {m: sum(times[m, k] for k in methods) for m in report["models"]}
        model_median = float(np.median(list(per_model.values())))
        heaviest = max(per_model, key=per_model.__getitem__)
        lines += [
            f"**Every run of case `{case}` timed alone** (`--per-run`: one process, the initial "
            "fit shared between methods with the same window, after an untimed warm-up), "
            "seconds:",
            "",
            "| model | " + " | ".join(f"`{m}`" for m in methods) + " | the model's runs |",
            "| --- |" + " ---: |" * (len(methods) + 1),
        ]
        for model in report["models"]:
            cells = " | ".join(f"{times[model, m]:.1f}" for m in methods)
            lines.append(f"| `{model}` | {cells} | {per_model[model]:.1f} |")
        lines += [
            "",
            f"Case `{case}`: {sum(values):.1f} s in {len(values)} runs. Slowest run "
            f"`{slowest[0]}` `{slowest[1]}` {times[slowest]:.1f} s = "
            f"**{times[slowest] / median:.1f}x** the median run ({median:.1f} s); slowest "
            f"model `{heaviest}` {per_model[heaviest]:.1f} s = "
            f"**{per_model[heaviest] / max(model_median, 1e-9):.1f}x** the median model "
            f"({model_median:.1f} s).",
            "",
        ]
    if "walls" in report:
        in_one = sum(sum(t.values()) for t in report.get("per_run", {}).values())
        lines += [
            "**The whole study** (both cases, as `vfm evaluate --jobs N` runs it: this process "
            "and N - 1 workers taking the models in turn):",
            "",
            "| how | wall, s | the runs one by one in one process / this |",
            "| --- | ---: | ---: |",
        ]
        if in_one:
            lines.append(
                f"| every run timed alone in one process (the tables above) | {in_one:.1f} | 1.00 |"
            )
        for jobs, wall in report["walls"].items():
            ratio = f"{in_one / wall:.2f}" if in_one else ""
            lines.append(f"| the whole study, `--jobs {jobs}` | {wall:.1f} | {ratio} |")
        lines += ["", f"Peak memory of this process: {report['peak_rss_mb']:,.0f} MB.", ""]
    if "variants" in report:
        variants = report["variants"]
        base = variants.get("defaults")
        runs = next(iter(variants.values()))
        names = [f"`{r['model']}` `{r['method']}` case `{r['case']}`" for r in runs]
        lines += [
            "**Each choice undone alone** (each line a process of its own, one after the "
            "other, one warm-up each): each run's wall time / the process's CPU time "
            "(user and system, every thread; on a loaded machine it moves less than the "
            "wall time), seconds, and in brackets its mean MAPE across wells (%), which "
            "shows that a choice changes the time, not the results (beyond rounding)"
            + (
                "; then the runs' wall and CPU time over the defaults' (higher: the choice "
                "saves more)."
                if base
                else "."
            ),
            "",
            "| variant | "
            + " | ".join(names)
            + (" | wall / defaults' | CPU / defaults' |" if base else " |"),
            "| --- |" + " ---: |" * (len(names) + (2 if base else 0)),
        ]
        for label, rs in variants.items():
            variable, value = VARIANTS[label]
            how = f" (`{variable}={value}`)" if variable and variable != "threads" else ""
            if variable == "threads":
                how = f" (`--threads {value}`)"
            cells = " | ".join(
                f"{r['seconds']:.1f} / {r['cpu_s']:.1f} ({r['mape']:.3f} %)" for r in rs
            )
            ratio = ""
            if base:
                wall = sum(r["seconds"] for r in rs) / sum(r["seconds"] for r in base)
                cpu = sum(r["cpu_s"] for r in rs) / sum(r["cpu_s"] for r in base)
                ratio = f" | {wall:.2f}x | {cpu:.2f}x"
            lines.append(f"| {label}{how} | {cells}{ratio} |")
        lines.append("")
    return "\n".join(lines)


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
