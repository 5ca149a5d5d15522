"""``POST /wells/{well}/well-tests``: a well-test result, stored durably, then learned from."""

from __future__ import annotations

import asyncio
from dataclasses import asdict
from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from service.errors import Busy, ServiceError
from service.http.deps import CountersDep, EngineDep, TokenDep, WellPath
from service.http.schemas import ErrorOut, WellTestOut
from service.inputs import parse_measurement
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
        401: {"model": ErrorOut},
        403: {"model": ErrorOut},
        404: {"model": ErrorOut},
        409: {"model": ErrorOut},
        422: {"model": ErrorOut},
        503: {"model": ErrorOut},
    },
)
async def post_well_test(
    well: WellPath, test: Measurement, _: TokenDep, engine: EngineDep, counters: CountersDep
) -> Any:
    try:
        checked = parse_measurement(test.model_dump(mode="json"))
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
    body = WellTestOut(**asdict(result)).model_dump()
    return JSONResponse(body, status_code=200 if result.status == "learned" else 202)
