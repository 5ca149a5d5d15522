"""The service's link to a message bus, behind a small interface the engine does not know about.

:class:`Transport` is what the service needs: start receiving (each message handed to
``deliver(key, payload, received_ns)`` on a receiver thread), publish a prediction,
stop. Two implementations share that path:

:class:`ZenohTransport` subscribes to ``<prefix>/**`` (with ``zenoh.wells`` set, to
``<prefix>/<pattern>/**`` per pattern: see :mod:`service.scaleout`) with a FifoChannel (never a
callback: a slow callback would stall every subscriber of the session) and hands each
message to ``deliver(key, payload, received_ns)`` on its own receiver thread. Predictions
go out on ``<prefix>/<well>/prediction`` with BLOCK congestion control (DROP would lose
them under load), never back to this session's own subscriber. They are sent with
``Session.put``, not one declared publisher per well: with zenoh 1.10, every publisher
a session keeps declared under the prefix of the keys it receives makes each message the
session *receives* cost a match against them, in Zenoh's receiving thread. With 1,000
wells' prediction publishers declared, that was 138 µs of CPU a message, and it capped
what a service could take in at about 7,400 messages/s before any of its own work
(``benchmarks/bench_zenoh_keys.py``).

With one worker (``queues.receiver = "worker"``, the default) no receiver thread runs: the
worker takes the messages itself between its items (:meth:`ZenohTransport.start_polled`
gives it a :class:`Source`). Each Zenoh ``recv`` lets go of the GIL; with a receiver
thread beside a busy worker, every message handed the GIL from one thread to the other
and back, and that hand-over cost more than the message's own work. A worker with
nothing to do waits in ``recv``; a session-local message wakes it (work put in its queue
from elsewhere, e.g. a well test over HTTP; a tick every half second for its timers).

Zenoh facts this relies on are in ``/work/shared/notes/zenoh.md``: never the default
config (it joins multicast and listens everywhere), close every session (an open one
hangs the interpreter at exit), never fork after ``zenoh.open``.

:class:`MemoryTransport` is the same without a network, for tests and for embedding the
engine: inputs put on it reach ``deliver`` on its receiver thread, in order, and its
bounded queue makes a sender wait as a BLOCK publisher does; predictions are recorded and
handed to its subscribers. It also offers the field side that
:class:`replay.client.FieldClient` drives (``put``, ``matching``, ``subscribe``), so the
replay tool, the benchmark and the tests run the real engine code path either way.
"""

from __future__ import annotations

import abc
import functools
import json
import logging
import queue
import re
import secrets
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any, Protocol

import zenoh

from service.config import ZenohSettings
from service.engine.registry import TokenBucket
from service.scaleout import WellSet
from vfm_core.errors import ConfigError
from vfm_core.messages import FLUSH_KEY, FLUSHED_KEY, prediction_key

__all__ = [
    "Transport",
    "Source",
    "ZenohTransport",
    "MemoryTransport",
    "zenoh_config",
    "session_locators",
    "key_matches",
]

logger = logging.getLogger("vfm.service.transport")

Deliver = Callable[[str, bytes, int], None]


class Source(Protocol):
    """Messages taken by the worker's own thread, not by a receiver thread.

    :meth:`poll` hands up to ``limit`` messages that have arrived to ``deliver`` (never
    waits) while ``more()`` is true; :meth:`wait` blocks until a message arrives (handed on),
    :meth:`wake` is called, or half a second has passed, unless ``ready()`` is already true
    once waiting is announced (so a wake between the caller's last look and the wait is
    never lost); :attr:`stopped` turns true once :meth:`Transport.stop_receiving` was asked,
    after every message that arrived before it was handed on."""

    stopped: bool
    #: true while :meth:`wait` is under way (a put from elsewhere then calls :meth:`wake`)
    waiting: bool

    def poll(self, limit: int, more: Callable[[], bool]) -> int: ...

    def wait(self, ready: Callable[[], bool]) -> None: ...

    def wake(self) -> None:
        """From any thread: end a :meth:`wait` now (nothing happens if none is under way)."""
        ...


