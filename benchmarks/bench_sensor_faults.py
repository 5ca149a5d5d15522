"""Benchmark: false faults and detection delays of the instrument-fault detectors.

Prints a table; asserts nothing. For each simulated field (``--seeds``, ``--wells``,
``--years``; seeds and sizes the tests do not use) it runs one
:class:`vfm_core.sensor_faults.WellSensorFaults` per well over the clean rows (every row's
inputs in time order, as the service sees them) and counts the faults raised per
well-year (``false/well-yr``, per kind; the design allows 0.1 for all kinds together).
Then, for each scenario (``--faults``: ``kind:sensor:size``, sizes relative to the
reading as :func:`vfm_core.faults_sim.inject_fault` takes them; drift per 30 days), it
injects one fault per well at a random time (seeded; at least ``--history-days`` after the
well's first row and 60 days before its last) and reports:

- ``found 7d``: the share of wells whose injected fault was detected within 7 days of
  its start with the right sensor (``right kind``: and the right kind);
- ``median delay d``: days from the fault's start to the first fault raised on that
  sensor after it (within 60 days);
- ``other sensors``: faults raised on other sensors in the 7 days after its start;
- ``reading unchanged``: injections that changed no reading (an offset up of a choke
  fully open, which stays at 1), left out of the shares.

Each row's inputs are fed, then its MPFM rate (``WellSensorFaults.measure``: the
choke-rate witness), as the service and ``vfm evaluate`` feed them. ``--faults larger``
runs the larger sizes of :data:`LARGER_FAULTS`. ``--hidden`` (as ``vfm simulate --hidden``
takes it, e.g. ``erosion:rate=0.15,valve``) and ``--physics`` simulate fields whose wells
change physically (choke wear, a valve curve, real gas, ...): the false faults are then
those such real changes raise, which must stay within the same budget. ``--at subcritical`` starts each fault at a
random row where the well flows subcritically (the true ``p_down / p_up`` at or above the
true critical ratio: the rate depends on ``p_down``): the offsets of ``p_down`` that matter
to the rate (most wells flow critically, where none does).

The cost per sample (``us/sample``) is the detector's own CPU time over all clean rows
(``time.process_time``; the service's whole per-sample path is about 115-125 us of CPU,
``bench_service.py --scenario engine``).

Usage::

    nice -n 10 .venv/bin/python benchmarks/bench_sensor_faults.py [--seeds 901,902,903]
        [--wells 8] [--years 4] [--markdown docs/benchmarks/generated/sensor-faults.md]

``--study`` measures instead the error of ``vfm evaluate`` during a fault and after it
(:func:`study_errors`): per seed, ``vfm simulate`` writes the field clean and again with one
fault per well (``--study-fault kind:sensor[:size]``, ``--fault-days`` long, from a random day at
least ``--history-days`` after the well's first row and ``--fault-days`` + 60 days before
its last; seeded), ``vfm evaluate`` (``--models``, ``--methods``, ``--split``) studies both,
and the study with every input taken as read (``run_study(sensor_faults=False)``, as
before the study held and stood in) the faulty one. MAPE (%) against the true rate
(``<field>.truth.parquet``) over the fault's rows (from its first faulty row) and over the
60 days after it, pooled over the wells, with the wells whose error is within 2x (during)
and 1.2x (after) of the clean field's, and how many of the faults the faulty study's
``sensor_faults.json`` has within 7 days of their start (right well and sensor; right kind).
An ``out_of_range`` fault's rows are removed when read with every input as read (as
``vfm evaluate --no-sensor-faults`` reads the file): its "as read" cells during the fault
are "-"::

    nice -n 10 .venv/bin/python benchmarks/bench_sensor_faults.py --study --seeds 4711,4712
        --wells 3 --years 2.5 --history-days 400 --split 2017-01-01
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd

from vfm_core.faults_sim import inject_fault
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.sensor_faults import KINDS, WellSensorFaults, mpfm_rates
from vfm_core.simulate import simulate_field

DEFAULT_FAULTS = (
    "frozen:p_down:0",
    "frozen:t_up:0",
    "spike:p_up:0.1",
    "spike:t_up:0.1",
    "offset:p_down:0.1",
    "offset:t_up:0.05",
    "offset:choke:0.05",
    "drift:p_up:0.05",
    "drift:p_down:0.1",
    "out_of_range:p_up:0",
)
#: the same kinds larger (``--faults larger``, written to ``sensor-faults-sizes.md``): what
#: the detectors need to find most faults within a week
LARGER_FAULTS = (
    "offset:p_down:0.2",
    "offset:t_up:0.1",
    "offset:choke:0.1",
    "offset:choke:0.2",
    "drift:p_up:0.2",
    "drift:p_down:0.3",
)
_DAY_NS = 86_400 * 10**9
#: the variants of the study compared: the clean field, the faulty one studied as the
#: service runs (stand-in, held), the faulty one with every input as read
_VARIANTS = ("clean", "fault", "as read")


def run_well(g: pd.DataFrame, det: WellSensorFaults | None = None) -> tuple[list, float]:
    """Every fault event of one well's rows (time order) and the detector's time (s): each
    row's inputs, then its MPFM rate (the choke-rate witness), as the service feeds them."""
    det = det or WellSensorFaults()
    times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64").tolist()
    values = g[list(INPUT_COLUMNS)].to_numpy(dtype=float).tolist()
    mpfm = mpfm_rates(g)
    seen: dict[int, object] = {}
    last = None
    started = time.process_time()  # CPU time: other processes on the machine do not count
    for t, row, rate in zip(times, values, mpfm, strict=True):
        if t != last:
            for e in det.update(t, row):
                seen[id(e)] = e
            last = t
        if rate == rate:  # not NaN
            for e in det.measure(t, rate, row):
                seen[id(e)] = e
    return list(seen.values()), time.process_time() - started


