"""Message schemas of the streaming interface (JSON over Zenoh and HTTP), validated with pydantic.

Key expressions, under a prefix (default ``vfm``; a site uses e.g. ``vfm/<field>``):

=====================================  ====  =======================================================
key                                    dir   payload
=====================================  ====  =======================================================
``<prefix>/<well>/sensors``            in    :class:`SensorSample` {time, choke, p_up, p_down, t_up, eta_gas, eta_oil}
``<prefix>/<well>/measurements/<src>``  in    :class:`Measurement` {time, q_total}; src = ``mpfm`` | ``well_test``
``<prefix>/<well>/prediction``         out   :class:`Prediction` {time, q_total, q_gas, q_oil, q_water, model, version}
=====================================  ====  =======================================================

A separator's total (the sum of its wells' rates, Sm3/h) comes in as a :class:`Measurement`
on ``<prefix>/<separator>/measurements/separator``; the service publishes its allocation to
the wells on ``<prefix>/<separator>/allocation`` (``service.engine.separators``).

A **sensor block** carries many samples of one well in one message on the same
``sensors`` key: the same fields, each an array of one length (rows in rising time order;
:func:`sensor_block` builds one). Its answer is one :class:`PredictionBlock` on the
``prediction`` key: the same fields, the rates and times as arrays (``model`` and
``version`` once). A block costs the service a fraction of one message per sample.

Units as in the observation format: choke fraction 0..1, pressures bar absolute,
temperature degC, mass fractions 0..1, rates Sm3/h; times ISO 8601 (UTC if naive).
Both the service and the replay tool use these classes, so the two cannot drift apart.
"""

from __future__ import annotations

import json
import math
import unicodedata
from collections.abc import Mapping, Sequence
from datetime import UTC, datetime
from typing import Any, Literal

import orjson
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from vfm_core.errors import ConfigError
from vfm_core.schema import INPUT_COLUMNS
from vfm_core.timeutil import iso, time_problem

__all__ = [
    "FLUSH_KEY",
    "FLUSHED_KEY",
    "SensorSample",
    "sample_outside_span",
    "Measurement",
    "Prediction",
    "prediction_json",
    "PredictionBlock",
    "sensor_block",
    "sensors_key",
    "measurement_key",
    "prediction_key",
    "parse_key",
    "validate_prefix",
    "validate_well_id",
    "well_id_problem",
    "WELL_ID_MAX",
]


def _utc(value: datetime) -> datetime:
    """The time in UTC, refused (ValueError, which pydantic reports) outside the span the VFM
    represents (int64 epoch nanoseconds: 1677 to 2262), including an offset that pushes it
    past year 1 or 9999."""
    problem = time_problem(value)
    if problem is not None:
        raise ValueError(problem[0].lower() + problem[1:].rstrip("."))
    return value.replace(tzinfo=UTC) if value.tzinfo is None else value.astimezone(UTC)


def _finite(value: float, name: str) -> float:
    if not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value}")
    return value


class SensorSample(BaseModel):
    """One steady-state sample of a well's sensors (units: fraction, bar a, bar a, degC, -, -)."""

    model_config = ConfigDict(extra="ignore", frozen=True, allow_inf_nan=False)

    time: datetime
    choke: float = Field(ge=0.0, le=1.0, description="choke opening, fraction 0..1")
    p_up: float = Field(gt=0.0, description="upstream pressure, bar absolute")
    p_down: float = Field(gt=0.0, description="downstream pressure, bar absolute")
    t_up: float = Field(description="upstream temperature, degC")
    eta_gas: float = Field(ge=0.0, le=1.0, description="gas mass fraction")
    eta_oil: float = Field(ge=0.0, le=1.0, description="oil mass fraction")

    @field_validator("time")
    @classmethod
    def _time_utc(cls, v: datetime) -> datetime:
        return _utc(v)

    @field_validator("choke", "p_up", "p_down", "t_up", "eta_gas", "eta_oil", mode="before")
    @classmethod
    def _no_nan(cls, v: object, info: object) -> object:
        if isinstance(v, float):
            _finite(v, getattr(info, "field_name", "value"))
        return v

    @model_validator(mode="after")
    def _physical(self) -> SensorSample:
        if self.p_down >= self.p_up:
            raise ValueError(
                f"p_down ({self.p_down} bar) must be below p_up ({self.p_up} bar): flow goes downstream"
            )
        if self.eta_gas + self.eta_oil > 1.0 + 1e-9:
            raise ValueError(
                f"eta_gas + eta_oil = {self.eta_gas + self.eta_oil:.4f} exceeds 1 (water = 1 - both)"
            )
        if self.t_up <= -273.15:
            raise ValueError(f"t_up = {self.t_up} degC is below absolute zero")
        return self

    def inputs(self) -> list[float]:
        """The six model inputs in :data:`vfm_core.schema.INPUT_COLUMNS` order."""
        return [self.choke, self.p_up, self.p_down, self.t_up, self.eta_gas, self.eta_oil]


