"""Checking what arrives: key expressions and JSON payloads, with a reason for every rejection.

The same functions check Zenoh payloads and HTTP bodies, so a bad value gets the same
reason and sentence on both paths: each raises :class:`service.errors.InvalidRequest`
with a short stable ``reason`` (a key of :data:`service.errors.REASONS`, the counters of
``GET /health``) and a sentence for people. :class:`Limits` bounds what is parsed at all:
the payload's size and the JSON's nesting depth. :class:`Counters` counts accepted inputs
and rejections by reason and logs each reason once, then at most once a minute with the
count since; everything it logs passes :func:`printable` first, so no input can forge a
log line (a newline or control character in a key or id is shown escaped).
"""

from __future__ import annotations

import json
import logging
import math
import re
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np
import orjson
from pydantic import TypeAdapter, ValidationError

from service.errors import InvalidRequest
from vfm_core.messages import (
    Measurement,
    SensorSample,
    parse_key,
    sample_outside_span,
    well_id_problem,
)
from vfm_core.timeutil import REPRESENTABLE_MAX, REPRESENTABLE_MIN, to_ns

__all__ = [
    "Counters",
    "Limits",
    "DEFAULT_LIMITS",
    "printable",
    "parse_sensor",
    "quick_sensor",
    "parse_measurement",
    "SensorBlock",
    "decode",
    "is_block",
    "parse_sensor_block",
    "classify_errors",
    "route_key",
    "SOURCES",
]

logger = logging.getLogger("vfm.service.inputs")

SOURCES: tuple[str, ...] = ("mpfm", "well_test")

_NUMERIC_SENSOR = ("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil")


def printable(text: object, limit: int = 200) -> str:
    """``text`` safe to log: at most ``limit`` characters, control and invisible characters
    escaped (``\\n``, ``\\x00``, ``\\u2028``), so no input can start a forged log line."""
    s = str(text)
    if len(s) > limit:
        s = s[:limit] + f"...({len(s)} characters)"
    return s if s.isprintable() else s.encode("unicode_escape").decode("ascii")


@dataclass(frozen=True)
class Limits:
    """What an inbound payload may be at most, before it is parsed: size and JSON depth."""

    max_bytes: int = 65_536
    max_depth: int = 32


DEFAULT_LIMITS = Limits()


def _depth_exceeds(data: Any, limit: int) -> bool:
    """Whether parsed JSON nests deeper than ``limit`` (iterative: no recursion to exhaust)."""
    stack: list[tuple[Any, int]] = [(data, 1)]
    while stack:
        value, depth = stack.pop()
        if isinstance(value, dict):
            children: Iterable[Any] = value.values()
        elif isinstance(value, list):
            children = value
        else:
            continue
        if depth > limit:
            return True
        stack.extend((child, depth + 1) for child in children)
    return False


def _openings(payload: bytes | str) -> int:
    """How many ``{`` and ``[`` the payload holds: JSON cannot nest deeper than that, so
    a payload with no more than the limit skips the walk of :func:`_depth_exceeds`."""
    if isinstance(payload, str):
        return payload.count("{") + payload.count("[")
    return payload.count(b"{") + payload.count(b"[")


def _loads(payload: bytes | str, limits: Limits = DEFAULT_LIMITS) -> dict[str, Any]:
    size = len(payload)
    if size > limits.max_bytes:
        raise InvalidRequest(
            f"The payload has {size:,} bytes; at most {limits.max_bytes:,} are accepted "
            "(a sample or measurement takes about 200).",
            "payload too large",
        )
    try:
        data = json.loads(payload)
    except RecursionError:
        raise InvalidRequest(
            f"The payload nests JSON deeper than {limits.max_depth} levels; a sample or "
            "measurement is one flat object.",
            "too deeply nested",
        ) from None
    except (ValueError, UnicodeDecodeError) as exc:
        raise InvalidRequest(
            f"The payload is not valid JSON ({printable(exc, 120)}).", "malformed JSON"
        ) from None
    if _openings(payload) > limits.max_depth and _depth_exceeds(data, limits.max_depth):
        raise InvalidRequest(
            f"The payload nests JSON deeper than {limits.max_depth} levels; a sample or "
            "measurement is one flat object.",
            "too deeply nested",
        )
    if not isinstance(data, dict):
        raise InvalidRequest(
            f"The payload must be a JSON object {{...}}, not {type(data).__name__}.",
            "not a JSON object",
        )
    return data


