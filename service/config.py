"""The service's settings: one validated tree, loaded once at start-up.

Sources, highest priority first: keyword overrides (tests), ``VFM_`` environment
variables with ``__`` between levels (``VFM_HTTP__PORT=8001``,
``VFM_MODEL__NAME=ham``, lists and tables as JSON: ``VFM_ZENOH__CONNECT='["tcp/router:7447"]'``),
the config file (``--config FILE``, TOML or JSON), then the defaults below.

A bad value stops the program with :class:`vfm_core.errors.ConfigError`, one sentence
per problem that names the setting, the value and the valid choices.

Security defaults: the HTTP API and the Zenoh listener bind to loopback only; a
non-loopback address is refused unless ``http.allow_remote`` / ``zenoh.allow_remote``
is set. Mutating HTTP endpoints need ``http.token``.
"""

from __future__ import annotations

import ipaddress
import json
import tomllib
from contextvars import ContextVar
from datetime import datetime
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)
from pydantic_settings import BaseSettings, PydanticBaseSettingsSource, SettingsConfigDict
from pydantic_settings.exceptions import SettingsError

from vfm_core.errors import ConfigError
from vfm_core.messages import validate_prefix, well_id_problem
from vfm_core.timeutil import PLAUSIBLE_MIN, time_problem, utc

__all__ = [
    "Settings",
    "method_problem",
    "ModelSettings",
    "ZenohSettings",
    "HttpSettings",
    "StoreSettings",
    "InputSettings",
    "QueueSettings",
    "DriftSettings",
    "AlarmSettings",
    "ResidualAlarmSettings",
    "SensorFaultSettings",
    "WellTestReviewSettings",
    "SeparatorSettings",
    "load_settings",
    "is_loopback_host",
    "endpoint_host",
]

_CONFIG_FILE: ContextVar[Path | None] = ContextVar("vfm_config_file", default=None)


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


def method_problem(text: str, min_retrain_period_s: float) -> str | None:
    """Why ``text`` cannot be a well's learning method in the service, as a sentence; None
    when it can. The one rule for the config (``model.method``) and for
    ``PUT /wells/{well}/model``: a registered method (:func:`vfm_core.learning.parse_method`)
    that the streaming learner runs (``LearningMethod.streaming``: not ``pbl:auto``), whose
    retrain period, if it has one, is at least ``min_retrain_period_s`` (a retrain every
    nanosecond would keep a worker retraining forever).
    """
    from vfm_core.learning import METHODS, parse_method

    try:
        method = parse_method(text)
    except ConfigError as exc:
        return str(exc)
    if not method.streaming:
        live = ", ".join(cls.example for cls in METHODS.values() if cls.streaming)
        return (
            f"The method '{text}' is not available in the streaming service; use one of {live} "
            "(for drift-triggered retrains, as pbl:auto does, set drift.on_drift = 'retrain')."
        )
    period = getattr(method, "period", None)
    if period is not None and period.total_seconds() < min_retrain_period_s:
        return (
            f"The method '{text}' retrains every {period}; the service retrains at most every "
            f"{min_retrain_period_s:g} s (model.min_retrain_period_s), so that retraining cannot "
            "keep a worker busy: choose a longer period, e.g. pbl:14d."
        )
    return None


