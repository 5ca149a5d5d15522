"""The running service: store + engine + transport + HTTP API, started and stopped in order.

:class:`Service` owns the parts; :func:`serve` runs it with uvicorn in the foreground
(``vfm serve``); :func:`running` runs it on background threads for tests and the demo::

    with running(settings) as svc:                       # Zenoh, as configured
        print(svc.http_url, svc.locators)
    with running(settings, MemoryTransport()) as svc:    # the same, without a network
        ...

Start order: store, transport (the Zenoh session), engine (restore or fit), workers,
subscriber, HTTP. Stop order is the reverse, and every Zenoh session is closed in
``finally``. The HTTP app is built by :func:`service.http.create_app`, which is handed the
service and never imports this module.
"""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import socket
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from service.config import Settings
from service.diagnosis import DiagnosisJobs
from service.engine import Engine
from service.http import create_app
from service.inputs import Counters
from service.scaleout import (
    InstanceClaim,
    WellSet,
    check_no_overlap,
    declare_claim,
    owner_sentence,
)
from service.store import Store
from service.transport import MemoryTransport, Transport, ZenohTransport
from vfm_core.errors import ConfigError
from vfm_core.runtime import configure

__all__ = ["Service", "serve", "running", "bind_socket"]

logger = logging.getLogger("vfm.service")


class Service:
    """All parts of one service instance; see the module docstring."""

    def __init__(self, settings: Settings, transport: Transport | None = None) -> None:
        self.settings = settings
        self.counters = Counters()
        self.diagnoses = DiagnosisJobs(settings)
        self._transport = transport
        self.store: Store | None = None
        self.engine: Engine | None = None
        self.transport: Transport | None = None
        self.locators: list[str] = []
        self.http_url: str | None = None
        self.started_at = time.time()
        self.ready = False
        self.own = WellSet(settings.zenoh.wells)
        self._claim: Any = None

    def start(self) -> None:
        configure(self.settings.torch_threads)  # torch's threads, glibc's malloc
        s = self.settings
        self.store = Store(s.store.path, s.store.synchronous)
        try:
            if self._transport is None:
                zt = ZenohTransport(s.zenoh, s.prefix, s.queues.receive_capacity)
                zt.open()
                self._transport = zt
            if isinstance(self._transport, ZenohTransport):
                # claim the wells first, then look for another claim: two instances started
                # together see each other (both refuse) instead of neither
                self._claim = declare_claim(self._transport.session, s.prefix, self.claim)
                if s.zenoh.instance_check_s > 0:
                    check_no_overlap(
                        self._transport.session, s.prefix, s.zenoh.wells, s.zenoh.instance_check_s
                    )
            self.transport = self._transport
            flushes = getattr(self.transport, "flushes", None)
            if flushes is not None:  # a bad flush is counted as any refused input is
                flushes.on_refused = self.counters.reject
            self.engine = Engine(
                s,
                self.store,
                self.counters,
                self.transport.publish,
                self.transport.forget,
                self.transport.publish_key,
            )
            self.engine.load()
            if s.model.name in ("mm", "hem", "ham") and not s.model.effects:
                # the compiled steps: ready before the first measurement arrives
                from vfm_core.learning.kernels import warm

                warm()
            source = None
            if s.queues.receiver == "worker" and s.queues.workers == 1:
                source = self.transport.start_polled(self.engine.deliver)
            self.engine.start(source)
            if source is None:  # a receiver thread (more workers, or zenoh.wells patterns)
                self.transport.start(self.engine.deliver)
            self.locators = self.transport.locators()
        except BaseException:
            self.stop()
            raise
        self.ready = True
        logger.info(
            "Serving %d well(s) (of %s) with %s/%s on %s under '%s/**'; store %s.",
            len(self.engine.wells),
            self.own.describe(),
            s.model.name,
            s.model.method,
            "an in-memory transport"
            if isinstance(self.transport, MemoryTransport)
            else "Zenoh " + (", ".join(self.locators) or ", ".join(s.zenoh.connect)),
            s.prefix,
            s.store.path,
        )

    def stop(self) -> None:
        self.ready = False
        self.diagnoses.stop()
        try:
            if self.transport is not None:
                self.transport.stop_receiving()
            if self.engine is not None:
                self.engine.stop()
        finally:
            try:
                if self._claim is not None:
                    self._claim.undeclare()
                    self._claim = None
                if self.transport is not None:
                    self.transport.close()
            finally:
                self.transport = None
                if self.store is not None:
                    self.store.close()
                    self.store = None

    # -- scale-out ----------------------------------------------------------------------
    def claim(self) -> InstanceClaim:
        """What this instance answers on ``<prefix>/@instances/<zid>`` (see service.scaleout)."""
        transport = self.transport or self._transport
        session = getattr(transport, "session", None) if transport is not None else None
        return InstanceClaim(
            zid=str(session.zid()) if session is not None else "-",
            prefix=self.settings.prefix,
            wells=list(self.own.patterns),
            http=self.http_url,
            locators=list(self.locators),
            started_at=self.started_at,
        )

    def foreign_well(self, well: str) -> str | None:
        """For a well another instance owns: the sentence of the HTTP 404 (names the owner
        if it answers on Zenoh); None for a well of this instance."""
        if well in self.own:
            return None
        session = None
        if isinstance(self.transport, ZenohTransport):
            session = self.transport.session
        return owner_sentence(session, self.settings.prefix, self.own, well)

    # -- what the API shows ---------------------------------------------------------------
    def _limits(self) -> dict[str, Any]:
        return _limits_of(self.settings)

    def health(self) -> dict[str, Any]:
        """Status, accepted and refused inputs, events, queues and where the service listens."""
        snap = self.counters.snapshot()
        engine = self.engine
        depths = engine.queue_depths() if engine is not None else []
        pending = engine.pending_measurements() if engine is not None else 0
        return {
            "status": "ok" if self.ready else "starting",
            "uptime_s": round(time.time() - self.started_at, 3),
            "wells": len(engine.wells) if engine is not None else 0,
            "received": int(getattr(self.transport, "received", 0)),
            "accepted": snap["accepted"],
            "rejected": snap["rejected"],
            "rejected_total": sum(snap["rejected"].values()),
            "not_ready": snap["events"].get("model not ready", 0),
            "predictions_published": snap["events"].get("predictions published", 0),
            "learned": snap["events"].get("learned", 0),
            "overflow": snap["events"].get("overflow", 0),
            "queue_depths": depths,
            "queue_capacity": self.settings.queues.worker_capacity,
            "busy_wells": engine.busy_wells() if engine is not None else [],
            "retired_wells": len(engine.retired) if engine is not None else 0,
            "limits": self._limits(),
            "pending_measurements": pending,
            "events": snap["events"],
            "zenoh": {
                "mode": self.settings.zenoh.mode,
                "locators": self.locators,
                "connect": self.settings.zenoh.connect,
                "prefix": self.settings.prefix,
                "wells": list(self.own.patterns),
            },
            "owned_wells": self.own.describe(),
            "store": str(self.settings.store.path),
        }


