"""Benchmark: false findings and detection delays of the pressure-rate witness.

Prints tables; asserts nothing. For each simulated field (``--seeds``, ``--wells``,
``--years``; seeds and sizes no choice of :mod:`vfm_core.pressure_witness` used) it runs
one :class:`vfm_core.pressure_witness.PressureWitness` per well over the clean rows (each
MPFM reading with its paired sample's choke, ``p_up`` and ``p_down``, in time order, as
the service would feed it) and counts the drifts raised per well-year (``false/well-yr``;
the witness's share of the detectors' budget is ``--share``, two of the 24 shares of 0.1
by default). Then, for each scenario (``--faults``: ``drift:sensor:size``, size per 30
days relative to the reading, as :func:`vfm_core.faults_sim.inject_fault` takes it), it
injects one drift per well at a random time (seeded; at least ``--history-days`` after the
well's first row and 60 days before its last) and reports:

- ``found 7d``: the share of wells whose drift the witness raised on the right sensor
  within 7 days of its start (``median delay d``: days to the first such finding, within
  60 days; ``found 60d``: within 60 days);
- ``other sensor``: findings on another sensor in the 60 days after the start;
- ``input tests 7d``: the same share for the input tests of
  :class:`vfm_core.sensor_faults.WellSensorFaults` on the same faulty rows (any kind, right
  sensor; the ``drift`` CUSUM on the input's own daily changes, mostly), their median
  delay (within 60 days), and ``either 7d`` for the witness and them together.

The cost (``us/day``) is the witness's CPU time over the clean rows per closed day.

Usage::

    nice -n 10 .venv/bin/python benchmarks/bench_pressure_witness.py --seeds 931,932,933 \\
        --wells 6 --years 3 [--markdown FILE]
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time

import numpy as np
import pandas as pd

from vfm_core.faults_sim import inject_fault
from vfm_core.pressure_witness import PressureWitness
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.sensor_faults import WellSensorFaults, mpfm_rates
from vfm_core.simulate import simulate_field

DEFAULT_FAULTS = (
    "drift:p_up:0.1",
    "drift:p_up:0.2",
    "drift:p_down:0.2",
    "drift:p_down:0.3",
    "drift:t_up:0.2",
)
#: two of the 24 shares of the detectors' 0.1 false faults per well-year (22 tests now,
#: and this witness's two: one per pressure it can name)
DEFAULT_SHARE = 2 * 0.1 / 24
_DAY_NS = 86_400 * 10**9


def run_witness(
    g: pd.DataFrame, share: float, window_days: int = 14
) -> tuple[list[tuple[int, object]], float, int]:
    """The findings of one well's rows (time order) as (time ns of the reading that
    raised it, finding), the witness's CPU time (s) and the days it closed."""
    w = PressureWitness(share, window_days=window_days)
    times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64").to_numpy()
    cols = g[["choke", "p_up", "p_down"]].to_numpy(dtype=float)
    rates = np.asarray(mpfm_rates(g), dtype=float)
    out = []
    started = time.process_time()
    for t, (u, p, pd_), q in zip(times.tolist(), cols.tolist(), rates.tolist(), strict=True):
        if q == q:  # not NaN: an MPFM reading
            f = w.rate(t, q, u, p, pd_)
            if f is not None:
                out.append((t, f))
    spent = time.process_time() - started
    return out, spent, len(w.days)


def run_inputs(g: pd.DataFrame) -> list:
    """The faults of the input tests (:class:`WellSensorFaults`) on one well's rows."""
    det = WellSensorFaults()
    times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64").tolist()
    values = g[list(INPUT_COLUMNS)].to_numpy(dtype=float).tolist()
    mpfm = mpfm_rates(g)
    seen: dict[int, object] = {}
    last = None
    for t, row, rate in zip(times, values, mpfm, strict=True):
        if t != last:
            for e in det.update(t, row):
                seen[id(e)] = e
            last = t
        if rate == rate:
            for e in det.measure(t, rate, row):
                seen[id(e)] = e
    return list(seen.values())


def _injected(
    g: pd.DataFrame, well: str, fault: tuple[str, str, str], start: pd.Timestamp, args
) -> tuple[float | None, int, float | None]:
    """One drift injected into one well's rows at ``start``: the days to the witness's first
    finding on the right sensor (None: none), its findings on another sensor within 60
    days, and the days to the input tests' first fault on that sensor (None: none, or
    --no-inputs)."""
    kind, sensor, size = fault
    faulty, truth = inject_fault(g, well, sensor, kind, start, size=float(size))
    t0 = pd.Timestamp(truth["start"]).value
    hits, _, _ = run_witness(faulty, args.share, args.window_days)
    raised = [(tt, f) for tt, f in hits if f.action == "raise" and tt >= t0]
    on = [(tt - t0) / _DAY_NS for tt, f in raised if f.sensor == sensor]
    other = sum(1 for tt, f in raised if f.sensor != sensor and tt - t0 <= 60 * _DAY_NS)
    inputs_delay = None
    if not args.no_inputs:
        ev = [(e.detected_ns - t0) / _DAY_NS for e in run_inputs(faulty) if e.sensor == sensor]
        inputs_delay = min((d for d in ev if d >= 0), default=None)
    return (min(on) if on else None), other, inputs_delay