class Transport(Protocol):
    """What the service needs from a message bus."""

    def start(self, deliver: Deliver) -> None: ...

    def start_polled(self, deliver: Deliver) -> Source | None:
        """Receive without a thread of its own: the caller takes the messages through the
        returned :class:`Source`; None when this transport cannot (then :meth:`start`)."""
        ...

    def publish(self, well: str, payload: bytes) -> None: ...

    def publish_key(self, key: str, payload: bytes) -> None:
        """Put an output on ``key`` (a separator's allocation), as predictions are put."""
        ...

    def forget(self, well: str) -> None:
        """Let go of what is held for a retired well (e.g. its prediction key)."""
        ...

    def locators(self) -> list[str]: ...

    def stop_receiving(self) -> None: ...

    def close(self) -> None: ...


def zenoh_config(zs: ZenohSettings, *, admin: bool = True) -> zenoh.Config:
    """A zenoh.Config from the settings (never the default one, which joins multicast)."""
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(zs.mode))
    cfg.insert_json5("scouting/multicast/enabled", json.dumps(zs.multicast_scouting))
    cfg.insert_json5("listen/endpoints", json.dumps([] if zs.mode == "client" else zs.listen))
    cfg.insert_json5("connect/endpoints", json.dumps(zs.connect))
    cfg.insert_json5(
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        json.dumps(zs.block_wait_before_close_ms * 1000),  # microseconds
    )
    if admin:
        cfg.insert_json5("adminspace/enabled", "true")
    return cfg


def session_locators(session: zenoh.Session, timeout: float = 2.0) -> list[str]:
    """The endpoints the session actually listens on (port 0 resolved), from its admin space."""
    zid = str(session.zid())
    found: list[str] = []
    for mode in ("peer", "router", "client"):
        try:
            for reply in session.get(f"@/{zid}/{mode}", timeout=timeout):
                if reply.ok is None:
                    continue
                try:
                    info = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    continue
                if isinstance(info, dict):
                    found.extend(str(x) for x in info.get("locators", []))
        except zenoh.ZError:  # pragma: no cover - admin space off
            continue
        if found:
            break
    return found


