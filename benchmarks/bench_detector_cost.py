"""Benchmark: the per-sample cost of the instrument-fault detectors against a prediction's.

Issue 39 sets a goal: detecting instrument faults (:mod:`vfm_core.sensor_faults`) should
cost under 20 % of a prediction. This script measures both in one run, side by side, in
CPU time (``time.process_time``: what other processes on a shared machine do is not
counted, but a busy machine still slows both; read the ratios, not the microseconds).
Prints a table; asserts nothing.

* The detector: :meth:`vfm_core.sensor_faults.WellSensorFaults.update`, one per well, over
  every row of simulated fields in time order, and :meth:`~WellSensorFaults.measure` with
  each row's MPFM rate (the choke-rate witness, :mod:`vfm_core.rate_witness`) (:func:`vfm_core.simulate.simulate_field`,
  clean, as ``bench_sensor_faults.py`` runs it), at the simulator's rate (1-3 samples a
  day: ``--seeds``, ``--wells``, ``--years``; there nearly every sample closes a day and
  runs the daily drift and offset tests of five inputs) and at one sample a minute
  (``--minute-wells`` wells for ``--minute-years``, the simulator's synchronised grid;
  there the per-sample tests dominate).
* A prediction: one well's :class:`vfm_core.learning.streaming.WellLearner` of each of
  ``--models`` with each of ``--methods`` (fitted on its first measurements), asked
  for sample after sample in time order as the service's worker asks for a single-sample
  message (:func:`vfm_core.learning.streaming.predict_many` with that one sample,
  ``service.engine.learning.Learning.predict_many``), and per row of blocks of
  ``--block`` rows as it asks for a sensor block (:meth:`WellLearner.predict_block`).
  One torch thread (the service's default).

Each figure is the best of ``--repeat`` rounds (the rounds interleave the parts, so a
busy spell of the machine hits them alike). The ratio is the detector's cost over the
prediction's, per sample.

Usage::

    nice -n 10 .venv/bin/python benchmarks/bench_detector_cost.py [--seeds 901,902]
        [--wells 8] [--years 4] [--minute-wells 3] [--minute-years 0.1]
        [--models mm,ham,lr] [--methods ol,bayes] [--samples 300] [--block 200]
        [--repeat 3] [--markdown docs/benchmarks/generated/detector-cost.md]
"""

from __future__ import annotations

import argparse
import copy
import shlex
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from vfm_core.learning import DEFAULT_TRAIN
from vfm_core.learning.streaming import WellLearner, predict_many
from vfm_core.runtime import configure
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.sensor_faults import WellSensorFaults, mpfm_rates
from vfm_core.simulate import simulate_field

#: a stream of one well: times (epoch ns), rows of the six inputs, and each row's MPFM rate
#: (Sm3/h; NaN on rows without one)
Stream = tuple[list[int], list[list[float]], list[float]]


def streams_of(frame: pd.DataFrame) -> list[Stream]:
    """Every well's rows of a field in time order, as the detector takes them."""
    out = []
    for _, g in frame.groupby("well", sort=True):
        g = g.sort_values("time", kind="stable")
        times = pd.to_datetime(g["time"], utc=True).dt.as_unit("ns").astype("int64")
        rows = g[list(INPUT_COLUMNS)].to_numpy(dtype=float).tolist()
        out.append((times.tolist(), rows, mpfm_rates(g)))
    return out


def detector_us(streams: list[Stream]) -> float:
    """CPU us a sample of one fresh detector per well over ``streams``."""
    rows = 0
    spent = 0.0
    for times, values, rates in streams:
        det = WellSensorFaults()
        last = None
        started = time.process_time()
        for t, row, q in zip(times, values, rates, strict=True):
            if t != last:  # a second row at one time carries only its measurement
                det.update(t, row)
                last = t
            if q == q:  # an MPFM rate: the choke-rate witness (not NaN)
                det.measure(t, q, row)
        spent += time.process_time() - started
        rows += len(times)
    return 1e6 * spent / max(rows, 1)