def decode(payload: bytes | str, limits: Limits = DEFAULT_LIMITS) -> dict[str, Any]:
    """A payload's JSON object, within ``limits``; :class:`InvalidRequest` otherwise."""
    return _loads(payload, limits)


def _check_numbers(data: dict[str, Any], fields: Iterable[str]) -> None:
    for name in fields:
        if name not in data:
            continue  # reported as a missing field by the schema
        value = data[name]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise InvalidRequest(
                f"{name} must be a number, got {json.dumps(value)[:40]} ({type(value).__name__}).",
                "wrong type",
            )
        try:
            finite = math.isfinite(value)
        except OverflowError:  # an integer with hundreds of digits
            finite = False
            digits = int(int(value).bit_length() * 0.30103) + 1
            value = f"an integer of about {digits} digits"
        if not finite:
            raise InvalidRequest(f"{name} must be a finite number, got {value}.", "not finite")


def _finite(value: float) -> bool:
    """``math.isfinite``, False for an integer too large for a float (hundreds of digits)."""
    try:
        return math.isfinite(value)
    except OverflowError:
        return False


def classify_errors(errors: list[dict[str, Any]]) -> tuple[str, str]:
    """A reason and a sentence for pydantic validation errors (the first error decides)."""
    e = errors[0]
    kind = str(e.get("type", ""))
    loc = [str(p) for p in e.get("loc", ()) if p not in ("body",)]
    field = loc[-1] if loc else ""
    msg = str(e.get("msg", "")).removeprefix("Value error, ")
    value = e.get("input")
    if kind == "json_invalid":
        return "malformed JSON", f"The payload is not valid JSON ({printable(msg, 120)})."
    if kind in ("model_type", "model_attributes_type", "dict_type"):
        return "not a JSON object", "The payload must be a JSON object {...}."
    if kind == "missing":
        missing = [str(x["loc"][-1]) for x in errors if x.get("type") == "missing" and x.get("loc")]
        return "missing field", f"Required field(s) missing: {', '.join(missing)}."
    if isinstance(value, float | int) and not isinstance(value, bool) and not _finite(value):
        return "not finite", f"{field} must be a finite number, got {printable(value, 60)}."
    if isinstance(value, str) and value.strip().lower().lstrip("+-") in ("nan", "inf", "infinity"):
        return "not finite", f"{field} must be a finite number, got {value!r}."
    if "finite" in msg:
        return "not finite", msg[0].upper() + msg[1:] + "."
    if field in ("p_up", "p_down") and kind in ("greater_than", "greater_than_equal"):
        return (
            "negative or zero pressure",
            f"{field} = {value} bar a; pressures must be above 0 bar absolute.",
        )
    if field == "choke" and kind in ("greater_than_equal", "less_than_equal"):
        return "choke outside 0..1", f"choke = {value}; the opening must be a fraction from 0 to 1."
    if field in ("eta_gas", "eta_oil") and kind in ("greater_than_equal", "less_than_equal"):
        return "fraction outside 0..1", f"{field} = {value}; mass fractions lie from 0 to 1."
    if field == "q_total" and kind in ("greater_than", "greater_than_equal"):
        return "negative rate", f"q_total = {value} Sm3/h; a measured rate cannot be negative."
    if "p_down" in msg and "p_up" in msg:
        return "p_down >= p_up", msg[0].upper() + msg[1:] + "."
    if "exceeds 1" in msg:
        return "fractions sum above 1", msg[0].upper() + msg[1:] + "."
    if "absolute zero" in msg:
        return "temperature below absolute zero", msg[0].upper() + msg[1:] + "."
    if field == "time" and "can represent" in msg:
        return "time out of range", msg[0].upper() + msg[1:] + "."
    if field == "time":
        return (
            "wrong type",
            f"time {json.dumps(value, default=str)[:40]} is not an ISO 8601 time ({msg}).",
        )
    return "wrong type", f"{field or 'The payload'}: {msg}."