class ZenohTransport:
    """Zenoh subscriber + receiver thread in, BLOCK puts per well out (no declared publishers)."""

    def __init__(self, settings: ZenohSettings, prefix: str, capacity: int = 4096) -> None:
        self.settings = settings
        self.prefix = prefix
        self.capacity = capacity
        self._session: zenoh.Session | None = None
        self._subscriber: zenoh.Subscriber | None = None
        self._thread: threading.Thread | None = None
        #: each well's prediction key, parsed once (not declared: see the module docstring)
        self._keys: dict[str, zenoh.KeyExpr] = {}
        self._stop_token = secrets.token_bytes(16)
        self._control_key = f"{prefix}/_vfm-control/stop"
        self.received = 0
        self._pattern_subs: list[zenoh.Subscriber] = []
        self._pattern_threads: list[threading.Thread] = []
        self._count_lock = threading.Lock()
        self._source: _ZenohSource | None = None
        self.flushes = Flushes(prefix, self.publish_key, lambda: self.received)

    def open(self) -> None:
        try:
            self._session = zenoh.open(zenoh_config(self.settings))
        except zenoh.ZError as exc:
            where = ", ".join(self.settings.connect or self.settings.listen)
            raise ConfigError(
                f"Zenoh could not start in {self.settings.mode} mode on {where}: "
                f"{str(exc).rstrip('. ')}. Check that the "
                "listen port is free (zenoh.listen) and, for a client, that the router runs (zenoh.connect)."
            ) from None

    @property
    def session(self) -> zenoh.Session:
        if self._session is None:
            raise RuntimeError("ZenohTransport.open() was not called")
        return self._session

    def start(self, deliver: Deliver) -> None:
        keys = WellSet(self.settings.wells).key_exprs(self.prefix)
        if len(keys) == 1 and keys[0] == f"{self.prefix}/**":
            self._start_all(deliver)
            return
        # scale-out: one subscriber per well pattern (the patterns are disjoint, so each
        # message arrives once), each with its FifoChannel and receiver thread; stopped by
        # undeclaring the subscriber, after which its channel is drained and its loop ends
        for i, key in enumerate(keys):
            sub = self.session.declare_subscriber(key, zenoh.handlers.FifoChannel(self.capacity))
            self._pattern_subs.append(sub)

            def receive(sub: zenoh.Subscriber = sub) -> None:
                for sample in sub:
                    with self._count_lock:
                        self.received += 1
                    key = str(sample.key_expr)
                    try:
                        deliver(key, sample.payload.to_bytes(), time.time_ns())
                    except Exception:  # a bug in one message must not end reception
                        logger.exception("Delivering %r failed", key[:200])

            thread = threading.Thread(target=receive, name=f"vfm-zenoh-receiver-{i}", daemon=True)
            self._pattern_threads.append(thread)
            thread.start()

    def start_polled(self, deliver: Deliver) -> Source | None:
        """One subscriber on ``<prefix>/**`` whose messages the caller takes (see
        :class:`Source`); None with ``zenoh.wells`` patterns (one subscriber and receiver
        thread per pattern: :meth:`start`)."""
        keys = WellSet(self.settings.wells).key_exprs(self.prefix)
        if not (len(keys) == 1 and keys[0] == f"{self.prefix}/**"):
            return None
        self._subscriber = self.session.declare_subscriber(
            f"{self.prefix}/**", zenoh.handlers.FifoChannel(self.capacity)
        )
        self._source = _ZenohSource(self, self._subscriber, deliver)
        return self._source

    def _start_all(self, deliver: Deliver) -> None:
        sub = self.session.declare_subscriber(
            f"{self.prefix}/**", zenoh.handlers.FifoChannel(self.capacity)
        )
        self._subscriber = sub
        stop_key, token = self._control_key, self._stop_token

        def receive() -> None:
            for sample in sub:
                key = str(sample.key_expr)
                if key == stop_key:
                    att = sample.attachment
                    if att is not None and secrets.compare_digest(att.to_bytes(), token):
                        return
                    continue
                if key == self.flushes.key:
                    self.flushes.take(sample.payload.to_bytes(), reports_done=False)
                    continue
                self.received += 1
                try:
                    deliver(key, sample.payload.to_bytes(), time.time_ns())
                except Exception:  # a bug in one message must not end reception
                    logger.exception("Delivering %r failed", key[:200])

        self._thread = threading.Thread(target=receive, name="vfm-zenoh-receiver", daemon=True)
        self._thread.start()

    def publish(self, well: str, payload: bytes) -> None:
        key = self._keys.get(well)
        if key is None:
            key = self._keys[well] = zenoh.KeyExpr(prediction_key(self.prefix, well))
        self.session.put(
            key,
            payload,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
            allowed_destination=zenoh.Locality.REMOTE,
        )

    def publish_key(self, key: str, payload: bytes) -> None:
        self.session.put(
            key,
            payload,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
            allowed_destination=zenoh.Locality.REMOTE,
        )

    def forget(self, well: str) -> None:
        """A retired well: let go of its prediction key (parsed again if it returns)."""
        self._keys.pop(well, None)

    def locators(self) -> list[str]:
        return session_locators(self.session)

    def stop_receiving(self, timeout: float = 10.0) -> None:
        """End the receiver thread (a local control message: recv cannot be interrupted)."""
        for sub in self._pattern_subs:
            sub.undeclare()
        for thread in self._pattern_threads:
            thread.join(timeout)
            if thread.is_alive():  # pragma: no cover - receiver stuck in deliver
                logger.warning("A Zenoh receiver thread did not stop within %.0f s.", timeout)
        self._pattern_subs.clear()
        self._pattern_threads.clear()
        source = self._source
        if source is not None and self._session is not None:
            self._session.put(
                self._control_key,
                b"",
                attachment=self._stop_token,
                allowed_destination=zenoh.Locality.SESSION_LOCAL,
            )
            if not source.stopped_event.wait(timeout):  # pragma: no cover - worker stuck
                logger.warning("The worker did not stop receiving within %.0f s.", timeout)
            source.close()
            self._source = None
        if self._thread is None or self._session is None:
            return
        self._session.put(
            self._control_key,
            b"",
            attachment=self._stop_token,
            allowed_destination=zenoh.Locality.SESSION_LOCAL,
        )
        self._thread.join(timeout)
        if self._thread.is_alive():  # pragma: no cover - receiver stuck in deliver
            logger.warning("The Zenoh receiver thread did not stop within %.0f s.", timeout)
        self._thread = None

    def close(self) -> None:
        try:
            self.stop_receiving()
            if self._subscriber is not None:
                try:
                    self._subscriber.undeclare()
                except zenoh.ZError:  # undeclared already
                    pass
                self._subscriber = None
            self._keys.clear()
        finally:
            if self._session is not None:
                self._session.close()
                self._session = None