#: in-span values that pass every rule of :class:`SensorSample` with any valid rest (see
#: :func:`sample_outside_span`): a choke half open, 20 degC, no gas nor oil
_STAND_INS = {"choke": 0.5, "t_up": 20.0, "eta_gas": 0.0, "eta_oil": 0.0}


def sample_outside_span(data: Mapping[str, Any]) -> SensorSample | None:
    """``data`` (a time and the six inputs) as a sample with its raw values when every input
    outside its physical span (:data:`vfm_core.sensor_faults.DEFAULT_RANGES`: a negative
    pressure, a choke or a fraction outside 0..1, a temperature below -60 degC) is set aside
    and the rest passes every rule of :class:`SensorSample` (its time too); None when no
    input is outside, or an input is missing, no number or not finite. Raises pydantic's
    ``ValidationError`` with the rest's problem when it breaks a rule: a zero pressure
    (inside the span, 0..1500 bar a), a p_down at or above an in-span p_up.

    One rule for both sides of the interface: the service takes such a sample while it
    watches instrument faults (an ``out_of_range`` fault), the replay sends it as it is."""
    from vfm_core.sensor_faults import DEFAULT_RANGES

    try:
        raw = {name: float(data[name]) for name in INPUT_COLUMNS}
    except (KeyError, TypeError, ValueError, OverflowError):
        return None
    if not all(map(math.isfinite, raw.values())):  # NaN is outside no span: refused as it is
        return None
    aside = [n for n, v in raw.items() if not DEFAULT_RANGES[n][0] <= v <= DEFAULT_RANGES[n][1]]
    if not aside:
        return None
    probe = dict(data, **{n: _STAND_INS[n] for n in aside if n in _STAND_INS})
    if "p_up" in aside and "p_down" in aside:
        probe.update(p_up=2.0, p_down=1.0)
    elif "p_up" in aside:  # above the kept p_down (a p_down of 0 still fails its own rule)
        probe["p_up"] = raw["p_down"] + 1.0
    elif "p_down" in aside:
        probe["p_down"] = raw["p_up"] / 2.0
    checked = SensorSample.model_validate(probe)
    return checked.model_copy(update={n: raw[n] for n in aside})


class Measurement(BaseModel):
    """A measured total rate, Sm3/h at standard conditions."""

    model_config = ConfigDict(extra="ignore", frozen=True, allow_inf_nan=False)

    time: datetime
    q_total: float = Field(ge=0.0, description="measured total rate, Sm3/h")

    @field_validator("time")
    @classmethod
    def _time_utc(cls, v: datetime) -> datetime:
        return _utc(v)

    @field_validator("q_total", mode="before")
    @classmethod
    def _no_nan(cls, v: object) -> object:
        if isinstance(v, float):
            _finite(v, "q_total")
        return v


class FallbackInput(BaseModel):
    """An input replaced in a prediction while it is flagged (units of the observation
    format: fraction, bar a, degC): ``value`` stood in for the reading ``measured``;
    ``spread`` is the standard deviation of how far the true value may have moved since its
    last trusted level, ``low`` / ``high`` its central 90 % span within the physical range;
    ``since``: when the fault began (ISO 8601 UTC)."""

    sensor: str
    kind: str
    value: float
    measured: float | None = None
    spread: float
    low: float
    high: float
    since: str | None = None


