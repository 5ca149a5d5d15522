"""``mtl`` live against ``vfm evaluate``: the service's MAPE beside the study's, per method.

A simulated field is written to a file; the service (in this process, store in a temporary
folder, default model settings) fits ``mtl`` on the rows before the split and is fed the
rest; its predictions are scored beside :func:`vfm_core.jobs.study.run_prequential`'s on
the same file. Two ways to feed it:

- ``zenoh`` (default): ``vfm replay --max`` over a loopback Zenoh session, as fast as the
  service takes it (the wells' messages may then be handled out of time order across wells,
  which moves a late measurement into the next day's round);
- ``paced``: the in-memory transport, each day's messages handled before the next day's
  (a service that keeps up with a live field): the study's numbers to float noise.

    python benchmarks/bench_mtl_live.py [--methods ol,pbl:14d] [--feed zenoh,paced]
        [--wells 3 --years 1 --seed 3 --split 2016-10-01]
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from replay.client import FieldClient
from replay.replayer import replay_frame
from service.app import Service, running
from service.testing import loopback_settings, wait_until
from service.transport import MemoryTransport
from vfm_core.jobs.study import mape, run_prequential
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field


def _paced(settings, frame: pd.DataFrame, split: str) -> dict[tuple[str, int], float]:
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service(str(frame["well"].iloc[0]))
            live = frame[frame["time"] >= pd.Timestamp(split, tz="UTC")]
            samples = measurements = 0
            for _, day in live.groupby(live["time"].dt.floor("D"), sort=True):
                sent = client.stream(day)
                samples += len(sent.samples)
                measurements += sent.measurements

                def handled(s: int = samples, m: int = measurements) -> bool:
                    snap = service.counters.snapshot()
                    return (
                        snap["accepted"].get("sensors", 0) >= s
                        and snap["events"].get("learned", 0) >= m
                    )

                wait_until(handled, 120, "the day's messages to be handled")
            time.sleep(0.5)  # the last commit's predictions
            return dict(client.predictions)
    finally:
        service.stop()


def _zenoh(settings, frame: pd.DataFrame, split: str) -> dict[tuple[str, int], float]:
    with running(settings) as svc:
        result = replay_frame(
            frame, connect=svc.locators, start=split, progress=False, idle_timeout=5.0
        )
    scored = result.scored
    return {
        (w, pd.Timestamp(t).value): float(q)
        for w, t, q in zip(scored["well"], scored["time"], scored["predicted"], strict=True)
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default="ol,pbl:14d")
    parser.add_argument("--feed", default="zenoh,paced")
    parser.add_argument("--wells", type=int, default=3)
    parser.add_argument("--years", type=float, default=1.0)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--split", default="2016-10-01")
    args = parser.parse_args()
    frame = validate_frame(
        simulate_field(wells=args.wells, years=args.years, seed=args.seed).observations
    ).frame
    print(f"field: {args.wells} wells, {args.years:g} years, seed {args.seed}, split {args.split}")
    print("| method | feed | MAPE service % | MAPE vfm evaluate % | max rel. diff | n | s |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "field.parquet"
        frame.to_parquet(data)
        for method in args.methods.split(","):
            study = run_prequential(frame, "mtl", method, split=args.split).predictions
            keys = [(w, t.value) for w, t in zip(study["well"], study["time"], strict=True)]
            for feed in args.feed.split(","):
                folder = Path(tmp) / f"{method.replace(':', '_')}-{feed}"
                folder.mkdir()
                settings = loopback_settings(
                    folder,
                    model={
                        "name": "mtl",
                        "method": method,
                        "history": str(data),
                        "history_until": args.split,
                    },
                )
                started = time.perf_counter()
                got = (_paced if feed == "paced" else _zenoh)(settings, frame, args.split)
                took = time.perf_counter() - started
                served = np.array([got.get(k, np.nan) for k in keys], dtype=float)
                offline = study["predicted"].to_numpy()
                diff = np.nanmax(np.abs(served - offline) / np.abs(offline))
                print(
                    f"| {method} | {feed} | {mape(served, study['measured']):.4f} | "
                    f"{mape(offline, study['measured']):.4f} | {diff:.1e} | "
                    f"{int(np.isfinite(served).sum())}/{len(keys)} | {took:.0f} |"
                )


if __name__ == "__main__":
    main()