_FLUSH_ID = re.compile(r"[A-Za-z0-9_-]{1,64}")


class Flushes:
    """A field client's flush: "have you taken in everything I sent before this?"

    The client puts its id (1-64 characters ``A-Za-z0-9_-``) on ``<prefix>/_vfm-control/flush``
    after its messages. Zenoh delivers one session's messages in order, so when the
    service takes the flush in, it has taken in every message that session sent before it.
    It answers on ``<prefix>/_vfm-control/flushed/<id>`` with ``{"id", "received", "done",
    "reports_done"}``: ``received`` its count of messages taken in (``GET /health``
    ``received``; the client compares its growth with what it sent), ``done`` false. A
    service whose one worker takes the messages itself (the default) answers again, with
    ``done`` true, once it has nothing left to do (every message taken in before the flush
    handled, stored and its answers published, so a client has them before that answer);
    ``reports_done`` says whether that second answer will come. A flush that names no valid
    id is refused with a counted reason (``bad flush``), and so are flushes beyond
    :attr:`MAX_RATE` a second (``flush rate``); at most :attr:`MAX_WAITING` wait for the
    second answer (more get the first only: ``flush flood``).
    """

    MAX_WAITING = 64
    #: flushes answered per second at most (a burst of as many): more are refused, counted
    MAX_RATE = 20

    def __init__(
        self, prefix: str, publish_key: Callable[[str, bytes], None], received: Callable[[], int]
    ) -> None:
        self.key = f"{prefix}/{FLUSH_KEY}"
        self._answer_prefix = f"{prefix}/{FLUSHED_KEY}/"
        self._publish = publish_key
        self._received = received
        #: flushes answered once, waiting for the worker to have nothing left to do
        self.waiting: list[str] = []
        #: ``Counters.reject(reason, sentence, where=key)`` for a flush refused (set by the app)
        self.on_refused: Callable[..., None] | None = None
        self._bucket = TokenBucket(self.MAX_RATE, int(self.MAX_RATE))

    def take(self, payload: bytes, reports_done: bool) -> None:
        """A flush taken in (from the thread that takes the messages)."""
        flush_id = payload.decode("ascii", "replace") if len(payload) <= 64 else ""
        if not _FLUSH_ID.fullmatch(flush_id):
            self._refuse(
                "bad flush",
                "A flush carries the id its answer goes to: 1-64 characters, letters, digits, "
                "'_' or '-'; it was not answered.",
            )
            return
        if not self._bucket.take():
            self._refuse(
                "flush rate",
                f"More than {self.MAX_RATE:g} flushes a second: this one was not answered "
                "(a replay sends two).",
            )
            return
        if reports_done and len(self.waiting) >= self.MAX_WAITING:
            self._refuse(
                "flush flood",
                f"More than {self.MAX_WAITING} flushes wait for the service to have nothing "
                "left to do; this one is answered once (taken in), not when done.",
            )
            reports_done = False
        self._answer(flush_id, done=False, reports_done=reports_done)
        if reports_done and flush_id not in self.waiting:
            self.waiting.append(flush_id)

    def idle(self) -> None:
        """The worker has nothing left to do: answer the flushes waiting for it."""
        if not self.waiting:
            return
        waiting, self.waiting = self.waiting, []
        for flush_id in waiting:
            self._answer(flush_id, done=True, reports_done=True)

    def _answer(self, flush_id: str, done: bool, reports_done: bool) -> None:
        body = {
            "id": flush_id,
            "received": int(self._received()),
            "done": done,
            "reports_done": reports_done,
        }
        try:
            self._publish(self._answer_prefix + flush_id, json.dumps(body).encode())
        except Exception as exc:  # the client went away: nothing to answer
            logger.debug("Answering flush %s failed: %s", flush_id, exc)

    def _refuse(self, reason: str, sentence: str) -> None:
        if self.on_refused is not None:
            self.on_refused(reason, sentence, where=self.key)
        else:
            logger.warning("%s", sentence)


