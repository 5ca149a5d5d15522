"""The service's per-sample path, its parts timed alone: CPU time a sample, in one thread.

The engine benchmark (``bench_service.py --scenario engine``) gives the whole process's
CPU a sample with one sample a message (about 115-125 µs on a 2-core machine), and a
sampling profiler of it overstates the parts that call torch: every torch call lets go of
the GIL, and the time the thread then waits to take it back counts as its own. This
script times two parts with nothing else running, so their CPU time is theirs:

* receiving: ``Intake.deliver`` on single-sample sensor messages of ``--wells`` wells
  (the route, the quick reader :func:`service.inputs.quick_sensor` or, for what it is not
  sure of, JSON, pydantic's checks of a sample and the time checks; the per-well fair
  queue), as the receiver thread runs it;
* predicting: ``predict_many`` on one sample of each of ``--wells`` plain ``mm`` + ``ol``
  learners in one call, as a worker's batch does (the wells stacked into one model, the
  compiled rate).

What remains of the engine's figure is the worker's per-sample bookkeeping (admission,
features, the store's rows, publishing) and the plant that feeds it. Prints figures;
asserts nothing. Run::

    .venv/bin/python benchmarks/bench_sample_path.py [--wells 1000] [--messages 20000]
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
import time
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pandas as pd
import torch

from service.engine.fairqueue import FairQueue
from service.engine.intake import Intake
from service.engine.registry import Registry
from service.inputs import Counters
from service.testing import loopback_settings
from vfm_core.learning import DEFAULT_TRAIN
from vfm_core.learning.streaming import WellLearner, predict_many
from vfm_core.runtime import configure
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field


def receiving(wells: int, messages: int) -> float:
    """CPU µs a message of ``Intake.deliver`` (every message accepted and queued)."""
    folder = Path(tempfile.mkdtemp(prefix="vfm-bench-path-"))
    settings = loopback_settings(
        folder,
        queues={"worker_capacity": messages + 1, "well_capacity": messages + 1},
        inputs={"new_wells_per_s": 1e9, "new_wells_burst": wells + 1, "max_wells": wells + 1},
    )
    counters = Counters()
    queue = FairQueue(messages + 1, messages + 1)
    intake = Intake(settings, counters, Registry(settings, {}), [queue])
    start = datetime.now(UTC) - timedelta(hours=2)
    body = {"choke": 0.5, "p_up": 80.0, "p_down": 30.0, "t_up": 60.0, "eta_gas": 0.2}
    payloads = [
        (
            f"{settings.prefix}/W{i % wells:05d}/sensors",
            json.dumps(
                {
                    "time": (start + timedelta(seconds=i // wells)).isoformat(),
                    **body,
                    "eta_oil": 0.5,
                }
            ).encode(),
        )
        for i in range(messages)
    ]
    began = time.process_time()
    for key, payload in payloads:
        intake.deliver(key, payload, time.time_ns())
    spent = time.process_time() - began
    refused = counters.snapshot()["rejected"]
    if refused or queue.qsize() != messages:
        raise SystemExit(f"not every message was queued: {refused}")
    return spent / messages * 1e6


def predicting(wells: int, calls: int) -> float:
    """CPU µs a sample of ``predict_many`` with one sample of each of ``wells`` learners."""
    field = simulate_field(wells=1, years=0.5, seed=3).observations
    rows = field[field["q_total"].notna()].iloc[:60]
    base = WellLearner("W", "mm", "ol", train=replace(DEFAULT_TRAIN["mm"], max_iter=20))
    base.fit_history(
        torch.tensor(rows[list(INPUT_COLUMNS)].to_numpy()),
        torch.tensor(rows["q_total"].to_numpy()),
        torch.tensor(pd.DatetimeIndex(rows["time"]).as_unit("ns").asi8),
    )
    learners = []
    for i in range(wells):
        learner = copy.deepcopy(base)
        learner.well = f"W{i:05d}"
        learners.append(learner)
    xs = [rows[list(INPUT_COLUMNS)].iloc[-1].tolist()] * wells
    whens = [rows["time"].iloc[-1]] * wells
    for _ in range(5):  # warm: the kernel, the stacked model of the group
        predict_many(learners, xs, whens)
    began = time.process_time()
    for _ in range(calls):
        out = predict_many(learners, xs, whens)
    spent = time.process_time() - began
    if any(r is None or not isinstance(r, dict) or r["q_total"] is None for r in out):
        raise SystemExit("a learner gave no prediction")
    return spent / (calls * wells) * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--wells", type=int, default=1000)
    parser.add_argument("--messages", type=int, default=20_000)
    parser.add_argument("--group", type=int, default=100, help="wells per predict_many call")
    parser.add_argument("--calls", type=int, default=300)
    args = parser.parse_args()
    configure(1)
    print(
        f"receiving (Intake.deliver, {args.messages:,} single-sample messages of "
        f"{args.wells:,} wells): {receiving(args.wells, args.messages):.1f} µs CPU a message"
    )
    print(
        f"predicting (predict_many, {args.group} wells' samples a call, mm + ol): "
        f"{predicting(args.group, args.calls):.1f} µs CPU a sample"
    )


if __name__ == "__main__":
    main()
