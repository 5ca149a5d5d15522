"""The service's per-sample path, its quick parts against the full ones they stand in for.

One sample a message is the service's commonest input, so its path has quick versions:
:func:`service.inputs.quick_sensor` reads a plain sample with orjson and plain comparisons
before the full path (stdlib JSON, pydantic, the time checks); the prediction message is
written by :func:`vfm_core.messages.prediction_json` instead of pydantic; the latency
histogram counts a commit at a time; :func:`vfm_core.timeutil.to_ns` works on integers.
Each must give exactly what the full version gives: the quick reader may only say "not
sure" (None), never accept what the full path refuses or read other values.
"""

from __future__ import annotations

import json
import math
import random
from datetime import UTC, datetime, timedelta, timezone

import numpy as np
import orjson
import pytest
import torch
from prometheus_client import CollectorRegistry, Histogram

from service.engine.observe import LATENCY_BUCKETS_S, LatencyHistogram
from service.errors import InvalidRequest
from service.inputs import DEFAULT_LIMITS, Limits, parse_sensor, quick_sensor
from vfm_core.learning.streaming import phase_split, phase_split_numpy
from vfm_core.messages import Prediction, prediction_json
from vfm_core.timeutil import from_ns, time_problem, to_ns

EARLIEST = datetime(1970, 1, 1, tzinfo=UTC)
NOW = datetime(2026, 11, 24, 12, tzinfo=UTC)
LATEST = NOW + timedelta(seconds=300)

GOOD = {
    "choke": 0.5,
    "p_up": 80.0,
    "p_down": 30.0,
    "t_up": 60.0,
    "eta_gas": 0.2,
    "eta_oil": 0.5,
}


def full_path(
    payload: bytes, limits: Limits = DEFAULT_LIMITS
) -> tuple[int, tuple[float, ...]] | str:
    """What the full path makes of a single-sample payload: (time ns, inputs), or the reason
    it refuses it (as ``Intake.deliver`` checks a sample: parse_sensor, then the time)."""
    try:
        sample = parse_sensor(payload, limits)
    except InvalidRequest as error:
        return str(error.reason)
    if time_problem(sample.time, earliest=EARLIEST) is not None:
        return "time out of range"
    t = to_ns(sample.time)
    if t > to_ns(LATEST):
        return "time in the future"
    return t, tuple(sample.inputs())


def quick(payload: bytes, limits: Limits = DEFAULT_LIMITS) -> tuple[int, tuple[float, ...]] | None:
    return quick_sensor(payload, limits, to_ns(EARLIEST), to_ns(LATEST))


TIMES = [
    "2026-11-24T02:00:00",
    "2026-11-24T02:00:00Z",
    "2026-11-24T02:00:00+00:00",
    "2026-11-24T02:00:00-00:00",
    "2026-11-24T02:00:00+05:30",
    "2026-11-24T02:00:00-09:00",
    "2026-11-24T02:00:00+00:60",  # fromisoformat takes it, pydantic refuses it
    "2026-11-24T02:00:00+06:97",
    "2026-11-24T02:00:00+24:00",
    "2026-11-24T02:00:00+23:59",
    "2026-11-24T02:00:00.5Z",
    "2026-11-24T02:00:00.123456Z",
    "2026-11-24T02:00:00.1234567Z",  # 7 digits: pydantic truncates; the full path reads it
    "2026-11-24 02:00:00Z",
    "2026-11-24t02:00:00z",
    "2026-11-24",
    "2026-11-24T02:00Z",
    "2026-11-24T24:00:00Z",
    "2026-02-30T00:00:00Z",
    "2026-11-24T02:00:60Z",
    "1969-12-31T23:59:59Z",  # before inputs.earliest_time
    "1970-01-01T00:00:00Z",
    "1600-01-01T00:00:00Z",
    "2300-01-01T00:00:00Z",
    "9999-12-31T23:59:59-05:00",  # an offset past year 9999
    "0001-01-01T00:00:00+01:00",
    "2026-11-24T12:05:00Z",  # exactly the latest accepted
    "2026-11-24T12:05:00.000001Z",  # a microsecond after it
    "2026-11-24T13:00:00+01:00",  # the same instant as 12:00Z
    1795485600,
    None,
    "",
    "nan",
]

#: the forms senders use, all read the quick way
COMMON = [*TIMES[:6], "2026-11-24T02:00:00.5Z", "2026-11-24T02:00:00.123456Z"]

