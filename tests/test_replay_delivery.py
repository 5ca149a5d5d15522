"""A replay knows whether the service took in everything it sent, and when it has all been
answered: the flush (``<prefix>/_vfm-control/flush``, :class:`service.transport.Flushes`),
over Zenoh and in memory, with a busy service, a lossy link and a receiver thread."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pandas as pd
import pytest

from replay.replayer import replay_frame
from service.app import running
from service.engine import worker as worker_module
from service.engine.items import MeasurementItem
from service.testing import loopback_settings
from service.transport import MemoryTransport
from vfm_core.messages import FLUSH_KEY
from vfm_core.observations import validate_frame
from vfm_core.simulate import simulate_field

pytestmark = pytest.mark.timeout(240)

SPLIT = "2016-10-01"


@pytest.fixture(scope="module")
def field(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    folder = tmp_path_factory.mktemp("delivery")
    frame = validate_frame(simulate_field(wells=2, years=1, seed=4).observations).frame
    data = folder / "field.csv"
    frame.to_csv(data, index=False)
    return data, frame


def _settings(folder: Path, data: Path, **queues: Any) -> Any:
    model = {"name": "mm", "method": "ol", "history": str(data), "history_until": SPLIT}
    return loopback_settings(folder, model=model, queues=queues or {})


def _after_split(frame: pd.DataFrame) -> pd.DataFrame:
    return frame[frame["time"] >= pd.Timestamp(SPLIT, tz="UTC")]


@pytest.fixture
def slow_measurements(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Every measurement takes the worker 0.15 s more (a retrain, a loaded machine)."""
    handle = worker_module.Workers._handle

    def slow(self: Any, item: Any, b: Any) -> None:
        if isinstance(item, MeasurementItem):
            time.sleep(0.15)
        handle(self, item, b)

    monkeypatch.setattr(worker_module.Workers, "_handle", slow)
    yield


def test_over_zenoh_the_service_confirms_every_message(
    field: tuple[Path, pd.DataFrame], tmp_path: Path
) -> None:
    data, frame = field
    with running(_settings(tmp_path, data)) as svc:
        result = replay_frame(
            frame, connect=svc.locators, start=SPLIT, progress=False, idle_timeout=5.0
        )
    rows = _after_split(frame)
    sent = result.samples_sent + result.measurements_sent
    assert result.delivery is not None
    assert result.delivery.sent == sent == len(rows) + int((rows["source"] != "").sum())
    assert result.delivery.taken_in == sent and result.delivery.lost == 0
    assert result.delivery.done and result.missing == 0
    assert f"The service confirmed taking in all {sent:,} messages sent" in result.summary()
    assert "had handled every message" in result.summary()


def test_a_busy_service_is_waited_for_to_the_end_not_for_the_idle_timeout(
    field: tuple[Path, pd.DataFrame], tmp_path: Path, slow_measurements: None
) -> None:
    """Each measurement holds the worker longer than the idle timeout; before the flush the
    replay stopped at the first such pause and counted the rest as unanswered."""
    data, frame = field
    bus = MemoryTransport()
    with running(_settings(tmp_path, data), bus):
        result = replay_frame(
            frame, bus=bus, start=SPLIT, progress=False, idle_timeout=0.05, final_timeout=120
        )
    assert result.measurements_sent > 5  # pauses enough to have stopped the old wait
    assert result.delivery is not None and result.delivery.done
    assert result.missing == 0 and result.predictions_received == result.samples_sent


class _Lossy:
    """A bus that drops every ``every``-th sensor sample on the way (a link that loses)."""

    def __init__(self, bus: MemoryTransport, every: int) -> None:
        self.bus, self.every, self.n, self.dropped = bus, every, 0, 0

    def put(self, key: str, payload: bytes | str) -> None:
        if key.endswith("/sensors"):
            self.n += 1
            if self.n % self.every == 0:
                self.dropped += 1
                return
        self.bus.put(key, payload)

    def matching(self, key: str, timeout: float) -> bool:
        return self.bus.matching(key, timeout)

    def subscribe(self, key_expr: str, callback: Any) -> Any:
        return self.bus.subscribe(key_expr, callback)


def test_messages_lost_on_the_way_are_counted_and_said(
    field: tuple[Path, pd.DataFrame], tmp_path: Path
) -> None:
    data, frame = field
    bus = MemoryTransport()
    lossy = _Lossy(bus, every=10)
    with running(_settings(tmp_path, data), bus):
        result = replay_frame(frame, bus=lossy, start=SPLIT, progress=False, idle_timeout=1.0)
    assert lossy.dropped > 0
    assert result.delivery is not None and result.delivery.lost == lossy.dropped
    assert result.missing == lossy.dropped  # the dropped samples, none other
    assert f"at least {lossy.dropped:,} were lost between the two sessions" in result.summary()


def test_a_receiver_thread_confirms_what_it_took_in_but_not_when_done(
    field: tuple[Path, pd.DataFrame], tmp_path: Path
) -> None:
    """With a receiver thread (more workers) the service answers a flush once taken in;
    the replay then waits for the answers as before."""
    data, frame = field
    bus = MemoryTransport()
    with running(_settings(tmp_path, data, workers=2, receiver="thread"), bus):
        result = replay_frame(frame, bus=bus, start=SPLIT, progress=False, idle_timeout=2.0)
    assert result.delivery is not None
    assert result.delivery.taken_in == result.delivery.sent and not result.delivery.done
    assert result.missing == 0
    assert "does not say when it has handled them" in result.summary()