def _limits_of(settings: Settings) -> dict[str, Any]:
    i, q, h, m = settings.inputs, settings.queues, settings.http, settings.model
    return {
        "max_payload_bytes": i.max_payload_bytes,
        "max_body_bytes": h.max_body_bytes,
        "max_json_depth": i.max_json_depth,
        "max_future_s": i.max_future_s,
        "earliest_time": i.earliest_time.isoformat(),
        "max_rate": i.max_rate,
        "rate_factor": i.rate_factor,
        "max_wells": i.max_wells,
        "new_wells_per_s": i.new_wells_per_s,
        "well_rate_hz": i.well_rate_hz,
        "well_capacity": q.well_capacity,
        "retrain_budget_s": m.retrain_budget_s,
        "min_retrain_period_s": m.min_retrain_period_s,
        "change_budget_s": m.change_budget_s,
    }


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket (port 0 = a free one), so the real port is known before serving."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise ConfigError(
            f"The HTTP API cannot listen on {host}:{port} ({exc.strerror}); choose another http.port "
            "(0 picks a free one)."
        ) from None
    sock.listen(128)
    sock.set_inheritable(True)
    return sock


def freeze_loaded_objects() -> int:
    """Exclude every object alive now from Python's cyclic garbage collector; returns how many.

    Called once the service is up (``queues.gc_freeze``). What is alive then is mostly the
    code of torch, pandas, pydantic, uvicorn and zenoh (some 400,000 functions, tuples and
    dicts): a full collection walks all of it and, measured under load on this 2-core
    machine, paused the workers 150-250 ms every 2 s (``benchmarks/bench_service.py
    --scenario flood``). Frozen objects are still freed by reference counting; only cycles
    among them are no longer looked for, and code and start-up state form none that end.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


class HeapFreezer:
    """Keeps what stays alive out of the cyclic garbage collector's full passes, as it grows.

    :func:`freeze_loaded_objects` at start-up leaves out the code; what the service makes
    afterwards and keeps (wells built after start, their state as it grows) would be walked
    by every full pass: measured with one freeze at start, the passes grew to 100-350 ms
    within 7 minutes at 1,000 wells and 1 Hz (``benchmarks/bench_service.py --seconds
    420``). :meth:`tick` (every ``every_s``) collects what was made since the last freeze
    (short: only that is walked) and freezes what survives. Frozen objects are still
    freed by reference counting, but not a cycle among them that becomes garbage: every
    ``thaw_s`` everything is unfrozen and collected once in full before freezing again.
    """

    def __init__(self, every_s: float, thaw_s: float, now: float) -> None:
        self.every_s = every_s
        self.thaw_s = thaw_s
        self.last = now
        self.last_thaw = now
        self.freezes = 0
        self.thaws = 0
        self.longest_s = 0.0

    def tick(self, now: float) -> bool:
        """Freeze again when ``every_s`` has passed (thaw first when ``thaw_s`` has);
        True when it did."""
        if self.every_s <= 0 or now - self.last < self.every_s:
            return False
        began = time.perf_counter()
        if now - self.last_thaw >= self.thaw_s:
            gc.unfreeze()
            self.last_thaw = now
            self.thaws += 1
        freeze_loaded_objects()
        self.longest_s = max(self.longest_s, time.perf_counter() - began)
        self.last = now
        self.freezes += 1
        return True


def _uvicorn_server(app: Any, settings: Settings, *, freeze_gc: bool = False) -> Any:
    import uvicorn

    config = uvicorn.Config(
        app,
        log_level="warning",
        access_log=False,
        lifespan="off",
        limit_concurrency=settings.http.max_connections,
        timeout_graceful_shutdown=settings.http.shutdown_grace_s,
    )

    class _Server(uvicorn.Server):
        async def startup(self, sockets: Any = None) -> None:
            await super().startup(sockets)
            if freeze_gc and self.started:  # uvicorn's own imports are done by now
                frozen = freeze_loaded_objects()
                logger.info(
                    "%d objects loaded at start-up left out of garbage collection "
                    "(queues.gc_freeze).",
                    frozen,
                )
                queues = settings.queues
                if queues.gc_refreeze_s > 0:
                    freezer = HeapFreezer(queues.gc_refreeze_s, queues.gc_thaw_s, time.monotonic())
                    self._vfm_refreeze = asyncio.get_running_loop().create_task(_refreeze(freezer))

        async def shutdown(self, sockets: Any = None) -> None:
            # live streams (GET /events) end now, not after http.shutdown_grace_s
            app.state.closing.set()
            await super().shutdown(sockets)

    return _Server(config)


async def _refreeze(freezer: HeapFreezer) -> None:
    """:meth:`HeapFreezer.tick` every ``every_s``, on the server's loop, until cancelled."""
    while True:
        await asyncio.sleep(freezer.every_s)
        freezer.tick(time.monotonic())
        if freezer.freezes % 60 == 1:
            logger.debug(
                "Heap frozen %d times (%d full), the longest %.0f ms.",
                freezer.freezes,
                freezer.thaws,
                freezer.longest_s * 1e3,
            )


def _url(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    host = f"[{host}]" if ":" in host else host
    return f"http://{host}:{port}"


class _StopServing(Exception):
    """SIGINT or SIGTERM: stop cleanly (uvicorn re-raises the signal after its own shutdown)."""


def _raise_stop(signum: int, frame: Any) -> None:
    raise _StopServing(signal.Signals(signum).name)


def serve(settings: Settings, on_ready: Callable[[Service], None] | None = None) -> int:
    """Run the service in the foreground until SIGINT/SIGTERM, then stop it cleanly."""
    main = threading.current_thread() is threading.main_thread()
    previous = (
        {sig: signal.signal(sig, _raise_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
        if main
        else {}
    )
    sock = bind_socket(settings.http.host, settings.http.port)
    service = Service(settings)
    try:
        service.start()
        service.http_url = _url(sock)
        server = _uvicorn_server(create_app(service), settings, freeze_gc=settings.queues.gc_freeze)
        if on_ready is not None:
            on_ready(service)
        server.run(sockets=[sock])
    except _StopServing as stop:
        logger.info("%s received: stopping.", stop)
    finally:
        try:
            service.stop()
            sock.close()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    logger.info("Stopped; the store %s is consistent.", settings.store.path)
    return 0


class _Running:
    def __init__(self, service: Service, server: Any, thread: threading.Thread) -> None:
        self.service = service
        self.server = server
        self.thread = thread

    @property
    def http_url(self) -> str:
        assert self.service.http_url is not None
        return self.service.http_url

    @property
    def locators(self) -> list[str]:
        return self.service.locators

    @property
    def engine(self) -> Engine:
        assert self.service.engine is not None
        return self.service.engine

    @property
    def transport(self) -> Transport:
        assert self.service.transport is not None
        return self.service.transport


@contextmanager
def running(settings: Settings, transport: Transport | None = None) -> Iterator[_Running]:
    """The service with its HTTP API on background threads; stopped (and Zenoh closed) on exit."""
    sock = bind_socket(settings.http.host, settings.http.port)
    service = Service(settings, transport)
    server = None
    thread = None
    try:
        service.start()
        service.http_url = _url(sock)
        server = _uvicorn_server(create_app(service), settings)
        thread = threading.Thread(
            target=server.run, kwargs={"sockets": [sock]}, name="vfm-http", daemon=True
        )
        thread.start()
        deadline = time.monotonic() + 10
        while not server.started and thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        yield _Running(service, server, thread)
    finally:
        if server is not None:
            server.should_exit = True
        if thread is not None:
            thread.join(10)
        service.stop()
        sock.close()
