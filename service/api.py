"""The HTTP API: thin routers over :class:`service.app.Service`, OpenAPI docs at ``/docs``.

=======================================  =====================================================
``GET /health``                          counts of accepted and rejected inputs (by reason),
                                         queue depths, overflow count
``GET /wells``                           every well with its model version
``GET /wells/{well}``                    model, method, physical parameters (value, unit),
                                         version, updates, last update, rolling MAPE, drift
``GET /wells/{well}/history``            samples, predictions and measurements in [start, end)
``POST /wells/{well}/well-tests``        a well-test result {time, q_total}: stored, then
                                         learned from; answers with the prediction before and
                                         after (bearer token required)
=======================================  =====================================================

Errors answer with ``{"detail": "<a sentence>", "reason": "<counter key>"}``: 401 (token
missing or wrong), 403 (no token configured), 404 (unknown well), 409 (duplicate), 422
(bad value), 503 (busy). Dependencies are injected with ``Annotated[..., Depends()]``,
so tests override :func:`get_service`.
"""

from __future__ import annotations

import asyncio
import secrets
from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Depends, FastAPI, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field

from service.app import Service
from service.engine import ModelChangeRefused, WellState, from_ns, to_ns
from service.inputs import REASONS, Rejected, classify_errors, parse_measurement
from vfm_core.messages import Measurement

__all__ = ["create_app", "get_service", "require_token"]

WELL_TEST_WAIT_S = 10.0


