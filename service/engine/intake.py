"""Receiving: check each inbound message, route it to the worker that owns its well, back-pressure.

The transport's receiver thread calls :meth:`Intake.deliver` with every message. It only
checks (key, payload, time, rate, well) and queues; it never learns and never builds a
model, so receiving never waits for learning. A well always goes to the same worker (a
hash of its id), into that worker's :class:`~service.engine.fairqueue.FairQueue`: one
FIFO per well (its messages keep their order), served round robin. When the well's FIFO
(``queues.well_capacity``) or the worker's queue (``queues.worker_capacity``) is full the
receiver waits up to ``queues.block_s`` (back-pressure: Zenoh's BLOCK congestion control
then slows the publisher), then drops the message and counts ``well flooding`` or
``queue overflow``. When the worker takes the messages itself (:attr:`Intake.hold`), it
cannot wait for its own queue: the message is held (:attr:`Intake.held`), no further one is
taken from the bus, and the worker works its queue and tries the held one again
(:meth:`Intake.retry_held`) until it fits or ``queues.block_s`` has passed. Well tests posted over HTTP enter here too
(:meth:`Intake.submit_well_test`).

A well outside this instance's ``zenoh.wells`` (scale-out: another instance owns it) is
refused as ``well of another instance``. A well not seen before is admitted by the :class:`~service.engine.registry.Registry`
(``inputs.unknown_wells``, ``inputs.max_wells``, ``inputs.new_wells_per_s``) if its id
passes :func:`vfm_core.messages.well_id_problem`, the one rule for well ids; its worker
creates it.

A single sensor sample is first read the quick way (:func:`service.inputs.quick_sensor`:
orjson and plain comparisons, about a sixth of the full path's CPU); anything it is not
sure of (a rule broken, a time written another way, a block) goes the full way, which gives
every refusal its reason and sentence.

A sensor block (a ``sensors`` payload whose fields are arrays) is checked as columns
(:func:`service.inputs.parse_sensor_block`): a bad row is refused alone, with its reason
and sentence, and the rows that pass are queued as one item that weighs in the worker's queue
by its memory (:func:`block_weight`). A per-well quota (``inputs.well_rate_hz``) counts a block's rows.

Times are checked here against one rule (:func:`vfm_core.timeutil.time_problem`): within
the span the VFM represents, not before ``inputs.earliest_time``, at most
``inputs.max_future_s`` ahead of the service's clock; rates against ``inputs.max_rate``
(the worker checks them against the well's own recent median).
"""

from __future__ import annotations

import functools
import logging
import time
import zlib
from concurrent.futures import Future
from datetime import datetime
from typing import Any, Literal

from service.config import Settings
from service.engine.fairqueue import FairQueue
from service.engine.items import MeasurementItem, SensorBlockItem, SensorItem
from service.engine.registry import Registry
from service.engine.separators import SeparatorItem, is_separator_key, parse_reading
from service.engine.state import WellTestResult
from service.errors import Busy, InvalidRequest, ServiceError, UnknownWell
from service.inputs import (
    Counters,
    Limits,
    SensorBlock,
    decode,
    is_block,
    parse_measurement,
    parse_sensor,
    parse_sensor_block,
    printable,
    quick_sensor,
    route_key,
)
from service.scaleout import WellSet
from vfm_core.messages import Measurement, well_id_problem
from vfm_core.timeutil import time_problem, to_ns

__all__ = ["Intake", "worker_of", "block_weight", "ROWS_PER_MESSAGE"]

logger = logging.getLogger("vfm.service.engine")


#: the keys seen lately and their (well, kind, source): checking a key's well id costs more
#: than looking it up; a bad key raises and is never kept
_route = functools.lru_cache(maxsize=16_384)(route_key)


#: rows of a sensor block that weigh as much as one message in a worker's queue: a queued
#: row holds about 60 bytes, a queued single sample about 1.4 kB (measured with tracemalloc)
ROWS_PER_MESSAGE = 16


