"""Domain errors as HTTP answers: one table from error class to status, and the handlers.

Every refusal answers ``{"detail": "<a sentence>", "reason": "<counter key or null>"}``.
The statuses (the engine knows none of them):

=====================  ======  ==================================================
error                  status  when
=====================  ======  ==================================================
``InvalidRequest``     422     a bad value (payload, time, model, effect, method)
``NotJson``            415     a body declared with a Content-Type that is not JSON
``UnknownWell``        404     the well is not known to this service (a well of
                               another instance: the sentence names its owner)
``Duplicate``          409     the same sample or measurement arrived before
``Conflict``           409     a model change of the well is already running
``NotAllowed``         403     no API token configured; an effect module not allowed
``NotAuthenticated``   401     the bearer token is missing or wrong
``Busy``               503     a queue stayed full or the answer took too long
``Starting``           503     the service is not running yet
``Stopping``           503     the service is stopping
=====================  ======  ==================================================

A request body that fails FastAPI's validation is classified like a Zenoh payload
(:func:`service.inputs.classify_errors`), counted under its reason and answered with 422;
one FastAPI cannot parse at all (JSON nested too deeply, say) likewise (422, ``too deeply
nested`` or ``malformed JSON``). A body above ``http.max_body_bytes`` is answered 413
(``payload too large``) by :class:`BodyLimit` before any of it is parsed. Every other
HTTP error (404 for an unknown path, 405, ...) has the same ``{detail, reason}`` shape.
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.errors import (
    Busy,
    Conflict,
    Duplicate,
    InvalidRequest,
    NotAllowed,
    NotAuthenticated,
    NotJson,
    ServiceError,
    Starting,
    Stopping,
    UnknownWell,
)
from service.http.deps import get_service
from service.inputs import classify_errors

__all__ = ["STATUS", "status_of", "install_error_handlers", "BodyLimit", "BodyTooLarge"]

#: the HTTP status of each domain error class (a subclass takes its nearest ancestor's)
STATUS: dict[type[ServiceError], int] = {
    InvalidRequest: 422,
    NotJson: 415,
    UnknownWell: 404,
    Duplicate: 409,
    Conflict: 409,
    NotAllowed: 403,
    NotAuthenticated: 401,
    Busy: 503,
    Starting: 503,
    Stopping: 503,
}


def status_of(error: ServiceError) -> int:
    """The HTTP status for a domain error (500 for one the table does not know)."""
    for cls in type(error).__mro__:
        if cls in STATUS:
            return STATUS[cls]
    return 500


def install_error_handlers(app: FastAPI) -> None:
    """Answer domain errors and invalid requests with a sentence and a reason."""

    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
        headers = {"WWW-Authenticate": "Bearer"} if isinstance(exc, NotAuthenticated) else None
        message = exc.message
        well = request.path_params.get("well")
        foreign = getattr(get_service(request), "foreign_well", None)
        if isinstance(exc, UnknownWell) and isinstance(well, str) and foreign is not None:
            # scale-out: a well of another instance; name it (a Zenoh query, off the loop)
            message = await run_in_threadpool(foreign, well) or message
        return JSONResponse(
            {"detail": message, "reason": exc.reason},
            status_code=status_of(exc),
            headers=headers,
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        counters = get_service(request).counters
        where = f"{request.method} {request.url.path}"
        if isinstance(exc, BodyTooLarge):
            return JSONResponse(
                {"detail": exc.detail, "reason": "payload too large"}, status_code=413
            )
        if exc.status_code == 400 and request.method in ("POST", "PUT", "PATCH"):
            # FastAPI could not parse the body at all (its JSON nests too deeply, ...)
            deep = isinstance(exc.__cause__, RecursionError)
            reason = "too deeply nested" if deep else "malformed JSON"
            sentence = (
                "The request body nests JSON too deeply; send one flat object."
                if deep
                else "The request body could not be read as JSON; send one JSON object."
            )
            counters.reject(reason, sentence, where=where)
            return JSONResponse({"detail": sentence, "reason": reason}, status_code=422)
        detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"There is no endpoint {request.url.path}; the API is described at /docs."
        elif exc.status_code == 405:
            detail = f"{request.method} is not allowed on {request.url.path}; see /docs."
        if not detail.endswith("."):
            detail += "."
        return JSONResponse(
            {"detail": detail, "reason": None},
            status_code=exc.status_code,
            headers=getattr(exc, "headers", None),
        )

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = list(exc.errors())
        reason, sentence = classify_errors(errors)  # type: ignore[arg-type]
        on_body = any(e.get("loc", ("",))[0] == "body" for e in errors)
        if on_body:
            get_service(request).counters.reject(
                reason, sentence, where=f"{request.method} {request.url.path}"
            )
        return JSONResponse({"detail": sentence, "reason": reason}, status_code=422)


class BodyTooLarge(StarletteHTTPException):
    """A request body above ``http.max_body_bytes`` (answered 413, ``payload too large``)."""

    def __init__(self, limit: int) -> None:
        super().__init__(
            413,
            f"The request body is larger than {limit:,} bytes (http.max_body_bytes); a well "
            "test or a model change takes a few hundred.",
        )


class BodyLimit:
    """ASGI middleware: refuse a request body above ``limit`` bytes before it is parsed.

    A declared ``Content-Length`` above the limit is answered at once; a body that grows
    past it while streaming ends in :class:`BodyTooLarge`, which the handler answers. Both
    are counted under ``payload too large`` via ``count(message, where)``.
    """

    def __init__(self, app: Any, limit: int, count: Any) -> None:
        self.app = app
        self.limit = limit
        self.count = count

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        if scope["type"] != "http" or scope.get("method") in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        where = f"{scope.get('method')} {scope.get('path')}"
        declared = dict(scope.get("headers") or []).get(b"content-length")
        too_large = BodyTooLarge(self.limit)
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            self.count(too_large.detail, where)
            response = JSONResponse(
                {"detail": too_large.detail, "reason": "payload too large"}, status_code=413
            )
            await response(scope, receive, send)
            return
        seen = 0

        async def limited() -> Any:
            nonlocal seen
            message = await receive()
            if message.get("type") == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    self.count(too_large.detail, where)
                    raise too_large
            return message

        await self.app(scope, limited, send)