def parse_sensor(
    payload: bytes | str | dict[str, Any],
    limits: Limits = DEFAULT_LIMITS,
    *,
    out_of_span: bool = False,
) -> SensorSample:
    """A checked :class:`SensorSample` from JSON (or an already decoded object).

    ``out_of_span`` (the service, while it watches instrument faults): a sample whose only
    problem is one or more inputs outside their physical span
    (:data:`vfm_core.sensor_faults.DEFAULT_RANGES`: a negative pressure, a choke or a
    fraction outside 0..1, a temperature below -60 degC) is accepted with its raw values
    (:func:`_set_aside`): the detectors raise an ``out_of_range`` fault, the prediction
    stands in for the input and its measurements are held. Without it, refused as before."""
    data = payload if isinstance(payload, dict) else _loads(payload, limits)
    _check_numbers(data, _NUMERIC_SENSOR)
    try:
        return SensorSample.model_validate(data)
    except ValidationError as exc:
        sample = _set_aside(data) if out_of_span else None
        if sample is not None:
            return sample
        reason, sentence = classify_errors(exc.errors(include_url=False))  # type: ignore[arg-type]
        raise InvalidRequest(sentence, reason) from None


def _set_aside(data: dict[str, Any]) -> SensorSample | None:
    """``data`` (numbers checked, :func:`_check_numbers`) as a sample with its raw values
    when every input outside its physical span is set aside and the rest passes every rule
    of :class:`SensorSample` (:func:`vfm_core.messages.sample_outside_span`, the rule the
    replay sends by); None when no input is outside. Raises :class:`InvalidRequest` with
    the rest's reason when it breaks a rule: a zero pressure (inside the span, 0..1500 bar
    a), a p_down at or above an in-span p_up."""
    try:
        return sample_outside_span(data)
    except ValidationError as exc:
        reason, sentence = classify_errors(exc.errors(include_url=False))  # type: ignore[arg-type]
        raise InvalidRequest(sentence, reason) from None


#: the times :func:`quick_sensor` reads itself: ISO 8601 with a ``T``, whole seconds or up to
#: six digits of fraction, ``Z``, an offset in hours (00-23) and minutes (00-59), or none
#: (UTC); any other text goes the full way (:func:`parse_sensor`). (``fromisoformat`` alone
#: would take an offset of ``+00:60``, which pydantic refuses.)
_QUICK_TIME = re.compile(
    r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(?:\.\d{1,6})?(?:Z|[+-](?:[01]\d|2[0-3]):[0-5]\d)?"
)
_SPAN_NS = (to_ns(REPRESENTABLE_MIN), to_ns(REPRESENTABLE_MAX))


def quick_sensor(
    payload: bytes, limits: Limits, earliest_ns: int, latest_ns: int
) -> tuple[int, tuple[float, float, float, float, float, float]] | None:
    """A single sensor sample's time (epoch ns) and six inputs when it passes every check
    of :func:`parse_sensor` and a time within ``earliest_ns .. latest_ns``, read the quick
    way (orjson, plain comparisons: about 2 µs against 25); None when it is not sure.

    None is no verdict: the caller reads the payload the full way, which accepts it or
    gives the reason and sentence. So this path only ever accepts what the full one
    accepts, with the same values: a sample that breaks a rule, a time written another
    way, a number given as text, JSON that orjson does not read as the standard library
    does (``NaN``, UTF-16) all take the full path.

    Kept beside pydantic for a measured reason (``benchmarks/bench_hand_vs_library.py``,
    three runs): letting pydantic read the bytes itself (``SensorSample``'s
    ``validate_json`` in strict mode, which agreed with the full path on 60,000 fuzzed
    payloads) costs 2.3-2.6 µs more CPU a message alone (5.6-5.9 against 3.2-3.3) and
    1.5-3.3 µs more in ``Intake.deliver`` (9.8-10.5 against 7.1-8.3; median 3.0), above
    the 2 % (2.3 µs) of the 116 µs the service spends on a single-sample message that no
    user would notice."""
    if len(payload) > limits.max_bytes or _openings(payload) > limits.max_depth:
        return None
    try:
        data = orjson.loads(payload)
    except orjson.JSONDecodeError:
        return None
    if type(data) is not dict:
        return None
    try:
        when = data["time"]
        values = (
            data["choke"],
            data["p_up"],
            data["p_down"],
            data["t_up"],
            data["eta_gas"],
            data["eta_oil"],
        )
    except KeyError:
        return None
    if type(when) is not str or _QUICK_TIME.fullmatch(when) is None:
        return None
    for v in values:
        if type(v) is not float and type(v) is not int:  # bool, text, null, lists
            return None
    choke, p_up, p_down, t_up, gas, oil = x = tuple(map(float, values))
    if not (
        math.isfinite(choke + p_up + p_down + t_up + gas + oil)
        and 0.0 <= choke <= 1.0
        and 0.0 < p_down < p_up
        and 0.0 <= gas <= 1.0
        and 0.0 <= oil <= 1.0
        and gas + oil <= 1.0 + 1e-9
        and t_up > -273.15
    ):
        return None
    try:
        t = to_ns(datetime.fromisoformat(when))
    except (ValueError, OverflowError):  # e.g. hour 24, 30 February, past year 9999
        return None
    if not (max(earliest_ns, _SPAN_NS[0]) <= t <= min(latest_ns, _SPAN_NS[1])):
        return None
    return t, x  # type: ignore[return-value]