class Prediction(BaseModel):
    """The service's answer to a sensor sample: predicted rates in Sm3/h.

    With a learning method that carries its uncertainty (``bayes``), ``q_total_std`` is the
    predictive standard deviation of the total rate a well test would measure, and
    ``q_total_p05`` / ``q_total_p95`` bound its central 90 % interval; otherwise they are
    null.

    ``fallback`` is null unless an input of the sample is flagged (a frozen or impossible
    reading, :mod:`vfm_core.sensor_faults`): then the rates were predicted with a stand-in
    for it, one :class:`FallbackInput` per replaced input, and the interval was widened to
    cover the stand-in's span (given even by a method without intervals).
    """

    time: datetime
    q_total: float
    q_gas: float | None = None
    q_oil: float | None = None
    q_water: float | None = None
    model: str
    version: int
    q_total_std: float | None = None
    q_total_p05: float | None = None
    q_total_p95: float | None = None
    fallback: list[FallbackInput] | None = None


def prediction_json(
    time_ns: int,
    q_total: float,
    q_gas: float | None,
    q_oil: float | None,
    q_water: float | None,
    model: str,
    version: int,
    q_total_std: float | None = None,
    q_total_p05: float | None = None,
    q_total_p95: float | None = None,
    fallback: Sequence[Mapping[str, Any]] | None = None,
) -> bytes:
    """The JSON of a :class:`Prediction` at ``time_ns`` (epoch ns), as
    ``Prediction(...).model_dump_json()`` writes it (the fields in order, the time in UTC
    with a ``Z``, null for a number that is not finite), written by orjson: the service
    sends one per sample, and this costs a tenth of building and dumping the model."""
    return orjson.dumps(
        {  # numbers as pydantic's fields take them: floats (an int 0 is 0.0), an int version
            "time": iso(time_ns),
            "q_total": float(q_total),
            "q_gas": None if q_gas is None else float(q_gas),
            "q_oil": None if q_oil is None else float(q_oil),
            "q_water": None if q_water is None else float(q_water),
            "model": str(model),
            "version": int(version),
            "q_total_std": None if q_total_std is None else float(q_total_std),
            "q_total_p05": None if q_total_p05 is None else float(q_total_p05),
            "q_total_p95": None if q_total_p95 is None else float(q_total_p95),
            "fallback": None if fallback is None else [dict(f) for f in fallback],
        }
    )


class PredictionBlock(BaseModel):
    """The service's answer to a sensor block: one :class:`Prediction` per answered row,
    as arrays of one length (Sm3/h); rows without an answer (the model not ready) are left
    out. The interval fields are null for a method that gives none."""

    time: list[datetime]
    q_total: list[float]
    q_gas: list[float | None]
    q_oil: list[float | None]
    q_water: list[float | None]
    model: str
    version: int
    q_total_std: list[float | None] | None = None
    q_total_p05: list[float | None] | None = None
    q_total_p95: list[float | None] | None = None

    def predictions(self) -> list[Prediction]:
        """The block's rows as single predictions."""
        rows = []
        for i, when in enumerate(self.time):
            interval = {
                k: None if v is None else v[i]
                for k, v in (
                    ("q_total_std", self.q_total_std),
                    ("q_total_p05", self.q_total_p05),
                    ("q_total_p95", self.q_total_p95),
                )
            }
            rows.append(
                Prediction(
                    time=when,
                    q_total=self.q_total[i],
                    q_gas=self.q_gas[i],
                    q_oil=self.q_oil[i],
                    q_water=self.q_water[i],
                    model=self.model,
                    version=self.version,
                    q_total_std=interval["q_total_std"],
                    q_total_p05=interval["q_total_p05"],
                    q_total_p95=interval["q_total_p95"],
                )
            )
        return rows