NUMBERS = [
    0.0,
    -0.0,
    1.0,
    0.5,
    1,
    0,
    80,
    1e-300,
    1e308,
    -1.0,
    1.0000001,
    -273.15,
    -273.1499,
    True,
    False,
    "0.5",
    None,
    [0.5],
    10**30,
    2**63,
    float("nan"),
    float("inf"),
]


def _payload(rng: random.Random) -> bytes:
    """A single-sample payload, mostly good, often with one thing wrong or unusual."""
    data: dict[str, object] = {"time": rng.choice(COMMON), **GOOD}
    for _ in range(rng.choice([0, 0, 1, 1, 2, 3])):
        name = rng.choice(["time", *GOOD])
        if name == "time":
            data["time"] = rng.choice(TIMES)
        elif rng.random() < 0.5:
            data[name] = rng.choice(NUMBERS)
        else:  # a plausible value near the bounds
            data[name] = rng.choice([rng.uniform(-0.1, 1.1), rng.uniform(0, 200), 30.0, 80.0])
    if rng.random() < 0.05:
        del data[rng.choice(list(data))]
    if rng.random() < 0.05:
        data["extra"] = rng.choice([1, "text", {"a": [1, 2]}, None])
    text = json.dumps(data)  # NaN and Infinity as the stdlib writes them
    if rng.random() < 0.03:  # a duplicate key: the last one counts, on both paths
        text = text[:-1] + ', "choke": 0.25}'
    if rng.random() < 0.02:
        return text.encode("utf-16")
    return text.encode()


def test_quick_sensor_never_disagrees_with_the_full_path() -> None:
    rng = random.Random(7)
    taken = refused = unsure = 0
    for _ in range(6000):
        payload = _payload(rng)
        full = full_path(payload)
        got = quick(payload)
        if got is None:
            unsure += 1
            refused += isinstance(full, str)
            continue
        assert not isinstance(full, str), (payload, full)  # never accepts a refused sample
        assert got[0] == full[0], payload  # the same time, to the nanosecond
        assert got[1] == full[1] and all(type(v) is float for v in got[1]), payload
        taken += 1
    # the quick path really takes most good samples, and the check met refusals too
    assert taken > 2000 and refused > 1000 and unsure >= refused, (taken, refused, unsure)


@pytest.mark.parametrize("when", COMMON)
def test_quick_sensor_reads_the_common_forms(when: str) -> None:
    payload = json.dumps({"time": when, **GOOD, "p_up": 80}).encode()
    got = quick(payload)
    assert got is not None and (got[0], got[1]) == full_path(payload)
    assert got[1] == (0.5, 80.0, 30.0, 60.0, 0.2, 0.5)


def test_quick_sensor_leaves_limits_to_the_full_path() -> None:
    padded = json.dumps({"time": "2026-11-24T02:00:00Z", **GOOD, "pad": "x" * 500}).encode()
    assert quick(padded) is not None
    assert quick(padded, Limits(max_bytes=200)) is None  # too large: the full path says so
    assert full_path(padded, Limits(max_bytes=200)) == "payload too large"
    nested = json.dumps({"time": "2026-11-24T02:00:00Z", **GOOD, "x": [[[[1]]]]}).encode()
    assert quick(nested, Limits(max_depth=3)) is None
    assert full_path(nested, Limits(max_depth=3)) == "too deeply nested"


def _rates(rng: random.Random) -> list[float | None]:
    pick = [
        rng.uniform(0, 500),
        rng.uniform(0, 1e-6),
        1e-7,
        1e22,
        0.1 + 0.2,
        float("nan"),
        float("inf"),
        None,
        np.float64(rng.uniform(0, 5)),
        np.float32(0.1),
        0,
        3,
    ]
    return [rng.choice(pick) for _ in range(6)]