def parse_measurement(
    payload: bytes | str | dict[str, Any], limits: Limits = DEFAULT_LIMITS
) -> Measurement:
    """A checked :class:`Measurement` from JSON (or an already decoded object)."""
    data = payload if isinstance(payload, dict) else _loads(payload, limits)
    _check_numbers(data, ("q_total",))
    try:
        return Measurement.model_validate(data)
    except ValidationError as exc:
        reason, sentence = classify_errors(exc.errors(include_url=False))  # type: ignore[arg-type]
        raise InvalidRequest(sentence, reason) from None


def is_block(data: dict[str, Any]) -> bool:
    """Whether a decoded sensor payload is a block (its fields are arrays), not one sample."""
    return isinstance(data.get("time"), list)


@dataclass
class SensorBlock:
    """The samples of one sensor block that passed: times [N] (epoch ns, rising) and the
    six inputs [N, 6] in file units, and the rows refused, each with its error."""

    times_ns: np.ndarray
    inputs: np.ndarray
    refused: list[tuple[int, InvalidRequest]] = field(default_factory=list)


_BLOCK_FIELDS = ("time", *_NUMERIC_SENSOR)


def parse_sensor_block(
    data: dict[str, Any],
    max_samples: int,
    check_time: Callable[[datetime, str], None],
    earliest_ns: int,
    latest_ns: int,
    *,
    out_of_span: bool = False,
) -> SensorBlock:
    """The samples of a decoded sensor block (:func:`is_block`), checked row by row.

    A block holds one well's samples as arrays of one length: ``time`` (ISO 8601 texts,
    rising) and the six inputs, as in :class:`~vfm_core.messages.SensorSample`. The rules
    are those of one sample, run on whole columns (times read by pydantic, as one
    sample's); a row that breaks one is refused alone, with the reason and sentence the
    same values get as one sample (from :func:`parse_sensor` and ``check_time``). The
    others pass, in the block's order: whether each is after the well's previous sample
    is the worker's check, as for single samples. A block that is not arrays of one
    length, or holds more than ``max_samples`` rows, is refused whole
    (:class:`InvalidRequest`). ``earliest_ns`` and ``latest_ns`` bound the times (epoch
    ns), as ``check_time`` does; ``out_of_span`` as for :func:`parse_sensor`."""
    n = _block_length(data, max_samples)
    x, bad = _block_columns(data, n)
    ns, unread = _block_times(data["time"], earliest_ns, latest_ns)
    bad |= unread
    choke, p_up, p_down, t_up, gas, oil = x.T
    with np.errstate(invalid="ignore"):
        bad |= ~np.isfinite(x).all(axis=1)
        bad |= (choke < 0) | (choke > 1) | (p_up <= 0) | (p_down <= 0) | (p_down >= p_up)
        bad |= (gas < 0) | (gas > 1) | (oil < 0) | (oil > 1) | (gas + oil > 1.0 + 1e-9)
        bad |= t_up <= -273.15
    keep = ~bad
    refused = _rows_alone(data, bad, x, ns, keep, check_time, out_of_span)
    rows = np.flatnonzero(keep)
    return SensorBlock(ns[rows], x[rows], refused)


