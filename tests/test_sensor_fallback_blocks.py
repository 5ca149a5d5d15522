"""The fallback in the block path (issue 39, item 3): a sensor block is answered as its rows
sent one by one, also when an instrument fault is raised, or ends, inside the block.

A block's rows are fed to the detectors before any is stored, and each row whose input has
an open fault of a kind that stands in is predicted with its fallback and a widened
interval, as a single sample would be; the rows without one keep the block's one model call.

The simulated field (seed 5583, one well, 0.8 years, p_up frozen for 30 days from day 200)
is used by no other test and sets no threshold: the test compares the two ways of sending
the same rows, which must agree.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pandas as pd
import pytest

from vfm_core.faults_sim import inject_fault
from vfm_core.sensor_faults import SENSORS

WELL = "W01"
BLOCK = 12  # rows per block: the fault's detection falls inside a block, not at its start


@pytest.fixture(scope="module")
def bad() -> pd.DataFrame:
    """One well's rows with p_up frozen for 30 days from day 200 (a frozen p_down holds
    nothing in this well's critical flow: tests/test_sensor_hold.py)."""
    from vfm_core.simulate import simulate_field

    obs = simulate_field(wells=1, years=0.8, seed=5583).observations.reset_index(drop=True)
    start = pd.to_datetime(obs["time"], utc=True).iloc[0] + pd.Timedelta(days=200)
    frame, _ = inject_fault(obs, WELL, "p_up", "frozen", start, days=30)
    return frame


def ns(times: pd.Series) -> np.ndarray:
    return pd.to_datetime(times, utc=True).dt.as_unit("ns").astype("int64").to_numpy()


@contextmanager
def running(folder: Path, method: str) -> Iterator[tuple[Any, Any, dict[int, Any]]]:
    """A loopback service (mm with ``method``), a field client, and what was published per
    sample time: the message's ``fallback`` (a block message has none: None)."""
    from replay.client import FieldClient
    from service.app import Service
    from service.testing import loopback_settings
    from service.transport import MemoryTransport

    settings = loopback_settings(folder, model={"name": "mm", "method": method})
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    published: dict[int, Any] = {}

    def on_message(key: str, payload: bytes) -> None:
        data = json.loads(payload)
        if isinstance(data["time"], list):  # a prediction block
            for t in data["time"]:
                published[pd.Timestamp(t).value] = None
        else:
            published[pd.Timestamp(data["time"]).value] = data["fallback"]

    service.start()
    unsubscribe = bus.subscribe(f"{settings.prefix}/{WELL}/prediction", on_message)
    try:
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service(WELL)
            yield service, client, published
    finally:
        unsubscribe()
        service.stop()


def send(service: Any, client: Any, rows: pd.DataFrame, blocks: bool, published: Any) -> None:
    """The rows in parts of :data:`BLOCK`: each part as one sensor block or as single
    samples, then the part's measurements; wait until all are handled and published."""
    from replay.client import sample_of
    from service.testing import wait_until
    from vfm_core.messages import Measurement

    expected = len(stored(service)[1]) + int((rows["source"] != "").sum())
    for first in range(0, len(rows), BLOCK):
        part = rows.iloc[first : first + BLOCK]
        times = [pd.Timestamp(t).to_pydatetime() for t in part["time"]]
        samples = [
            sample_of(t, x) for t, x in zip(times, part[list(SENSORS)].to_numpy(), strict=True)
        ]
        if blocks:
            client.send_block(WELL, samples)
        else:
            for sample in samples:
                client.send_sample(WELL, sample)
        for t, source, q in zip(times, part["source"], part["q_total"], strict=True):
            if source:
                client.send_measurement(WELL, str(source), Measurement(time=t, q_total=float(q)))
    last = int(ns(rows["time"])[-1])

    def done() -> bool:
        st = service.engine.wells.get(WELL)
        return st is not None and st.last_time_ns == last and not st.pending

    wait_until(done, 60, "every row to be handled")
    wait_until(lambda: last in published, 30, "the last prediction")
    # the measurements after the last sample are stored and settled after it

    def settled() -> bool:
        measurements = stored(service)[1]
        return len(measurements) == expected and all(m.status != "pending" for m in measurements)

    wait_until(settled, 30, "every measurement stored and settled")


def stored(service: Any) -> tuple[list[Any], list[Any]]:
    samples, measurements = service.store.history(WELL, 0, 2**62, 100_000)[:2]
    return samples, measurements


def view(service: Any) -> dict[str, Any]:
    from service.http import create_app

    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app=create_app(service))
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.get(f"/wells/{WELL}")

    out: dict[str, Any] = asyncio.run(go()).json()
    return out