def test_prediction_json_is_what_pydantic_writes() -> None:
    rng = random.Random(3)
    base = to_ns(datetime(2026, 11, 24, tzinfo=UTC))
    for k in range(500):
        t = base + rng.choice([0, 1_000, 123_456_000, 10**9]) * (k + 1)
        q_total = rng.uniform(0, 900)
        rest = _rates(rng)
        version = rng.choice([rng.randrange(0, 10**6), np.int64(4)])
        model = rng.choice(["mm", "mm+erosion", "ham"])
        ours = prediction_json(t, q_total, *rest[:3], model, version, *rest[3:])
        theirs = Prediction(
            time=from_ns(t),
            q_total=q_total,
            q_gas=rest[0],
            q_oil=rest[1],
            q_water=rest[2],
            model=model,
            version=version,
            q_total_std=rest[3],
            q_total_p05=rest[4],
            q_total_p95=rest[5],
        ).model_dump_json()
        assert json.loads(ours) == json.loads(theirs)  # null where not finite, on both
        assert Prediction.model_validate_json(ours).time == from_ns(t)
        plain = all(v is None or type(v) in (float, int) for v in rest)
        if plain:  # Python numbers: the very same bytes (an int rate written 3.0)
            assert ours == theirs.encode(), (ours, theirs)


def test_latency_histogram_counts_as_prometheus_does() -> None:
    rng = random.Random(5)
    values = [rng.choice([*LATENCY_BUCKETS_S, 0.0, 20.0]) for _ in range(500)]
    values += [rng.expovariate(200.0) for _ in range(2000)]
    ours = LatencyHistogram("lat_seconds", "latency", LATENCY_BUCKETS_S)
    registry = CollectorRegistry()
    theirs = Histogram("lat_seconds", "latency", buckets=LATENCY_BUCKETS_S, registry=registry)
    start = 0
    while start < len(values):  # a commit at a time, small ones (no numpy) and large ones
        size = rng.choice([1, 2, 15, 16, 256])
        ours.observe_many(values[start : start + size])
        start += size
    ours.observe_many([])
    for v in values:
        theirs.observe(v)
    (family,) = ours.collect()
    (theirs_family,) = registry.collect()
    assert (family.name, family.type, family.documentation) == (
        theirs_family.name,
        theirs_family.type,
        theirs_family.documentation,
    )
    got = {(s.name, tuple(s.labels.items())): s.value for s in family.samples}
    want = {(s.name, tuple(s.labels.items())): s.value for s in theirs_family.samples}
    assert list(got) == list(want)  # the same samples in the same order, _created too
    for key, value in want.items():
        if key[0].endswith("_created"):
            assert abs(got[key] - value) < 60.0
            continue
        assert math.isclose(got[key], value, rel_tol=1e-12), key
    assert got[("lat_seconds_count", ())] == len(values)


def test_to_ns_is_exact() -> None:
    rng = random.Random(11)
    epoch = datetime(1970, 1, 1, tzinfo=UTC)
    span_us = int(
        (datetime(2262, 4, 10, tzinfo=UTC) - datetime(1677, 9, 22, tzinfo=UTC))
        / timedelta(microseconds=1)
    )
    start = datetime(1677, 9, 22, tzinfo=UTC)
    for _ in range(20_000):
        when = start + timedelta(microseconds=rng.randrange(span_us))
        want = ((when - epoch) // timedelta(microseconds=1)) * 1000
        assert to_ns(when) == want
        assert to_ns(when.replace(tzinfo=None)) == want  # naive: UTC
        shifted = when.astimezone(timezone(timedelta(minutes=rng.randrange(-900, 900))))
        assert to_ns(shifted) == want
        assert from_ns(want) == when
    assert to_ns(epoch) == 0 and to_ns(epoch - timedelta(microseconds=1)) == -1000
    assert orjson.loads(prediction_json(0, 1.0, None, None, None, "mm", 1))["time"] == (
        "1970-01-01T00:00:00Z"
    )


def test_phase_split_numpy_is_phase_split() -> None:
    rng = np.random.default_rng(4)
    n = 5000
    x = np.column_stack(
        [
            rng.uniform(0, 1, n),
            rng.uniform(20, 300, n),
            rng.uniform(5, 20, n),
            rng.uniform(20, 120, n),
            rng.uniform(0, 1, n),
            np.zeros(n),
        ]
    )
    x[:, 5] = rng.uniform(0, 1, n) * (1.0 - x[:, 4])
    x[:10, 4:] = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [0.5, 0.5], [0.2, 0.0]] * 2
    q = rng.uniform(0, 800, n)
    want = phase_split(torch.from_numpy(q).reshape(n, 1), torch.from_numpy(x).reshape(n, 1, 6))
    got = phase_split_numpy(q, x)
    for name, values in want.items():
        assert np.array_equal(got[name], values[:, 0].numpy()), name  # to the last bit
