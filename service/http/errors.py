"""Domain errors as HTTP answers: one table from error class to status, and the handlers.

Every refusal answers ``{"detail": "<a sentence>", "reason": "<counter key or null>"}``.
The statuses (the engine knows none of them):

=====================  ======  ==================================================
error                  status  when
=====================  ======  ==================================================
``InvalidRequest``     422     a bad value (payload, time, model, effect, method)
``UnknownWell``        404     the well is not known to this service
``Duplicate``          409     the same sample or measurement arrived before
``Conflict``           409     a model change of the well is already running
``NotAllowed``         403     no API token configured; an effect module not allowed
``NotAuthenticated``   401     the bearer token is missing or wrong
``Busy``               503     a queue stayed full or the answer took too long
``Starting``           503     the service is not running yet
``Stopping``           503     the service is stopping
=====================  ======  ==================================================

A request body that fails FastAPI's validation is classified like a Zenoh payload
(:func:`service.inputs.classify_errors`), counted under its reason and answered with 422.
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service.errors import (
    Busy,
    Conflict,
    Duplicate,
    InvalidRequest,
    NotAllowed,
    NotAuthenticated,
    ServiceError,
    Starting,
    Stopping,
    UnknownWell,
)
from service.http.deps import get_service
from service.inputs import classify_errors

__all__ = ["STATUS", "status_of", "install_error_handlers"]

#: the HTTP status of each domain error class (a subclass takes its nearest ancestor's)
STATUS: dict[type[ServiceError], int] = {
    InvalidRequest: 422,
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
        return JSONResponse(
            {"detail": exc.message, "reason": exc.reason},
            status_code=status_of(exc),
            headers=headers,
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