def _matters(g: pd.DataFrame, faulty: pd.DataFrame, p_cr: pd.Series, sensor: str, t0: int) -> bool:
    """Whether the true rate depends on ``p_down`` in the 7 days after ``t0`` (ns) on the
    true reading or the faulty one: ``p_down / p_up`` reaches the row's true critical ratio
    (the simulator's ``p_cr_true``) on some row. Only for ``p_down`` (False otherwise)."""
    if sensor != "p_down":
        return False
    times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64").to_numpy()
    week = (times >= t0) & (times < t0 + 7 * _DAY_NS)
    p_up = g["p_up"].to_numpy(dtype=float)[week]
    ratio = np.maximum(
        g["p_down"].to_numpy(dtype=float)[week], faulty["p_down"].to_numpy(dtype=float)[week]
    )
    return bool(np.any(ratio / p_up >= p_cr.to_numpy(dtype=float)[week]))


def cost_per_minute_samples(days: int = 20) -> float:
    """CPU us a sample on a synthetic stream of one sample a minute (noisy slow walks of
    six inputs): the daily tests then run once per 1440 samples."""
    rng = np.random.default_rng(5)
    n = days * 1440
    level = np.array([0.5, 120.0, 30.0, 60.0, 0.1, 0.6])
    noise = np.array([0.0, 0.3, 0.1, 0.1, 1e-4, 1e-4])
    walk = np.cumsum(rng.normal(0.0, 1.0, (n, 6)) * noise * 0.01, axis=0)
    values = (level + walk + rng.normal(0.0, 1.0, (n, 6)) * noise).tolist()
    times = (1_600_000_000 * 10**9 + np.arange(n, dtype=np.int64) * 60 * 10**9).tolist()
    det = WellSensorFaults()
    started = time.process_time()
    for t, row in zip(times, values, strict=True):
        det.update(t, row)
    return 1e6 * (time.process_time() - started) / n


