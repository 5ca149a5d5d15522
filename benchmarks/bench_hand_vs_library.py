"""Two hand-written pieces of the service's per-sample path against the library they stand in for.

Both are timed side by side in one run, in one thread, CPU time (``time.process_time``),
the best of ``--repeats`` rounds (the least disturbed by the other processes on the
machine), each round after a garbage collection (else the garbage of one round is
collected during the next, which doubled every other ``Intake.deliver`` figure):

* **the sample reader**: :func:`service.inputs.quick_sensor` (orjson, a pattern for the
  time, the model's rules written out as comparisons) against pydantic reading the same
  bytes itself (:func:`pydantic_reader`: ``SensorSample``'s ``validate_json`` in strict
  mode, pydantic-core's JSON parser and the model's validators, then the same time
  bounds), and the full path both stand before (:func:`service.inputs.parse_sensor`: the
  standard library's JSON, the number checks, pydantic on the decoded object); µs a
  message alone, on single-sample messages as senders write them, and in
  ``Intake.deliver`` as the receiver runs it (``bench_sample_path.receiving``) with
  either reader;
* **the latency histogram**: :class:`service.engine.observe.LatencyHistogram` (a commit's
  latencies counted in one call and one lock) against ``prometheus_client.Histogram``
  (``observe`` once a sample); µs a sample, for commits of 1, 16 and 256 samples.

The margin that does not matter to a user is 2 % of the CPU the whole service spends a
sample on the path where the piece runs (``bench_service.py --scenario engine``,
docs/benchmarks/service.md): that benchmark's own figures move by 20-30 % between a quiet
machine and one at load 1, so 2 % is far inside what any user could see. The reader runs
only on single-sample messages (116-155 µs a sample): 2.3 µs. The histogram counts every
sample, also on the fastest path (blocks of 200 samples, about 18 µs a sample): 0.36 µs.
Prints figures; asserts nothing. Run::

    .venv/bin/python benchmarks/bench_hand_vs_library.py [--messages 20000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import gc
import json
import random
import time
from collections.abc import Callable
from datetime import UTC, datetime, timedelta

from prometheus_client import CollectorRegistry, Histogram
from pydantic import ValidationError

from service.engine.observe import LATENCY_BUCKETS_S, LatencyHistogram
from service.inputs import DEFAULT_LIMITS, Limits, parse_sensor, quick_sensor
from vfm_core.messages import SensorSample
from vfm_core.timeutil import REPRESENTABLE_MAX, REPRESENTABLE_MIN, to_ns

#: the margins (µs a sample) under which a library's extra cost does not matter to a user:
#: 2 % of the service's CPU a sample where the piece runs (see the module docstring)
READER_MARGIN_US = 0.02 * 116.0
HISTOGRAM_MARGIN_US = 0.02 * 18.0


def _payloads(n: int, seed: int = 1) -> list[bytes]:
    """Single-sample sensor messages in the forms senders write (all of them good)."""
    rng = random.Random(seed)
    start = datetime(2026, 11, 24, tzinfo=UTC)
    out = []
    for i in range(n):
        when = start + timedelta(seconds=i)
        text = rng.choice(
            [when.isoformat(), when.strftime("%Y-%m-%dT%H:%M:%SZ"), when.isoformat() + "Z"]
        ).replace("+00:00Z", "Z")
        p_up = rng.uniform(40, 200)
        body = {
            "time": text,
            "choke": rng.uniform(0, 1),
            "p_up": p_up,
            "p_down": rng.uniform(5, p_up - 1),
            "t_up": rng.uniform(20, 120),
            "eta_gas": rng.uniform(0, 0.5),
            "eta_oil": rng.uniform(0, 0.5),
        }
        out.append(json.dumps(body).encode())
    return out


_SAMPLE = SensorSample.__pydantic_validator__
_SPAN_NS = (to_ns(REPRESENTABLE_MIN), to_ns(REPRESENTABLE_MAX))


def pydantic_reader(
    payload: bytes, limits: Limits, earliest_ns: int, latest_ns: int
) -> tuple[int, tuple[float, ...]] | None:
    """The library's way, a drop-in for :func:`service.inputs.quick_sensor`: pydantic reads
    the bytes itself, in strict mode (a number written as text or a bool, which the full
    path refuses, is no verdict), with the same size and depth guards and time bounds.
    (It agreed with the full path on 60,000 payloads of the fuzzer of
    ``tests/test_sample_path.py``, seeds 3, 7 and 11, when this was measured.)"""
    if len(payload) > limits.max_bytes or payload.count(b"{") + payload.count(b"[") > (
        limits.max_depth
    ):
        return None
    try:
        sample = _SAMPLE.validate_json(payload, strict=True)
    except ValidationError:
        return None
    t = to_ns(sample.time)
    if not (max(earliest_ns, _SPAN_NS[0]) <= t <= min(latest_ns, _SPAN_NS[1])):
        return None
    return t, (
        sample.choke,
        sample.p_up,
        sample.p_down,
        sample.t_up,
        sample.eta_gas,
        sample.eta_oil,
    )


def full_reader(
    payload: bytes, earliest_ns: int, latest_ns: int
) -> tuple[int, tuple[float, ...]] | None:
    """The full path the quick reader stands before (standard JSON, checks, pydantic)."""
    sample = parse_sensor(payload, DEFAULT_LIMITS)
    t = to_ns(sample.time)
    if not earliest_ns <= t <= latest_ns:
        return None
    return t, tuple(sample.inputs())


def _quick(payload: bytes, earliest_ns: int, latest_ns: int) -> object:
    return quick_sensor(payload, DEFAULT_LIMITS, earliest_ns, latest_ns)


def _pydantic(payload: bytes, earliest_ns: int, latest_ns: int) -> object:
    return pydantic_reader(payload, DEFAULT_LIMITS, earliest_ns, latest_ns)


def receiving(messages: int, repeats: int) -> dict[str, float] | None:
    """µs of CPU a message of ``Intake.deliver`` with each reader (1,000 wells' single-sample
    messages, every one queued); None where the intake no longer calls ``quick_sensor``."""
    import bench_sample_path

    import service.engine.intake as intake

    if not hasattr(intake, "quick_sensor"):
        return None
    own = intake.quick_sensor
    readers = {
        "quick_sensor (hand-written)": own,
        "pydantic validate_json, strict": pydantic_reader,
    }
    out = dict.fromkeys(readers, float("inf"))
    try:
        bench_sample_path.receiving(1000, messages)  # warm: the first run in a process is slower
        for _ in range(repeats):  # the readers in turn, so a disturbance hits both alike
            for name, reader in readers.items():
                intake.quick_sensor = reader  # type: ignore[assignment]
                # collected first: the garbage of the run before would otherwise be
                # collected during this one (it doubled every other run's figure)
                gc.collect()
                out[name] = min(out[name], bench_sample_path.receiving(1000, messages))
    finally:
        intake.quick_sensor = own
    return out


def _best_cpu(run: Callable[[], None], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        gc.collect()
        began = time.process_time()
        run()
        best = min(best, time.process_time() - began)
    return best


def readers(messages: int, repeats: int) -> dict[str, float]:
    """µs of CPU a message of each reader (every message accepted by each)."""
    payloads = _payloads(messages)
    earliest = to_ns(datetime(1970, 1, 1, tzinfo=UTC))
    latest = to_ns(datetime(2100, 1, 1, tzinfo=UTC))
    out = {}
    for name, read in (
        ("quick_sensor (hand-written)", _quick),
        ("pydantic validate_json, strict", _pydantic),
        ("parse_sensor (the full path)", full_reader),
    ):
        got = [read(p, earliest, latest) for p in payloads[:200]]
        if any(g is None for g in got):
            raise SystemExit(f"{name} refused a good sample")

        def run(read: Callable[..., object] = read) -> None:
            for p in payloads:
                read(p, earliest, latest)

        out[name] = _best_cpu(run, repeats) / messages * 1e6
    return out


def histograms(samples: int, repeats: int, commit: int) -> dict[str, float]:
    """µs of CPU a sample of each histogram, ``commit`` latencies at a time."""
    rng = random.Random(5)
    values = [rng.expovariate(200.0) for _ in range(samples)]
    chunks = [values[i : i + commit] for i in range(0, samples, commit)]
    ours = LatencyHistogram("lat_seconds", "latency", LATENCY_BUCKETS_S)
    theirs = Histogram(
        "lat_seconds", "latency", buckets=LATENCY_BUCKETS_S, registry=CollectorRegistry()
    )

    def hand() -> None:
        for chunk in chunks:
            ours.observe_many(chunk)

    def library() -> None:
        observe = theirs.observe
        for chunk in chunks:
            for v in chunk:
                observe(v)

    return {
        "LatencyHistogram.observe_many (hand-written)": _best_cpu(hand, repeats) / samples * 1e6,
        "prometheus_client Histogram.observe": _best_cpu(library, repeats) / samples * 1e6,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--messages", type=int, default=20_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(f"reading a single-sample message ({args.messages:,} messages, best of {args.repeats}):")
    read = readers(args.messages, args.repeats)
    for name, us in read.items():
        print(f"  {name:46s} {us:6.2f} µs CPU a message")
    hand, library = list(read.values())[:2]
    print(
        f"  library - hand-written: {library - hand:+.2f} µs "
        f"(margin {READER_MARGIN_US:.2f} µs: {'within' if library - hand <= READER_MARGIN_US else 'over'})"
    )
    deliver = receiving(args.messages, args.repeats)
    if deliver is None:
        print("Intake.deliver no longer calls quick_sensor: no end-to-end comparison.")
    else:
        print(f"Intake.deliver, {args.messages:,} single-sample messages of 1,000 wells:")
        for name, us in deliver.items():
            print(f"  {name:46s} {us:6.2f} µs CPU a message")
        hand, library = deliver.values()
        verdict = "within" if library - hand <= READER_MARGIN_US else "over"
        print(
            f"  library - hand-written: {library - hand:+.2f} µs "
            f"(margin {READER_MARGIN_US:.2f} µs: {verdict})"
        )
    for commit in (1, 16, 256):
        print(f"latency histogram, commits of {commit} samples:")
        hist = histograms(args.messages * 5, args.repeats, commit)
        for name, us in hist.items():
            print(f"  {name:46s} {us:6.3f} µs CPU a sample")
        hand, library = hist.values()
        verdict = "within" if library - hand <= HISTOGRAM_MARGIN_US else "over"
        print(
            f"  library - hand-written: {library - hand:+.3f} µs "
            f"(margin {HISTOGRAM_MARGIN_US:.2f} µs: {verdict})"
        )


if __name__ == "__main__":
    main()