class ModelSettings(_Section):
    """The per-well model and its learning method (see ``vfm evaluate``)."""

    name: str = Field(
        default="mm",
        description="model: lr, nn, mm, hem, ham, last, or mtl (field-wide: one network shared "
        "by every well this instance serves, learning in day rounds; needs queues.workers = 1)",
    )
    method: str = Field(default="ol", description="ol or pbl:<period>[:window=<span>]")
    effects: list[str] = Field(
        default_factory=list,
        description="effects extending mm, hem or ham (vfm diagnose names them), e.g. "
        "['erosion', 'real_gas'] or 'mypkg.effects:Scale'",
    )
    effect_modules: list[str] = Field(
        default_factory=list,
        description="modules whose effect classes (module:Class) may be named in "
        "PUT /wells/{well}/model; the library's effects are always allowed",
    )
    seed: int = Field(default=0, ge=0)
    model_kwargs: dict[str, Any] = Field(default_factory=dict, description="model hyperparameters")
    train: dict[str, Any] = Field(default_factory=dict, description="overrides of TrainSettings")
    online: dict[str, Any] = Field(default_factory=dict, description="overrides of OnlineSettings")
    history: Path | None = Field(default=None, description="observation file for the initial fit")
    history_until: datetime | None = Field(
        default=None, description="only history rows before this time (UTC) are used"
    )
    retrain_budget_s: float = Field(
        default=30.0,
        ge=0,
        description="wall-clock budget of one retrain or first fit of a live well, s (0: none); "
        "past it the fit stops where it is (model.train.time_budget_s overrides it)",
    )
    min_retrain_period_s: float = Field(
        default=3600.0,
        ge=0,
        description="shortest retrain period a method may have (pbl:<period>), s; also over HTTP",
    )
    max_catch_up_retrains: int = Field(
        default=10,
        ge=1,
        description="when a sample or measurement comes more than this many retrain periods "
        "after the next scheduled retrain (a long gap), one retrain replaces them all",
    )
    change_budget_s: float = Field(
        default=300.0,
        gt=0,
        description="PUT /wells/{well}/model: how long the new model's fit may take, s; "
        "past it the change is abandoned (503) and the current model kept",
    )
    remember_max: int = Field(
        default=50_000,
        ge=10,
        description="measurements a well remembers at most (the latest) for retrains, model "
        "changes and checkpoints; each checkpoint stores them, so without a bound both grow "
        "for ever (50,000: 137 years of daily readings, 104 days of one every 3 minutes, about "
        "4.5 MB per checkpoint); with more, pbl retrains on the latest only (per-well models; "
        "the field-wide mtl remembers everything)",
    )

    @field_validator("name")
    @classmethod
    def _known_model(cls, v: str) -> str:
        from vfm_core.models import MODELS

        if v not in MODELS:
            raise ValueError(f"unknown model '{v}'; choose one of {', '.join(MODELS)}")
        return v

    @property
    def field_wide(self) -> bool:
        """True for a model whose parameters are shared by the wells (``mtl``): the service
        runs one :class:`vfm_core.learning.field.FieldLearner` for all the wells it serves."""
        from vfm_core.models import MODELS

        return bool(MODELS[self.name].shared)

    @field_validator("method")
    @classmethod
    def _known_method(cls, v: str) -> str:
        from vfm_core.learning import parse_method

        try:  # the full rule (with the minimum period) runs once every field is read
            parse_method(v)
        except ConfigError as exc:
            raise ValueError(str(exc).rstrip(".")) from None
        return v.strip()

    @field_validator("history_until")
    @classmethod
    def _utc(cls, v: datetime | None) -> datetime | None:
        return None if v is None else utc(v)

    @field_validator("effects", mode="before")
    @classmethod
    def _effect_list(cls, v: Any) -> Any:
        return [e.strip() for e in v.split(",") if e.strip()] if isinstance(v, str) else v

    @property
    def full_name(self) -> str:
        """The model with its effects, as checkpoints name it (e.g. ``mm+erosion``)."""
        from vfm_core.effects import resolve_effects

        return "+".join([self.name, *(c.name for c in resolve_effects(self.effects))])

    @model_validator(mode="after")
    def _settings_exist(self) -> ModelSettings:
        from vfm_core.learning import DEFAULT_ONLINE, DEFAULT_TRAIN, settings_from_dict

        problem = method_problem(self.method, self.min_retrain_period_s)
        if problem is not None:
            raise ValueError(f"model.method: {problem[0].lower()}{problem[1:]}".rstrip("."))

        if self.effects and self.field_wide:
            raise ValueError(
                f"model.effects: effects extend the physics models (mm, hem, ham), not the "
                f"field-wide '{self.name}'; remove model.effects or choose one of those models"
            )
        if self.effects:
            from vfm_core.learning.streaming import WellLearner

            try:
                WellLearner("check", self.name, "ol", effects=self.effects)
            except ConfigError as exc:
                raise ValueError(f"model.effects: {exc}".rstrip(".")) from None

        for what, base, given in (
            ("train", DEFAULT_TRAIN[self.name], self.train),
            ("online", DEFAULT_ONLINE[self.name], self.online),
        ):
            try:
                settings_from_dict(base, given)
            except (ConfigError, TypeError) as exc:
                raise ValueError(f"model.{what}: {exc}".rstrip(".")) from None
        return self