def sensor_block(samples: Sequence[SensorSample]) -> bytes:
    """The JSON payload of a sensor block: one well's samples (rising in time) in one
    message, each field an array (see the module docstring)."""
    if not samples:
        raise ValueError("A sensor block needs at least one sample.")
    block: dict[str, list[Any]] = {
        "time": [s.time.isoformat().replace("+00:00", "Z") for s in samples]
    }
    for name in INPUT_COLUMNS:
        block[name] = [getattr(s, name) for s in samples]
    return json.dumps(block, allow_nan=False).encode()


Source = Literal["mpfm", "well_test"]


def validate_prefix(prefix: str) -> str:
    """A key-expression prefix: non-empty chunks, no wildcards, no leading/trailing '/'."""
    chunks = prefix.split("/")
    if not prefix or any(not c or any(ch in c for ch in "*$?#") for c in chunks):
        raise ConfigError(
            f"The key prefix '{prefix}' is invalid: use chunks separated by single '/', "
            "without wildcards or a leading/trailing '/', e.g. vfm or vfm/field-a."
        )
    return prefix


#: The longest well id accepted anywhere (files, Zenoh keys, HTTP paths), characters.
WELL_ID_MAX = 128


def well_id_problem(well: str) -> str | None:
    """Why ``well`` cannot be a well id, as a sentence; None when it can.

    One rule on every path (observation files, Zenoh keys, HTTP, the config): 1 to
    :data:`WELL_ID_MAX` characters, no control characters (a newline in an id would forge
    log lines), none of ``/ * $ ? #`` (they have a meaning in key expressions), not ``.`` or
    ``..``, no space at either end, and no ``@`` first (Zenoh reads such a chunk verbatim: no
    wildcard matches it, so ``<prefix>/**`` would never see the well's messages).
    """
    shown = repr(well[:40] + ("..." if len(well) > 40 else ""))
    if not well:
        return "The well id is empty."
    if len(well) > WELL_ID_MAX:
        return f"The well id {shown} has {len(well)} characters; at most {WELL_ID_MAX} are allowed."
    if any(unicodedata.category(ch) in ("Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp") for ch in well):
        return f"The well id {shown} holds control or invisible characters; use printable ones."
    if any(ch in well for ch in "/*$?#"):
        return (
            f"The well id {shown} cannot be used in a key expression (no '/', '*', '$', '?', '#')."
        )
    if well in (".", ".."):
        return f"The well id {shown} is not a name."
    if well != well.strip():
        return f"The well id {shown} starts or ends with a space."
    if well.startswith("@"):
        return (
            f"The well id {shown} starts with '@': Zenoh reads such a key chunk verbatim, so no "
            "wildcard subscriber (the service's, the field's) would see its messages."
        )
    return None


def validate_well_id(well: str) -> str:
    """``well`` if it is a valid well id (see :func:`well_id_problem`), else a ConfigError."""
    problem = well_id_problem(well)
    if problem is not None:
        raise ConfigError(problem)
    return well


def _well_chunk(well: str) -> str:
    return validate_well_id(well)


def sensors_key(prefix: str, well: str) -> str:
    return f"{prefix}/{_well_chunk(well)}/sensors"


def measurement_key(prefix: str, well: str, source: str) -> str:
    return f"{prefix}/{_well_chunk(well)}/measurements/{source}"


def prediction_key(prefix: str, well: str) -> str:
    return f"{prefix}/{_well_chunk(well)}/prediction"


#: a field client's flush (its id as the payload) and the service's answers to it
#: (``<prefix>/<FLUSHED_KEY>/<id>``): see :class:`service.transport.Flushes`
FLUSH_KEY = "_vfm-control/flush"
FLUSHED_KEY = "_vfm-control/flushed"


def parse_key(prefix: str, key: str) -> tuple[str, str, str | None] | None:
    """Split ``<prefix>/<well>/sensors`` or ``.../measurements/<source>`` into (well, kind, source)."""
    if not key.startswith(prefix + "/"):
        return None
    parts = key[len(prefix) + 1 :].split("/")
    if len(parts) == 2 and parts[1] in ("sensors", "prediction"):
        return parts[0], parts[1], None
    if len(parts) == 3 and parts[1] == "measurements":
        return parts[0], "measurements", parts[2]
    return None