def test_a_bad_flush_is_refused_with_a_counted_reason(
    field: tuple[Path, pd.DataFrame], tmp_path: Path
) -> None:
    data, _ = field
    bus = MemoryTransport()
    answers: list[tuple[str, bytes]] = []
    with running(_settings(tmp_path, data), bus) as svc:
        bus.subscribe("vfm/_vfm-control/flushed/*", lambda k, p: answers.append((k, p)))
        bus.put(f"vfm/{FLUSH_KEY}", b"not an id!")
        bus.put(f"vfm/{FLUSH_KEY}", b"x" * 65)
        bus.put(f"vfm/{FLUSH_KEY}", b"good_id-1")
        deadline = time.monotonic() + 20
        while len(answers) < 2 and time.monotonic() < deadline:
            time.sleep(0.02)
        rejected = svc.service.counters.snapshot()["rejected"]
    assert rejected.get("bad flush") == 2
    assert [k for k, _ in answers] == ["vfm/_vfm-control/flushed/good_id-1"] * 2
    assert b'"done": false' in answers[0][1] and b'"done": true' in answers[1][1]


def test_flushes_are_bounded_in_rate_and_in_how_many_wait() -> None:
    """A flood of flushes costs the service little: beyond MAX_RATE a second they are
    refused (counted), and at most MAX_WAITING wait for the 'done' answer."""
    from service.transport import Flushes

    published: list[str] = []
    refused: list[str] = []
    flushes = Flushes("vfm", lambda key, body: published.append(key), lambda: 7)
    flushes.on_refused = lambda reason, sentence, where: refused.append(reason)
    for k in range(int(Flushes.MAX_RATE) + 5):  # at once: the burst, then refused
        flushes.take(f"id{k}".encode(), reports_done=True)
    assert len(published) == int(Flushes.MAX_RATE)
    assert refused == ["flush rate"] * 5
    flushes.idle()
    assert len(published) == 2 * int(Flushes.MAX_RATE)  # each answered again, done
    time.sleep(1.0)  # the bucket fills again at MAX_RATE a second
    flushes.waiting = [f"w{k}" for k in range(Flushes.MAX_WAITING)]
    flushes.take(b"late", reports_done=True)
    assert refused[-1] == "flush flood" and "late" not in flushes.waiting
    assert published[-1] == "vfm/_vfm-control/flushed/late"


class _Stopping:
    """A bus whose service stops after the replay's last message: nothing answers, and no
    subscriber matches the replay's keys any more."""

    def __init__(self) -> None:
        self.alive = True

    def put(self, key: str, payload: bytes | str) -> None:
        if key.endswith(FLUSH_KEY):
            self.alive = False  # the service stops before it takes the flush in

    def matching(self, key: str, timeout: float) -> bool:
        return self.alive

    def subscribe(self, key_expr: str, callback: Any) -> Any:
        return lambda: None


def test_a_service_that_stops_is_told_apart_from_a_busy_one() -> None:
    """Without a sign of life the replay asks whether the service still subscribes; one
    that stopped ends the wait in seconds, not after the 120 s a busy service is given."""
    from replay.client import FieldClient
    from replay.delivery import GONE_CHECK_S, await_delivery

    with FieldClient(_Stopping(), "vfm") as client:
        began = time.monotonic()
        out = await_delivery(
            client, {("W01", 0)}, sent=10, start=0, idle_timeout=1.0, final_timeout=60.0
        )
        waited = time.monotonic() - began
    assert out.gone and out.taken_in is None and not out.done
    assert GONE_CHECK_S <= waited < GONE_CHECK_S + 5.0, waited
    assert "went away" in out.line()


class _LateWord:
    """A bus whose service has answered every sample when it takes the last flush in, and
    says it is done ``late`` s after (a last measurement still being handled)."""

    def __init__(self, late: float) -> None:
        self.late, self.callback, self.timers = late, None, []

    def put(self, key: str, payload: bytes | str) -> None:
        if not key.endswith(FLUSH_KEY) or self.callback is None:
            return
        flush_id = payload.decode() if isinstance(payload, bytes) else payload
        key_out = f"vfm/_vfm-control/flushed/{flush_id}"

        def answer(done: bool) -> None:
            body = {"id": flush_id, "received": 3, "done": done, "reports_done": True}
            self.callback(key_out, json.dumps(body).encode())

        answer(False)
        timer = threading.Timer(self.late, answer, args=(True,))
        self.timers.append(timer)
        timer.start()

    def matching(self, key: str, timeout: float) -> bool:
        return True

    def subscribe(self, key_expr: str, callback: Any) -> Any:
        self.callback = callback
        return lambda: None


def test_the_services_word_is_waited_for_when_every_sample_is_already_answered() -> None:
    """CI at 2013bee: every sample was answered before the service's 'done' came, and the
    replay stopped at once and said the service does not tell when it is done."""
    from replay.client import FieldClient
    from replay.delivery import await_delivery

    bus = _LateWord(late=0.3)
    with FieldClient(bus, "vfm") as client:
        out = await_delivery(client, set(), sent=3, start=0, idle_timeout=10.0, final_timeout=60.0)
    assert out.done and out.taken_in == 3 and 0.3 <= out.waited_s < 5.0, out
    assert "had handled them all" in out.line()
    bus = _LateWord(late=30.0)  # a word that does not come: --idle-timeout bounds the wait
    with FieldClient(bus, "vfm") as client:
        out = await_delivery(client, set(), sent=3, start=0, idle_timeout=0.5, final_timeout=60.0)
    for timer in bus.timers:
        timer.cancel()
    assert not out.done and out.taken_in == 3 and out.waited_s < 5.0, out