@dataclass
class Predictor:
    """A fitted learner of one well and the sensor rows after its history."""

    model: str
    method: str
    learner: WellLearner
    x: np.ndarray  # [N, 6] inputs in file units
    t: np.ndarray  # [N] epoch ns


def make_predictor(model: str, method: str, frame: pd.DataFrame, history: int) -> Predictor:
    """A ``model`` + ``method`` learner fitted on the first ``history`` measurements of the
    frame's first well (a short fit: what a prediction costs does not depend on it)."""
    well = sorted(frame["well"].unique())[0]
    g = frame[frame["well"] == well].sort_values("time", kind="stable")
    meas = g[g["q_total"].notna()].iloc[:history]
    ns = pd.DatetimeIndex(pd.to_datetime(g["time"], utc=True)).as_unit("ns").asi8
    learner = WellLearner(well, model, method, train=replace(DEFAULT_TRAIN[model], max_iter=20))
    learner.fit_history(
        torch.tensor(meas[list(INPUT_COLUMNS)].to_numpy(dtype=float)),
        torch.tensor(meas["q_total"].to_numpy(dtype=float)),
        torch.tensor(pd.DatetimeIndex(pd.to_datetime(meas["time"], utc=True)).as_unit("ns").asi8),
    )
    after = ns > int(pd.Timestamp(meas["time"].iloc[-1]).value)
    x = g[list(INPUT_COLUMNS)].to_numpy(dtype=float)[after]
    return Predictor(model, method, learner, x, ns[after])


def single_us(p: Predictor, samples: int) -> float:
    """CPU us a sample of ``predict_many`` with one sample, sample after sample (a copy of
    the learner: its features move on with the samples)."""
    learner = copy.deepcopy(p.learner)
    n = min(samples, len(p.t))
    rows, times = p.x[:n].tolist(), p.t[:n].tolist()
    for i in range(min(5, n)):  # warm: the compiled kernels, the first call's caches
        predict_many([learner], [rows[i]], [times[i]])
    started = time.process_time()
    for i in range(5, n):
        out = predict_many([learner], [rows[i]], [times[i]])
    spent = time.process_time() - started
    if n <= 5 or not isinstance(out[0], dict) or out[0]["q_total"] is None:
        raise SystemExit(f"{p.model} + {p.method} gave no prediction.")
    return 1e6 * spent / (n - 5)


def block_us(p: Predictor, block: int, samples: int) -> float | None:
    """CPU us a row of ``predict_block`` over blocks of ``block`` rows (None for a learner
    that takes no blocks: a model that may change while predicting)."""
    learner = copy.deepcopy(p.learner)
    n = min(len(p.t), max(samples, 2 * block))
    if n < 2 * block:
        return None
    try:
        learner.predict_block(p.x[:block], p.t[:block])  # warm
    except ValueError:
        return None
    started = time.process_time()
    rows = 0
    for start in range(block, n - block + 1, block):
        learner.predict_block(p.x[start : start + block], p.t[start : start + block])
        rows += block
    return 1e6 * (time.process_time() - started) / rows


def measure(args: argparse.Namespace) -> dict[str, float | None]:
    """Every figure of the table, the best of ``--repeat`` interleaved rounds."""
    seeds = [int(s) for s in args.seeds.split(",") if s]
    sim = [s for seed in seeds for s in streams_of(_field(args, seed))]
    minute = streams_of(
        simulate_field(
            wells=args.minute_wells,
            years=args.minute_years,
            seed=seeds[0],
            sample_every_days=1.0 / 1440.0,
        ).observations
    )
    frame = simulate_field(wells=1, years=2.0, seed=seeds[0] + 1).observations
    predictors = [
        make_predictor(m, k, frame, args.history)
        for m in args.models.split(",")
        for k in args.methods.split(",")
    ]
    best: dict[str, float | None] = {}

    def keep(key: str, value: float | None) -> None:
        if value is not None:
            old = best.get(key)
            best[key] = value if old is None else min(old, value)
        else:
            best.setdefault(key, None)

    for _ in range(args.repeat):
        keep("detector sim", detector_us(sim))
        keep("detector minute", detector_us(minute))
        for p in predictors:
            keep(f"{p.model}+{p.method} single", single_us(p, args.samples))
            keep(f"{p.model}+{p.method} block", block_us(p, args.block, args.samples))
    best["rows sim"] = float(sum(len(t) for t, _, _ in sim))
    best["rows minute"] = float(sum(len(t) for t, _, _ in minute))
    return best