def _fault_specs(path: Path, args: argparse.Namespace, seed: int) -> list[str]:
    """One ``--fault`` spec per well of the field at ``path`` long enough for it (seeded)."""
    from vfm_core.observations import load_observations

    frame = load_observations(path).frame
    rng = np.random.default_rng(seed + 20_000)
    kind, sensor, *size = args.study_fault.split(":")
    specs = []
    for well, g in frame.groupby("well", sort=True):
        t = pd.to_datetime(g["time"], utc=True)
        span = (t.max() - t.min()).total_seconds() / 86_400
        latest = span - args.fault_days - 60.0
        if latest > args.history_days:
            start = t.min() + pd.Timedelta(days=rng.uniform(args.history_days, latest))
            spec = f"{well},{sensor},{kind},{start.isoformat()},{''.join(size)},"
            specs.append(spec + f"{args.fault_days:g}")
    return specs


def _errors(pred: pd.DataFrame, truth: pd.DataFrame, fault: dict, after: bool) -> dict:
    """Absolute errors (%) against the true rate of ``pred``'s rows of the fault's well in
    the fault (``after``: the 60 days after it), per (model, method)."""
    t0, t1 = pd.Timestamp(fault["start"]), pd.Timestamp(fault["end"])
    lo, hi = (t1, t1 + pd.Timedelta(days=60)) if after else (t0, t1)
    rows = pred[(pred["well"] == fault["well"]) & (pred["time"] >= lo) & (pred["time"] <= hi)]
    if after:
        rows = rows[rows["time"] > t1]
    rows = rows.merge(truth[["well", "time", "q_true"]], on=["well", "time"])
    err = 100 * (rows["predicted"] - rows["q_true"]).abs() / rows["q_true"]
    return {key: g.to_numpy() for key, g in err.groupby([rows["model"], rows["method"]])}


def study_errors(args: argparse.Namespace) -> str:
    """The ``--study`` table (see the module docstring)."""
    from vfm_core.cli import main as vfm
    from vfm_core.jobs.evaluate import run_study
    from vfm_core.observations import load_observations
    from vfm_core.simulate import load_truth

    errors: dict[tuple, list[np.ndarray]] = {}  # (model, method, variant, after) -> per fault
    n_faults = 0
    found = np.zeros(2, dtype=int)  # in sensor_faults.json within 7 days: sensor, and kind
    for seed in [int(s) for s in args.seeds.split(",") if s]:
        folder = Path(tempfile.mkdtemp(prefix=f"bench-faults-{seed}-"))
        sim = ["simulate", "--wells", str(args.wells), "--years", str(args.years)]
        sim += ["--seed", str(seed), "--quiet"]
        vfm([*sim, "--out", str(folder / "clean.parquet")])
        specs = _fault_specs(folder / "clean.parquet", args, seed)
        vfm([*sim, "--out", str(folder / "fault.parquet"), *(f"--fault={s}" for s in specs)])
        preds = {}
        for name in ("clean", "fault"):
            vfm(["evaluate", str(folder / f"{name}.parquet"), "--out", str(folder / name),
                 "--models", args.models, "--methods", args.methods, "--split", args.split,
                 "--quiet", "--no-report", "--jobs", "1"])  # fmt: skip
            preds[name] = pd.read_parquet(folder / name / "predictions.parquet")
        frame = load_observations(folder / "fault.parquet").frame
        preds["as read"] = run_study(
            frame, models=args.models.split(","), methods=args.methods.split(","),
            split=args.split, progress=False, sensor_faults=False,
        ).predictions  # fmt: skip
        meta, truth = load_truth(folder / "fault.parquet")
        truth["time"] = pd.to_datetime(truth["time"], utc=True)
        combos = [(m, k) for m in args.models.split(",") for k in args.methods.split(",")]
        written = json.loads((folder / "fault" / "sensor_faults.json").read_text())
        for fault in meta["faults"]:
            n_faults += 1
            found += _found_in(written["sensor_faults"], fault)
            for variant, pred in preds.items():
                for after in (False, True):
                    got = _errors(pred, truth, fault, after)
                    for key in combos:  # none: no row predicted there (removed as read)
                        err = got.get(key, np.empty(0))
                        errors.setdefault((*key, variant, after), []).append(err)
        shutil.rmtree(folder, ignore_errors=True)
    return _study_table(errors, n_faults) + (
        f"\n\nIn `vfm evaluate`'s sensor_faults.json within 7 days of the start: {found[0]} of "
        f"{n_faults} on the right well and sensor, {found[1]} with the right kind."
    )


