"""Reading a well (``GET /wells``, ``GET /wells/{well}``, ``GET /wells/{well}/history`` and
its CSV form ``history.csv``, ``GET /wells/{well}/parameters``) and retiring one
(``DELETE /wells/{well}``).

Query times follow the one rule for times (:func:`vfm_core.timeutil.time_problem`): a
time outside 1677-09-22..2262-04-10 answers 422 (``time out of range``), never 500.
"""

from __future__ import annotations

import json
from datetime import datetime
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import StreamingResponse

from service.errors import InvalidRequest, unknown_well
from service.http.deps import (
    EngineDep,
    KnownWell,
    MaybeEngineDep,
    ServiceDep,
    StoreDep,
    TokenDep,
    WellPath,
)
from service.http.model_changes import versions_of
from service.http.schemas import (
    ErrorOut,
    HistoryOut,
    ParameterHistoryOut,
    RetiredOut,
    WellOut,
    WellSummary,
)
from vfm_core.timeutil import REPRESENTABLE_MAX, REPRESENTABLE_MIN, iso, time_problem, to_ns, utc

__all__ = ["router"]

router = APIRouter(prefix="/wells", tags=["wells"])

#: the span of int64 epoch nanoseconds, the defaults of start and end
_EARLIEST = REPRESENTABLE_MIN
_LATEST = REPRESENTABLE_MAX


@router.get("", response_model=list[WellSummary], summary="All wells")
def list_wells(engine: MaybeEngineDep) -> list[dict[str, Any]]:
    return [] if engine is None else engine.well_summaries()


@router.get(
    "/{well}",
    response_model=WellOut,
    summary="One well's model state",
    responses={404: {"model": ErrorOut}},
)
def well_state(well: WellPath, engine: MaybeEngineDep, service: ServiceDep) -> dict[str, Any]:
    if engine is None:
        raise unknown_well(well)
    out = engine.well_view(well)
    st = engine.wells.get(well)
    if st is not None:  # the trial of the last model change (service.engine.trial)
        running = st.trial
        ended = list(st.trials)
        out["trial"] = running.view() if running is not None else (ended[-1] if ended else None)
        out["trials"] = ended
    out["versions"] = versions_of(service.store, well) if service.store is not None else []
    if st is not None:  # the alarm on the residuals (service.engine.residual_alarms)
        out["residual_alarm"] = st.residual_alarm_state()
        out["sensor_faults"] = st.sensor_faults_view()  # vfm_core.sensor_faults
        out["fallback"] = st.fallback  # the inputs replaced at the latest sample, or None
        out["latest_prediction"] = engine.observer.latest_prediction(well)
    return out


def _parse_time(value: str | None, name: str, default: datetime) -> datetime:
    if value is None:
        return default
    try:
        t = datetime.fromisoformat(value.strip().replace("Z", "+00:00"))
    except ValueError:
        raise InvalidRequest(
            f"{name}={value[:40]!r} is not an ISO 8601 time; write it like 2019-03-01T06:00:00Z.",
            "wrong type",
        ) from None
    problem = time_problem(t, what=name)
    if problem is not None:
        raise InvalidRequest(problem.rstrip(".") + "; omit it for no bound.", "time out of range")
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
            "q_total_std": s.q_total_std,
            "q_total_p05": s.q_total_p05,
            "q_total_p95": s.q_total_p95,
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


#: the most parameter rows one request returns
MAX_PARAMETER_ROWS = 10_000


