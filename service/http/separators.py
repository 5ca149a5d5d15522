"""The separators over HTTP (``docs/guide/separator.md``): the latest allocation of each
separator's total, and readings posted by hand.

* ``GET /separators``: every configured separator (``separators.members``) with its wells
  and its latest settled reading (time, measured total, sum of the wells' predictions,
  reconciliation residual; Sm3/h).
* ``GET /separators/{name}``: the separator's wells, its latest allocation (per well the
  prediction ``q_pred``, allocated rate ``q_alloc`` and 90 % interval ``lo90``/``hi90``,
  Sm3/h, and the reading's residual = measured total - sum of predictions), its recent
  readings (for the workbench's chart) and its readings counted by status.
* ``POST /separators/{name}/measurements`` (token): a reading ``{time, q_total}`` (Sm3/h),
  checked by :func:`service.inputs.parse_measurement` as a Zenoh reading is; answered once
  stored, with its allocation (200) or ``pending`` while it waits for its wells' samples (202).
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Request
from fastapi.responses import JSONResponse

from service.errors import Busy, InvalidRequest, ServiceError
from service.http.deps import CountersDep, EngineDep, ServiceDep, TokenDep
from service.http.schemas import POSTED_MEASUREMENT_ERRORS, ErrorOut, measurement_body
from service.inputs import Limits, parse_measurement
from vfm_core.messages import WELL_ID_MAX, Measurement, well_id_problem

__all__ = ["router", "READING_WAIT_S"]

#: how long a caller waits for its reading to be stored (and allocated), s
READING_WAIT_S = 10.0

router = APIRouter(prefix="/separators", tags=["separators"])


def checked_name(
    name: Annotated[
        str,
        Path(description=f"separator name: 1 to {WELL_ID_MAX} printable characters, no / * $ ? #"),
    ],
) -> str:
    """The separator's name of the path, if it follows the rule for ids (422 otherwise)."""
    problem = well_id_problem(name)
    if problem is not None:
        raise InvalidRequest(problem, "unparseable key")
    return name


NamePath = Annotated[str, Depends(checked_name)]


@router.get("", summary="Every separator with its wells and latest reading (Sm3/h)")
def list_separators(engine: EngineDep) -> list[dict[str, Any]]:
    return engine.separator_overview()


@router.get(
    "/{name}",
    summary="A separator's latest allocation and reconciliation residual (Sm3/h)",
    responses={404: {"model": ErrorOut}},
)
def get_separator(name: NamePath, engine: EngineDep) -> dict[str, Any]:
    return engine.separator_view(name)


@router.post(
    "/{name}/measurements",
    summary="Post a reading of the separator's total (Sm3/h): stored, allocated, learned from",
    responses={
        202: {"description": "stored; waiting for its wells' samples at its time"},
        **POSTED_MEASUREMENT_ERRORS,
    },
    openapi_extra=measurement_body(Measurement.model_json_schema()),
)
async def post_reading(
    name: NamePath,
    request: Request,
    _: TokenDep,
    engine: EngineDep,
    counters: CountersDep,
    service: ServiceDep,
) -> Any:
    body = await request.body()
    where = f"POST /separators/{name}/measurements"
    try:
        checked = parse_measurement(
            body,
            Limits(service.settings.http.max_body_bytes, service.settings.inputs.max_json_depth),
        )
        future = engine.submit_reading(name, checked)
    except ServiceError as error:  # refused before reaching the worker: count it here
        if error.reason is not None:
            counters.reject(error.reason, error.message, where=where)
        raise
    try:  # refused by the worker (which counted it): the domain error propagates
        result = await asyncio.wait_for(asyncio.wrap_future(future), READING_WAIT_S)
    except TimeoutError:
        raise Busy(
            f"The reading was queued but not handled within {READING_WAIT_S:g} s; the service "
            f"is overloaded. It is stored once handled; check GET /separators/{name}."
        ) from None
    return JSONResponse(result, status_code=202 if result["status"] == "pending" else 200)
