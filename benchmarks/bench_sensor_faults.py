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
- ``other sensors``: faults raised on other sensors in the 7 days after its start.

The cost per sample (``us/sample``) is the detector's own CPU time over all clean rows
(``time.process_time``; the service's whole per-sample path is about 115-125 us of CPU,
``bench_service.py --scenario engine``).

Usage::

    nice -n 10 .venv/bin/python benchmarks/bench_sensor_faults.py [--seeds 901,902,903]
        [--wells 8] [--years 4] [--markdown docs/benchmarks/generated/sensor-faults.md]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from collections import Counter

import numpy as np
import pandas as pd

from vfm_core.faults_sim import inject_fault
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.sensor_faults import KINDS, WellSensorFaults
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
_DAY_NS = 86_400 * 10**9


def run_well(g: pd.DataFrame) -> tuple[list, float]:
    """Every fault event of one well's rows (time order) and the detector's time (s)."""
    det = WellSensorFaults()
    times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64").tolist()
    values = g[list(INPUT_COLUMNS)].to_numpy(dtype=float).tolist()
    seen: dict[int, object] = {}
    started = time.process_time()  # CPU time: other processes on the machine do not count
    for t, row in zip(times, values, strict=True):
        for e in det.update(t, row):
            seen[id(e)] = e
    return list(seen.values()), time.process_time() - started


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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="901,902,903")
    ap.add_argument("--wells", type=int, default=8)
    ap.add_argument("--years", type=float, default=4.0)
    ap.add_argument("--faults", default=",".join(DEFAULT_FAULTS))
    ap.add_argument("--history-days", type=float, default=180.0)
    ap.add_argument("--markdown", help="also write the tables as Markdown to this file")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    scenarios = [s.split(":") for s in args.faults.split(",") if s]

    well_years = 0.0
    false: Counter[str] = Counter()
    by_sensor: Counter[tuple[str, str]] = Counter()
    rows = 0
    spent = 0.0
    results: dict[str, list[tuple[bool, bool, float | None, int]]] = {
        ":".join(s): [] for s in scenarios
    }
    for seed in seeds:
        frame = simulate_field(wells=args.wells, years=args.years, seed=seed).observations
        rng = np.random.default_rng(seed + 10_000)
        for well, g in frame.groupby("well", sort=True):
            g = g.sort_values("time", kind="stable")
            t = pd.to_datetime(g["time"], utc=True)
            span_days = (t.iloc[-1] - t.iloc[0]).total_seconds() / 86_400
            well_years += span_days / 365.25
            events, dt = run_well(g)
            rows += len(g)
            spent += dt
            false.update(e.kind for e in events)
            by_sensor.update((e.kind, e.sensor) for e in events)
            if span_days < args.history_days + 90:
                continue
            for kind, sensor, size in scenarios:
                offset = rng.uniform(args.history_days, span_days - 60.0)
                start = t.iloc[0] + pd.Timedelta(days=offset)
                faulty, truth = inject_fault(
                    g, str(well), sensor, kind, start, size=float(size), days=None
                )
                found, _ = run_well(faulty)
                t0 = pd.Timestamp(truth["start"]).value
                on = [e for e in found if e.sensor == sensor and e.detected_ns >= t0]
                first = min(on, key=lambda e: e.detected_ns) if on else None
                delay = (first.detected_ns - t0) / _DAY_NS if first is not None else None
                in7 = delay is not None and delay <= 7.0
                kind_ok = in7 and any(
                    e.kind == kind and (e.detected_ns - t0) / _DAY_NS <= 7.0 for e in on
                )
                week = t0 + 7 * _DAY_NS
                others = sum(1 for e in found if e.sensor != sensor and t0 <= e.detected_ns <= week)
                results[f"{kind}:{sensor}:{size}"].append(
                    (in7, kind_ok, delay if delay is not None and delay <= 60 else None, others)
                )

    lines = [
        f"Command: `{' '.join(['python', 'benchmarks/bench_sensor_faults.py', *map(shlex.quote, sys.argv[1:] if argv is None else argv)])}`",
        "",
        f"Clean fields: seeds {args.seeds}, {args.wells} wells, {args.years:g} years: "
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
        "| injected fault (kind:sensor:size) | wells | found 7d | right kind 7d | "
        "median delay d | other sensors |",
        "| --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for name, res in results.items():
        n = len(res)
        delays = [d for _, _, d, _ in res if d is not None]
        med = f"{np.median(delays):.1f}" if delays else "-"
        lines.append(
            f"| {name} | {n} | {100 * sum(r[0] for r in res) / max(n, 1):.0f} % | "
            f"{100 * sum(r[1] for r in res) / max(n, 1):.0f} % | {med} | "
            f"{sum(r[3] for r in res)} |"
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
