"""``GET /wells``, ``GET /wells/{well}`` and ``GET /wells/{well}/history``: reading a well."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query

from service.errors import InvalidRequest, unknown_well
from service.http.deps import KnownWell, MaybeEngineDep, StoreDep, WellPath
from service.http.schemas import ErrorOut, HistoryOut, WellOut, WellSummary
from vfm_core.timeutil import iso, to_ns, utc

__all__ = ["router"]

router = APIRouter(prefix="/wells", tags=["wells"])

#: the span of int64 epoch nanoseconds, the defaults of start and end
_EARLIEST = datetime(1677, 9, 22, tzinfo=UTC)
_LATEST = datetime(2262, 4, 11, tzinfo=UTC)


@router.get("", response_model=list[WellSummary], summary="All wells")
def list_wells(engine: MaybeEngineDep) -> list[dict[str, Any]]:
    return [] if engine is None else engine.well_summaries()


@router.get(
    "/{well}",
    response_model=WellOut,
    summary="One well's model state",
    responses={404: {"model": ErrorOut}},
)
def well_state(well: WellPath, engine: MaybeEngineDep) -> dict[str, Any]:
    if engine is None:
        raise unknown_well(well)
    return engine.well_view(well)


def _parse_time(value: str | None, name: str, default: datetime) -> datetime:
    if value is None:
        return default
    try:
        t = datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise InvalidRequest(
            f"{name}='{value}' is not an ISO 8601 time; write it like 2019-03-01T06:00:00Z.",
            "wrong type",
        ) from None
    return utc(t)


@router.get(
    "/{well}/history",
    response_model=HistoryOut,
    summary="Samples, predictions, measurements",
    responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
def well_history(
    well: KnownWell,
    store: StoreDep,
    start: Annotated[
        str | None, Query(description="ISO 8601, inclusive (default: the beginning)")
    ] = None,
    end: Annotated[str | None, Query(description="ISO 8601, exclusive (default: no end)")] = None,
    limit: Annotated[
        int, Query(ge=1, le=100_000, description="at most this many rows per list")
    ] = 10_000,
) -> dict[str, Any]:
    t0 = _parse_time(start, "start", _EARLIEST)
    t1 = _parse_time(end, "end", _LATEST)
    if t1 <= t0:
        raise InvalidRequest(
            f"end ({t1.isoformat()}) must be after start ({t0.isoformat()}).", "wrong type"
        )
    samples, measurements = store.history(well, to_ns(t0), to_ns(t1), limit)
    s_out = [
        {
            "time": iso(s.time_ns),
            "choke": s.choke,
            "p_up": s.p_up,
            "p_down": s.p_down,
            "t_up": s.t_up,
            "eta_gas": s.eta_gas,
            "eta_oil": s.eta_oil,
            "received": iso(s.received_ns),
        }
        for s in samples
    ]
    p_out = [
        {
            "time": iso(s.time_ns),
            "q_total": s.q_total,
            "q_gas": s.q_gas,
            "q_oil": s.q_oil,
            "q_water": s.q_water,
            "version": s.version,
        }
        for s in samples
        if s.q_total is not None
    ]
    m_out = [
        {
            "time": iso(m.time_ns),
            "source": m.source,
            "q_total": m.q_total,
            "received": iso(m.received_ns),
            "via": m.via,
            "status": m.status,
            "paired_sample_time": iso(m.sample_time_ns),
            "predicted": m.predicted,
            "version_after": m.version_after,
        }
        for m in measurements
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
