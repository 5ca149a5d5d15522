"""The field side of the streaming interface: publish a field's inputs, collect the predictions.

One client for the replay tool (``vfm replay``), the service benchmark and the tests.
:class:`FieldClient` publishes sensor samples and measurements of wells on a
:class:`FieldBus` and collects the predictions the service answers with: by (well,
sample time), with a count, the latest answered sample time per well and, if asked, the
latency from sending a sample to receiving its prediction. Two buses fit:

* :class:`ZenohBus`: a Zenoh session that connects only (no multicast, no listener), puts
  with BLOCK congestion control on a key only once the service's subscriber has matched
  it (nothing reaches a subscriber that has not matched), and a FifoChannel subscriber
  read by its own thread (never a callback: a slow one would stall the session). A key's
  publisher is declared only to see that match, then undeclared: with zenoh 1.10, every
  publisher a session keeps declared under the prefix of the keys it receives makes each
  message it receives (here, the predictions) cost a match against them, 138 µs a message
  with 1,000 wells' publishers (``benchmarks/bench_zenoh_keys.py``).
* :class:`service.transport.MemoryTransport`: the service's in-memory transport offers
  the same three methods, so the same client drives the real engine without a network.
  This package does not import ``service``: the bus is handed in.

Payloads are the pydantic models of :mod:`vfm_core.messages`; units as in the observation
format (fraction 0..1, bar a, degC, Sm3/h).
"""

from __future__ import annotations

import json
import logging
import secrets
import threading
import time
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Protocol

import numpy as np
import pandas as pd
import zenoh
from pydantic import ValidationError
from tqdm import tqdm

from vfm_core import observations
from vfm_core.errors import ConfigError, VFMError
from vfm_core.messages import (
    FLUSH_KEY,
    FLUSHED_KEY,
    Measurement,
    SensorSample,
    measurement_key,
    sample_outside_span,
    sensor_block,
    sensors_key,
    validate_prefix,
)
from vfm_core.schema import INPUT_COLUMNS, SOURCE, SOURCES, TARGET, TIME, WELL
from vfm_core.timeutil import to_ns

__all__ = [
    "FieldBus",
    "FieldClient",
    "FlushAnswer",
    "ZenohBus",
    "Streamed",
    "ReplayError",
    "field_config",
    "sample_of",
]

logger = logging.getLogger("vfm.replay.client")


class ReplayError(VFMError):
    """The field side could not run: no service matched, or the link closed."""


def _no_service(key: str, timeout: float) -> ReplayError:
    return ReplayError(
        f"No service subscribes to {key} after {timeout:g} s. Start `vfm serve` first, and check "
        "that --connect points at its Zenoh endpoint (or the router) and --prefix matches."
    )


class FieldBus(Protocol):
    """What the field client needs of a message bus."""

    def put(self, key: str, payload: bytes | str) -> None:
        """Send one message; in order per bus; waits while the receiver cannot take it."""
        ...

    def matching(self, key: str, timeout: float) -> bool:
        """Whether a service subscribes to ``key`` (waiting up to ``timeout`` s)."""
        ...

    def subscribe(
        self, key_expr: str, callback: Callable[[str, bytes], None]
    ) -> Callable[[], None]:
        """Call ``callback(key, payload)`` per message on ``key_expr``; returns the unsubscribe."""
        ...


def field_config(
    connect: Sequence[str], *, mode: str = "peer", block_wait_before_close_ms: int = 600_000
) -> zenoh.Config:
    """A loopback-safe Zenoh config for the field side: connect only, no multicast, no listener.

    ``block_wait_before_close_ms``: how long a BLOCK put may wait for a busy service before
    Zenoh closes the link (its default, 5 s, is too short for a replay).
    """
    if mode not in ("peer", "client"):
        raise ConfigError(f"Zenoh mode '{mode}' is not valid for replay; choose peer or client.")
    if not connect:
        raise ConfigError("Give at least one --connect endpoint, e.g. tcp/127.0.0.1:7447.")
    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps(mode))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("listen/endpoints", "[]")
    cfg.insert_json5("connect/endpoints", json.dumps(list(connect)))
    cfg.insert_json5(
        "transport/link/tx/queue/congestion_control/block/wait_before_close",
        json.dumps(block_wait_before_close_ms * 1000),  # microseconds
    )
    return cfg


