"""Benchmark of scale-out: one, two and three `vfm serve` instances behind one Zenoh router.

Per run, a router (a Python Zenoh session in router mode, in its own process: zenohd is
not installable here) and N `vfm serve` instances as its clients, each owning the wells
whose id ends in some digits (``zenoh.wells = ["*0", "*3", ...]``); this process is the
plant, also a client of the router. The same field (copies of ten simulated wells,
``mm`` + ``ol``, an MPFM reading every few minutes per well that the instances learn
from) is sent in every run:

* every well at 1 Hz (spread over the second) for ``--seconds``: latency from putting a
  sample to receiving its prediction, p50 / p99 / max, and loss;
* a burst of ``--burst`` samples, every well in turn, as fast as Zenoh's BLOCK congestion
  control lets them: the rate sustained without loss (all samples answered / time).

Everything (router, plant, instances) shares this machine's cores, which caps what more
instances can add: on a 2-core machine the third instance has no core of its own. Prints
figures; asserts nothing. Usage::

    .venv/bin/python benchmarks/bench_scaleout.py [--instances 1,2,3] [--wells 300]
        [--seconds 20] [--burst 10000]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pandas as pd

from replay.client import FieldClient, ZenohBus, sample_of
from service.testing import ServeProcess
from vfm_core.data import target_mask
from vfm_core.messages import Measurement
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

ROUTER = """
import json, sys, zenoh
cfg = zenoh.Config()
cfg.insert_json5("mode", '"router"')
cfg.insert_json5("scouting/multicast/enabled", "false")
cfg.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
with zenoh.open(cfg):
    print("router ready", flush=True)
    sys.stdin.read()  # until the benchmark closes stdin
