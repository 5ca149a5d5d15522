"""Benchmark of the streaming service: latency and sustained rate, two processes over loopback.

``vfm serve`` runs in a subprocess (model ``mm``, method ``ol``, store in a temp folder);
this process is the plant: every well sends one sensor sample a second (spread evenly
over the second), and a measurement (MPFM reading, paired with that sample) every few
minutes per well, which the service learns from online. Figures per field size:

* latency from putting a sample to receiving its prediction, p50 / p99 / max (ms);
* the sustained rate: samples sent and predictions received per second, and how many
  were lost (should be zero);
* a burst: the same wells' samples sent as fast as Zenoh's BLOCK congestion control lets
  them, to find the rate the service sustains without loss; ``--block 1,40`` runs one burst
  per message size (1: one sample a message; more: sensor blocks of that many rows). A
  burst's messages are made before its clock starts: the plant's JSON is not measured.

Fairness (``--scenario flood``): two wells with a history; a good well sends a sample every
50 ms from this process while, from a second process with its own Zenoh session, another
well floods as fast as Zenoh's BLOCK congestion control lets it (several thousand samples
a second) -- or, with ``--flood-kind names``, a stream of new well names, or with
``--flood-kind blocks``, sensor blocks of that well (``--flood-block`` rows, 500). Figures: the
good well's latency (send to prediction) before and during the flood, p50 / p99 / max, and
what the flood got (sent, accepted, refused by reason).

In-process (``--scenario engine``): the engine with the in-memory transport in this one
process, no Zenoh and no second process: ``--burst`` samples of ``--wells`` wells (and
their measurements) put as fast as the receive queue takes them; the rate at which their
predictions are published is the process's own cost per sample. ``--profile N`` prints the
N most expensive functions of every thread (cProfile per thread).

Prints figures; asserts nothing (shared 2-core machines are noisy). Usage::

    .venv/bin/python benchmarks/bench_service.py [--wells 100,1000] [--seconds 30] [--burst 20000]
    .venv/bin/python benchmarks/bench_service.py --scenario flood [--flood-kind samples|names]
    .venv/bin/python benchmarks/bench_service.py --scenario flood --flood-kind blocks \
        --flood-block 200 --inputs 'well_rate_hz = 100'   # with a per-well quota
    .venv/bin/python benchmarks/bench_service.py --scenario engine --wells 1000 [--profile 30]
    .venv/bin/python benchmarks/bench_service.py --scenario engine --wells 1000 --block 1,40
    .venv/bin/python benchmarks/bench_service.py --markdown docs/benchmarks/generated/service.md

With ``--markdown PATH`` it runs the set of measurements the documentation's page on the
service's performance shows, and writes them there as a Markdown fragment (the command,
the date, the machine's CPUs and load, then the tables; about 8-10 minutes on a 2-core
machine): over Zenoh, ``--wells`` (1,000) at 1 Hz for ``--seconds`` (20), then a burst
(``--burst``, 30,000 samples) per message size of ``--block`` (1, 40, 200), with the
defaults beside a receiver thread (``queues.receiver = "thread"``) and beside ``mm``'s
online step in torch (``VFM_KERNELS=0``); in-process, the same wells' burst
(``--engine-burst``, 20,000) with the defaults beside sensor blocks, beside batches of one
message (``queues.batch_max = 1``: no cross-well batching) and beside the torch step, then
a measurement learned with every sample (``--learn-wells`` 100, ``--learn-burst`` 5,000),
batched and not; and the fairness of a flood of one well.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import tempfile
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from replay.client import FieldClient, ZenohBus, sample_of
from service.testing import ServeProcess
from vfm_core.data import target_mask
from vfm_core.messages import Measurement, sensor_block
from vfm_core.observations import validate_frame
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.simulate import simulate_field


def make_history(
    folder: Path, wells: int, rows_per_well: int, source: str = "mpfm"
) -> tuple[Path, dict[str, np.ndarray]]:
    """A history of ``wells`` wells (copies of ten simulated ones) and each well's input rows;
    with ``source`` ``well_test`` every measured row of the history is booked as a well
    test (wells without a meter of their own: the paper's case 2)."""
    base = validate_frame(simulate_field(wells=10, years=1, seed=1).observations).frame
    base = base[target_mask(base, "all")]
    if source != "mpfm":
        base = base.assign(source=source)
    names = [f"B{j:04d}" for j in range(wells)]
    parts, inputs = [], {}
    for j, name in enumerate(names):
        own = base[base["well"] == f"W{j % 10 + 1:02d}"]
        hist = own.iloc[:rows_per_well].copy()
        hist["well"] = name
        parts.append(hist)
        live = own.iloc[rows_per_well:]
        inputs[name] = live[
            ["choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil", "q_total"]
        ].to_numpy()
    path = folder / "history.parquet"
    pd.concat(parts, ignore_index=True).to_parquet(path)
    return path, inputs


class Plant:
    """The sending side: the shared field client on Zenoh, timing each sample to its prediction."""

    def __init__(self, endpoint: str, wells: str = "*") -> None:
        self.bus = ZenohBus.connect(
            [endpoint], block_wait_before_close_ms=600_000, capacity=1 << 17
        )
        self.client = FieldClient(self.bus, "vfm", track_latency=True, wells=wells)

    @property
    def received(self) -> int:
        return self.client.count

    @property
    def latency(self) -> list[float]:
        return self.client.latency_s

    def ready(self, well: str) -> None:
        """Declare and match the well's publishers before the clock starts."""
        for key in (f"vfm/{well}/sensors", f"vfm/{well}/measurements/mpfm"):
            if not self.bus.matching(key, 30.0):
                raise RuntimeError(f"No service subscribes to {key}.")

    def send(self, well: str, when: datetime, row: np.ndarray, measure: bool) -> None:
        self.client.send_sample(well, sample_of(when, row[:6]))
        if measure:
            self.client.send_measurement(
                well, "mpfm", Measurement(time=when, q_total=float(row[6]))
            )

    def close(self) -> None:
        try:
            self.client.close()
        finally:
            self.bus.close()


def block_messages(
    names: list[str],
    inputs: dict[str, np.ndarray],
    t0: datetime,
    per_well: int,
    block: int,
    measure_every_s: float,
    phase: np.ndarray | None = None,
    prefix: str = "vfm",
    source: str = "mpfm",
) -> list[tuple[str, bytes]]:
    """(key, payload) of every well's samples at 1 s steps from ``t0``, ``block`` samples a
    message (1: one sample a message), each block followed by the measurements of its
    samples (one every ``measure_every_s`` per well; MPFM readings, or well tests with
    ``source`` ``well_test``)."""
    messages: list[tuple[str, bytes]] = []
    for first in range(0, per_well, block):
        steps = range(first, min(first + block, per_well))
        for j, name in enumerate(names):
            samples, measured = [], []
            offset = j if phase is None else int(phase[j])
            for step in steps:
                when = t0 + timedelta(seconds=step)
                row = inputs[name][step % len(inputs[name])]
                samples.append(sample_of(when, row[:6]))
                if (step + offset) % int(measure_every_s) == 0:
                    m = Measurement(time=when, q_total=float(row[6]))
                    measured.append(m.model_dump_json().encode())
            key = f"{prefix}/{name}/sensors"
            if block == 1:
                messages.append((key, samples[0].model_dump_json().encode()))
            else:  # one sensor block, then the measurements of its samples
                messages.append((key, sensor_block(samples)))
            messages += [(f"{prefix}/{name}/measurements/{source}", m) for m in measured]
    return messages


def run_field(
    wells: int,
    seconds: float,
    burst: int,
    measure_every_s: float,
    workers: int,
    synchronous: str,
    history_rows: int,
    queues: str = "",
    blocks: tuple[int, ...] = (1,),
    env: dict[str, str] | None = None,
) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="vfm-bench-") as tmp:
        folder = Path(tmp)
        history, inputs = make_history(folder, wells, history_rows)
        cfg = folder / "vfm.toml"
        cfg.write_text(f"""
[model]
name = "mm"
method = "ol"
history = "{history}"
[zenoh]
listen = ["tcp/127.0.0.1:0"]
[http]
port = 0
[store]
path = "{folder / "store.sqlite"}"
synchronous = "{synchronous}"
[queues]
workers = {workers}
{queues}
""")
        started = time.perf_counter()
        serve = ServeProcess(cfg, folder / "serve.log", env=env).start(timeout=1800)
        startup = time.perf_counter() - started
        plant = Plant(serve.zenoh)
        names = sorted(inputs)
        for name in names:  # declare and match every publisher before the clock starts
            plant.ready(name)
        rng = np.random.default_rng(0)
        phase = rng.uniform(0, measure_every_s, wells)
        try:
            # -- 1 Hz per well, spread over each second ------------------------------------------
            t0_wall = datetime.now(UTC).replace(microsecond=0) - timedelta(hours=1)
            t0 = time.perf_counter()
            sent = 0
            k = 0
            n_seconds = int(seconds)
            for second in range(n_seconds):
                for j, name in enumerate(names):
                    due = t0 + second + j / wells
                    wait = due - time.perf_counter()
                    if wait > 0:
                        time.sleep(wait)
                    row = inputs[name][(second + k) % len(inputs[name])]
                    measure = (second + phase[j]) % measure_every_s < 1.0
                    plant.send(name, t0_wall + timedelta(seconds=second), row, measure)
                    sent += 1
            send_s = time.perf_counter() - t0
            deadline = time.monotonic() + 120
            while plant.received < sent and time.monotonic() < deadline:
                time.sleep(0.05)
            steady_s = time.perf_counter() - t0
            lat = np.array(plant.latency) * 1000.0
            within_10ms = service_share_within(serve.http_url, 0.01)
            steady = {
                "service_within_10ms": within_10ms,
                "sent": sent,
                "received": plant.received,
                "lost": sent - plant.received,
                "send_rate": sent / send_s,
                "p50_ms": float(np.percentile(lat, 50)) if len(lat) else float("nan"),
                "p99_ms": float(np.percentile(lat, 99)) if len(lat) else float("nan"),
                "max_ms": float(lat.max()) if len(lat) else float("nan"),
                "elapsed_s": steady_s,
            }
            # -- bursts: as fast as BLOCK lets us, one per message size ------------------------
            bursts = []
            t1_wall = t0_wall + timedelta(seconds=n_seconds + 1)
            per_well = max(1, burst // wells)
            for block in blocks:
                plant.latency.clear()
                base_received = plant.received
                # every message made before the clock starts (the sender's JSON is not
                # measured): one sample a message, or sensor blocks
                puts = block_messages(
                    names, inputs, t1_wall, per_well, block, measure_every_s, phase
                )
                t1 = time.perf_counter()
                for key, payload in puts:
                    plant.bus.put(key, payload)
                n_burst = per_well * len(names)
                burst_send_s = time.perf_counter() - t1
                deadline = time.monotonic() + 300
                while plant.received - base_received < n_burst and time.monotonic() < deadline:
                    time.sleep(0.02)
                burst_s = time.perf_counter() - t1
                got = plant.received - base_received
                lat = np.array(plant.latency) * 1000.0
                bursts.append(
                    {
                        "block": block,
                        "sent": n_burst,
                        "received": got,
                        "lost": n_burst - got,
                        "send_s": burst_send_s,
                        "elapsed_s": burst_s,
                        "rate": got / burst_s,
                        "p50_ms": float(np.percentile(lat, 50)) if len(lat) else float("nan"),
                    }
                )
                t1_wall += timedelta(seconds=per_well + 1)
        finally:
            plant.close()
            serve.stop()
        import sqlite3

        con = sqlite3.connect(folder / "store.sqlite")
        learned = con.execute(
            "SELECT COUNT(*) FROM measurements WHERE status = 'learned'"
        ).fetchone()[0]
        con.close()
        return {
            "wells": wells,
            "startup_s": startup,
            "learned": learned,
            **{f"steady_{k}": v for k, v in steady.items()},
            "bursts": bursts,
        }


def _flood(
    endpoint: str,
    kind: str,
    seconds: float,
    row: list[float],
    t0_ns: int,
    out: Any,
    rows: int = 500,
) -> None:
    """The flooding side, in its own process and Zenoh session: as fast as BLOCK lets it."""
    import zenoh

    from replay.client import field_config

    names = kind == "names"
    with zenoh.open(field_config([endpoint], block_wait_before_close_ms=600_000)) as session:
        pub = session.declare_publisher(
            "vfm/F/sensors",
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )
        deadline = time.monotonic() + 30
        while not getattr(pub.matching_status, "matching", False):
            if time.monotonic() > deadline:
                out.put(-1)
                return
            time.sleep(0.01)
        inputs = (
            f'"choke": {row[0]}, "p_up": {row[1]}, "p_down": {row[2]}, "t_up": {row[3]}, '
            f'"eta_gas": {row[4]}, "eta_oil": {row[5]}'
        )
        n = 0
        end = time.monotonic() + seconds
        while kind == "blocks" and time.monotonic() < end:  # sensor blocks of `rows` rows
            times = [
                datetime.fromtimestamp((t0_ns + (n + i) * 1000) / 1e9, UTC).isoformat()
                for i in range(rows)
            ]
            block: dict[str, Any] = {"time": times}
            for j, name in enumerate(INPUT_COLUMNS):
                block[name] = [row[j]] * rows
            pub.put(json.dumps(block))
            n += rows
        while kind != "blocks" and time.monotonic() < end:
            for _ in range(100):
                when = datetime.fromtimestamp((t0_ns + n * 1000) / 1e9, UTC).isoformat()
                payload = f'{{"time": "{when}", {inputs}}}'
                if names:
                    session.put(
                        f"vfm/N{n:06d}/sensors",
                        payload,
                        congestion_control=zenoh.CongestionControl.BLOCK,
                    )
                else:
                    pub.put(payload)
                n += 1
        pub.undeclare()
    out.put(n)


def service_share_within(http_url: str, bound_s: float) -> float:
    """The share of predictions the service stored within ``bound_s`` of the sample's arrival
    (its own ``vfm_prediction_latency_seconds`` histogram, so without the transport and
    this process): tells the service's part of the latency from the plant's."""
    import httpx
    from prometheus_client.parser import text_string_to_metric_families

    text = httpx.get(f"{http_url}/metrics", timeout=30).text
    within = count = float("nan")
    for family in text_string_to_metric_families(text):
        if family.name != "vfm_prediction_latency_seconds":
            continue
        for sample in family.samples:
            if sample.name.endswith("_bucket") and float(sample.labels["le"]) == bound_s:
                within = sample.value
            elif sample.name.endswith("_count"):
                count = sample.value
    return within / count if count else float("nan")


def run_flood(
    kind: str,
    baseline_s: float,
    flood_s: float,
    period_s: float,
    queues: str = "",
    rows: int = 500,
    inputs_toml: str = "",
) -> dict[str, Any]:
    """A good well's latency before and during a flood from another process (see the docstring)."""
    import multiprocessing as mp

    import httpx

    with tempfile.TemporaryDirectory(prefix="vfm-bench-flood-") as tmp:
        folder = Path(tmp)
        history, inputs = make_history(folder, 2, 60)
        # the history's wells are B0000 and B0001: rename them G (good) and F (flooding)
        frame = pd.read_parquet(history)
        frame["well"] = frame["well"].map({"B0000": "G", "B0001": "F"})
        frame.to_parquet(history)
        g_rows, f_rows = inputs["B0000"], inputs["B0001"]
        cfg = folder / "vfm.toml"
        cfg.write_text(f"""
[model]
name = "mm"
method = "ol"
history = "{history}"
[zenoh]
listen = ["tcp/127.0.0.1:0"]
[http]
port = 0
[store]
path = "{folder / "store.sqlite"}"
synchronous = "normal"
[inputs]
{inputs_toml}
[queues]
{queues}
""")
        serve = ServeProcess(cfg, folder / "serve.log").start(timeout=600)
        # the good well's answers only: timing it must not mean parsing the flood's answers
        # too (that backlog in this process once read as the service's delay)
        plant = Plant(serve.zenoh, wells="G")
        plant.ready("G")
        t_now = datetime.now(UTC).replace(microsecond=0) - timedelta(minutes=30)
        try:

            def good(seconds: float, start: datetime, k0: int) -> tuple[list[float], int, int]:
                plant.latency.clear()
                sent = 0
                t0 = time.perf_counter()
                k = k0
                while time.perf_counter() - t0 < seconds:
                    when = start + timedelta(milliseconds=k)
                    plant.client.send_sample("G", sample_of(when, g_rows[k % len(g_rows)][:6]))
                    sent += 1
                    k += 1
                    time.sleep(period_s)
                wait_end = time.monotonic() + 60
                while len(plant.latency) < sent and time.monotonic() < wait_end:
                    time.sleep(0.05)
                return [x * 1000.0 for x in plant.latency], sent, k

            before, sent_before, k = good(baseline_s, t_now, 0)
            ctx = mp.get_context("spawn")
            out = ctx.Queue()
            flood_t0 = int((t_now + timedelta(minutes=1)).timestamp() * 1e9)
            proc = ctx.Process(
                target=_flood,
                args=(serve.zenoh, kind, flood_s, list(f_rows[0][:6]), flood_t0, out, rows),
            )
            proc.start()
            time.sleep(1.0)  # let the flood start
            during, sent_during, _ = good(flood_s - 1.0, t_now, k)
            flooded = out.get(timeout=120)
            proc.join(30)
            health = httpx.get(f"{serve.http_url}/health", timeout=30).json()
        finally:
            plant.close()
            serve.stop()

    def stats(lat: list[float], sent: int) -> dict[str, float]:
        a = np.array(lat) if lat else np.array([float("nan")])
        return {
            "sent": sent,
            "answered": len(lat),
            "p50_ms": float(np.percentile(a, 50)),
            "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()),
        }

    return {
        "kind": kind,
        "rows": rows,
        "before": stats(before, sent_before),
        "during": stats(during, sent_during),
        "flood_sent": flooded,
        "flood_s": flood_s,
        "accepted": health["accepted"],
        "rejected": health["rejected"],
        "wells": health["wells"],
        "overflow": health["overflow"],
    }


def run_engine(
    wells: int,
    burst: int,
    measure_every_s: float,
    history_rows: int,
    profile: int,
    queues: str,
    block: int = 1,
    synchronous: str = "normal",
    model: str = "mm",
    method: str = "ol",
    source: str = "mpfm",
) -> dict[str, Any]:
    """The engine in this process with the in-memory transport (see the module docstring).
    ``model`` and ``method`` are the service's; ``source`` the meter of the history and of
    the burst's measurements (``well_test``: wells learned from well tests only). Before the
    clock starts, one sample per well an hour before the burst is answered (a warm-up: a
    retrain due at the first live sample, as ``refresh=auto``'s for such wells after the
    history, runs there, not in the burst)."""
    import cProfile
    import io
    import pstats
    import threading

    from service.app import Service
    from service.testing import loopback_settings
    from service.transport import MemoryTransport

    try:
        import tomllib

        extra_queues = tomllib.loads(queues) if queues else {}
    except Exception as exc:  # pragma: no cover - a typo in --queues
        raise SystemExit(f"--queues is not TOML: {exc}") from None
    with tempfile.TemporaryDirectory(prefix="vfm-bench-engine-") as tmp:
        folder = Path(tmp)
        history, inputs = make_history(folder, wells, history_rows, source)
        settings = loopback_settings(
            folder,
            model={"name": model, "method": method, "history": str(history)},
            queues=extra_queues,
            store={"path": str(folder / "store.sqlite"), "synchronous": synchronous},
        )
        bus = MemoryTransport(settings.prefix, capacity=4096, keep=16)
        service = Service(settings, bus)
        profiles: list[cProfile.Profile] = []

        def start_profile(*_: Any) -> None:  # each new thread profiles itself
            prof = cProfile.Profile()
            profiles.append(prof)
            prof.enable()

        if profile:
            threading.setprofile(start_profile)
        started = time.perf_counter()
        service.start()
        startup = time.perf_counter() - started
        names = sorted(inputs)
        got = [0]
        done = threading.Event()
        lock = threading.Lock()

        def on_prediction(key: str, payload: bytes) -> None:
            n = payload.count(b'Z"')  # the answers' times (a prediction block holds many)
            with lock:
                got[0] += n
                if got[0] >= total[0]:
                    done.set()

        total = [burst]

        try:
            if True:  # no field client: its own parsing of predictions would run on the worker
                if not bus.matching(f"{settings.prefix}/{names[0]}/sensors", 30.0):
                    raise RuntimeError("The engine does not receive.")
                unsubscribe = bus.subscribe(f"{settings.prefix}/**", on_prediction)
                # the payloads are made before the clock starts: this measures the service
                per_well = max(1, burst // wells)
                t0_wall = datetime.now(UTC).replace(microsecond=0) - timedelta(
                    seconds=per_well + 3600
                )
                warm = block_messages(
                    names, inputs, t0_wall - timedelta(hours=1), 1, 1, 1e9, None, settings.prefix
                )
                total[0] = sum(key.endswith("/sensors") for key, _ in warm)
                for key, payload in warm:
                    bus.put(key, payload)
                if not done.wait(900.0):
                    raise RuntimeError(f"The warm-up got {got[0]} of {total[0]} predictions.")
                with lock:
                    got[0] = 0
                    done.clear()
                total[0] = per_well * len(names)
                messages = block_messages(
                    names,
                    inputs,
                    t0_wall,
                    per_well,
                    block,
                    measure_every_s,
                    None,
                    settings.prefix,
                    source,
                )
                t1 = time.perf_counter()
                cpu1 = time.process_time()
                if profile:
                    main_prof = cProfile.Profile()
                    main_prof.enable()
                for key, payload in messages:
                    bus.put(key, payload)
                seen = -1
                while not done.wait(10.0) and got[0] != seen:  # stop when nothing moves
                    seen = got[0]
                elapsed = time.perf_counter() - t1
                cpu = time.process_time() - cpu1
                if profile:
                    main_prof.disable()
                    threading.setprofile(None)  # type: ignore[arg-type]
                unsubscribe()
        finally:
            service.stop()
        snap = service.counters.snapshot()
    out: dict[str, Any] = {
        "wells": wells,
        "startup_s": startup,
        "sent": total[0],
        "received": got[0],
        "elapsed_s": elapsed,
        "rate": got[0] / elapsed,
        # CPU time of the whole process per prediction: less sensitive than the rate to
        # other jobs on a shared machine (it still includes this thread's puts)
        "cpu_us": cpu / max(got[0], 1) * 1e6,
        "accepted": snap["accepted"],
        "rejected": snap["rejected"],
    }
    if profile:
        buf = io.StringIO()
        stats = pstats.Stats(main_prof, stream=buf)
        for prof in profiles:
            try:
                prof.disable()
            except Exception:  # noqa: S110 - a thread that ended
                pass
            stats.add(prof)
        stats.sort_stats("tottime").print_stats(profile)
        stats.sort_stats("cumulative").print_stats(profile)
        if os.environ.get("VFM_BENCH_PSTATS"):  # the raw statistics, for pstats' callers
            stats.dump_stats(os.environ["VFM_BENCH_PSTATS"])
        out["profile"] = buf.getvalue()
    return out


@contextlib.contextmanager
def environment(**values: str) -> Iterator[None]:
    """``os.environ`` with ``values`` set inside the block (the engine in this process)."""
    before = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


#: the rows over Zenoh of ``--markdown``: a label, [queues] lines, the service's environment
ZENOH_ROWS: tuple[tuple[str, str, dict[str, str]], ...] = (
    ("defaults (the worker takes the messages from Zenoh)", "", {}),
    ('a receiver thread (`queues.receiver = "thread"`)', 'receiver = "thread"', {}),
    ("`mm`'s online step in torch (`VFM_KERNELS=0`)", "", {"VFM_KERNELS": "0"}),
)


def markdown_suite(args: argparse.Namespace) -> str:
    """Run what the docs' page shows (see the module docstring); return it as Markdown."""
    import platform
    import sys

    started = time.perf_counter()
    wells = int(args.wells.split(",")[0])
    blocks = tuple(int(b) for b in args.block.split(","))
    zenoh_rows = []
    for label, queues, env in ZENOH_ROWS:
        print(f"\nover Zenoh: {label}", flush=True)
        r = run_field(
            wells,
            args.seconds,
            args.burst,
            args.measure_every,
            args.workers,
            args.synchronous or "full",
            args.history_rows,
            "\n".join(q for q in (args.queues, queues) if q),
            blocks,
            env,
        )
        print(json.dumps({k: v for k, v in r.items()}, default=str), flush=True)
        zenoh_rows.append((label, r))

    def engine(wells: int, burst: int, every: float, block: int, queues: str) -> dict[str, Any]:
        r = run_engine(
            wells, burst, every, args.history_rows, 0, queues, block, args.synchronous or "normal"
        )
        print(
            f"  {r['received']:,} of {r['sent']:,} in {r['elapsed_s']:.1f} s = "
            f"{r['rate']:,.0f} samples/s, {r['cpu_us']:.0f} us CPU a sample",
            flush=True,
        )
        return r

    engine_rows: list[tuple[str, str, dict[str, Any]]] = []
    groups = (
        (
            f"{wells:,} wells, a burst of {args.engine_burst:,} samples, a measurement every "
            f"{args.measure_every:g} s per well",
            wells,
            args.engine_burst,
            args.measure_every,
            [
                ("defaults, one sample a message", 1, "", {}),
                *[(f"sensor blocks of {b}", b, "", {}) for b in blocks if b > 1],
                ("batches of one message (`queues.batch_max = 1`)", 1, "batch_max = 1", {}),
                ("`mm`'s online step in torch (`VFM_KERNELS=0`)", 1, "", {"VFM_KERNELS": "0"}),
            ],
        ),
        (
            f"{args.learn_wells:,} wells, a burst of {args.learn_burst:,} samples, a "
            "measurement with every sample (all learned online)",
            args.learn_wells,
            args.learn_burst,
            1.0,
            [
                ("defaults (the batch's measurements learned in one call)", 1, "", {}),
                ("batches of one message (`queues.batch_max = 1`)", 1, "batch_max = 1", {}),
            ],
        ),
    )
    for title, n, burst, every, rows in groups:
        for label, block, queues, env in rows:
            print(f"\nin-process, {title}: {label}", flush=True)
            with environment(**env):
                r = engine(n, burst, every, block, "\n".join(q for q in (args.queues, queues) if q))
            engine_rows.append((title, label, r))

    print("\nfairness: a flood of one well", flush=True)
    flood = run_flood(
        "samples",
        5.0,
        args.flood_seconds,
        0.05,
        args.queues,
        args.flood_block,
        "max_block_samples = 1000",
    )

    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    argv = " ".join(sys.argv[1:])
    store = args.synchronous or "full"
    lines = [
        f"Written by `python benchmarks/bench_service.py {argv}` on "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC in {(time.perf_counter() - started) / 60:.1f} "
        f"min: {os.cpu_count()} CPUs ({platform.machine()}), load average (1, 5, 15 min) "
        f"{load[0]:.1f}, {load[1]:.1f}, {load[2]:.1f} at the end. Model `mm`, method `ol`, "
        f"{args.history_rows} history rows per well for the initial fit; every line a run "
        "of its own, one after the other.",
        "",
        f'**Two processes over Zenoh** (`vfm serve`, store `synchronous = "{store}"`, and '
        f"this process as the plant, on the same cores): {wells:,} wells at 1 Hz for "
        f"{args.seconds:g} s, each well's samples spread over the second and a measurement "
        f"every {args.measure_every:g} s per well learned online; latency from putting a "
        "sample to receiving its prediction; *in the service within 10 ms*: the share of "
        "predictions stored within 10 ms of their sample's arrival (the service's own "
        f"`vfm_prediction_latency_seconds`). Then bursts of {args.burst:,} samples as fast "
        "as Zenoh's BLOCK lets the plant send them (the messages made before the clock "
        "starts), samples answered a second:",
        "",
        "| service | 1 Hz lost | p50 | p99 | max | in the service within 10 ms | "
        + " | ".join(
            "burst, one sample a message" if b == 1 else f"burst, blocks of {b}" for b in blocks
        )
        + " |",
        "| --- | ---: | ---: | ---: | ---: | ---: |" + " ---: |" * len(blocks),
    ]
    for label, r in zenoh_rows:
        cells = " | ".join(
            f"{u['rate']:,.0f}" + ("" if not u["lost"] else f" ({u['lost']:,} lost)")
            for u in r["bursts"]
        )
        lines.append(
            f"| {label} | {r['steady_lost']} of {r['steady_sent']:,} | "
            f"{r['steady_p50_ms']:.1f} ms | {r['steady_p99_ms']:.1f} ms | "
            f"{r['steady_max_ms']:.1f} ms | {100 * r['steady_service_within_10ms']:.2f} % | "
            f"{cells} |"
        )
    lines += [
        "",
        "**The engine in one process** (the in-memory transport, no Zenoh, store "
        f'`synchronous = "{args.synchronous or "normal"}"`): a burst put as fast as the '
        "receive queue takes it (the messages made before the clock starts); the rate at "
        "which its predictions are published, the process's CPU time per sample, and the "
        "rate over the first line's of its group (higher is faster):",
    ]
    first: dict[str, float] = {}
    for title, label, r in engine_rows:
        if title not in first:
            first[title] = r["rate"]
            lines += [
                "",
                f"{title}:",
                "",
                "| service | samples/s | CPU a sample | rate / the first line's |",
                "| --- | ---: | ---: | ---: |",
            ]
        lost = r["sent"] - r["received"]
        note = f" ({lost:,} unanswered)" if lost else ""
        lines.append(
            f"| {label} | {r['rate']:,.0f}{note} | {r['cpu_us']:,.0f} µs | "
            f"{r['rate'] / first[title]:.2f} |"
        )
    lines += [
        "",
        f"**Fairness**: a good well sends a sample every 50 ms while another process floods "
        f"one other well as fast as Zenoh's BLOCK lets it for {flood['flood_s']:g} s "
        f"({flood['flood_sent']:,} samples sent, {flood['flood_sent'] / flood['flood_s']:,.0f} "
        "a second); the good well's latency, send to prediction:",
        "",
        "| the good well | answered | p50 | p99 | max |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for phase in ("before", "during"):
        r = flood[phase]
        lines.append(
            f"| {phase} the flood | {r['answered']} of {r['sent']} | {r['p50_ms']:.1f} ms | "
            f"{r['p99_ms']:.1f} ms | {r['max_ms']:.1f} ms |"
        )
    lines += [
        "",
        f"The service accepted {flood['accepted']} and refused "
        f"{json.dumps(flood['rejected']) if flood['rejected'] else 'nothing'} "
        f"(overflow: {json.dumps(flood['overflow'])}).",
        "",
    ]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--wells", default=None, help="comma-separated field sizes (100,1000; --markdown: 1000)"
    )
    parser.add_argument(
        "--seconds", type=float, default=None, help="length of the 1 Hz run (30; --markdown: 20)"
    )
    parser.add_argument(
        "--burst", type=int, default=None, help="samples in the burst (20,000; --markdown: 30,000)"
    )
    parser.add_argument(
        "--measure-every", type=float, default=180.0, help="seconds between a well's MPFM readings"
    )
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument(
        "--synchronous",
        default=None,
        choices=["full", "normal"],
        help="the store's synchronous mode (default: full over Zenoh, normal in-process)",
    )
    parser.add_argument(
        "--history-rows", type=int, default=60, help="history rows per well for the initial fit"
    )
    parser.add_argument("--scenario", default="load", choices=["load", "flood", "engine"])
    parser.add_argument(
        "--profile", type=int, default=0, help="engine: print the N costliest functions"
    )
    parser.add_argument(
        "--block",
        default=None,
        help="samples per sensor message in the burst (engine and load scenarios), "
        "comma-separated sizes run side by side (1: one sample a message; more: sensor blocks; "
        "default 1, with --markdown 1,40,200)",
    )
    parser.add_argument("--model", default="mm", help="engine: the service's model (mm)")
    parser.add_argument("--method", default="ol", help="engine: the service's method (ol)")
    parser.add_argument(
        "--measure-source",
        default="mpfm",
        choices=["mpfm", "well_test"],
        help="engine: the meter of the history and of the burst's measurements (mpfm; "
        "well_test: wells learned from well tests only, the paper's case 2)",
    )
    parser.add_argument("--flood-kind", default="samples", choices=["samples", "names", "blocks"])
    parser.add_argument(
        "--flood-block", type=int, default=500, help="rows per block with --flood-kind blocks"
    )
    parser.add_argument("--flood-seconds", type=float, default=10.0)
    parser.add_argument(
        "--queues", default="", help="TOML lines for [queues], e.g. 'receive_capacity = 256'"
    )
    parser.add_argument(
        "--inputs",
        default="",
        help="flood: TOML lines for [inputs], e.g. 'well_rate_hz = 100' (a per-well quota)",
    )
    parser.add_argument(
        "--markdown",
        metavar="PATH",
        default=None,
        help="run the measurements the docs' page shows and write them as Markdown here",
    )
    parser.add_argument(
        "--engine-burst", type=int, default=20_000, help="--markdown: samples of the engine's burst"
    )
    parser.add_argument(
        "--learn-wells", type=int, default=100, help="--markdown: wells of the learning burst"
    )
    parser.add_argument(
        "--learn-burst", type=int, default=5_000, help="--markdown: samples of the learning burst"
    )
    args = parser.parse_args()
    md = args.markdown is not None
    args.wells = args.wells or ("1000" if md else "100,1000")
    args.seconds = args.seconds if args.seconds is not None else (20.0 if md else 30.0)
    args.burst = args.burst if args.burst is not None else (30_000 if md else 20_000)
    args.block = args.block or ("1,40,200" if md else "1")
    if md:
        from vfm_core.fileio import write_text_atomic

        write_text_atomic(args.markdown, markdown_suite(args))
        print(f"\nwrote {args.markdown}")
        return
    if args.scenario == "engine":
        print(
            f"vfm engine in this process (in-memory transport, no Zenoh): {args.model} + "
            f"{args.method}, measurements from {args.measure_source}, "
            f"store synchronous={args.synchronous or 'normal'}, {args.burst:,} samples put as fast as the "
            "receive queue takes them."
        )
        for wells in [int(w) for w in args.wells.split(",")]:
            for block in [int(b) for b in args.block.split(",")]:
                r = run_engine(
                    wells,
                    args.burst,
                    args.measure_every,
                    args.history_rows,
                    args.profile,
                    args.queues,
                    block,
                    args.synchronous or "normal",
                    args.model,
                    args.method,
                    args.measure_source,
                )
                how = "one sample a message" if block == 1 else f"sensor blocks of {block} samples"
                print(
                    f"\n{wells} wells, {how} (start-up incl. fit {r['startup_s']:.1f} s): "
                    f"{r['sent']:,} samples, {r['received']:,} predictions published in "
                    f"{r['elapsed_s']:.2f} s = {r['rate']:,.0f} samples/s ({r['cpu_us']:.0f} us "
                    f"of CPU per sample); accepted {r['accepted']}, refused {r['rejected']}"
                )
                if "profile" in r:
                    print(r["profile"])
        return
    if args.scenario == "flood":
        f = run_flood(
            args.flood_kind,
            5.0,
            args.flood_seconds,
            0.05,
            args.queues,
            args.flood_block,
            f"max_block_samples = {max(args.flood_block, 1000)}\n{args.inputs}",
        )
        blocks = f" in sensor blocks of {f['rows']} rows" if f["kind"] == "blocks" else ""
        print(
            f"Fairness: a good well sends a sample every 50 ms; another process floods "
            f"{'new well names' if f['kind'] == 'names' else 'one well'}{blocks} for "
            f"{f['flood_s']:g} s ({f['flood_sent']:,} samples sent, "
            f"{f['flood_sent'] / f['flood_s']:,.0f}/s)."
        )
        for phase in ("before", "during"):
            r = f[phase]
            print(
                f"  good well {phase:<6} the flood: {r['answered']}/{r['sent']} answered, latency p50 "
                f"{r['p50_ms']:.1f} ms, p99 {r['p99_ms']:.1f} ms, max {r['max_ms']:.1f} ms"
            )
        print(
            f"  service: {f['wells']} wells, accepted {f['accepted']}, refused {f['rejected']}, "
            f"overflow {f['overflow']}"
        )
        return
    print(
        f"vfm service benchmark: mm + ol, store synchronous={args.synchronous or 'full'}, workers={args.workers}, "
        f"{args.seconds:g} s at 1 Hz per well, a measurement every {args.measure_every:g} s per well."
    )
    for wells in [int(w) for w in args.wells.split(",")]:
        r = run_field(
            wells,
            args.seconds,
            args.burst,
            args.measure_every,
            args.workers,
            args.synchronous or "full",
            args.history_rows,
            args.queues,
            tuple(int(b) for b in args.block.split(",")),
        )
        print(
            f"\n{wells} wells (start-up incl. fit {r['startup_s']:.1f} s; {r['learned']} online updates)"
        )
        print(
            f"  1 Hz per well: sent {r['steady_sent']:,} at {r['steady_send_rate']:,.0f}/s, received "
            f"{r['steady_received']:,}, lost {r['steady_lost']}; latency p50 {r['steady_p50_ms']:.1f} ms, "
            f"p99 {r['steady_p99_ms']:.1f} ms, max {r['steady_max_ms']:.1f} ms; in the service "
            f"(arrival to stored prediction) {100 * r['steady_service_within_10ms']:.2f} % "
            "within 10 ms"
        )
        for u in r["bursts"]:
            how = "one sample a message" if u["block"] == 1 else f"sensor blocks of {u['block']}"
            print(
                f"  burst, {how}: {u['sent']:,} samples sent in {u['send_s']:.1f} s, "
                f"{u['received']:,} answered after {u['elapsed_s']:.1f} s = {u['rate']:,.0f} "
                f"samples/s sustained, lost {u['lost']}"
            )


if __name__ == "__main__":
    main()