def _block_length(data: dict[str, Any], max_samples: int) -> int:
    """The rows of a sensor block whose fields are all arrays of one length, 1 to
    ``max_samples``; else the block is refused whole (:class:`InvalidRequest`)."""
    missing = [name for name in _BLOCK_FIELDS if name not in data]
    if missing:
        raise InvalidRequest(f"Required field(s) missing: {', '.join(missing)}.", "missing field")
    scalar = [name for name in _BLOCK_FIELDS if not isinstance(data[name], list)]
    if scalar:
        raise InvalidRequest(
            "In a sensor block every field is an array (time is one); "
            f"{', '.join(scalar)} {'is' if len(scalar) == 1 else 'are'} not.",
            "malformed block",
        )
    n = len(data["time"])
    lengths = {name: len(data[name]) for name in _BLOCK_FIELDS}
    if len(set(lengths.values())) != 1 or n == 0:
        shown = ", ".join(f"{k} {v}" for k, v in lengths.items())
        raise InvalidRequest(
            f"The arrays of a sensor block must have one length, at least 1; got {shown}.",
            "malformed block",
        )
    if n > max_samples:
        raise InvalidRequest(
            f"The sensor block holds {n:,} samples; at most {max_samples:,} are accepted "
            "(inputs.max_block_samples). Send it in smaller blocks.",
            "block too large",
        )
    return n


def _block_columns(data: dict[str, Any], n: int) -> tuple[np.ndarray, np.ndarray]:
    """The six inputs of a block as an (n, 6) array, NaN where a value is not a number,
    and a mask of the rows that need a look alone (all False here)."""
    x = np.empty((n, 6))
    bad = np.zeros(n, dtype=bool)
    for j, name in enumerate(_NUMERIC_SENSOR):
        column = data[name]
        try:
            if not all(type(v) is float or type(v) is int for v in column):
                raise TypeError
            x[:, j] = column
        except (TypeError, OverflowError, ValueError):  # text, true/false, a huge integer
            for i, v in enumerate(column):
                try:
                    x[i, j] = v if type(v) is float or type(v) is int else np.nan
                except OverflowError:
                    x[i, j] = np.nan
    return x, bad


def _rows_alone(
    data: dict[str, Any],
    bad: np.ndarray,
    x: np.ndarray,
    ns: np.ndarray,
    keep: np.ndarray,
    check_time: Callable[[datetime, str], None],
    out_of_span: bool = False,
) -> list[tuple[int, InvalidRequest]]:
    """Each row the column checks flagged, read as one sample (``out_of_span`` as for
    :func:`parse_sensor`): refused with that sample's reason and sentence, or (if it passes
    after all) written back into ``x``, ``ns`` and ``keep``. Returns the refused rows with
    their errors."""
    refused: list[tuple[int, InvalidRequest]] = []
    # (``keep`` is the caller's array, written in place: a row that passes alone is kept)
    for i in np.flatnonzero(bad).tolist():  # the row alone decides, with one sample's words
        try:
            row = {name: data[name][i] for name in _BLOCK_FIELDS}
            sample = parse_sensor(row, out_of_span=out_of_span)
            check_time(sample.time, "sample")
            ns[i] = to_ns(sample.time)
        except InvalidRequest as error:
            refused.append((i, error))
            continue
        except Exception as exc:  # noqa: BLE001 - whatever a row holds, it is refused alone
            refused.append(
                (
                    i,
                    InvalidRequest(
                        f"The row cannot be read ({printable(exc, 120)}).", "wrong type"
                    ),
                )
            )
            continue
        x[i] = sample.inputs()
        keep[i] = True
    return refused


#: how one sample's time is read (pydantic, as :class:`SensorSample` reads it)
_TIMES = TypeAdapter(list[datetime])
_TIME = TypeAdapter(datetime)