class _PolledSource(abc.ABC):
    """What a :class:`Source` does whatever the bus: take messages while there are any
    (:meth:`poll`), or wait for the next (:meth:`wait`); a subclass says how to take one
    without waiting (:meth:`_try`), with waiting (:meth:`_block`: None when it gave up) and
    what one is (:meth:`_take`). A bus that is gone (:class:`_Gone`) stops receiving, never
    the worker: it then only works its queue."""

    def __init__(self, flushes: Flushes) -> None:
        self.stopped = False
        self.stopped_event = threading.Event()
        #: true while the worker is in (or about to enter) a wait
        self.waiting = False
        self.flushes = flushes

    @abc.abstractmethod
    def _try(self) -> Any:
        """A message that has arrived, or None (never waits)."""

    @abc.abstractmethod
    def _block(self) -> Any:
        """The next message, or None when the wait gave up (a wake, a timeout)."""

    @abc.abstractmethod
    def _take(self, message: Any) -> None:
        """Hand one message on (or act on a control message)."""

    def poll(self, limit: int, more: Callable[[], bool]) -> int:
        n = 0
        while n < limit and not self.stopped and more():
            try:
                message = self._try()
            except _Gone as exc:
                self._gone(exc)
                break
            if message is None:
                break
            self._take(message)
            n += 1
        return n

    def wait(self, ready: Callable[[], bool]) -> None:
        if self.stopped:
            return
        self.waiting = True
        try:
            if ready():
                return
            self.flushes.idle()  # everything taken in before is handled and answered
            message = self._block()
        except _Gone as exc:
            self._gone(exc)
            return
        finally:
            self.waiting = False
        if message is not None:
            self._take(message)

    def _stop(self) -> None:
        self.stopped = True
        self.stopped_event.set()

    def _gone(self, exc: Exception) -> None:
        logger.warning("The subscription ended (%s); no more messages are taken.", exc)
        self._stop()


class _Gone(Exception):
    """The bus's subscription is gone (e.g. undeclared by a close that did not wait)."""