def run(folder: Path, method: str, bad: pd.DataFrame, blocks: bool, cut: int) -> dict[str, Any]:
    """Send the rows up to ``cut``, read the well's view, send the rest; what came out."""
    with running(folder, method) as (service, client, published):
        send(service, client, bad.iloc[:cut], blocks, published)
        fallback_at_cut = view(service)["fallback"]
        send(service, client, bad.iloc[cut:], blocks, published)
        samples, measurements = stored(service)
        return {
            "samples": {s.time_ns: s for s in samples},
            "status": {(m.time_ns, m.source): m.status for m in measurements},
            "published": dict(published),
            "fallback_at_cut": fallback_at_cut,
            "fallback_at_end": view(service)["fallback"],
        }


def same_fallback(a: list[dict[str, Any]] | None, b: list[dict[str, Any]] | None) -> bool:
    """The same stand-ins (sensor, kind, since alike; numbers to rounding), or both None."""
    if a is None or b is None:
        return a is b
    return len(a) == len(b) and all(
        x.keys() == y.keys()
        and all(
            x[k] == pytest.approx(y[k], rel=1e-9) if isinstance(x[k], float) else x[k] == y[k]
            for k in x
        )
        for x, y in zip(a, b, strict=True)
    )


@pytest.mark.timeout(180)
@pytest.mark.parametrize("method", ["bayes", "ol"])  # with its own interval, and without
def test_a_block_gets_the_fallback_from_the_row_a_fault_is_raised_at(
    bad: pd.DataFrame, tmp_path: Path, method: str, predict_block_calls: list[int]
) -> None:
    calls = predict_block_calls
    times = ns(bad["time"])
    # cut the sending at a block's end inside the frozen run (its middle)
    frozen = np.flatnonzero(bad["p_up"].diff().to_numpy() == 0.0)
    cut = (int(np.median(frozen)) // BLOCK) * BLOCK
    one = run(tmp_path / "one", method, bad, blocks=False, cut=cut)
    assert calls == []
    block = run(tmp_path / "block", method, bad, blocks=True, cut=cut)

    # the fault stood in: its rows have a fallback, and it is raised inside a block
    flagged = sorted(t for t, f in one["published"].items() if f is not None)
    assert len(flagged) > 20
    assert {e["sensor"] for f in one["published"].values() if f for e in f} == {"p_up"}
    first = int(np.searchsorted(times, flagged[0]))
    assert first % BLOCK != 0, "the fault is raised at a block's first row: no test"
    assert one["fallback_at_cut"] is not None and one["fallback_at_cut"][0]["sensor"] == "p_up"

    # per row, the block path gives what one by one gives
    assert block["published"].keys() == one["published"].keys()
    assert len(one["published"]) >= len(times) - BLOCK  # all but the first part (no model yet)
    differ = [
        t for t in one["published"] if not same_fallback(block["published"][t], one["published"][t])
    ]
    assert differ == [], f"{len(differ)} row(s) differ, the first at {pd.Timestamp(differ[0])}"
    assert same_fallback(block["fallback_at_cut"], one["fallback_at_cut"])
    assert same_fallback(block["fallback_at_end"], one["fallback_at_end"])
    assert block["samples"].keys() == one["samples"].keys()
    for t, s in one["samples"].items():
        b = block["samples"][t]
        assert b.version == s.version and b.p_down == s.p_down, pd.Timestamp(t)
        for name in ("q_total", "q_gas", "q_oil", "q_water", "q_total_std", "q_total_p05",
                     "q_total_p95"):  # fmt: skip
            x, y = getattr(b, name), getattr(s, name)
            assert (x is None) == (y is None), (name, pd.Timestamp(t))
            if x is not None:
                assert x == pytest.approx(y, rel=1e-9), (name, pd.Timestamp(t))
    # an interval round the fallback's rate, with ol too (as wide as the rate moves over
    # the stand-in's span: zero wide where it does not move)
    flagged_rows = [block["samples"][t] for t in flagged]
    assert all(s.q_total_p05 <= s.q_total <= s.q_total_p95 for s in flagged_rows)
    assert block["status"] == one["status"]
    assert "held" in set(one["status"].values())  # learning held during the fault, both ways
    # and the block path kept its one model call per run of rows without a stand-in: every
    # row after the first part (no model yet: one by one) in a block call, but the rows with
    # a stand-in, each predicted on its own with its fallback
    assert sum(calls) + len(flagged) == len(times) - BLOCK, (sum(calls), len(flagged))
    assert max(calls) == BLOCK  # a block without a fault: one call