def _field(args: argparse.Namespace, seed: int) -> pd.DataFrame:
    return simulate_field(wells=args.wells, years=args.years, seed=seed).observations


def table(args: argparse.Namespace, f: dict[str, float | None], argv: list[str]) -> str:
    """The Markdown table: a line per model and method, the detector's cost at both rates
    against its single-sample and block predictions."""
    sim, minute = f["detector sim"], f["detector minute"]
    assert sim is not None and minute is not None
    command = " ".join(["python", "benchmarks/bench_detector_cost.py", *map(shlex.quote, argv)])
    lines = [
        f"Command: `{command}`",
        "",
        f"Detector (`WellSensorFaults.update` and `measure`), CPU a sample: **{sim:.1f} us** at the "
        f"simulator's 1-3 samples a day (seeds {args.seeds}, {args.wells} wells, "
        f"{args.years:g} years, {f['rows sim']:.0f} samples), **{minute:.1f} us** at one "
        f"sample a minute ({args.minute_wells} wells, {args.minute_years:g} years, "
        f"{f['rows minute']:.0f} samples). Prediction: one well's learner, CPU a sample "
        f"(single: `predict_many` with one sample, as a single-sample message; block: a "
        f"row of `predict_block` over {args.block} rows, as the service answers a sensor "
        f"block; '-' where the learner takes no blocks). Best of {args.repeat} rounds; the "
        "goal is a ratio under 20 %.",
        "",
        "| model + method | prediction us, single | detector / single, 1-3 a day | "
        "detector / single, 1 a minute | prediction us, block row | "
        "detector / block row, 1-3 a day | detector / block row, 1 a minute |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for m in args.models.split(","):
        for k in args.methods.split(","):
            one, row = f[f"{m}+{k} single"], f[f"{m}+{k} block"]
            assert one is not None
            cells = [f"{one:.1f}", f"{100 * sim / one:.0f} %", f"{100 * minute / one:.0f} %"]
            if row is None:
                cells += ["-", "-", "-"]
            else:
                cells += [f"{row:.1f}", f"{100 * sim / row:.0f} %", f"{100 * minute / row:.0f} %"]
            lines.append(f"| {m} + {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default="901,902", help="simulated fields (detector)")
    ap.add_argument("--wells", type=int, default=8)
    ap.add_argument("--years", type=float, default=4.0)
    ap.add_argument("--minute-wells", type=int, default=3)
    ap.add_argument("--minute-years", type=float, default=0.1, help="at least 1/12")
    ap.add_argument("--models", default="mm,ham,lr")
    ap.add_argument("--methods", default="ol,bayes")
    ap.add_argument("--history", type=int, default=100, help="measurements in the fit")
    ap.add_argument("--samples", type=int, default=300, help="single-sample predictions")
    ap.add_argument("--block", type=int, default=200, help="rows a prediction block")
    ap.add_argument("--repeat", type=int, default=3, help="rounds (best of)")
    ap.add_argument("--markdown", help="also write the table as Markdown to this file")
    args = ap.parse_args(argv)
    configure(1)
    figures = measure(args)
    text = table(args, figures, sys.argv[1:] if argv is None else argv)
    print(text)
    if args.markdown:
        path = Path(args.markdown)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(
            "<!-- written by benchmarks/bench_detector_cost.py; do not edit -->\n\n" + text + "\n"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