def _detection_rows(results: dict[str, list[tuple]], no_inputs: bool) -> list[str]:
    """The detection table's rows, one per injected drift."""
    lines = []
    for name, res in results.items():
        n = max(len(res), 1)
        delays = [d for d, _, _ in res if d is not None and d <= 60]
        in7 = [d is not None and d <= 7 for d, _, _ in res]
        med = f"{np.median(delays):.1f}" if delays else "-"
        if no_inputs:
            inp = either = inp_med = "-"
        else:
            inp7 = [r[2] is not None and r[2] <= 7 for r in res]
            inp = f"{100 * sum(inp7) / n:.0f} %"
            either = f"{100 * sum(a or b for a, b in zip(in7, inp7, strict=True)) / n:.0f} %"
            inp_delays = [r[2] for r in res if r[2] is not None and r[2] <= 60]
            inp_med = f"{np.median(inp_delays):.1f}" if inp_delays else "-"
        lines.append(
            f"| {name} | {len(res)} | {100 * sum(in7) / n:.0f} % | "
            f"{100 * len(delays) / n:.0f} % | {med} | {sum(r[1] for r in res)} | "
            f"{inp} | {inp_med} | {either} |"
        )
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="931,932,933")
    ap.add_argument("--wells", type=int, default=6)
    ap.add_argument("--years", type=float, default=3.0)
    ap.add_argument("--faults", default=",".join(DEFAULT_FAULTS), help="drift:sensor:size,...")
    ap.add_argument("--share", type=float, default=DEFAULT_SHARE)
    ap.add_argument("--window-days", type=int, default=14, help="the longest ramp tested")
    ap.add_argument("--history-days", type=float, default=180.0)
    ap.add_argument(
        "--sample-every-days",
        type=float,
        help="every well's rows on one grid this many days apart (denser MPFM readings)",
    )
    ap.add_argument("--no-inputs", action="store_true", help="skip the input tests' columns")
    ap.add_argument("--markdown", help="also write the tables as Markdown to this file")
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    scenarios = [s.split(":") for s in args.faults.split(",") if s]
    wall = time.perf_counter()

    well_years, false_n, days, spent = 0.0, [], 0, 0.0
    false_by: dict[str, int] = {}
    results: dict[str, list[tuple]] = {":".join(s): [] for s in scenarios}
    for seed in seeds:
        frame = simulate_field(
            wells=args.wells, years=args.years, seed=seed, sample_every_days=args.sample_every_days
        ).observations
        rng = np.random.default_rng(seed + 10_000)  # the fault times of bench_sensor_faults
        for well, g in frame.groupby("well", sort=True):
            g = g.sort_values("time", kind="stable")
            t = pd.to_datetime(g["time"], utc=True)
            span_days = (t.iloc[-1] - t.iloc[0]).total_seconds() / 86_400
            well_years += span_days / 365.25
            found, dt, n_days = run_witness(g, args.share, args.window_days)
            spent += dt
            days += n_days
            false_n.append(len([f for _, f in found if f.action == "raise"]))
            for _, f in found:
                if f.action == "raise":
                    false_by[f.sensor] = false_by.get(f.sensor, 0) + 1
            if span_days < args.history_days + 90:
                continue
            for kind, sensor, size in scenarios:
                offset = rng.uniform(args.history_days, span_days - 60.0)
                start = t.iloc[0] + pd.Timedelta(days=offset)
                name = f"{kind}:{sensor}:{size}"
                results[name].append(_injected(g, str(well), (kind, sensor, size), start, args))

    cmd = ["python", "benchmarks/bench_pressure_witness.py"]
    cmd += list(map(shlex.quote, sys.argv[1:] if argv is None else argv))
    total = sum(false_n)
    lines = [
        f"Command: `{' '.join(cmd)}`",
        "",
        f"Clean fields: seeds {args.seeds}, {args.wells} wells, {args.years:g} years: "
        f"{well_years:.1f} well-years, {days} closed days; share {args.share:.4f} false "
        f"drifts per well-year; witness cost {1e6 * spent / max(days, 1):.0f} us of CPU a "
        f"closed day; {time.perf_counter() - wall:.0f} s wall in all.",
        "",
        "| clean fields | false drifts | false/well-yr | by sensor | wells with any |",
        "| --- | ---: | ---: | --- | ---: |",
        f"| pressure-rate witness | {total} | {total / max(well_years, 1e-9):.4f} | "
        + ", ".join(f"{k} {v}" for k, v in sorted(false_by.items()))
        + f" | {sum(1 for n in false_n if n)} of {len(false_n)} |",
        "",
        "| injected drift (kind:sensor:size per 30 d) | wells | found 7d | found 60d | "
        "median delay d | other sensor | input tests 7d | input tests median delay d | "
        "either 7d |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    lines += _detection_rows(results, args.no_inputs)
    text = "\n".join(lines)
    print(text)
    if args.markdown:
        with open(args.markdown, "w", encoding="utf-8") as out:
            out.write("<!-- written by benchmarks/bench_pressure_witness.py; do not edit -->\n\n")
            out.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