def block_weight(rows: int) -> int:
    """What a sensor block of ``rows`` rows counts against ``queues.worker_capacity``: one
    message, and one more per :data:`ROWS_PER_MESSAGE` rows (its memory, in messages)."""
    return 1 + rows // ROWS_PER_MESSAGE


def worker_of(well: str, workers: int) -> int:
    """The worker that owns ``well`` (stable across restarts); a separator's wells are
    routed by the separator's name (:meth:`service.config.SeparatorSettings.route`)."""
    return zlib.crc32(well.encode()) % workers


class Intake:
    """The receiving side of the engine; see the module docstring."""

    def __init__(
        self,
        settings: Settings,
        counters: Counters,
        registry: Registry,
        queues: list[FairQueue],
    ) -> None:
        self.settings = settings
        self.counters = counters
        self.registry = registry
        self.queues = queues
        self.limits = Limits(settings.inputs.max_payload_bytes, settings.inputs.max_json_depth)
        self._future_ns = int(settings.inputs.max_future_s * 1e9)
        self._earliest_ns = to_ns(settings.inputs.earliest_time)
        #: a sample with an input outside its physical span is taken (an ``out_of_range``
        #: fault: stored raw, stood in for, not learned) while faults are watched
        self._out_of_span = bool(settings.sensor_faults.enabled)
        #: the wells this instance owns (scale-out, ``zenoh.wells``)
        self.own = WellSet(settings.zenoh.wells)
        #: the worker itself calls :meth:`deliver`: a message that does not fit is held,
        #: not waited for (see the module docstring)
        self.hold = False
        #: the message held: the item, where it came from, until when it may wait (monotonic s)
        self.held: tuple[SensorItem | SensorBlockItem | MeasurementItem, str, float] | None = None

    def deliver(self, key: str, payload: bytes, received_ns: int) -> None:
        """One inbound message: check, then queue for the well's worker (never learns)."""
        if is_separator_key(key):
            self._deliver_reading(key, payload, received_ns)
            return
        well: str | None = None
        try:
            well, kind, source = _route(self.settings.prefix, key)
            if kind == "prediction":
                # outputs, e.g. of another service instance: not ours to take in
                self.counters.event("outputs ignored")
                return
            if well not in self.own:
                raise InvalidRequest(
                    f"The well {well} is not one of this instance's wells ("
                    f"zenoh.wells = {self.own.describe()}); another instance owns it. The "
                    "message was not taken in: check that the sender and this instance "
                    "share a router and that the instances' zenoh.wells are disjoint.",
                    "well of another instance",
                )
            self.registry.quota_spent(well)  # a flooding well: refused before decoding
            item: SensorItem | SensorBlockItem | MeasurementItem
            if kind == "sensors":
                quick = quick_sensor(
                    payload, self.limits, self._earliest_ns, time.time_ns() + self._future_ns
                )
                if quick is not None:  # a plain single sample that passes every check
                    item = SensorItem(well, quick[0], quick[1], received_ns)
                elif is_block(data := decode(payload, self.limits)):
                    block = self.parse_block(data)
                    if block.refused:
                        known = well if self.registry.known(well) else None
                        for row, error in block.refused:
                            self.counters.reject(
                                str(error.reason),
                                f"Row {row} of the sensor block: {error.message}",
                                where=key,
                                well=known,
                            )
                    if not len(block.times_ns):
                        return
                    item = SensorBlockItem(well, block.times_ns, block.inputs, received_ns)
                else:
                    # watched for instrument faults, an input out of its span is one
                    sample = parse_sensor(data, self.limits, out_of_span=self._out_of_span)
                    self.check_time(sample.time, "sample")
                    item = SensorItem(well, to_ns(sample.time), tuple(sample.inputs()), received_ns)
            else:
                measurement = parse_measurement(payload, self.limits)
                self.check_time(measurement.time, "measurement")
                self.check_rate(measurement.q_total, well)
                item = MeasurementItem(well, measurement, str(source), received_ns)
            self.registry.admit(well)
            self.registry.quota(
                well, len(item.times_ns) if isinstance(item, SensorBlockItem) else 1
            )
        except ServiceError as error:  # every refusal here is of an input: it has a reason
            if error.reason is not None:
                known = well if well is not None and self.registry.known(well) else None
                self.counters.reject(error.reason, error.message, where=key, well=known)
            return
        except Exception as exc:  # a bug must not end reception, and must be counted
            self.counters.event("internal errors")
            logger.exception("Checking a message on %s failed: %s", printable(key), exc)
            return
        self._enqueue(item, key)

    def _deliver_reading(self, key: str, payload: bytes, received_ns: int) -> None:
        """A separator's reading (:mod:`service.engine.separators`), checked as a
        measurement is and queued at its separator's worker; an allocation (another
        instance's output) is ignored."""
        try:
            item = parse_reading(self.settings, key, payload, self.limits, received_ns)
            if item is None:
                self.counters.event("outputs ignored")
                return
            self.check_time(item.measurement.time, "separator reading")
            self.check_rate(item.measurement.q_total, item.well)
        except ServiceError as error:
            if error.reason is not None:
                self.counters.reject(error.reason, error.message, where=key)
            return
        except Exception as exc:  # a bug must not end reception, and must be counted
            self.counters.event("internal errors")
            logger.exception("Checking a message on %s failed: %s", printable(key), exc)
            return
        self._enqueue(item, key)

    def submit_reading(self, item: SeparatorItem) -> None:
        """Queue a separator's reading posted over HTTP (its future answers once it is
        stored). Raises :class:`InvalidRequest` for a bad time or rate, :class:`Busy` when
        the queue stays full."""
        self.check_time(item.measurement.time, "separator reading")
        self.check_rate(item.measurement.q_total, item.well)
        full = self._put(item, timeout=2.0)
        if full != "ok":
            raise Busy(
                "The service is busy (its queue is full); retry in a few seconds.",
                "well flooding" if full == "well" else "queue overflow",
            )

    def parse_block(self, data: dict[str, Any]) -> SensorBlock:
        """The rows of a sensor block that pass the checks of one sample (see
        :func:`service.inputs.parse_sensor_block`), with the time bounds of :meth:`check_time`."""
        return parse_sensor_block(
            data,
            self.settings.inputs.max_block_samples,
            self.check_time,
            to_ns(self.settings.inputs.earliest_time),
            time.time_ns() + self._future_ns,
            out_of_span=self._out_of_span,
        )

    def submit_well_test(self, well: str, measurement: Measurement) -> Future[WellTestResult]:
        """Queue a well test; the future answers after it is stored (and learned).

        Raises (before queueing) :class:`InvalidRequest` for a bad time, rate or well id,
        :class:`UnknownWell` for a well this service does not serve (HTTP never creates
        one; a well still being created from its first Zenoh message is not served yet, as
        for every other endpoint), or :class:`Busy` when the queue stays full.
        """
        problem = well_id_problem(well)
        if problem is not None:
            raise InvalidRequest(problem, "unparseable key")
        self.check_time(measurement.time, "well test")
        self.check_rate(measurement.q_total, well)
        self.registry.admit(well, create=False)  # a retired or unknown well: refused
        if well not in self.registry.wells:  # admitted as new over Zenoh, not built yet
            raise UnknownWell(
                f"The well {well} is not served yet: it is being created from its first "
                "Zenoh message. Retry once GET /wells lists it.",
                "unknown well",
            )
        fut: Future[WellTestResult] = Future()
        item = MeasurementItem(
            well, measurement, "well_test", time.time_ns(), via="http", future=fut
        )
        route = self.settings.separators.route(well)
        full = self.queues[worker_of(route, len(self.queues))].put(well, item, timeout=2.0)
        if full != "ok":
            raise Busy(
                "The service is busy (its queue is full); retry in a few seconds.",
                "well flooding" if full == "well" else "queue overflow",
            )
        return fut

    def check_time(self, when: datetime, what: str) -> None:
        """Refuse a time outside the representable span, before ``inputs.earliest_time`` or
        further ahead than ``inputs.max_future_s``."""
        problem = time_problem(
            when, earliest=self.settings.inputs.earliest_time, what=f"{what} time"
        )
        if problem is not None:
            raise InvalidRequest(
                problem.rstrip(".") + " (inputs.earliest_time and the int64-nanosecond span "
                "1677-09-22..2262-04-10 bound it).",
                "time out of range",
            )
        ahead = to_ns(when) - time.time_ns()
        if ahead > self._future_ns:
            raise InvalidRequest(
                f"The {what} time {when.isoformat()} lies {ahead / 3.6e12:.2f} h ahead of the "
                f"service's clock; at most {self.settings.inputs.max_future_s:g} s ahead is "
                "accepted (inputs.max_future_s), so that a sample from the future cannot hold "
                "back the well's real-time samples. Check the sender's clock and time zone.",
                "time in the future",
            )

    def check_rate(self, q_total: float, well: str) -> None:
        """Refuse a rate above ``inputs.max_rate`` (Sm3/h)."""
        cap = self.settings.inputs.max_rate
        if q_total > cap:
            raise InvalidRequest(
                f"q_total = {q_total:.6g} Sm3/h of {well} is above {cap:g} Sm3/h "
                "(inputs.max_rate), more than any well produces; check the meter's unit.",
                "implausible rate",
            )

    def _put(
        self, item: SensorItem | SensorBlockItem | MeasurementItem, timeout: float = 0.0
    ) -> Literal["ok", "well", "total"]:
        """Queue ``item`` at its well's worker (a block weighs its memory), waiting up to
        ``timeout`` s for room."""
        q = self.queues[worker_of(self.settings.separators.route(item.well), len(self.queues))]
        weight = block_weight(len(item.times_ns)) if isinstance(item, SensorBlockItem) else 1
        return q.put(item.well, item, timeout=timeout, weight=weight)

    def _enqueue(self, item: SensorItem | SensorBlockItem | MeasurementItem, where: str) -> None:
        if self._put(item) == "ok":
            return
        self.counters.event("backpressure waits")
        if self.hold:
            self.held = (item, where, time.monotonic() + self.settings.queues.block_s)
            return
        full = self._put(item, self.settings.queues.block_s)
        if full != "ok":
            self._drop(item, where, full)

    def retry_held(self) -> bool:
        """Put the held message in its queue if it fits now (True), or drop and count it
        once it has waited ``queues.block_s`` (True); False while it still waits."""
        if self.held is None:
            return True
        item, where, deadline = self.held
        full = self._put(item)
        if full != "ok" and time.monotonic() < deadline:
            return False
        self.held = None
        if full != "ok":
            self._drop(item, where, full)
        return True

    def _drop(
        self,
        item: SensorItem | SensorBlockItem | MeasurementItem,
        where: str,
        full: Literal["well", "total"],
    ) -> None:
        """Count a message dropped because its queue stayed full for ``queues.block_s``."""
        q = self.queues[worker_of(self.settings.separators.route(item.well), len(self.queues))]
        if q.depth(item.well) == 0:
            self.registry.abandon(item.well)  # a new well whose first message was dropped
        block = self.settings.queues.block_s
        if full == "well":
            self.counters.event("well flooding")
            cap = self.settings.queues.well_capacity
            sep = self.settings.separators.separator_of(item.well)
            queue = (
                f"The queue of {item.well} stayed full ({cap} messages, queues.well_capacity)"
                if sep is None
                else f"The queue of {item.well}'s separator {sep}, which its wells share, stayed "
                f"full ({cap} messages per well, queues.well_capacity)"
            )
            self.counters.reject(
                "well flooding",
                f"{queue} for {block:g} s; the message was dropped. The "
                "well sends faster than the service learns from it: slow the sender down.",
                where=where,
            )
            return
        self.counters.event("overflow")
        self.counters.reject(
            "queue overflow",
            f"The worker queue stayed full for {block:g} s; the message was dropped. "
            "The service cannot keep up: add workers (queues.workers) or slow the sender.",
            where=where,
        )
