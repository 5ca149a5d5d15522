"""``POST /wells/{well}/measurements/review``: the operator's decision on a well test held
for review (``GET /wells/{well}``: ``held_for_review``; :class:`service.engine.alarms.WellTestReview`).

``accept`` learns it now, paired with its stored sample, and answers as a learned well
test does (200, the prediction before and after); ``reject`` keeps it stored with status
``rejected``, never learned (202). Both are recorded in the store (``reviews``: the
decision and its time) and counted (events ``reviews accepted``, ``reviews rejected``). A
measurement not held for review answers 422, one decided before 409 (both ``no such
review``); a bad body 422, an unknown well 404. Needs the bearer token.
"""

from __future__ import annotations

import asyncio
from dataclasses import asdict
from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response

from service.errors import Busy, ServiceError
from service.http.deps import CountersDep, EngineDep, TokenDep, WellPath
from service.http.schemas import ErrorOut, ReviewIn, WellTestOut

__all__ = ["router"]

#: how long a caller waits for the decision to be stored (and, accepted, learned), s
REVIEW_WAIT_S = 10.0

router = APIRouter(prefix="/wells", tags=["wells"])


@router.post(
    "/{well}/measurements/review",
    response_model=WellTestOut,
    summary="Accept or reject a well test held for review",
    responses={
        202: {"model": WellTestOut, "description": "rejected: stored, never learned"},
        401: {"model": ErrorOut},
        403: {"model": ErrorOut},
        404: {"model": ErrorOut, "description": "no such well"},
        409: {"model": ErrorOut, "description": "decided before"},
        422: {"model": ErrorOut, "description": "a bad body, or no such held measurement"},
        503: {"model": ErrorOut},
    },
)
async def review(
    well: WellPath, body: ReviewIn, _: TokenDep, engine: EngineDep, counters: CountersDep
) -> Any:
    where = f"POST /wells/{well}/measurements/review"
    try:
        future = engine.submit_review(well, body.time, body.source, body.decision)
    except ServiceError as error:  # refused before reaching the worker: count it here
        if error.reason is not None:
            counters.reject(error.reason, error.message, where=where)
        raise
    try:  # refused by the worker (which counted it): the domain error propagates
        result = await asyncio.wait_for(asyncio.wrap_future(future), REVIEW_WAIT_S)
    except TimeoutError:
        raise Busy(
            f"The decision was queued but not handled within {REVIEW_WAIT_S:g} s; the service "
            f"is overloaded. It is still applied once handled; check GET /wells/{well}."
        ) from None
    return Response(
        WellTestOut(**asdict(result)).model_dump_json(),
        status_code=200 if result.status == "learned" else 202,
        media_type="application/json",
    )