def _block_times(
    texts: list[Any], earliest_ns: int, latest_ns: int
) -> tuple[np.ndarray, np.ndarray]:
    """A block's times as epoch ns, read as one sample's time is read, and the rows whose
    time cannot be read or lies outside ``earliest_ns .. latest_ns`` (True)."""
    n = len(texts)
    try:
        stamps: list[datetime | None] = list(_TIMES.validate_python(texts))
    except ValidationError:
        stamps = []
        for v in texts:
            try:
                stamps.append(_TIME.validate_python(v))
            except ValidationError:
                stamps.append(None)
    ns = np.zeros(n, dtype=np.int64)
    bad = np.zeros(n, dtype=bool)
    for i, when in enumerate(stamps):
        try:
            v = None if when is None else to_ns(when)
        except (OverflowError, ValueError):  # an offset beyond year 1 or 9999
            v = None
        if v is None or not earliest_ns <= v <= latest_ns:
            bad[i] = True
        else:
            ns[i] = v
    return ns, bad


def route_key(prefix: str, key: str) -> tuple[str, str, str | None]:
    """(well, kind, source) of an inbound key, or :class:`InvalidRequest`; kind is sensors|measurements|prediction.

    The well id must pass :func:`vfm_core.messages.well_id_problem`, the one rule for ids."""
    parsed = parse_key(prefix, key)
    if parsed is None:
        raise InvalidRequest(
            f"The key {printable(repr(key), 120)} is not {prefix}/<well>/sensors or "
            f"{prefix}/<well>/measurements/<source>.",
            "unparseable key",
        )
    well, kind, source = parsed
    problem = well_id_problem(well)
    if problem is not None:
        raise InvalidRequest(problem, "unparseable key")
    if kind == "measurements" and source not in SOURCES:
        raise InvalidRequest(
            f"The measurement source {printable(repr(source), 60)} of {well} is not one of "
            f"{', '.join(SOURCES)}.",
            "unknown source",
        )
    return well, kind, source


class Counters:
    """Thread-safe counts of accepted inputs, rejections by reason and other events."""

    LOG_EVERY_S = 60.0
    #: wells whose rejections are also counted per well (bounded: ids come from outside)
    MAX_WELLS = 10_000

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.rejected_by_well: dict[str, Counter[str]] = {}
        self.events: Counter[str] = Counter()
        self._last_log: dict[str, float] = {}
        self._since_log: Counter[str] = Counter()

    def accept(self, kind: str, n: int = 1) -> None:
        with self._lock:
            self.accepted[kind] += n

    def event(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.events[name] += n

    def reject(self, reason: str, message: str, where: str = "", well: str | None = None) -> None:
        """Count a rejection (also under ``well`` when given, for the first MAX_WELLS wells);
        log the first of each reason, then at most once a minute."""
        now = time.monotonic()
        with self._lock:
            self.rejected[reason] += 1
            if well is not None:
                per_well = self.rejected_by_well.get(well)
                if per_well is None and len(self.rejected_by_well) < self.MAX_WELLS:
                    per_well = self.rejected_by_well[well] = Counter()
                if per_well is not None:
                    per_well[reason] += 1
            self._since_log[reason] += 1
            last = self._last_log.get(reason)
            if last is not None and now - last < self.LOG_EVERY_S:
                return
            count = self._since_log.pop(reason)
            self._last_log[reason] = now
        where = f" ({printable(where)})" if where else ""
        message = printable(message, 400)
        if last is None:
            logger.warning("Rejected input: %s%s: %s", reason, where, message)
        else:
            logger.warning(
                "Rejected %d input(s) for '%s' in the last minute%s; latest: %s",
                count,
                reason,
                where,
                message,
            )

    def rejected_of(self, well: str) -> dict[str, int]:
        """The rejections counted for one well, by reason."""
        with self._lock:
            return dict(self.rejected_by_well.get(well, {}))

    def forget(self, well: str) -> None:
        """Drop a well's own counts (it was retired)."""
        with self._lock:
            self.rejected_by_well.pop(well, None)

    def snapshot(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {
                "accepted": dict(self.accepted),
                "rejected": dict(self.rejected),
                "events": dict(self.events),
            }