class ApiError(Exception):
    """An HTTP error with a sentence and a counter reason."""

    def __init__(
        self,
        status: int,
        detail: str,
        reason: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.reason = reason
        self.headers = headers


# -- response models (the OpenAPI schema) ----------------------------------------------------
class ErrorOut(BaseModel):
    detail: str = Field(description="what was wrong, as a sentence")
    reason: str | None = Field(None, description="the rejection counter this was counted under")


class HealthOut(BaseModel):
    status: str
    uptime_s: float
    wells: int
    accepted: dict[str, int] = Field(
        description="accepted inputs: sensors, measurements, well_tests"
    )
    rejected: dict[str, int] = Field(description="rejected inputs by reason")
    rejected_total: int
    not_ready: int = Field(
        description="samples not answered because the well's model had no data yet"
    )
    predictions_published: int
    learned: int
    overflow: int = Field(description="messages dropped because a worker queue stayed full")
    queue_depths: list[int]
    queue_capacity: int
    pending_measurements: int
    events: dict[str, int]
    zenoh: dict[str, Any]
    store: str


class Parameter(BaseModel):
    value: float
    unit: str


class RollingMape(BaseModel):
    value: float | None = Field(description="MAPE in percent over the last paired measurements")
    n: int
    window: int | None
    unit: str = "%"


class WellSummary(BaseModel):
    well: str
    model: str
    method: str
    ready: bool
    version: int
    n_updates: int
    last_update: str | None


class ModelChangeIn(BaseModel):
    model_config = ConfigDict(extra="forbid", protected_namespaces=())

    model: str | None = Field(
        default=None,
        description="base model: mm, hem, ham, lr, nn or last (default: the current one)",
    )
    effects: list[str] = Field(
        default_factory=list,
        description="effects extending mm, hem or ham, e.g. ['erosion'] or "
        "['erosion:step_at=2019-06-01', 'mypkg.effects:Scale']; [] for none",
    )
    method: str | None = Field(
        default=None, description="ol or pbl:<period> (default: the current one)"
    )


class HoldoutOut(BaseModel):
    holdout_rows: int = Field(description="latest stored measurements held out to compare")
    holdout_from: str | None = None
    before: float | None = Field(
        default=None, description="MAPE (%) of the current model, fitted on the older rows"
    )
    after: float | None = Field(
        default=None, description="MAPE (%) of the new model, fitted on the same rows"
    )
    unit: str = "%"
    fit_s: float | None = Field(default=None, description="time the fits took, s")


class ModelChangeOut(BaseModel):
    model_config = ConfigDict(protected_namespaces=())

    time: str
    model_before: str
    model_after: str
    effects: list[str] = Field(default_factory=list, description="the new model's effects")
    method: str
    version_before: int
    version_after: int
    holdout: HoldoutOut
    caught_up: int = Field(
        default=0,
        description="measurements learned while the new model was fitted, taught to it before the swap",
    )
    rolling_mape_before: float | None = Field(
        description="rolling MAPE (%) of the replaced model at the change"
    )


class WellOut(WellSummary):
    model_config = ConfigDict(protected_namespaces=())

    parameters: dict[str, Parameter] = Field(description="physical parameters, SI units")
    rolling_mape: RollingMape
    measurements_remembered: int = Field(
        description="measurements the model keeps for retrains and model changes"
    )
    model_changes: list[ModelChangeOut] = Field(
        description="models set over HTTP, oldest first; the rolling MAPE restarts at each"
    )
    drift: dict[str, Any]
    samples: int = Field(description="samples accepted since start")
    measurements: int = Field(description="measurements accepted since start")
    last_sample_time: str | None
    pending_measurements: int


class SampleOut(BaseModel):
    time: str
    choke: float
    p_up: float
    p_down: float
    t_up: float
    eta_gas: float
    eta_oil: float
    received: str


class PredictionOut(BaseModel):
    time: str
    q_total: float
    q_gas: float | None
    q_oil: float | None
    q_water: float | None
    version: int | None


class MeasurementOut(BaseModel):
    time: str
    source: str
    q_total: float
    received: str
    via: str
    status: str = Field(description="pending | learned | unpaired")
    paired_sample_time: str | None
    predicted: float | None = Field(
        description="the prediction at the paired sample, before learning"
    )
    version_after: int | None


class HistoryOut(BaseModel):
    well: str
    start: str
    end: str
    samples: list[SampleOut]
    predictions: list[PredictionOut]
    measurements: list[MeasurementOut]
    truncated: bool


class WellTestOut(BaseModel):
    well: str
    time: str
    q_total: float
    stored: bool = True
    status: str = Field(
        description="learned, or pending (waiting for the sensor sample at its time)"
    )
    message: str
    paired_sample_time: str | None
    before: dict[str, float | None] = Field(
        description="prediction at the paired sample before learning, Sm3/h"
    )
    after: dict[str, float | None] = Field(
        description="prediction at the same inputs after learning, Sm3/h"
    )
    version_before: int
    version_after: int
    model_changed: bool


# -- dependencies ------------------------------------------------------------------------------
def get_service(request: Request) -> Service:
    return request.app.state.service  # type: ignore[no-any-return]


ServiceDep = Annotated[Service, Depends(get_service)]
_bearer = HTTPBearer(auto_error=False, description="the service's http.token")


def require_token(
    service: ServiceDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Mutating endpoints: 403 when no token is configured, 401 when it is missing or wrong."""
    token = service.settings.http.token
    if token is None:
        raise ApiError(
            403,
            "Posting is disabled because no API token is configured; set http.token in the config file "
            "or VFM_HTTP__TOKEN in the environment, restart, and send 'Authorization: Bearer <token>'.",
        )
    if credentials is None or not secrets.compare_digest(
        credentials.credentials.encode(), token.get_secret_value().encode()
    ):
        raise ApiError(
            401,
            "A valid bearer token is required: send 'Authorization: Bearer <token>' "
            "with the service's http.token.",
            headers={"WWW-Authenticate": "Bearer"},
        )


TokenDep = Annotated[None, Depends(require_token)]
WellPath = Annotated[str, Path(description="well id", min_length=1, max_length=200)]


def _state(service: Service, well: str) -> WellState:
    engine = service.engine
    st = engine.wells.get(well) if engine is not None else None
    if st is None:
        raise ApiError(
            404,
            f"The well '{well}' is not known to this service; GET /wells lists the wells.",
            reason=None,
        )
    return st


def _iso(ns: int | None) -> str | None:
    return None if ns is None else from_ns(int(ns)).isoformat().replace("+00:00", "Z")


# -- routers -----------------------------------------------------------------------------------
health_router = APIRouter(tags=["health"])
wells_router = APIRouter(prefix="/wells", tags=["wells"])


@health_router.get("/health", response_model=HealthOut, summary="Counters, queues and status")
def health(service: ServiceDep) -> dict[str, Any]:
    return service.health()


@wells_router.get("", response_model=list[WellSummary], summary="All wells")
def list_wells(service: ServiceDep) -> list[dict[str, Any]]:
    engine = service.engine
    if engine is None:
        return []
    return [dict(st.snapshot) for st in list(engine.wells.values())]


@wells_router.get(
    "/{well}",
    response_model=WellOut,
    summary="One well's model state",
    responses={404: {"model": ErrorOut}},
)
def well_state(well: WellPath, service: ServiceDep) -> dict[str, Any]:
    st = _state(service, well)
    out = dict(st.snapshot)
    out.update(
        rolling_mape=st.rolling_mape(),
        drift=st.drift_state(),
        samples=st.samples,
        measurements=st.measurements,
        last_sample_time=_iso(st.last_time_ns),
        pending_measurements=len(st.pending),
        model_changes=list(st.model_changes),
    )
    return out


@wells_router.put(
    "/{well}/model",
    response_model=ModelChangeOut,
    summary="Replace the well's model (e.g. add an effect found by vfm diagnose)",
    description=(
        "Fits the new model on the well's stored history, compares it with the current one on "
        "the latest 20 % of that history, then swaps it in between two messages with a higher "
        "version; learning goes on during the fit and nothing is lost. Needs the bearer token. "
        "GET /wells/{well} then shows the new model, its parameters and its rolling MAPE."
    ),
    responses={
        401: {"model": ErrorOut},
        403: {"model": ErrorOut, "description": "no token configured, or a module not allowed"},
        404: {"model": ErrorOut},
        409: {"model": ErrorOut},
        422: {"model": ErrorOut},
        503: {"model": ErrorOut},
    },
)
def change_model(
    well: WellPath, body: ModelChangeIn, service: ServiceDep, _: TokenDep
) -> dict[str, Any]:
    engine = service.engine
    if engine is None:
        raise ApiError(503, "The service is starting; retry in a few seconds.")
    try:
        return engine.change_model(well, body.model, body.effects, body.method)
    except ModelChangeRefused as exc:
        raise ApiError(exc.status, exc.message) from None


def _parse_time(value: str | None, name: str, default: datetime) -> datetime:
    if value is None:
        return default
    try:
        t = datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise ApiError(
            422,
            f"{name}='{value}' is not an ISO 8601 time; write it like 2019-03-01T06:00:00Z.",
            reason="wrong type",
        ) from None
    return t.replace(tzinfo=UTC) if t.tzinfo is None else t.astimezone(UTC)


@wells_router.get(
    "/{well}/history",
    response_model=HistoryOut,
    summary="Samples, predictions, measurements",
    responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
def well_history(
    well: WellPath,
    service: ServiceDep,
    start: Annotated[
        str | None, Query(description="ISO 8601, inclusive (default: the beginning)")
    ] = None,
    end: Annotated[str | None, Query(description="ISO 8601, exclusive (default: no end)")] = None,
    limit: Annotated[
        int, Query(ge=1, le=100_000, description="at most this many rows per list")
    ] = 10_000,
) -> dict[str, Any]:
    _state(service, well)
    t0 = _parse_time(start, "start", datetime(1677, 9, 22, tzinfo=UTC))
    t1 = _parse_time(end, "end", datetime(2262, 4, 11, tzinfo=UTC))
    if t1 <= t0:
        raise ApiError(
            422,
            f"end ({t1.isoformat()}) must be after start ({t0.isoformat()}).",
            reason="wrong type",
        )
    assert service.store is not None
    samples, measurements = service.store.history(well, to_ns(t0), to_ns(t1), limit)
    s_out, p_out = [], []
    for t, choke, p_up, p_down, t_up, eg, eo, rec, q, qg, qo, qw, version in samples:
        s_out.append(
            {
                "time": _iso(t),
                "choke": choke,
                "p_up": p_up,
                "p_down": p_down,
                "t_up": t_up,
                "eta_gas": eg,
                "eta_oil": eo,
                "received": _iso(rec),
            }
        )
        if q is not None:
            p_out.append(
                {
                    "time": _iso(t),
                    "q_total": q,
                    "q_gas": qg,
                    "q_oil": qo,
                    "q_water": qw,
                    "version": version,
                }
            )
    m_out = [
        {
            "time": _iso(t),
            "source": src,
            "q_total": q,
            "received": _iso(rec),
            "via": via,
            "status": status,
            "paired_sample_time": _iso(st_ns),
            "predicted": pred,
            "version_after": ver,
        }
        for t, src, q, rec, via, status, st_ns, pred, ver in measurements
    ]
    return {
        "well": well,
        "start": t0.isoformat(),
        "end": t1.isoformat(),
        "samples": s_out,
        "predictions": p_out,
        "measurements": m_out,
        "truncated": len(samples) >= limit or len(measurements) >= limit,
    }


@wells_router.post(
    "/{well}/well-tests",
    response_model=WellTestOut,
    summary="Post a well-test result: stored durably, then learned from",
    responses={
        202: {
            "model": WellTestOut,
            "description": "stored; waiting for the sensor sample at its time",
        },
        401: {"model": ErrorOut},
        403: {"model": ErrorOut},
        404: {"model": ErrorOut},
        409: {"model": ErrorOut},
        422: {"model": ErrorOut},
        503: {"model": ErrorOut},
    },
)
async def post_well_test(
    well: WellPath, test: Measurement, service: ServiceDep, _: TokenDep
) -> Any:
    engine = service.engine
    if engine is None:
        raise ApiError(503, "The service is starting; retry in a few seconds.")
    try:
        checked = parse_measurement(test.model_dump(mode="json"))
        future = engine.submit_well_test(well, checked)
    except Rejected as r:  # refused before reaching the worker: count it here
        service.counters.reject(r.reason, r.message, where=f"POST /wells/{well}/well-tests")
        raise ApiError(r.status, r.message, reason=r.reason) from None
    try:
        result = await asyncio.wait_for(asyncio.wrap_future(future), WELL_TEST_WAIT_S)
    except Rejected as r:  # refused by the worker, which counted it
        raise ApiError(r.status, r.message, reason=r.reason) from None
    except TimeoutError:
        raise ApiError(
            503,
            f"The well test was queued but not handled within {WELL_TEST_WAIT_S:g} s; the "
            f"service is overloaded. It is still stored once handled; check GET /wells/{well}/history.",
        ) from None
    body = WellTestOut(**result.__dict__).model_dump()
    return JSONResponse(body, status_code=200 if result.status == "learned" else 202)


def create_app(service: Service) -> FastAPI:
    """The FastAPI app for a service (``app.state.service``)."""
    app = FastAPI(
        title="vfm: streaming virtual flow meter",
        version="1",
        description=(
            "Predicted rates for every sensor sample over Zenoh; model state, history and well tests over "
            "HTTP. Units: bar absolute, degC, fractions 0..1, Sm3/h; times ISO 8601 UTC. "
            "Rejection reasons: " + "; ".join(f"'{k}': {v}" for k, v in REASONS.items()) + "."
        ),
    )
    app.state.service = service

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return JSONResponse(
            {"detail": exc.detail, "reason": exc.reason},
            status_code=exc.status,
            headers=exc.headers,
        )

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = list(exc.errors())
        reason, sentence = classify_errors(errors)  # type: ignore[arg-type]
        on_body = any(e.get("loc", ("",))[0] == "body" for e in errors)
        svc: Service = request.app.state.service
        if on_body:
            svc.counters.reject(reason, sentence, where=f"{request.method} {request.url.path}")
        return JSONResponse({"detail": sentence, "reason": reason}, status_code=422)

    app.include_router(health_router)
    app.include_router(wells_router)
    return app
