"""Who takes the messages from the bus: the one worker itself (``queues.receiver =
"worker"``, the default), or a receiver thread (``"thread"``).

With the worker as receiver there is no thread to wait on a full queue: a message that
does not fit is held, the worker works its queue and tries it again, and drops and counts
it once ``queues.block_s`` has passed. A worker with nothing to do waits in Zenoh's
``recv``; work put in its queue from elsewhere (a well test over HTTP) wakes it.
"""

from __future__ import annotations

import json
import threading
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import zenoh

from replay.client import FieldClient, sample_of
from service.app import Service
from service.engine.fairqueue import FairQueue
from service.engine.intake import Intake
from service.engine.registry import Registry
from service.inputs import Counters
from service.testing import loopback_settings
from service.transport import MemoryTransport, ZenohTransport, zenoh_config
from vfm_core.messages import Measurement

pytestmark = pytest.mark.timeout(120)

T0 = datetime(2020, 3, 1, 6, 0, tzinfo=UTC)
INPUTS = (0.4, 120.0, 30.0, 60.0, 0.1, 0.6)  # fraction, bar a, bar a, degC, -, -


def _sample(when: datetime) -> bytes:
    names = ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil")
    return json.dumps({"time": when.isoformat(), **dict(zip(names, INPUTS, strict=True))}).encode()


def test_a_message_that_does_not_fit_is_held_then_queued_or_dropped_and_counted(
    tmp_path: Path,
) -> None:
    settings = loopback_settings(tmp_path, queues={"block_s": 0.3})
    counters = Counters()
    q = FairQueue(capacity=100, well_capacity=1)
    intake = Intake(settings, counters, Registry(settings, {}), [q])
    intake.hold = True
    now = datetime.now(UTC) - timedelta(minutes=5)
    key = f"{settings.prefix}/W01/sensors"
    intake.deliver(key, _sample(now), time.time_ns())
    intake.deliver(key, _sample(now + timedelta(seconds=1)), time.time_ns())
    # the second did not fit the well's queue (1 message): held, not waited for
    assert intake.held is not None and q.depth("W01") == 1
    assert not intake.retry_held()  # still no room, still within block_s
    first = q.get_nowait()
    assert intake.retry_held() and intake.held is None  # room: queued, in order
    second = q.get_nowait()
    assert first.time_ns < second.time_ns
    # a held message that finds no room within block_s is dropped with its reason
    intake.deliver(key, _sample(now + timedelta(seconds=2)), time.time_ns())
    intake.deliver(key, _sample(now + timedelta(seconds=3)), time.time_ns())
    assert intake.held is not None
    time.sleep(0.35)
    assert intake.retry_held() and intake.held is None
    assert counters.snapshot()["rejected"] == {"well flooding": 1}
    assert counters.snapshot()["events"]["backpressure waits"] == 2


def test_the_worker_takes_zenoh_messages_itself_and_a_wake_ends_its_wait(tmp_path: Path) -> None:
    settings = loopback_settings(tmp_path)
    transport = ZenohTransport(settings.zenoh, settings.prefix, capacity=64)
    transport.open()
    got: list[tuple[str, bytes]] = []
    try:
        source = transport.start_polled(lambda key, payload, _ns: got.append((key, payload)))
        assert source is not None
        source.tick_s = 3600.0  # type: ignore[attr-defined]  # no tick: only a wake ends a wait
        # a message from another session is taken by poll, on the caller's thread
        cfg = zenoh_config(
            settings.zenoh.model_copy(update={"listen": [], "connect": transport.locators()}),
            admin=False,
        )
        with zenoh.open(cfg) as field:
            deadline = time.monotonic() + 20
            while not got and time.monotonic() < deadline:
                field.put(f"{settings.prefix}/W01/sensors", b"{}")
                time.sleep(0.05)
                source.poll(10, lambda: True)
        assert got and got[0] == (f"{settings.prefix}/W01/sensors", b"{}")
        # a wait with nothing to take ends on a wake from another thread
        ended = threading.Event()

        def wait() -> None:
            source.wait(lambda: False)
            ended.set()

        waiter = threading.Thread(target=wait, daemon=True)
        waiter.start()
        deadline = time.monotonic() + 10
        while not source.waiting and time.monotonic() < deadline:
            time.sleep(0.01)
        assert source.waiting and not ended.is_set()
        source.wake()
        assert ended.wait(10), "the wake did not end the wait"
        # ready() true once waiting is announced: no wait at all
        source.wait(lambda: True)

        def work() -> None:  # as the worker: take what comes, wait when there is nothing
            while not source.stopped:
                source.poll(10, lambda: True)
                source.wait(lambda: False)

        worker = threading.Thread(target=work, daemon=True)
        worker.start()
        began = time.monotonic()
        transport.stop_receiving()  # its stop message ends the worker's wait
        assert source.stopped and time.monotonic() - began < 10
        worker.join(10)
        assert not worker.is_alive()
    finally:
        transport.close()


@pytest.mark.parametrize("receiver", ["worker", "thread"])
def test_a_well_test_posted_while_the_worker_waits_is_answered(
    tmp_path: Path, receiver: str
) -> None:
    """The worker waits in the bus; a well test put in its queue from another thread (as
    over HTTP) wakes it and is learned: the next prediction is the well test's rate."""
    settings = loopback_settings(
        tmp_path, model={"name": "last", "method": "ol"}, queues={"receiver": receiver}
    )
    bus = MemoryTransport(settings.prefix)
    service = Service(settings, bus)
    service.start()
    try:
        assert service.engine is not None
        with FieldClient(bus, settings.prefix) as client:
            client.wait_for_service("W01")
            client.send_sample("W01", sample_of(T0, INPUTS))
            deadline = time.monotonic() + 20
            while not service.engine.has_well("W01") and time.monotonic() < deadline:
                time.sleep(0.02)
            began = time.monotonic()
            future = service.engine.submit_well_test("W01", Measurement(time=T0, q_total=800.0))
            result = future.result(timeout=20)
            assert time.monotonic() - began < 20
            assert result.status == "learned"
            later = T0 + timedelta(minutes=5)
            client.send_sample("W01", sample_of(later, INPUTS))
            assert client.wait_for_prediction("W01", later) == pytest.approx(800.0)
        threads = {t.name for t in threading.enumerate()}
        assert ("vfm-memory-receiver" in threads) == (receiver == "thread")
    finally:
        service.stop()


def test_a_subscriber_gone_under_the_worker_ends_receiving_not_the_worker(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    settings = loopback_settings(tmp_path)
    transport = ZenohTransport(settings.zenoh, settings.prefix, capacity=16)
    transport.open()
    try:
        source = transport.start_polled(lambda *_: None)
        assert source is not None
        source._sub.undeclare()  # type: ignore[attr-defined]  # as a close that did not wait
        assert source.poll(10, lambda: True) == 0  # no exception: the worker goes on
        assert source.stopped
        source.wait(lambda: False)  # returns at once
        assert "no more messages are taken" in caplog.text
    finally:
        transport.close()