"""


def _cpu_s(pid: int) -> float:
    """CPU time (user + system) of a process so far, s (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def make_history(
    folder: Path, wells: int, rows_per_well: int
) -> tuple[Path, dict[str, np.ndarray]]:
    """A history of ``wells`` wells (copies of ten simulated ones) and each well's live rows."""
    base = validate_frame(simulate_field(wells=10, years=1, seed=1).observations).frame
    base = base[target_mask(base, "all")]
    parts, inputs = [], {}
    for j in range(wells):
        name = f"B{j:04d}"
        own = base[base["well"] == f"W{j % 10 + 1:02d}"]
        hist = own.iloc[:rows_per_well].copy()
        hist["well"] = name
        parts.append(hist)
        inputs[name] = own.iloc[rows_per_well:][
            ["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil", "q_total"]
        ].to_numpy()
    path = folder / "history.parquet"
    pd.concat(parts, ignore_index=True).to_parquet(path)
    return path, inputs


def patterns(instances: int) -> list[list[str]]:
    """The well patterns of each instance: by the last digit of the id (disjoint)."""
    return [[f"*{d}" for d in range(10) if d % instances == i] for i in range(instances)]


def run(
    instances: int, wells: int, seconds: float, burst: int, measure_every_s: float, rows: int
) -> dict[str, float]:
    with tempfile.TemporaryDirectory(prefix="vfm-scaleout-") as tmp:
        folder = Path(tmp)
        history, inputs = make_history(folder, wells, rows)
        endpoint = f"tcp/127.0.0.1:{_free_port()}"
        router = subprocess.Popen(
            [sys.executable, "-c", ROUTER, endpoint],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
        serves: list[ServeProcess] = []
        plant = None
        try:
            assert router.stdout is not None and "ready" in router.stdout.readline()
            for i, own in enumerate(patterns(instances)):
                cfg = folder / f"vfm{i}.toml"
                cfg.write_text(f"""
[model]
name = "mm"
method = "ol"
history = "{history}"
[zenoh]
mode = "client"
connect = ["{endpoint}"]
listen = []
wells = {json.dumps(own)}
[http]
port = 0
[store]
path = "{folder / f"store{i}.sqlite"}"
synchronous = "full"
""")
                serves.append(ServeProcess(cfg, folder / f"serve{i}.log"))
            started = time.perf_counter()
            waits = [_start_async(s) for s in serves]  # together: their fits overlap
            for wait in waits:
                wait()
            startup = time.perf_counter() - started
            bus = ZenohBus.connect(
                [endpoint], mode="client", block_wait_before_close_ms=600_000, capacity=1 << 17
            )
            plant = FieldClient(bus, "vfm", track_latency=True)
            names = sorted(inputs)
            for name in names:
                for key in (f"vfm/{name}/sensors", f"vfm/{name}/measurements/mpfm"):
                    if not bus.matching(key, 60.0):
                        raise RuntimeError(f"No instance subscribes to {key}.")
            phase = np.random.default_rng(0).uniform(0, measure_every_s, wells)

            def send(name: str, when: datetime, row: np.ndarray, measure: bool) -> None:
                plant.send_sample(name, sample_of(when, row[:6]))
                if measure:
                    plant.send_measurement(
                        name, "mpfm", Measurement(time=when, q_total=float(row[6]))
                    )

            # -- every well at 1 Hz ------------------------------------------------------------
            t0_wall = datetime.now(UTC).replace(microsecond=0) - timedelta(hours=1)
            t0 = time.perf_counter()
            sent = 0
            for second in range(int(seconds)):
                for j, name in enumerate(names):
                    wait = t0 + second + j / wells - time.perf_counter()
                    if wait > 0:
                        time.sleep(wait)
                    row = inputs[name][second % len(inputs[name])]
                    measure = (second + phase[j]) % measure_every_s < 1.0
                    send(name, t0_wall + timedelta(seconds=second), row, measure)
                    sent += 1
            deadline = time.monotonic() + 120
            while plant.count < sent and time.monotonic() < deadline:
                time.sleep(0.05)
            lat = np.array(plant.latency_s) * 1000.0
            out: dict[str, float] = {
                "instances": instances,
                "startup_s": startup,
                "steady_sent": sent,
                "steady_lost": sent - plant.count,
                "steady_p50_ms": float(np.percentile(lat, 50)),
                "steady_p99_ms": float(np.percentile(lat, 99)),
                "steady_max_ms": float(lat.max()),
            }
            # -- burst ---------------------------------------------------------------------------
            plant.latency_s.clear()
            base = plant.count
            pids = {"router": router.pid, "plant": os.getpid()}
            pids.update({f"instance{i}": s.proc.pid for i, s in enumerate(serves) if s.proc})
            cpu0 = {k: _cpu_s(pid) for k, pid in pids.items()}
            t1_wall = t0_wall + timedelta(seconds=int(seconds) + 1)
            t1 = time.perf_counter()
            n = 0
            for step in range(max(1, burst // wells)):
                for j, name in enumerate(names):
                    row = inputs[name][step % len(inputs[name])]
                    measure = (step + int(phase[j])) % int(measure_every_s) == 0
                    send(name, t1_wall + timedelta(seconds=step), row, measure)
                    n += 1
            deadline = time.monotonic() + 300
            while plant.count - base < n and time.monotonic() < deadline:
                time.sleep(0.02)
            elapsed = time.perf_counter() - t1
            cpu = {k: (_cpu_s(pid) - cpu0[k]) / elapsed for k, pid in pids.items()}
            got = plant.count - base
            lat = np.array(plant.latency_s) * 1000.0
            out.update(
                burst_sent=n,
                burst_lost=n - got,
                burst_rate=got / elapsed,
                burst_p99_ms=float(np.percentile(lat, 99)) if len(lat) else float("nan"),
                burst_cores=sum(cpu.values()),
                burst_instance_cores=sum(v for k, v in cpu.items() if k.startswith("instance")),
                burst_plant_cores=cpu["plant"],
                burst_router_cores=cpu["router"],
                load=os.getloadavg()[0],
            )
            return out
        finally:
            if plant is not None:
                plant.close()
                plant.bus.close()
            for s in serves:
                s.stop()
            if router.stdin is not None:
                router.stdin.close()
            router.wait(30)


def _start_async(serve: ServeProcess) -> Callable[[], None]:
    """Start ``serve`` on a thread; the returned function waits for it to be ready."""
    errors: list[BaseException] = []

    def target() -> None:
        try:
            serve.start(timeout=1800)
        except BaseException as exc:  # re-raised by the waiter
            errors.append(exc)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()

    def wait() -> None:
        thread.join()
        if errors:
            raise errors[0]

    return wait


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--instances", default="1,2,3", help="comma-separated instance counts")
    parser.add_argument("--wells", type=int, default=300)
    parser.add_argument("--seconds", type=float, default=20.0, help="length of the 1 Hz run")
    parser.add_argument("--burst", type=int, default=10_000, help="samples in the burst")
    parser.add_argument("--measure-every", type=float, default=180.0)
    parser.add_argument("--history-rows", type=int, default=60)
    args = parser.parse_args()
    cores = os.cpu_count() or 1
    print(
        f"vfm scale-out benchmark: {args.wells} wells, mm + ol, store synchronous=full, a router "
        f"process, the plant and N instances on one machine with {cores} cores (they share them: "
        f"{cores} cores cap what more instances add); {args.seconds:g} s at 1 Hz per well, then a "
        f"burst of {args.burst:,} samples."
    )
    rows = []
    for k in [int(x) for x in args.instances.split(",")]:
        r = run(k, args.wells, args.seconds, args.burst, args.measure_every, args.history_rows)
        rows.append(r)
        print(
            f"  {k} instance(s): start-up {r['startup_s']:.1f} s; 1 Hz: lost {r['steady_lost']:.0f} "
            f"of {r['steady_sent']:,.0f}, p50 {r['steady_p50_ms']:.1f} ms, p99 "
            f"{r['steady_p99_ms']:.1f} ms, max {r['steady_max_ms']:.1f} ms; burst: "
            f"{r['burst_rate']:,.0f} samples/s sustained, lost {r['burst_lost']:.0f} of "
            f"{r['burst_sent']:,.0f}, p99 {r['burst_p99_ms']:.0f} ms; cores busy during the burst: "
            f"instances {r['burst_instance_cores']:.2f}, plant {r['burst_plant_cores']:.2f}, "
            f"router {r['burst_router_cores']:.2f} (load average {r['load']:.1f})",
            flush=True,
        )
    print(
        "\n| instances | 1 Hz lost | p50 | p99 | max | burst samples/s (lost) | cores busy "
        "(instances + plant + router) |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(
            f"| {r['instances']:.0f} | {r['steady_lost']:.0f} of {r['steady_sent']:,.0f} | "
            f"{r['steady_p50_ms']:.1f} ms | {r['steady_p99_ms']:.1f} ms | "
            f"{r['steady_max_ms']:.0f} ms | {r['burst_rate']:,.0f} ({r['burst_lost']:.0f}) | "
            f"{r['burst_cores']:.2f} |"
        )


if __name__ == "__main__":
    main()