def is_loopback_host(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``."""
    host = host.strip("[]")
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def endpoint_host(endpoint: str) -> str | None:
    """The host of a Zenoh endpoint ``proto/host:port[#...]``; None for local-only transports."""
    proto, _, rest = endpoint.partition("/")
    if proto.startswith("unixsock") or proto in ("unixpipe", "vsock"):
        return None
    rest = rest.split("#", 1)[0].split("?", 1)[0]
    if rest.startswith("["):
        return rest[1 : rest.find("]")]
    return rest.rsplit(":", 1)[0]


class ZenohSettings(_Section):
    """How the service joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = False
    #: a BLOCK put that has waited this long closes the link (zenoh's default is 5 s)
    block_wait_before_close_ms: int = Field(default=60_000, ge=1)
    allow_remote: bool = Field(default=False, description="allow listen endpoints outside loopback")
    wells: list[str] = Field(
        default_factory=list,
        description="scale-out: the wells this instance owns, as well ids with * for any "
        "characters (e.g. ['W0*', 'W1*']); empty: every well. It subscribes only to these "
        "wells' key expressions; a well must never belong to two instances",
    )
    instance_check_s: float = Field(
        default=2.0,
        ge=0,
        description="at start, how long to wait for other instances to say which wells they "
        "own (an overlap stops this one), s; 0: no check",
    )

    @field_validator("wells", mode="before")
    @classmethod
    def _well_list(cls, v: Any) -> Any:
        return [w.strip() for w in v.split(",") if w.strip()] if isinstance(v, str) else v

    @field_validator("wells")
    @classmethod
    def _patterns(cls, v: list[str]) -> list[str]:
        from service.scaleout import overlapping, pattern_problem

        for pattern in v:
            problem = pattern_problem(pattern)
            if problem is not None:
                raise ValueError(problem[0].lower() + problem[1:].rstrip("."))
        for i, a in enumerate(v):
            pair = overlapping([a], v[i + 1 :]) if v[i + 1 :] else None
            if pair is not None:
                raise ValueError(
                    f"the patterns '{pair[0]}' and '{pair[1]}' match the same well ids; "
                    "merge them or make them disjoint, so that each message arrives once"
                )
        return v

    @model_validator(mode="after")
    def _loopback(self) -> ZenohSettings:
        if self.mode == "client" and not self.connect:
            raise ValueError(
                "zenoh.mode = 'client' needs at least one zenoh.connect endpoint (the router), "
                "e.g. ['tcp/127.0.0.1:7447']"
            )
        for ep in self.listen:
            if "/" not in ep:
                raise ValueError(f"zenoh.listen endpoint '{ep}' is not of the form tcp/HOST:PORT")
            host = endpoint_host(ep)
            if host is not None and not is_loopback_host(host) and not self.allow_remote:
                raise ValueError(
                    f"zenoh.listen endpoint '{ep}' is not on loopback; listening on other "
                    "interfaces exposes the service: set zenoh.allow_remote = true to allow it, "
                    "or use tcp/127.0.0.1:PORT"
                )
        for ep in self.connect:
            if "/" not in ep:
                raise ValueError(f"zenoh.connect endpoint '{ep}' is not of the form tcp/HOST:PORT")
        return self


class HttpSettings(_Section):
    """The HTTP API (FastAPI on uvicorn)."""

    host: str = "127.0.0.1"
    port: int = Field(default=8000, ge=0, le=65535, description="0 picks a free port")
    allow_remote: bool = Field(default=False, description="allow binding outside loopback")
    token: SecretStr | None = Field(default=None, description="bearer token for mutating endpoints")
    max_body_bytes: int = Field(
        default=65_536, ge=1024, description="largest request body accepted (413 above), bytes"
    )
    max_connections: int = Field(
        default=64, ge=1, description="concurrent connections and requests (503 above)"
    )
    max_model_changes: int = Field(
        default=1, ge=1, description="model changes fitted at the same time (503 above)"
    )
    shutdown_grace_s: int = Field(
        default=5,
        ge=0,
        description="at SIGTERM, how long requests in flight (a model change) may take to "
        "finish before the service stops anyway, s",
    )
    max_export_rows: int = Field(
        default=1_000_000, ge=1, description="most rows GET /wells/{well}/history.csv returns"
    )
    diagnosis_budget_s: float = Field(
        default=900.0,
        gt=0,
        description="wall-clock budget of one diagnosis started over HTTP (POST "
        "/wells/{well}/diagnosis); it is stopped and reported as failed beyond it, s",
    )

    @model_validator(mode="after")
    def _loopback(self) -> HttpSettings:
        if not is_loopback_host(self.host) and not self.allow_remote:
            raise ValueError(
                f"http.host = '{self.host}' is not a loopback address; serving the API on other "
                "interfaces exposes it: set http.allow_remote = true (and http.token) to allow "
                "it, or use 127.0.0.1"
            )
        if self.token is not None and len(self.token.get_secret_value()) < 16:
            raise ValueError(
                "http.token must be at least 16 characters long; generate one with "
                "`python -c 'import secrets; print(secrets.token_urlsafe(32))'`"
            )
        return self


class StoreSettings(_Section):
    """The durable store (SQLite, WAL)."""

    path: Path = Path("vfm-store.sqlite")
    #: full: every commit is fsync'ed (survives power loss); normal: survives a killed process
    synchronous: Literal["full", "normal"] = "full"
    checkpoint_every: int = Field(
        default=10,
        ge=1,
        description="checkpoint after this many model updates (a restart re-learns the rest)",
    )
    keep_checkpoints: int = Field(default=3, ge=1, description="checkpoints kept per well")
    parameters_every: int = Field(
        default=10,
        ge=1,
        description="record a well's physical parameters (GET /wells/{well}/parameters) after "
        "this many model updates, and at every model change",
    )
    parameters_kept: int = Field(
        default=5000, ge=10, description="parameter rows kept per well (the oldest are pruned)"
    )


class InputSettings(_Section):
    """What is accepted and how measurements are paired with samples."""

    wells: list[str] = Field(default_factory=list, description="wells known from the start")
    unknown_wells: Literal["create", "reject"] = "create"
    max_future_s: float = Field(
        default=300.0,
        gt=0,
        description="reject times further ahead of the service's clock than this, s "
        "(the clock skew allowed; a sample from the future blocks the well's later ones until then)",
    )
    earliest_time: datetime = Field(
        default=PLAUSIBLE_MIN, description="reject times before this one (UTC) as implausible"
    )
    max_payload_bytes: int = Field(
        default=65_536, ge=256, description="largest Zenoh payload accepted, bytes"
    )
    max_json_depth: int = Field(
        default=32, ge=2, description="deepest JSON nesting accepted (a message is flat: 1)"
    )
    max_block_samples: int = Field(
        default=1000,
        ge=1,
        le=100_000,
        description="most samples in one sensor block (a message whose fields are arrays); "
        "max_payload_bytes bounds it too (about 100 bytes a sample)",
    )
    max_rate: float = Field(
        default=1e7, gt=0, description="largest measured q_total accepted, Sm3/h"
    )
    rate_factor: float = Field(
        default=20.0,
        ge=0,
        description="refuse a q_total more than this many times above or below the median of "
        "the well's recent measurements (0: off)",
    )
    rate_history: int = Field(
        default=50, ge=1, description="recent measurements of a well whose median is the reference"
    )
    rate_min_history: int = Field(
        default=5, ge=1, description="measurements a well needs before rate_factor applies"
    )
    max_wells: int = Field(
        default=2000,
        ge=1,
        description="most wells the service holds; a new well beyond is refused "
        "(wells of the config, the store and the history are always loaded)",
    )
    new_wells_per_s: float = Field(
        default=10.0, gt=0, description="new wells created per second at most (on first sight)"
    )
    new_wells_burst: int = Field(
        default=100, ge=1, description="new wells that may appear at once before the rate applies"
    )
    well_rate_hz: float = Field(
        default=0.0,
        ge=0,
        description="per-well quota: messages per second a well may send (0: no quota; "
        "fairness then comes from the per-well queues alone)",
    )
    well_burst: int = Field(
        default=1000, ge=1, description="messages a well may send at once above well_rate_hz"
    )
    pair_tolerance_s: float = Field(
        default=300.0, ge=0, description="measurement-to-sample time tolerance"
    )
    pending_max: int = Field(
        default=100, ge=1, description="measurements waiting for their sample, per well"
    )
    pending_timeout_s: float = Field(default=60.0, gt=0, description="wall-clock wait for a sample")

    @field_validator("earliest_time")
    @classmethod
    def _earliest(cls, v: datetime) -> datetime:
        problem = time_problem(v, what="inputs.earliest_time")
        if problem is not None:
            raise ValueError(problem[0].lower() + problem[1:].rstrip("."))
        return utc(v)

    @field_validator("wells")
    @classmethod
    def _well_ids(cls, v: list[str]) -> list[str]:
        for well in v:
            problem = well_id_problem(well)
            if problem is not None:
                raise ValueError(problem[0].lower() + problem[1:].rstrip("."))
        return v


class QueueSettings(_Section):
    """Receive path: Zenoh FifoChannel -> receiver (the worker, or a thread) -> bounded
    per-worker queues."""

    receive_capacity: int = Field(
        default=64,
        ge=16,
        description="the Zenoh FifoChannel; a well's message waits behind at most this many "
        "messages of other wells before it reaches its own queue (small keeps that wait short; "
        "the senders' BLOCK congestion control buffers the rest)",
    )
    worker_capacity: int = Field(
        default=10_000,
        ge=16,
        description="messages a worker's queue holds at most (a sensor block counts 1 + "
        "rows/16: its memory in messages)",
    )
    well_capacity: int = Field(
        default=1000,
        ge=1,
        description="messages queued per well at most; the worker serves its wells round robin",
    )
    workers: int = Field(default=1, ge=1, le=64)
    receiver: Literal["worker", "thread"] = Field(
        default="worker",
        description="who takes the messages from Zenoh: 'worker', the one worker itself "
        "between its items (no receiver thread: a busy worker and a receiver thread handed "
        "the GIL to each other at every message, which cost more than the message's own "
        "work); 'thread', a receiver thread of its own (always so with more workers, or with "
        "zenoh.wells patterns)",
    )
    #: how long the receiver waits on a full worker queue or a full well queue
    #: (back-pressure through Zenoh's BLOCK congestion control) before it drops the message
    #: and counts a 'queue overflow' or 'well flooding'
    block_s: float = Field(default=10.0, ge=0)
    batch_max: int = Field(
        default=256, ge=1, description="at most this many messages per store commit"
    )
    batch_ms: float = Field(
        default=20.0, gt=0, description="commit and publish at least this often while busy, ms"
    )
    gc_freeze: bool = Field(
        default=True,
        description="`vfm serve`: once started, leave the objects loaded so far (the code of "
        "torch, pandas, ...) out of Python's cyclic garbage collector, whose full passes over "
        "them paused the workers 150-250 ms every few seconds under load",
    )
    gc_refreeze_s: float = Field(
        default=10.0,
        ge=0,
        description="`vfm serve` with gc_freeze: freeze again this often, s (0: at start only): "
        "what stays alive since (wells built after start, their growing state) leaves the "
        "collector too, so its full passes stay short as the service fills (they reached 350 ms "
        "after 7 minutes at 1,000 wells and 1 Hz with one freeze at start)",
    )
    gc_thaw_s: float = Field(
        default=3600.0,
        gt=0,
        description="`vfm serve` with gc_freeze: this often, s, unfreeze everything and collect "
        "once in full before freezing again, so that frozen objects that later form garbage "
        "cycles are freed (one full pass, a few hundred ms)",
    )


class DriftSettings(_Section):
    """The per-well streaming Hotelling T^2 test on the inputs of paired measurements: a
    notice "operating point outside the training data", not an alarm (the alarm is
    ``residual_alarm``)."""

    enabled: bool = True
    reference_size: int = Field(default=200, ge=3)
    alpha: float = Field(default=0.01, gt=0, lt=1)
    confirm: int = Field(default=5, ge=1)
    #: record: store and show a confirmed drift; retrain: also retrain the well on its data
    on_drift: Literal["record", "retrain"] = "record"


class AlarmSettings(_Section):
    """When the service raises a well's alarms (GET /wells/{well}, the workbench)."""

    mpfm_well_test_rel: float = Field(
        default=0.1,
        ge=0,
        description="alarm when the median of a well's MPFM readings near a well test differs "
        "from the well test by more than this fraction of it (0: off)",
    )
    mpfm_well_test_window_s: float = Field(
        default=86_400.0,
        gt=0,
        description="the MPFM readings compared with a well test lie within this many seconds "
        "of it, either side",
    )


class WellTestReviewSettings(_Section):
    """Well-test QC (:class:`service.engine.alarms.WellTestReview`; ``docs/guide/sensor-faults.md``):
    a well test far outside the model's predictive distribution, and off the MPFM near it
    too, is held for the operator's review instead of being learned."""

    enabled: bool = Field(
        default=True, description="hold such well tests for review (false: learn every one)"
    )
    k: float = Field(
        default=3.29,
        ge=2,
        le=20,
        description="hold when |log(well test / prediction)| exceeds k predictive sd: 3.29 holds "
        "1 well test in 1,000 that the model's own (Gaussian) distribution would produce",
    )
    min_residuals: int = Field(
        default=10,
        ge=3,
        le=1000,
        description="a method without an interval: the spread is taken from the well's last "
        "learned residuals, and no well test is held before it has this many",
    )
    residuals: int = Field(
        default=50, ge=3, le=1000, description="recent learned residuals kept per well"
    )
    min_sd: float = Field(
        default=0.01,
        gt=0,
        le=1,
        description="floor of the predictive sd in log space (a well test is seldom better "
        "than 1 %)",
    )


class SeparatorSettings(_Section):
    """Which wells flow into which separator (``docs/guide/separator.md``): a reading of a
    separator's total (``<prefix>/<separator>/measurements/separator`` or
    ``POST /separators/{name}/measurements``) measures the sum of its wells' rates; wells
    with ``bayes`` learn from it jointly and it is allocated back to them."""

    members: dict[str, list[str]] = Field(
        default_factory=dict,
        description="separator -> the wells that flow into it (a well flows into one "
        "separator; a separator's name is not a well's)",
    )
    noise: float = Field(
        default=0.015,
        gt=0,
        le=0.5,
        description="relative noise (sd) of a separator's total: a separator meter's 1-2 %",
    )
    sample_window_s: float = Field(
        default=21_600.0,
        gt=0,
        description="a member well counts at a reading with its latest sample at or before "
        "it, if at most this old, s; older (or none): shut in, it contributes 0",
    )
    learn: bool = Field(
        default=True,
        description="the wells (bayes) learn from each reading; false: readings are "
        "allocated (and their residuals kept) without moving the wells' models",
    )
    cross: bool = Field(
        default=True,
        description="keep the cross-covariances between a separator's wells, so that a "
        "well test of one moves the others (as vfm evaluate); false: block-diagonal, each "
        "well's own filter state only",
    )

    @field_validator("members")
    @classmethod
    def _one_separator_per_well(cls, v: dict[str, list[str]]) -> dict[str, list[str]]:
        seen: dict[str, str] = {}
        for sep, wells in v.items():
            for name in (sep, *wells):
                problem = well_id_problem(name)
                if problem is not None:
                    raise ValueError(problem[0].lower() + problem[1:].rstrip("."))
            if not wells:
                raise ValueError(
                    f"the separator '{sep}' has no wells; list the wells that flow into it"
                )
            for well in wells:
                if well in seen:
                    where = "twice" if seen[well] == sep else f"on '{seen[well]}' and on '{sep}'"
                    raise ValueError(
                        f"the well '{well}' is listed {where}; a well flows into one separator"
                    )
                seen[well] = sep
        clash = sorted(set(v) & set(seen))
        if clash:
            raise ValueError(
                f"'{clash[0]}' names a separator and a well; give the separator a name of its own"
            )
        return v

    def separator_of(self, well: str) -> str | None:
        """The separator ``well`` flows into (None: none)."""
        for sep, wells in self.members.items():
            if well in wells:
                return sep
        return None

    def route(self, well: str) -> str:
        """The name that places ``well`` on its worker: its separator's (a separator's
        wells all learn on one worker, where a reading updates them together), else its own."""
        if not self.members:
            return well
        return self.separator_of(well) or well


class TrialSettings(_Section):
    """The trial of a model change against the model it replaced, run as a shadow
    (``docs/guide/trials.md``; :mod:`service.engine.trial`)."""

    enabled: bool = Field(
        default=True,
        description="after a model change over HTTP, keep the replaced model running as a "
        "shadow on the same samples and compare both",
    )
    duration_s: float = Field(
        default=30 * 86_400.0,
        gt=0,
        description="the trial's length in data time (sample timestamps), s",
    )
    min_pairs: int = Field(
        default=30,
        ge=1,
        description="the trial goes on past duration_s until this many measurements are "
        "paired with both models' predictions",
    )
    max_duration_s: float = Field(
        default=180 * 86_400.0,
        gt=0,
        description="the trial ends at this data time after its start even with fewer pairs, s",
    )
    block_s: float = Field(
        default=86_400.0,
        gt=0,
        description="the paired differences are averaged over blocks of this much data time, "
        "s, before the test (meter errors are correlated within a day)",
    )
    alpha: float = Field(
        default=0.05,
        gt=0,
        lt=1,
        description="level of the one-sided test 'the shadow is better'; a rollback when p < alpha",
    )
    rule: Literal["block_t", "keep"] = Field(
        default="block_t",
        description="block_t: roll back when the one-sided t-test on block means says the "
        "shadow is better; keep: never roll back automatically (the trial only reports)",
    )
    keep_versions: int = Field(
        default=10,
        ge=1,
        le=1000,
        description="earlier model versions kept per well for a rollback",
    )


class SensorFaultSettings(_Section):
    """The instrument-fault detectors, per well and input (:mod:`vfm_core.sensor_faults`;
    ``docs/guide/sensor-faults.md``): frozen, spike, offset, drift, out of range."""

    enabled: bool = Field(
        default=True,
        description="run the detectors on every sample (about 25 us of CPU per sample at one "
        "a minute; false: no instrument faults, nothing held, and a sample with an input "
        "outside its physical span refused instead of taken as an out_of_range fault)",
    )
    false_per_well_year: float = Field(
        default=0.1,
        gt=0,
        le=10,
        description="false faults per well-year allowed over all of a well's tests (sets "
        "every test's threshold)",
    )


class ResidualAlarmSettings(_Section):
    """The alarm on the model's standardised residuals: a self-starting two-sided CUSUM
    per well and meter (:mod:`vfm_core.residual_alarm`; ``docs/guide/alarms.md``)."""

    enabled: bool = True
    arl0: float = Field(
        default=1000.0,
        ge=10,
        le=1e7,
        description="target in-control run length: periods between false alarms of one "
        "meter's stream when nothing changed; sets the CUSUM threshold h (Siegmund)",
    )
    k: float = Field(
        default=0.5,
        gt=0,
        le=3,
        description="CUSUM reference, in standard deviations of a period's mean residual "
        "(0.5: tuned to a shift of one standard deviation)",
    )
    mpfm_period_s: float = Field(
        default=86_400.0,
        ge=0,
        le=30 * 86_400.0,
        description="MPFM residuals are averaged over periods of this length, s (0: none)",
    )
    well_test_period_s: float = Field(
        default=0.0,
        ge=0,
        le=30 * 86_400.0,
        description="well-test residuals are averaged over periods of this length, s (0: none)",
    )
    window: int = Field(
        default=365, ge=5, le=100_000, description="period means in the self-starting scale"
    )
    min_periods: int = Field(
        default=30, ge=5, le=100_000, description="periods before a meter's stream is tested"
    )
    clip: float = Field(
        default=4.0, gt=0, le=100, description="bound on a standardised period mean"
    )
    lags: int = Field(
        default=3,
        ge=0,
        le=30,
        description="lags of the long-run (autocorrelation-corrected) scale, periods",
    )
    scale: Literal["winsorised", "mad"] = Field(
        default="winsorised",
        description="the self-starting reference's centre and scale: 'winsorised' (mean and "
        "sd of the period means clipped at median +- 3 robust sd) or 'mad' (median and "
        "1.4826 MAD, the rule before s45: too narrow for period means of varying counts)",
    )
    accept_periods: int = Field(
        default=30,
        ge=0,
        le=100_000,
        description="an alarm still active after this many periods closes as an accepted new "
        "level and the reference restarts from the periods since its signal (0: never, the "
        "rule before s46: an alarm whose level never comes back stays active for good)",
    )
    alarm_on_return: bool = Field(
        default=False,
        description="whether, after an accepted alarm, a return toward the level before it "
        "may raise an alarm (false, the default since s47: going back is quiet, going "
        "beyond the old level is an alarm; true: the rule of s46)",
    )

    @model_validator(mode="after")
    def _consistent(self) -> ResidualAlarmSettings:
        if self.min_periods > self.window:
            raise ValueError(
                f"residual_alarm.min_periods ({self.min_periods}) must not exceed "
                f"residual_alarm.window ({self.window})"
            )
        if 0 < self.accept_periods < 5:
            raise ValueError(
                f"residual_alarm.accept_periods ({self.accept_periods}) must be 0 (never) or "
                "at least 5 periods"
            )
        if self.clip <= self.k:
            raise ValueError(
                f"residual_alarm.clip ({self.clip}) must exceed residual_alarm.k ({self.k})"
            )
        return self


class Settings(BaseSettings):
    """Everything ``vfm serve`` can be told; see the module docstring for the sources."""

    model_config = SettingsConfigDict(
        env_prefix="VFM_", env_nested_delimiter="__", extra="forbid", validate_default=True
    )

    prefix: str = Field(default="vfm", description="key-expression prefix")
    model: ModelSettings = Field(default_factory=ModelSettings)
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    http: HttpSettings = Field(default_factory=HttpSettings)
    store: StoreSettings = Field(default_factory=StoreSettings)
    inputs: InputSettings = Field(default_factory=InputSettings)
    queues: QueueSettings = Field(default_factory=QueueSettings)
    drift: DriftSettings = Field(default_factory=DriftSettings)
    alarms: AlarmSettings = Field(default_factory=AlarmSettings)
    well_test_review: WellTestReviewSettings = Field(default_factory=WellTestReviewSettings)
    trial: TrialSettings = Field(default_factory=TrialSettings)
    residual_alarm: ResidualAlarmSettings = Field(default_factory=ResidualAlarmSettings)
    sensor_faults: SensorFaultSettings = Field(default_factory=SensorFaultSettings)
    separators: SeparatorSettings = Field(default_factory=SeparatorSettings)
    rolling_window: int = Field(
        default=50, ge=1, description="paired measurements in the rolling MAPE"
    )
    torch_threads: int = Field(
        default=1, ge=1, le=64, description="torch intra-op threads (tiny tensors: 1)"
    )
    log_level: Literal["debug", "info", "warning", "error"] = "info"

    @field_validator("prefix")
    @classmethod
    def _prefix(cls, v: str) -> str:
        try:
            return validate_prefix(v)
        except ConfigError as exc:
            raise ValueError(str(exc).rstrip(".")) from None

    @model_validator(mode="after")
    def _field_wide_on_one_worker(self) -> Settings:
        if self.model.field_wide and self.queues.workers > 1:
            raise ValueError(
                f"model.name = '{self.model.name}' is field-wide: one model learns from every well "
                "in time order, on one worker; set queues.workers = 1 (it is "
                f"{self.queues.workers}), or choose a per-well model to use more workers"
            )
        return self

    @model_validator(mode="after")
    def _own_wells(self) -> Settings:
        from service.scaleout import WellSet

        own = WellSet(self.zenoh.wells)
        outside = [w for w in self.inputs.wells if w not in own]
        if outside:
            raise ValueError(
                f"inputs.wells names {', '.join(outside[:5])}, outside this instance's wells "
                f"(zenoh.wells = {self.zenoh.wells}); list only the wells it owns"
            )
        return self

    @model_validator(mode="after")
    def _separators_apart_from_wells(self) -> Settings:
        from service.scaleout import WellSet

        members = self.separators.members
        named = sorted(set(members) & set(self.inputs.wells))
        if named:
            raise ValueError(
                f"separators.members names '{named[0]}' a separator, but inputs.wells lists it "
                "as a well; give the separator a name of its own"
            )
        own = WellSet(self.zenoh.wells)
        outside = [n for sep, ws in members.items() for n in (sep, *ws) if n not in own]
        if outside:
            raise ValueError(
                f"separators.members names {', '.join(outside[:5])}, outside this instance's "
                f"wells (zenoh.wells = {self.zenoh.wells}); a separator and its wells are "
                "served by one instance"
            )
        return self

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        return (init_settings, env_settings, _FileSource(settings_cls, _CONFIG_FILE.get()))

    def public_dict(self) -> dict[str, Any]:
        """The settings as JSON-safe values, the token masked."""
        data = self.model_dump(mode="json")
        data["http"]["token"] = "***" if self.http.token is not None else None
        return data


class _FileSource(PydanticBaseSettingsSource):
    """A TOML or JSON config file (by suffix)."""

    def __init__(self, settings_cls: type[BaseSettings], path: Path | None) -> None:
        super().__init__(settings_cls)
        self.path = path
        self.data = _read_config_file(path) if path is not None else {}

    def get_field_value(self, field: Any, field_name: str) -> tuple[Any, str, bool]:
        return self.data.get(field_name), field_name, False

    def __call__(self) -> dict[str, Any]:
        return dict(self.data)


def _read_config_file(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise ConfigError(
            f"The config file {path} does not exist; give the path of a .toml or .json file."
        )
    suffix = path.suffix.lower()
    try:
        if suffix == ".toml":
            with path.open("rb") as handle:
                data = tomllib.load(handle)
        elif suffix == ".json":
            data = json.loads(path.read_text(encoding="utf-8"))
        else:
            raise ConfigError(f"The config file {path} must end in .toml or .json, not '{suffix}'.")
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"The config file {path} cannot be read: {exc}.") from None
    if not isinstance(data, dict):
        raise ConfigError(f"The config file {path} must hold a table of settings at the top level.")
    # relative paths in the file are relative to the file, not to the working directory
    base = path.resolve().parent
    for section, key in (("store", "path"), ("model", "history")):
        value = data.get(section, {}).get(key) if isinstance(data.get(section), dict) else None
        if isinstance(value, str) and value and not Path(value).is_absolute():
            data[section][key] = str(base / value)
    return data


def _describe(error: dict[str, Any]) -> str:
    where = ".".join(str(p) for p in error.get("loc", ()) if p != "__root__")
    msg = str(error.get("msg", "invalid")).removeprefix("Value error, ")
    if error.get("type") == "extra_forbidden":
        return (
            f"The setting '{where}' is unknown; check its spelling against the documented settings."
        )
    value = error.get("input")
    shown = "" if isinstance(value, dict) or where == "" else f" = {value!r}"
    head = f"The setting '{where}'{shown}" if where else "The settings"
    return f"{head} is invalid: {msg}."


def load_settings(config_file: str | Path | None = None, **overrides: Any) -> Settings:
    """Load and validate the settings; raise :class:`ConfigError` with every problem found."""
    token = _CONFIG_FILE.set(Path(config_file) if config_file is not None else None)
    try:
        return Settings(**overrides)
    except ValidationError as exc:
        problems = [_describe(e) for e in exc.errors(include_url=False)]  # type: ignore[arg-type]
        raise ConfigError(" ".join(problems)) from None
    except SettingsError as exc:  # an environment variable that is not the JSON it must be
        raise ConfigError(
            f"{exc}. Environment variables set a list or a table as JSON, e.g. "
            """VFM_ZENOH__CONNECT='["tcp/router:7447"]' or VFM_ZENOH__WELLS='["W0*"]'; """
            "check the VFM_* variables of this shell."
        ) from None
    finally:
        _CONFIG_FILE.reset(token)