class ZenohBus:
    """The field side on Zenoh: BLOCK puts on keys once matched, FifoChannel subscribers.

    Close it (or use ``with``): an open session hangs the interpreter at exit.
    """

    #: after the first match, wait this long so the service also sees our subscriber, s
    SETTLE_S = 0.3

    def __init__(
        self, session: zenoh.Session, *, match_timeout: float = 30.0, capacity: int = 65536
    ) -> None:
        self.session = session
        self.match_timeout = match_timeout
        self.capacity = capacity
        #: the keys the service has matched, parsed once (none stays declared)
        self._matched: dict[str, zenoh.KeyExpr] = {}
        self._settled = False

    @classmethod
    def connect(
        cls,
        connect: Sequence[str],
        *,
        mode: str = "peer",
        block_wait_before_close_ms: int = 600_000,
        match_timeout: float = 30.0,
        capacity: int = 65536,
    ) -> ZenohBus:
        """A session that connects to ``connect`` (the service or a router)."""
        cfg = field_config(
            connect, mode=mode, block_wait_before_close_ms=block_wait_before_close_ms
        )
        return cls(zenoh.open(cfg), match_timeout=match_timeout, capacity=capacity)

    def matching(self, key: str, timeout: float) -> bool:
        """True once a subscriber (the service's) matches ``key``; False after ``timeout`` s.

        Asks Zenoh each time (a publisher declared for the question, then undeclared);
        :meth:`put` asks only before its first message on a key."""
        pub = self.session.declare_publisher(key)
        try:
            deadline = time.monotonic() + timeout
            # the stubs say bool, zenoh 1.10 returns a MatchingStatus (always truthy): read .matching
            while not getattr(pub.matching_status, "matching", False):
                if time.monotonic() > deadline:
                    return False
                time.sleep(0.01)
        finally:
            pub.undeclare()
        self._matched[key] = zenoh.KeyExpr(key)
        if not self._settled:
            self._settled = True
            time.sleep(self.SETTLE_S)
        return True

    def put(self, key: str, payload: bytes | str) -> None:
        """Publish on ``key``; the first time, wait for the service to match (else ReplayError)."""
        expr = self._matched.get(key)
        if expr is None:
            if not self.matching(key, self.match_timeout):
                raise _no_service(key, self.match_timeout)
            expr = self._matched[key]
        self.session.put(
            expr,
            payload,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def subscribe(
        self, key_expr: str, callback: Callable[[str, bytes], None]
    ) -> Callable[[], None]:
        sub = self.session.declare_subscriber(key_expr, zenoh.handlers.FifoChannel(self.capacity))

        def read() -> None:
            for sample in sub:  # ends when the subscriber is undeclared
                try:
                    callback(str(sample.key_expr), sample.payload.to_bytes())
                except Exception:  # one bad message must not end reception
                    logger.exception("Handling a message on %s failed", sample.key_expr)

        thread = threading.Thread(target=read, name="vfm-field-rx", daemon=True)
        thread.start()

        def unsubscribe() -> None:
            sub.undeclare()
            thread.join(5)

        return unsubscribe

    def close(self) -> None:
        self._matched.clear()
        self.session.close()

    def __enter__(self) -> ZenohBus:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def sample_of(
    when: datetime, inputs: Iterable[float], *, out_of_span: bool = False
) -> SensorSample:
    """A sensor sample from its time and six inputs (INPUT_COLUMNS order); ValidationError if bad.

    ``out_of_span``: a sample whose only problem is one or more inputs outside their
    physical span (a negative pressure, a choke or a fraction outside 0..1, a temperature
    below -60 degC; :func:`vfm_core.messages.sample_outside_span`) keeps its raw values
    instead: a service that watches instrument faults raises an ``out_of_range`` fault on
    it, one that does not refuses it and counts the reason."""
    choke, p_up, p_down, t_up, eta_gas, eta_oil = (float(v) for v in inputs)
    data = {
        "time": when,
        "choke": choke,
        "p_up": p_up,
        "p_down": p_down,
        "t_up": t_up,
        "eta_gas": eta_gas,
        "eta_oil": eta_oil,
    }
    try:
        return SensorSample.model_validate(data)
    except ValidationError:
        kept = sample_outside_span(data) if out_of_span else None
        if kept is None:
            raise
        return kept


@dataclass(frozen=True)
class FlushAnswer:
    """The service's answer to a flush (see :meth:`FieldClient.flush`)."""

    #: its count of messages taken in (``GET /health`` ``received``)
    received: int
    #: everything taken in before the flush is handled and answered
    done: bool
    #: a second answer with ``done`` will come (one worker takes the messages itself)
    reports_done: bool


@dataclass
class Streamed:
    """What :meth:`FieldClient.stream` sent."""

    samples: list[tuple[str, int]] = field(default_factory=list)  # (well, sample time ns)
    measurements: int = 0
    skipped: int = 0  # rows whose values fail the message schema
    #: samples sent with an input outside its physical span (raw values: out_of_range faults)
    out_of_span: int = 0
    started: float = 0.0  # time.monotonic() when sending began
    #: separator readings sent, (separator, time ns) each
    readings: list[tuple[str, int]] = field(default_factory=list)


class _ReadingQueue:
    """The separator readings of :meth:`FieldClient.stream`, each sent just before the first
    row after its time (``times``: the rows'), paced as the rows with ``speed``."""

    def __init__(
        self,
        client: FieldClient,
        readings: pd.DataFrame | None,
        times: pd.DatetimeIndex,
        out: Streamed,
        speed: float | None,
    ) -> None:
        if readings is None:
            readings = pd.DataFrame({TIME: times[:0], "separator": [], TARGET: []})
        self.client, self.out, self.speed, self.t0 = client, out, speed, times[0]
        self.times = pd.DatetimeIndex(readings[TIME])
        self.before_row = np.searchsorted(
            times.as_unit("ns").asi8, self.times.as_unit("ns").asi8, side="right"
        )
        self.names = readings["separator"].astype(str).to_numpy()
        self.totals = readings[TARGET].to_numpy(dtype=float)
        self.py = [t.to_pydatetime() for t in self.times]
        self.next = 0

    def send_before(self, row: int) -> None:
        """Send the readings due before row ``row`` (a reading whose values fail the message
        schema is skipped and counted)."""
        out = self.out
        while self.next < len(self.before_row) and self.before_row[self.next] <= row:
            k = self.next
            self.next += 1
            if self.speed is not None:
                due = out.started + (self.times[k] - self.t0).total_seconds() / self.speed
                if (wait := due - time.monotonic()) > 0:
                    time.sleep(wait)
            try:
                self.client.send_reading(self.names[k], self.py[k], float(self.totals[k]))
            except ValidationError:
                out.skipped += 1
                continue
            out.readings.append((str(self.names[k]), to_ns(self.py[k])))


class FieldClient:
    """Publishes a field's sensor samples and measurements; collects the predictions.

    ``predictions`` maps (well, sample time in epoch ns) to the predicted q_total (Sm3/h);
    ``latest`` holds the latest answered sample time per well; with ``track_latency``,
    ``latency_s`` holds the seconds from sending each sample to receiving its prediction.
    ``wells`` (one key chunk, default ``*``) limits the predictions collected to those wells,
    so a client timing one well does not also parse every other well's answers.
    Close it to end the prediction subscription (the bus stays open: its owner closes it).
    """

    def __init__(
        self,
        bus: FieldBus,
        prefix: str = "vfm",
        *,
        match_timeout: float = 30.0,
        track_latency: bool = False,
        wells: str = "*",
    ) -> None:
        if not wells or "/" in wells:
            raise ConfigError(
                f"wells = {wells!r}: one key chunk naming the wells whose predictions to collect "
                "(a well id, or a pattern such as 'W0*'; '*' for all)."
            )
        self.bus = bus
        self.prefix = validate_prefix(prefix)
        self.match_timeout = match_timeout
        self.track_latency = track_latency
        self.predictions: dict[tuple[str, int], float] = {}
        self.latest: dict[str, int] = {}
        self.latency_s: list[float] = []
        self.count = 0
        self.bad = 0
        self.last_at = time.monotonic()
        self._sent_at: dict[tuple[str, int], float] = {}
        self._lock = threading.Lock()
        self._n_prefix = len(prefix) + 1
        self._unsubscribe: Callable[[], None] | None = bus.subscribe(
            f"{prefix}/{wells}/prediction", self._on_prediction
        )
        #: the separators' allocations received (``collect_allocations``): (separator, time
        #: ns) -> the message (``q_total``, ``predicted``, ``residual``, ``status``, ...)
        self.allocations: dict[tuple[str, int], dict[str, object]] = {}
        self._unsubscribe_allocations: Callable[[], None] | None = None
        #: the service's answers to this client's flushes, by flush id (in arrival order)
        self.flush_answers: dict[str, list[FlushAnswer]] = {}
        self._unsubscribe_flushed: Callable[[], None] | None = None

    def flush(self, timeout: float) -> str | None:
        """Put a flush after everything sent so far: the service answers it once it has taken
        in every message this client sent before (``done`` false, its ``received`` count),
        and, where it says so (``reports_done``), again once it has handled them all and
        published their answers (``done`` true); see :class:`service.transport.Flushes`.
        Returns the flush's id (its answers gather in :attr:`flush_answers`), or None when
        no service subscribes to the flush key within ``timeout`` s (one that answers no
        flushes: an instance that owns some wells only, ``zenoh.wells``)."""
        key = f"{self.prefix}/{FLUSH_KEY}"
        if self._unsubscribe_flushed is None:
            self._unsubscribe_flushed = self.bus.subscribe(
                f"{self.prefix}/{FLUSHED_KEY}/*", self._on_flushed
            )
        if not self.bus.matching(key, timeout):
            return None
        flush_id = secrets.token_hex(8)
        with self._lock:
            self.flush_answers[flush_id] = []
        self.bus.put(key, flush_id)
        return flush_id

    def service_present(self, timeout: float) -> bool:
        """Whether a service still subscribes to the flush key (False: it stopped)."""
        return self.bus.matching(f"{self.prefix}/{FLUSH_KEY}", timeout)

    def _on_flushed(self, key: str, payload: bytes) -> None:
        try:
            data = json.loads(payload)
            flush_id = str(data["id"])
            answer = FlushAnswer(
                received=int(data["received"]),
                done=bool(data["done"]),
                reports_done=bool(data.get("reports_done", False)),
            )
        except (ValueError, KeyError, TypeError):
            with self._lock:
                self.bad += 1
            return
        with self._lock:
            answers = self.flush_answers.get(flush_id)
            if answers is not None:  # another client's flush: not ours
                answers.append(answer)

    def collect_allocations(self) -> None:
        """Also collect the separators' allocations (``<prefix>/*/allocation``), which the
        service publishes once it has settled each separator reading."""
        if self._unsubscribe_allocations is None:
            self._unsubscribe_allocations = self.bus.subscribe(
                f"{self.prefix}/*/allocation", self._on_allocation
            )

    def _on_allocation(self, key: str, payload: bytes) -> None:
        try:
            data = json.loads(payload)
            sep = str(data["separator"])
            when = to_ns(datetime.fromisoformat(str(data["time"]).replace("Z", "+00:00")))
        except (ValueError, KeyError, TypeError):
            with self._lock:
                self.bad += 1
            return
        with self._lock:
            self.allocations[(sep, when)] = data

    # -- receiving --------------------------------------------------------------------------
    def _on_prediction(self, key: str, payload: bytes) -> None:
        now = time.perf_counter()
        well = key[self._n_prefix :].rsplit("/", 1)[0]
        try:
            data = json.loads(payload)
            times, rates = data["time"], data["q_total"]
            if not isinstance(times, list):  # one prediction, else a prediction block
                times, rates = [times], [rates]
            if len(times) != len(rates):
                raise ValueError("a prediction block's arrays differ in length")
            answers = [
                (to_ns(datetime.fromisoformat(str(t).replace("Z", "+00:00"))), float(q))
                for t, q in zip(times, rates, strict=True)
            ]
        except (ValueError, KeyError, TypeError):
            with self._lock:
                self.bad += 1
            return
        with self._lock:
            for t, q in answers:
                self.predictions[(well, t)] = q
                self.count += 1
                if t > self.latest.get(well, t - 1):
                    self.latest[well] = t
                if self.track_latency:
                    sent = self._sent_at.pop((well, t), None)
                    if sent is not None:
                        self.latency_s.append(now - sent)
            self.last_at = time.monotonic()

    def answered(self, expected: Collection[tuple[str, int]]) -> int:
        """How many of the (well, time ns) samples ``expected`` have a prediction."""
        with self._lock:
            return sum(1 for k in expected if k in self.predictions)

    def prediction(self, well: str, when: datetime) -> float | None:
        """The q_total predicted for the well's sample at ``when`` (None: not received)."""
        with self._lock:
            return self.predictions.get((well, to_ns(when)))

    def wait_for_prediction(self, well: str, when: datetime, timeout: float = 20.0) -> float:
        """Wait for the prediction of the well's sample at ``when``; TimeoutError if none comes."""
        deadline = time.monotonic() + timeout
        while (q := self.prediction(well, when)) is None:
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"No prediction for the sample of {well} at {when.isoformat()} within {timeout:g} s."
                )
            time.sleep(0.01)
        return q

    def wait_for_answers(
        self,
        expected: Collection[tuple[str, int]],
        *,
        idle_timeout: float,
        final_timeout: float,
        since: float | None = None,
        first_timeout: float = 30.0,
    ) -> int:
        """Wait until every expected (well, time ns) is answered, or none came for
        ``idle_timeout`` s (wells without a model never answer), at most ``final_timeout`` s.
        Until the first of them is answered the patience is ``first_timeout`` s instead (a
        service busy with its first samples on a loaded machine answers late, and it is no
        sign that it has stopped). The idle clock starts no earlier than this call (the
        sending's end). Returns how many are answered."""
        began = time.monotonic()
        since = began if since is None else since
        deadline = began + final_timeout
        wanted = set(expected)
        got = first = 0
        while time.monotonic() < deadline:
            with self._lock:
                if self.count >= len(wanted):
                    got = sum(1 for k in wanted if k in self.predictions)
                elif not first:
                    first = sum(1 for k in wanted if k in self.predictions)
                idle = time.monotonic() - max(self.last_at, began)
            if got == len(wanted):
                break
            patience = idle_timeout if got or first else max(idle_timeout, first_timeout)
            if idle > patience and time.monotonic() - since > patience:
                break
            time.sleep(0.05)
        with self._lock:
            return sum(1 for k in wanted if k in self.predictions)

    # -- sending ----------------------------------------------------------------------------
    def wait_for_service(self, well: str) -> None:
        """Wait until the service subscribes to the well's samples (ReplayError after the timeout)."""
        key = sensors_key(self.prefix, well)
        if not self.bus.matching(key, self.match_timeout):
            raise _no_service(key, self.match_timeout)

    def send_sample(self, well: str, sample: SensorSample) -> None:
        if self.track_latency:
            with self._lock:
                self._sent_at[(well, to_ns(sample.time))] = time.perf_counter()
        self.bus.put(sensors_key(self.prefix, well), sample.model_dump_json())

    def send_block(self, well: str, samples: Sequence[SensorSample]) -> None:
        """Several samples of one well (rising in time) in one sensor block: the service
        answers with one prediction block."""
        if self.track_latency:
            sent = time.perf_counter()
            with self._lock:
                for sample in samples:
                    self._sent_at[(well, to_ns(sample.time))] = sent
        self.bus.put(sensors_key(self.prefix, well), sensor_block(samples))

    def send_measurement(self, well: str, source: str, measurement: Measurement) -> None:
        """An MPFM reading (``mpfm``) or a well test (``well_test``)."""
        self.bus.put(measurement_key(self.prefix, well, source), measurement.model_dump_json())

    def put_raw(self, key: str, payload: bytes | str) -> None:
        """Any payload on any key (for tests of what the service refuses)."""
        self.bus.put(key, payload)

    def send_reading(self, separator: str, when: datetime, q_total: float) -> None:
        """A separator's total (Sm3/h) at ``when``, on ``<prefix>/<separator>/measurements/separator``."""
        measurement = Measurement(time=when, q_total=q_total)
        self.bus.put(
            measurement_key(self.prefix, separator, "separator"), measurement.model_dump_json()
        )

    def stream(
        self,
        rows: pd.DataFrame,
        *,
        speed: float | None = None,
        stop: threading.Event | None = None,
        progress: bool = False,
        readings: pd.DataFrame | None = None,
    ) -> Streamed:
        """Send observation rows (time-sorted) as they would arrive live: per row the sensor
        sample, then its measurement if it has one. ``speed``: N times real time (None: as
        fast as the bus takes them); ``stop`` ends the stream early. A second row of a well
        at the same time carries only its measurement; rows whose values fail the message
        schema are skipped and counted. A row whose only problem is an input outside its
        physical span is sent with its raw values (``sample_of(..., out_of_span=True)``) and
        counted in ``out_of_span``: the service decides (an ``out_of_range`` fault while it
        watches instrument faults, else refused with its reason).

        ``readings``: separator readings (``time``, ``separator``, ``q_total`` in Sm3/h, as
        :class:`vfm_core.separator_format.SeparatorData` holds them), each sent in time
        order after the wells' rows at or before its time (the service counts a well's
        sample at the reading's time in it, see docs/guide/separator.md)."""
        out = Streamed(started=time.monotonic())
        if rows.empty:
            return out
        times = pd.DatetimeIndex(rows[TIME])
        t0_data = times[0]
        # each reading goes out just before the first row after its time (or at the end)
        pending = _ReadingQueue(self, readings, times, out, speed)
        wells = rows[WELL].astype(str).to_numpy()
        x = rows[list(INPUT_COLUMNS)].to_numpy(dtype=float)
        outside = np.asarray(observations.outside_span(rows).any(axis=1))  # sent raw, counted
        q = rows[TARGET].to_numpy(dtype=float)
        src = rows[SOURCE].astype(str).to_numpy()
        py_times = [t.to_pydatetime() for t in times]
        last_sent: dict[str, int] = {}
        for i in tqdm(
            range(len(rows)),
            total=len(rows),
            unit="row",
            desc="replay",
            disable=not progress,
            mininterval=0.5,
        ):
            if stop is not None and stop.is_set():
                break
            pending.send_before(i)
            well, when = wells[i], py_times[i]
            if speed is not None:
                due = out.started + (times[i] - t0_data).total_seconds() / speed
                wait = due - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
            t_ns = to_ns(when)
            if last_sent.get(well) != t_ns:
                try:
                    sample = sample_of(when, x[i], out_of_span=True)
                except ValidationError:
                    out.skipped += 1
                    continue
                out.out_of_span += bool(outside[i])
                self.send_sample(well, sample)
                out.samples.append((well, t_ns))
                last_sent[well] = t_ns
            if src[i] in SOURCES and np.isfinite(q[i]):
                self.send_measurement(well, src[i], Measurement(time=when, q_total=float(q[i])))
                out.measurements += 1
        if stop is None or not stop.is_set():
            pending.send_before(len(rows))
        return out

    def close(self) -> None:
        if self._unsubscribe is not None:
            self._unsubscribe()
            self._unsubscribe = None
        if self._unsubscribe_allocations is not None:
            self._unsubscribe_allocations()
            self._unsubscribe_allocations = None
        if self._unsubscribe_flushed is not None:
            self._unsubscribe_flushed()
            self._unsubscribe_flushed = None

    def __enter__(self) -> FieldClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
