"""``GET /events``: the service's live events as server-sent events (``text/event-stream``).

Fed by the engine's :class:`~service.engine.observe.Observer` from what the workers
committed, never by the workers directly: each client has a bounded queue (drop-oldest;
the drops are sent as a ``dropped`` event and counted in ``/metrics``), and the stream
reads it every :data:`POLL_S` seconds, so a slow or stalled client never holds a worker.
Each event is ``event: <type>`` and ``data: <one JSON object>``; types ``prediction``,
``measurement``, ``learned``, ``drift`` (the operating point left the training data),
``model``, ``alarm`` (a residual alarm started or ended), ``trial`` (a model change's trial
ended) (see :mod:`service.engine.observe`) and ``dropped``. A comment line every :data:`KEEPALIVE_S` s keeps proxies from closing an
idle stream. The stream ends when the service stops; browsers reconnect by themselves.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import APIRouter, Query, Request
from fastapi.responses import StreamingResponse

from service.errors import InvalidRequest, unknown_well
from service.http.deps import EngineDep
from service.http.schemas import ErrorOut
from vfm_core.messages import well_id_problem

__all__ = ["router", "POLL_S", "KEEPALIVE_S"]

POLL_S = 0.25
KEEPALIVE_S = 15.0

router = APIRouter(tags=["live"])


@router.get(
    "/events",
    summary="Live events (server-sent events)",
    description=(
        "A text/event-stream of what the service stores, as it commits it: predictions "
        "(q_total and its p05..p95, Sm3/h), measurements, learned measurements (with the "
        "prediction made at their sample), drift events and model changes. ?well=W01 for one "
        "well. A client that reads too slowly loses the oldest events (a 'dropped' event says "
        "how many)."
    ),
    response_class=StreamingResponse,
    responses={200: {"content": {"text/event-stream": {}}}, 404: {"model": ErrorOut}},
)
async def events(
    request: Request,
    engine: EngineDep,
    well: Annotated[str | None, Query(description="only this well's events")] = None,
) -> StreamingResponse:
    if well is not None:
        problem = well_id_problem(well)
        if problem is not None:
            raise InvalidRequest(problem, "unparseable key")
        if not engine.has_well(well):
            raise unknown_well(well)
    observer = engine.observer
    closing = request.app.state.closing
    sub = observer.subscribe(well)

    async def stream() -> AsyncIterator[str]:
        try:
            yield "retry: 2000\n: connected\n\n"
            last = time.monotonic()
            while not (closing.is_set() or observer.closed.is_set()):
                batch, dropped = sub.take()
                out = []
                if dropped:
                    out.append(f"event: dropped\ndata: {json.dumps({'dropped': dropped})}\n\n")
                for event in batch:
                    data = json.dumps(event, allow_nan=False, default=str)
                    out.append(f"event: {event['type']}\ndata: {data}\n\n")
                if out:
                    last = time.monotonic()
                    yield "".join(out)
                elif time.monotonic() - last > KEEPALIVE_S:
                    last = time.monotonic()
                    yield ": keep-alive\n\n"
                if await request.is_disconnected():
                    break
                await asyncio.sleep(POLL_S)
        finally:
            observer.unsubscribe(sub)

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )
