"""What the service refuses to do, as domain errors: one hierarchy, written out here.

The input checks, the engine and the HTTP layer raise these; none of them carries an HTTP
status. Each error holds a sentence for people (``message``, also ``str(error)``) and a
``reason``: the kind of refused input, a key of :data:`REASONS` and of the rejection
counters in ``GET /health``; None when no input was refused (a read of an unknown well, a
model change that cannot run now)::

    ServiceError            anything the service refuses, with a sentence
    +-- InvalidRequest      a value is wrong: a bad payload or time, an unknown model or effect
    |   +-- NotJson         an HTTP body declared as something else than JSON (Content-Type)
    +-- UnknownWell         the well is not known to this service
    +-- Duplicate           the same sample or measurement arrived before
    +-- Conflict            the request clashes with one still running (a second model change)
    +-- NotAllowed          the configuration does not permit it (no API token, a module not
    |                       listed in model.effect_modules)
    +-- NotAuthenticated    the bearer token is missing or wrong
    +-- Unavailable         the service cannot take it now; retrying later may work
        +-- Busy            a queue stayed full, or the answer took too long
        +-- Starting        the service is not running yet
        +-- Stopping        the service is stopping

The HTTP layer maps each class to a status in one table (:mod:`service.http.error_responses`):
422 (415 for ``NotJson``), 404, 409, 409, 403, 401 and 503 for the three kinds of
``Unavailable``.
"""

from __future__ import annotations

__all__ = [
    "REASONS",
    "ServiceError",
    "InvalidRequest",
    "NotJson",
    "UnknownWell",
    "Duplicate",
    "Conflict",
    "NotAllowed",
    "NotAuthenticated",
    "Unavailable",
    "Busy",
    "Starting",
    "Stopping",
    "unknown_well",
]

#: Every reason an input can be refused for, with what it means (the rejection counters).
REASONS: dict[str, str] = {
    "malformed JSON": "the payload is not valid JSON",
    "not declared JSON": "an HTTP body's Content-Type is not application/json (nor another "
    "JSON type such as application/merge-patch+json)",
    "payload too large": "the payload is larger than inputs.max_payload_bytes (Zenoh) or "
    "http.max_body_bytes (HTTP)",
    "too deeply nested": "the JSON nests deeper than inputs.max_json_depth",
    "not a JSON object": "the payload is JSON but not an object {...}",
    "missing field": "a required field is absent",
    "wrong type": "a field has the wrong type (text or true/false where a number belongs, a bad time)",
    "not finite": "a number is NaN or infinite",
    "negative or zero pressure": "p_up or p_down is not above 0 bar a",
    "p_down >= p_up": "the downstream pressure is not below the upstream one",
    "choke outside 0..1": "the choke opening is not a fraction 0..1",
    "fraction outside 0..1": "eta_gas or eta_oil is not within 0..1",
    "fractions sum above 1": "eta_gas + eta_oil exceeds 1",
    "temperature below absolute zero": "t_up is at or below -273.15 degC",
    "negative rate": "q_total is below 0",
    "implausible rate": "q_total is above inputs.max_rate, or more than inputs.rate_factor times "
    "above or below the median of the well's recent measurements",
    "time in the future": "the time lies further ahead than inputs.max_future_s",
    "time out of range": "the time lies outside 1677-09-22..2262-04-10 (what int64 nanoseconds "
    "hold) or before inputs.earliest_time",
    "time going backwards": "a sensor sample is older than the well's previous one",
    "block too large": "a sensor block holds more samples than inputs.max_block_samples",
    "malformed block": "a sensor block's fields are not arrays of one length (at least one sample)",
    "duplicate": "the same sample or measurement arrived before",
    "unknown well": "the well is not known and inputs.unknown_wells = 'reject' (or, over HTTP, "
    "the well is not known: HTTP never creates a well)",
    "well of another instance": "the well is outside this instance's zenoh.wells (scale-out: "
    "another instance owns it)",
    "retired well": "the well was retired with DELETE /wells/{well}; purge it to reuse the id",
    "too many wells": "the service holds inputs.max_wells wells; a new one is not created",
    "too many new wells": "new wells appear faster than inputs.new_wells_per_s (burst "
    "inputs.new_wells_burst); a new one is not created now",
    "unparseable key": "the key expression is not <prefix>/<well>/sensors or .../measurements/<source>, "
    "or its well id is not valid",
    "unknown source": "the measurement source is not mpfm or well_test",
    "unknown separator": "a separator reading names a separator that separators.members does not "
    "list (or a well: a well's total goes under mpfm or well_test)",
    "no sensor sample within tolerance": "no sample of the well lies within inputs.pair_tolerance_s",
    "sensor fault at the sample": "an input of the paired sample has an instrument fault "
    "(vfm_core.sensor_faults): the measurement is stored (status held), not learned from",
    "held for review": "a well test lies outside the model's predictive distribution "
    "(well_test_review.k sd) and off the MPFM near it: stored (status review), not learned "
    "until the operator accepts it (POST /wells/{well}/measurements/review)",
    "no such review": "a review decision names no measurement of the well held for review, "
    "or one decided before",
    "queue overflow": "the worker queue stayed full for queues.block_s; the message was dropped",
    "well flooding": "the well sends faster than its share: its own queue (queues.well_capacity) "
    "stayed full for queues.block_s, or it exceeded inputs.well_rate_hz",
}


class ServiceError(Exception):
    """Something the service refuses: a sentence, and the rejection reason if an input was refused."""

    def __init__(self, message: str, reason: str | None = None) -> None:
        super().__init__(message)
        if reason is not None and reason not in REASONS:
            raise ValueError(f"'{reason}' is not a rejection reason; add it to REASONS first.")
        self.message = message
        self.reason = reason


class InvalidRequest(ServiceError):
    """A value is wrong: a payload that fails its checks, a bad time, an unknown model or effect."""


class NotJson(InvalidRequest):
    """An HTTP request body whose Content-Type says it is not JSON (the API takes JSON only)."""


class UnknownWell(ServiceError):
    """The well is not known to this service (and is not created on sight)."""


class Duplicate(ServiceError):
    """The same sample or measurement arrived before; it is stored once."""


class Conflict(ServiceError):
    """The request clashes with one that is still running."""


class NotAllowed(ServiceError):
    """The configuration does not permit the request."""


class NotAuthenticated(ServiceError):
    """The request needs the service's bearer token and did not carry it."""


class Unavailable(ServiceError):
    """The service cannot take the request now; retrying later may work."""


class Busy(Unavailable):
    """A queue stayed full, or the answer did not come in time."""


class Starting(Unavailable):
    """The service is not running yet."""


class Stopping(Unavailable):
    """The service is stopping."""


def unknown_well(well: str) -> UnknownWell:
    """The refusal of a request about a well this service does not know (no input refused)."""
    return UnknownWell(
        f"The well '{well}' is not known to this service; GET /wells lists the wells."
    )