def _found_in(written: list[dict], fault: dict) -> np.ndarray:
    """[right sensor, right kind]: whether ``written`` (``sensor_faults.json``'s faults)
    has one on ``fault``'s well and sensor detected within 7 days of its start."""
    t0 = pd.Timestamp(fault["start"])
    on = [
        f
        for f in written
        if (f["well"], f["sensor"]) == (fault["well"], fault["sensor"])
        and t0 <= pd.Timestamp(f["detected"]) <= t0 + pd.Timedelta(days=7)
    ]
    return np.array([bool(on), any(f["kind"] == fault["kind"] for f in on)], dtype=int)


def _study_table(errors: dict[tuple, list[np.ndarray]], n_faults: int) -> str:
    """The ``--study`` table: a column per model and method, a line per variant and span."""
    combos = sorted({(m, k) for m, k, _, _ in errors})
    lines = [
        f"{n_faults} faults (one per well). MAPE (%) against the true rate, pooled; wells: "
        "those within 2x (during) or 1.2x (after) of the clean field's MAPE.",
        "",
        "| | " + " | ".join(f"{m} {k}" for m, k in combos) + " |",
        "|---|" + "---|" * len(combos),
    ]

    def pooled(m: str, k: str, v: str, after: bool) -> float:
        joined = np.concatenate(errors[(m, k, v, after)])
        return float(np.mean(joined)) if len(joined) else float("nan")

    def cell(x: float) -> str:  # "-": no row predicted (an input out of range, removed)
        return f"{x:.2f}" if np.isfinite(x) else "-"

    for after, span, limit in ((False, "during", 2.0), (True, "60 days after", 1.2)):
        for v in _VARIANTS:
            cells = [cell(pooled(m, k, v, after)) for m, k in combos]
            lines.append(f"| MAPE {span}, {v} | " + " | ".join(cells) + " |")
        for v in _VARIANTS[1:]:
            cells = []
            for m, k in combos:
                ratio = pooled(m, k, v, after) / pooled(m, k, "clean", after)
                per_well = [
                    (a, c)
                    for a, c in zip(
                        errors[(m, k, v, after)], errors[(m, k, "clean", after)], strict=True
                    )
                    if len(a) and len(c)
                ]
                within = sum(np.mean(a) <= limit * np.mean(c) for a, c in per_well)
                cells.append(f"{cell(ratio)} ({within}/{len(per_well)})")
            lines.append(
                f"| {span}: {v} / clean (wells within {limit:g}x) | " + " | ".join(cells) + " |"
            )
    return "\n".join(lines)