@router.get(
    "/{well}/parameters",
    response_model=ParameterHistoryOut,
    summary="The physical parameters over time, with their uncertainty",
    description=(
        "The recorded rows of the well's physical parameters (store table parameter_history: "
        "one row per store.parameters_every model updates and one at each model change, the "
        "latest store.parameters_kept per well), per parameter as series of time, value and "
        "std (SI units; std only with a Bayesian method such as bayes), with its unit and "
        "bounds. A model change changes the names (an effect adds e.g. erosion.rate): a "
        "parameter's series holds the rows that have it; model_changes says where. The latest "
        "`limit` rows in [since, until) are returned, oldest first."
    ),
    responses={404: {"model": ErrorOut}, 422: {"model": ErrorOut}},
)
def well_parameters(
    well: KnownWell,
    store: StoreDep,
    since: Annotated[
        str | None, Query(description="ISO 8601, inclusive (default: the beginning)")
    ] = None,
    until: Annotated[str | None, Query(description="ISO 8601, exclusive (default: no end)")] = None,
    limit: Annotated[
        int,
        Query(ge=1, le=MAX_PARAMETER_ROWS, description="at most this many rows (the latest)"),
    ] = 2000,
) -> dict[str, Any]:
    t0 = _parse_time(since, "since", _EARLIEST)
    t1 = _parse_time(until, "until", _LATEST)
    if t1 <= t0:
        raise InvalidRequest(
            f"until ({t1.isoformat()}) must be after since ({t0.isoformat()}).", "wrong type"
        )
    rows, more = store.parameter_history(well, to_ns(t0), to_ns(t1), limit)
    series: dict[str, dict[str, Any]] = {}
    changes: list[dict[str, Any]] = []
    previous: str | None = None
    for row in rows:
        try:
            params = json.loads(row.parameters)
        except ValueError:  # pragma: no cover - written by this service as JSON
            continue
        when = iso(row.time_ns)
        if previous is not None and row.model != previous:
            changes.append({"time": when, "model_before": previous, "model_after": row.model})
        previous = row.model
        for name, p in params.items():
            s = series.setdefault(
                name,
                {
                    "unit": p.get("unit") or "",
                    "low": p.get("low"),
                    "high": p.get("high"),
                    "time": [],
                    "value": [],
                    "std": [],
                    "version": [],
                },
            )
            s["time"].append(when)
            s["value"].append(p.get("value"))
            s["std"].append(p.get("std"))
            s["version"].append(row.version)
    return {
        "well": well,
        "since": t0.isoformat(),
        "until": t1.isoformat(),
        "rows": len(rows),
        "truncated": more,
        "parameters": series,
        "model_changes": changes,
    }


@router.get(
    "/{well}/history.csv",
    summary="History as CSV in the observation format (streamed)",
    description=(
        "One row per stored sample (choke, p_up, p_down, t_up, eta_gas, eta_oil), with the "
        "measured q_total and its source on the row of the sample a learned measurement was "
        "paired with (or a row of its own at the measurement's time, with the paired sample's "
        "inputs), and the service's prediction at each sample (predicted, predicted_std, "
        "predicted_p05, predicted_p95, version). A first line '# ...' gives the units (bar "
        "absolute, degC, fractions, Sm3/h, UTC); comment=false leaves it out, so that vfm "
        "evaluate and vfm diagnose read the file as it is. At most http.max_export_rows rows."
    ),
    response_class=StreamingResponse,
    responses={
        200: {"content": {"text/csv": {}}},
        404: {"model": ErrorOut},
        422: {"model": ErrorOut},
    },
)
def well_history_csv(
    well: KnownWell,
    service: ServiceDep,
    start: Annotated[str | None, Query(description="ISO 8601, inclusive")] = None,
    end: Annotated[str | None, Query(description="ISO 8601, exclusive")] = None,
    limit: Annotated[int | None, Query(ge=1, description="at most this many rows")] = None,
    comment: Annotated[bool, Query(description="a first '# units' line")] = True,
) -> StreamingResponse:
    from service.export import connect_read_only, csv_lines

    t0 = _parse_time(start, "start", _EARLIEST)
    t1 = _parse_time(end, "end", _LATEST)
    if t1 <= t0:
        raise InvalidRequest(
            f"end ({t1.isoformat()}) must be after start ({t0.isoformat()}).", "wrong type"
        )
    cap = service.settings.http.max_export_rows
    con = connect_read_only(service.settings.store.path)
    lines = csv_lines(
        con,
        well,
        to_ns(t0),
        to_ns(t1),
        limit=min(limit or cap, cap),
        comment=comment,
        close=True,
    )
    return StreamingResponse(
        lines,
        media_type="text/csv; charset=utf-8",
        headers={"Content-Disposition": f'attachment; filename="{well}-history.csv"'},
    )


@router.delete(
    "/{well}",
    response_model=RetiredOut,
    summary="Retire a well: stop serving it, keep (default) or purge its data",
    description=(
        "After what is queued for the well, its model is checkpointed and it is no longer "
        "served or loaded at a restart; its messages are refused as 'retired well'. Its data "
        "(samples, predictions, measurements, checkpoints) stay in the store, readable with "
        "vfm export, unless purge=true deletes them all, which also frees the id for a new "
        "well. Needs the bearer token."
    ),
    responses={
        401: {"model": ErrorOut},
        403: {"model": ErrorOut},
        404: {"model": ErrorOut},
        503: {"model": ErrorOut},
    },
)
def retire_well(
    _: TokenDep,
    well: KnownWell,
    engine: EngineDep,
    purge: Annotated[bool, Query(description="also delete every row of the well")] = False,
) -> dict[str, Any]:
    return engine.retire_well(well, purge=purge)