class _ZenohSource(_PolledSource):
    """The :class:`Source` of :meth:`ZenohTransport.start_polled`: ``try_recv`` / ``recv``
    on the subscriber's FifoChannel from the worker's thread; woken by a session-local
    message on ``<prefix>/_vfm-control/wake`` (from :meth:`wake`, and every half second
    from a ticker thread while the worker waits)."""

    #: how often a waiting worker is woken for its timers (s)
    tick_s = 0.5

    def __init__(self, transport: ZenohTransport, sub: zenoh.Subscriber, deliver: Deliver) -> None:
        super().__init__(transport.flushes)
        self.transport = transport
        self._sub = sub
        self._deliver = deliver
        self._stop_key = transport._control_key
        self._wake_key = zenoh.KeyExpr(f"{transport.prefix}/_vfm-control/wake")
        self._control = f"{transport.prefix}/_vfm-control/"
        self._token = transport._stop_token
        self._closed = threading.Event()
        self._ticker = threading.Thread(target=self._tick, name="vfm-zenoh-ticker", daemon=True)
        self._ticker.start()

    def _try(self) -> zenoh.Sample | None:
        try:
            return self._sub.try_recv()
        except zenoh.ZError as exc:
            raise _Gone(str(exc)) from None

    def _block(self) -> zenoh.Sample:
        try:
            return self._sub.recv()
        except zenoh.ZError as exc:
            raise _Gone(str(exc)) from None

    def _take(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if key.startswith(self._control):
            if key == self.flushes.key:
                self.flushes.take(sample.payload.to_bytes(), reports_done=True)
                return
            att = sample.attachment
            if att is not None and secrets.compare_digest(att.to_bytes(), self._token):
                if key == self._stop_key:
                    self._stop()
            return
        self.transport.received += 1
        try:
            self._deliver(key, sample.payload.to_bytes(), time.time_ns())
        except Exception:  # a bug in one message must not end reception
            logger.exception("Delivering %r failed", key[:200])

    def wake(self) -> None:
        if not self.waiting or self.stopped:
            return
        session = self.transport._session
        if session is None:  # pragma: no cover - closed under us
            return
        try:
            session.put(
                self._wake_key,
                b"",
                attachment=self._token,
                allowed_destination=zenoh.Locality.SESSION_LOCAL,
            )
        except zenoh.ZError as exc:  # pragma: no cover - session closing
            logger.debug("Waking the worker failed: %s", exc)

    def _tick(self) -> None:
        while not self._closed.wait(self.tick_s):
            self.wake()

    def close(self) -> None:
        self._closed.set()
        self._ticker.join(2.0)


@functools.lru_cache(maxsize=65_536)  # asked once per prediction and subscriber
def key_matches(expr: str, key: str) -> bool:
    """Whether ``key`` matches the key expression ``expr`` (``*`` one chunk, ``**`` any)."""

    def match(e: list[str], k: list[str]) -> bool:
        if not e:
            return not k
        if e[0] == "**":
            return any(match(e[1:], k[i:]) for i in range(len(k) + 1))
        return bool(k) and (e[0] == "*" or e[0] == k[0]) and match(e[1:], k[1:])

    return match(expr.split("/"), key.split("/"))


class MemoryTransport:
    """Inputs in and predictions out in memory, on the same receiver-thread path as Zenoh.

    ``capacity`` bounds the receive queue (as ``queues.receive_capacity`` bounds Zenoh's
    FifoChannel); :attr:`published` keeps the latest ``keep`` predictions as
    ``(key, payload)``. Subscribers are called on the worker thread that publishes, so
    they must be quick and must not put inputs themselves.
    """

    def __init__(self, prefix: str = "vfm", capacity: int = 4096, keep: int = 100_000) -> None:
        self.prefix = prefix
        self.received = 0
        self.published: deque[tuple[str, bytes]] = deque(maxlen=keep)
        #: wells the engine let go of (retired), in order
        self.forgotten: list[str] = []
        #: each well's prediction key (made once: the well id is checked when it is made)
        self._keys: dict[str, str] = {}
        # None: stop; _WAKE: end a wait (a Source's)
        self._inbox: queue.Queue[tuple[str, bytes] | None] = queue.Queue(capacity)
        self._thread: threading.Thread | None = None
        self._source: _MemorySource | None = None
        self._receiving = threading.Event()
        self._subscribers: dict[int, tuple[str, Callable[[str, bytes], None]]] = {}
        self._sub_lock = threading.Lock()
        self._next_id = 0
        self.flushes = Flushes(prefix, self.publish_key, lambda: self.received)

    # -- the service's side (Transport) ---------------------------------------------------
    def start_polled(self, deliver: Deliver) -> Source | None:
        """The caller takes the inputs put on this transport (see :class:`Source`)."""
        self._source = _MemorySource(self, deliver)
        self._receiving.set()
        return self._source

    def start(self, deliver: Deliver) -> None:
        inbox = self._inbox

        def receive() -> None:
            while (message := inbox.get()) is not None:
                if message is _WAKE:
                    continue
                key, payload = message
                if key == self.flushes.key:
                    self.flushes.take(payload, reports_done=False)
                    continue
                self.received += 1
                try:
                    deliver(key, payload, time.time_ns())
                except Exception:  # a bug in one message must not end reception
                    logger.exception("Delivering %r failed", key[:200])

        self._thread = threading.Thread(target=receive, name="vfm-memory-receiver", daemon=True)
        self._receiving.set()
        self._thread.start()

    def forget(self, well: str) -> None:
        self.forgotten.append(well)

    def publish(self, well: str, payload: bytes) -> None:
        key = self._keys.get(well)
        if key is None:
            key = prediction_key(self.prefix, well)
            if len(self._keys) < 65_536:
                self._keys[well] = key
        self.publish_key(key, payload)

    def publish_key(self, key: str, payload: bytes) -> None:
        self.published.append((key, payload))
        with self._sub_lock:
            subscribers = list(self._subscribers.values())
        for expr, callback in subscribers:
            if key_matches(expr, key):
                callback(key, payload)

    def locators(self) -> list[str]:
        return []

    def stop_receiving(self, timeout: float = 10.0) -> None:
        """End the receiver thread once it has handed on what was put before."""
        source = self._source
        if source is not None:
            self._receiving.clear()
            self._inbox.put(None)
            if not source.stopped_event.wait(timeout):  # pragma: no cover - worker stuck
                logger.warning("The worker did not stop receiving within %.0f s.", timeout)
            self._source = None
        if self._thread is None:
            return
        self._receiving.clear()
        self._inbox.put(None)
        self._thread.join(timeout)
        if self._thread.is_alive():  # pragma: no cover - receiver stuck in deliver
            logger.warning("The memory receiver thread did not stop within %.0f s.", timeout)
        self._thread = None

    def close(self) -> None:
        self.stop_receiving()
        with self._sub_lock:
            self._subscribers.clear()

    # -- the field's side (what replay.client.FieldClient needs) ---------------------------
    def put(self, key: str, payload: bytes | str) -> None:
        """Send an input; waits while the receive queue is full (like a BLOCK publisher)."""
        self._inbox.put((key, payload.encode() if isinstance(payload, str) else payload))

    def matching(self, key: str, timeout: float) -> bool:
        """Whether a service receives ``key`` (waits up to ``timeout`` s for it to start)."""
        return self._receiving.wait(timeout) and key.startswith(self.prefix + "/")

    def subscribe(
        self, key_expr: str, callback: Callable[[str, bytes], None]
    ) -> Callable[[], None]:
        """Call ``callback(key, payload)`` for every prediction matching ``key_expr``; returns
        the function that ends the subscription."""
        with self._sub_lock:
            token = self._next_id
            self._next_id += 1
            self._subscribers[token] = (key_expr, callback)

        def unsubscribe() -> None:
            with self._sub_lock:
                self._subscribers.pop(token, None)

        return unsubscribe


#: what :meth:`_MemorySource.wake` puts in a memory transport's inbox, and what its source
#: makes of the stop (a None) in it (both told apart by identity)
_WAKE: tuple[str, bytes] = ("", b"wake")
_STOP: tuple[str, bytes] = ("", b"stop")


class _MemorySource(_PolledSource):
    """The :class:`Source` of :meth:`MemoryTransport.start_polled`: the inbox read from
    the worker's thread (a ``None`` in it: stop; :data:`_WAKE`: end a wait)."""

    def __init__(self, transport: MemoryTransport, deliver: Deliver) -> None:
        super().__init__(transport.flushes)
        self.transport = transport
        self._deliver = deliver
        self._inbox = transport._inbox

    def _try(self) -> tuple[str, bytes] | None:
        try:
            message = self._inbox.get_nowait()
        except queue.Empty:
            return None
        return _STOP if message is None else message

    def _block(self) -> tuple[str, bytes] | None:
        try:
            message = self._inbox.get(timeout=0.5)
        except queue.Empty:
            return None
        return _STOP if message is None else message

    def _take(self, message: tuple[str, bytes]) -> None:
        if message is _STOP:
            self._stop()
            return
        if message is _WAKE:
            return
        key, payload = message
        if key == self.flushes.key:
            self.flushes.take(payload, reports_done=True)
            return
        self.transport.received += 1
        try:
            self._deliver(key, payload, time.time_ns())
        except Exception:  # a bug in one message must not end reception
            logger.exception("Delivering %r failed", key[:200])

    def wake(self) -> None:
        if self.waiting and not self.stopped:
            try:
                self._inbox.put_nowait(_WAKE)
            except queue.Full:  # full: the wait ends on what is in it
                pass