def _fields(args: argparse.Namespace) -> str:
    """What the fields are, for the table's first line (the default: clean fields)."""
    if not args.hidden and args.physics == "sachdeva":
        return "Clean fields"
    return (
        f"Fields without instrument faults ({args.physics} physics, hidden effects "
        f"{args.hidden or 'none'})"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="901,902,903")
    ap.add_argument("--wells", type=int, default=8)
    ap.add_argument("--years", type=float, default=4.0)
    ap.add_argument(
        "--faults",
        default=",".join(DEFAULT_FAULTS),
        help="kind:sensor:size,... ('larger': the larger sizes of LARGER_FAULTS)",
    )
    ap.add_argument("--history-days", type=float, default=180.0)
    ap.add_argument(
        "--at",
        choices=("any", "subcritical"),
        default="any",
        help="where faults start: a random day (any), or a random row where the true "
        "p_down / p_up reaches the true critical ratio (subcritical: the rate depends on "
        "p_down; wells without such a row are left out)",
    )
    ap.add_argument(
        "--hidden",
        default="",
        help="hidden physical effects of the fields, as vfm simulate --hidden takes them "
        "(e.g. erosion:rate=0.15,valve): real changes of the wells that must raise no "
        "instrument fault (default none: clean fields)",
    )
    ap.add_argument(
        "--physics", default="sachdeva", help="the fields' truth physics (vfm simulate --physics)"
    )
    ap.add_argument("--markdown", help="also write the tables as Markdown to this file")
    ap.add_argument("--study", action="store_true", help="error of vfm evaluate at a fault")
    ap.add_argument(
        "--study-fault",
        default="frozen:p_down",
        help="kind:sensor[:size] (--study; size as --faults, default the kind's)",
    )
    ap.add_argument("--fault-days", type=float, default=60.0, help="fault length (--study)")
    ap.add_argument("--models", default="mm,ham", help="models (--study)")
    ap.add_argument("--methods", default="bayes,ol", help="methods (--study)")
    ap.add_argument("--split", default="2017-01-01", help="first day scored (--study)")
    args = ap.parse_args(argv)
    if args.study:
        print(study_errors(args))
        return 0
    seeds = [int(s) for s in args.seeds.split(",") if s]
    faults = ",".join(LARGER_FAULTS) if args.faults == "larger" else args.faults
    scenarios = [s.split(":") for s in faults.split(",") if s]

    well_years = 0.0
    false: Counter[str] = Counter()
    by_sensor: Counter[tuple[str, str]] = Counter()
    rows = 0
    spent = 0.0
    unchanged: Counter[str] = Counter()  # injections that changed no reading
    results: dict[str, list[tuple[bool, bool, float | None, int, bool]]] = {
        ":".join(s): [] for s in scenarios
    }
    set_points: Counter[str] = Counter()  # p_down steps not raised, per reason
    for seed in seeds:
        field = simulate_field(
            wells=args.wells,
            years=args.years,
            seed=seed,
            hidden=[args.hidden] if args.hidden else [],
            physics=args.physics,
        )
        frame, p_cr_true = field.observations, field.truth_samples["p_cr_true"]
        rng = np.random.default_rng(seed + 10_000)
        for well, g in frame.groupby("well", sort=True):
            g = g.sort_values("time", kind="stable")
            t = pd.to_datetime(g["time"], utc=True)
            span_days = (t.iloc[-1] - t.iloc[0]).total_seconds() / 86_400
            well_years += span_days / 365.25
            det = WellSensorFaults()
            events, dt = run_well(g, det)
            set_points.update(getattr(det, "set_points", {}))
            set_points["drift"] += getattr(det, "drifts_set_aside", 0)
            rows += len(g)
            spent += dt
            false.update(e.kind for e in events)
            by_sensor.update((e.kind, e.sensor) for e in events)
            if span_days < args.history_days + 90:
                continue
            for kind, sensor, size in scenarios:
                offset = rng.uniform(args.history_days, span_days - 60.0)
                start = t.iloc[0] + pd.Timedelta(days=offset)
                if args.at == "subcritical":  # a random row where the rate depends on p_down
                    days = (t - t.iloc[0]).dt.total_seconds().to_numpy() / 86_400
                    ratio = g["p_down"].to_numpy(dtype=float) / g["p_up"].to_numpy(dtype=float)
                    at = np.flatnonzero(
                        (days >= args.history_days)
                        & (days <= span_days - 60.0)
                        & (ratio >= p_cr_true.loc[g.index].to_numpy(dtype=float))
                    )
                    if not len(at):
                        continue
                    start = t.iloc[int(rng.choice(at))]
                faulty, truth = inject_fault(
                    g, str(well), sensor, kind, start, size=float(size), days=None
                )
                name = f"{kind}:{sensor}:{size}"
                changed = faulty[sensor].to_numpy(dtype=float) != g[sensor].to_numpy(dtype=float)
                if not changed.any():  # a choke fully open stays at 1: no fault to find
                    unchanged[name] += 1
                    continue
                found, _ = run_well(faulty)
                t0 = pd.Timestamp(truth["start"]).value
                matters = _matters(g, faulty, p_cr_true.loc[g.index], sensor, t0)
                on = [e for e in found if e.sensor == sensor and e.detected_ns >= t0]
                first = min(on, key=lambda e: e.detected_ns) if on else None
                delay = (first.detected_ns - t0) / _DAY_NS if first is not None else None
                in7 = delay is not None and delay <= 7.0
                kind_ok = in7 and any(
                    e.kind == kind and (e.detected_ns - t0) / _DAY_NS <= 7.0 for e in on
                )
                week = t0 + 7 * _DAY_NS
                others = sum(1 for e in found if e.sensor != sensor and t0 <= e.detected_ns <= week)
                results[name].append(
                    (
                        in7,
                        kind_ok,
                        delay if delay is not None and delay <= 60 else None,
                        others,
                        matters,
                    )
                )

    lines = [
        f"Command: `{' '.join(['python', 'benchmarks/bench_sensor_faults.py', *map(shlex.quote, sys.argv[1:] if argv is None else argv)])}`",
        "",
        f"{_fields(args)}: seeds {args.seeds}, {args.wells} wells, "
        f"{args.years:g} years: "
        f"{well_years:.1f} well-years, {rows} samples; detector cost "
        f"{1e6 * spent / max(rows, 1):.0f} us/sample of CPU at the simulator's 1-3 samples a "
        f"day, {cost_per_minute_samples():.0f} us/sample at one sample a minute.",
        "",
        "| kind | false faults | false/well-yr | by sensor |",
        "| --- | ---: | ---: | --- |",
    ]
    for kind in KINDS:
        where = ", ".join(f"{s} {n}" for (k, s), n in sorted(by_sensor.items()) if k == kind)
        lines.append(f"| {kind} | {false[kind]} | {false[kind] / well_years:.3f} | {where} |")
    total = sum(false.values())
    lines.append(f"| **all** | {total} | {total / well_years:.3f} | |")
    lines += [
        "",
        f"`p_down` steps not raised as offsets: {set_points['critical']} in critical flow "
        f"(the rate does not depend on `p_down`), {set_points['slight']} near it (no "
        "choke law above the floor lets the step move the rate beyond the noise of the "
        "meter's means), "
        f"{set_points['followed']} that the "
        "measured rate followed (a real change of the back pressure); `p_down` drift "
        f"alarms not raised: {set_points['drift']} in critical flow.",
        "",
        "| injected fault (kind:sensor:size) | wells | found 7d | right kind 7d | "
        "median delay d | other sensors | reading unchanged | rate depends on it: wells, "
        "found 7d |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, res in results.items():
        n = len(res)
        delays = [d for _, _, d, _, _ in res if d is not None]
        med = f"{np.median(delays):.1f}" if delays else "-"
        sub = [r for r in res if r[4]]
        matter = (
            f"{len(sub)}, {100 * sum(r[0] for r in sub) / len(sub):.0f} %"
            if name.split(":")[1] == "p_down" and sub
            else ("0" if name.split(":")[1] == "p_down" else "")
        )
        lines.append(
            f"| {name} | {n} | {100 * sum(r[0] for r in res) / max(n, 1):.0f} % | "
            f"{100 * sum(r[1] for r in res) / max(n, 1):.0f} % | {med} | "
            f"{sum(r[3] for r in res)} | {unchanged[name]} | {matter} |"
        )
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        with open(args.markdown, "w", encoding="utf-8") as out:
            out.write("<!-- written by benchmarks/bench_sensor_faults.py; do not edit -->\n\n")
            out.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
