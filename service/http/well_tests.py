"""``POST /wells/{well}/well-tests``: a well-test result, stored durably, then learned from.

The body is read raw and checked by :func:`service.inputs.parse_measurement`, the very
function that checks a Zenoh measurement (with the same size and depth limits), so both
paths refuse the same inputs with the same reasons. A body declared as anything but JSON
answers 415 (``not declared JSON``, :func:`service.http.deps.require_json_body`). HTTP never
creates a well: a well test of a well that ``GET /wells`` does not list (a typo, or a well
still being created from its first Zenoh message) answers 404 (``unknown well``), as every
other endpoint about that well would.
"""

from __future__ import annotations

import asyncio
from dataclasses import asdict
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response

from service.errors import Busy, ServiceError
from service.http.deps import CountersDep, EngineDep, ServiceDep, TokenDep, WellPath
from service.http.schemas import (
    POSTED_MEASUREMENT_ERRORS,
    WellTestOut,
    measurement_body,
)
from service.inputs import Limits, parse_measurement
from vfm_core.messages import Measurement

__all__ = ["router", "WELL_TEST_WAIT_S"]

#: how long a caller waits for its well test to be stored (and learned), s
WELL_TEST_WAIT_S = 10.0

router = APIRouter(prefix="/wells", tags=["wells"])


@router.post(
    "/{well}/well-tests",
    response_model=WellTestOut,
    summary="Post a well-test result: stored durably, then learned from",
    responses={
        202: {
            "model": WellTestOut,
            "description": "stored; waiting for the sensor sample at its time",
        },
        **POSTED_MEASUREMENT_ERRORS,
    },
    openapi_extra=measurement_body(Measurement.model_json_schema()),
)
async def post_well_test(
    well: WellPath,
    request: Request,
    _: TokenDep,
    engine: EngineDep,
    counters: CountersDep,
    service: ServiceDep,
) -> Any:
    body = await request.body()
    inputs = service.settings.inputs
    try:
        checked = parse_measurement(
            body, Limits(service.settings.http.max_body_bytes, inputs.max_json_depth)
        )
        future = engine.submit_well_test(well, checked)
    except ServiceError as error:  # refused before reaching the worker: count it here
        if error.reason is not None:
            counters.reject(error.reason, error.message, where=f"POST /wells/{well}/well-tests")
        raise
    try:  # refused by the worker (which counted it): the domain error propagates
        result = await asyncio.wait_for(asyncio.wrap_future(future), WELL_TEST_WAIT_S)
    except TimeoutError:
        raise Busy(
            f"The well test was queued but not handled within {WELL_TEST_WAIT_S:g} s; the "
            f"service is overloaded. It is still stored once handled; check GET /wells/{well}/history."
        ) from None
    # pydantic writes a non-finite number as null (json.dumps would refuse it: a 500)
    return Response(
        WellTestOut(**asdict(result)).model_dump_json(),
        status_code=200 if result.status == "learned" else 202,
        media_type="application/json",
    )
