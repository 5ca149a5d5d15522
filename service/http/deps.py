"""What the routers depend on, injected with ``Annotated[..., Depends()]`` so tests can override it.

:class:`ServiceView` is all the HTTP layer needs of the running service (its settings,
counters, engine and store, and the health summary); :class:`service.app.Service` is
one, and the HTTP package never imports :mod:`service.app`. ``app.state.service`` holds
it. Override :func:`get_service`, :func:`get_engine` or :func:`get_store` in
``app.dependency_overrides`` to run a router against stand-ins.

:func:`require_token` guards every mutating endpoint, and these are exactly the endpoints
that take a body: after the token it refuses a body declared as anything but JSON
(:func:`require_json_body`, 415, counted as ``not declared JSON``). A body sent without a
Content-Type is read as JSON, as FastAPI reads it.

The one rule for wells over HTTP: a well is known exactly when ``GET /wells`` lists it
(:func:`known_well`). Every endpoint about a well answers 404 for any other well, and HTTP
never creates one, whatever ``inputs.unknown_wells`` says (that setting is about Zenoh
only): a well test posted for a well not listed is refused (``unknown well``), also while
the well is being created from its first Zenoh message; once it is listed, every endpoint
takes it.
"""

from __future__ import annotations

import secrets
from typing import Annotated, Any, Protocol

from fastapi import Depends, Path, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.config import Settings
from service.engine import Engine
from service.errors import (
    InvalidRequest,
    NotAllowed,
    NotAuthenticated,
    NotJson,
    Starting,
    unknown_well,
)
from service.inputs import Counters, printable
from service.store import Store
from vfm_core.messages import WELL_ID_MAX, well_id_problem

__all__ = [
    "ServiceView",
    "get_service",
    "get_engine",
    "get_running_engine",
    "get_store",
    "get_counters",
    "require_token",
    "require_json_body",
    "ServiceDep",
    "EngineDep",
    "MaybeEngineDep",
    "StoreDep",
    "CountersDep",
    "TokenDep",
    "WellPath",
    "KnownWell",
]


class ServiceView(Protocol):
    """What the HTTP layer reads of the service."""

    settings: Settings
    counters: Counters
    engine: Engine | None
    store: Store | None

    def health(self) -> dict[str, Any]: ...


def get_service(request: Request) -> ServiceView:
    return request.app.state.service  # type: ignore[no-any-return]


ServiceDep = Annotated[ServiceView, Depends(get_service)]


def get_engine(service: ServiceDep) -> Engine | None:
    """The engine, or None before the service has started."""
    return service.engine


MaybeEngineDep = Annotated[Engine | None, Depends(get_engine)]


def get_running_engine(engine: MaybeEngineDep) -> Engine:
    """The engine of a started service (503 before)."""
    if engine is None:
        raise Starting("The service is starting; retry in a few seconds.")
    return engine


EngineDep = Annotated[Engine, Depends(get_running_engine)]


def get_store(service: ServiceDep) -> Store:
    if service.store is None:
        raise Starting("The service is starting; retry in a few seconds.")
    return service.store


StoreDep = Annotated[Store, Depends(get_store)]


def get_counters(service: ServiceDep) -> Counters:
    return service.counters


CountersDep = Annotated[Counters, Depends(get_counters)]

_bearer = HTTPBearer(auto_error=False, description="the service's http.token")


def require_token(
    service: ServiceDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    request: Request,
) -> None:
    """Mutating endpoints: refused when no token is configured, or it is missing or wrong;
    then a body that is not declared JSON (:func:`require_json_body`)."""
    token = service.settings.http.token
    if token is None:
        raise NotAllowed(
            "Posting is disabled because no API token is configured; set http.token in the config file "
            "or VFM_HTTP__TOKEN in the environment, restart, and send 'Authorization: Bearer <token>'."
        )
    if credentials is None or not secrets.compare_digest(
        credentials.credentials.encode(), token.get_secret_value().encode()
    ):
        raise NotAuthenticated(
            "A valid bearer token is required: send 'Authorization: Bearer <token>' "
            "with the service's http.token."
        )
    require_json_body(request, service.counters)


def _is_json(content_type: str) -> bool:
    """Whether a Content-Type value names JSON: application/json or application/<x>+json."""
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (
        media.startswith("application/") and media.endswith("+json")
    )


def require_json_body(request: Request, counters: Counters) -> None:
    """Refuse (415, counted as ``not declared JSON``) a request body whose Content-Type is
    not JSON: the API documents JSON bodies, and a body sent as text/plain or a form must
    not be read as JSON behind its sender's back. No body, or no Content-Type: nothing to
    refuse here (FastAPI reads a body without one as JSON)."""
    content_type = request.headers.get("content-type")
    if content_type is None or _is_json(content_type):
        return
    has_body = request.headers.get("content-length", "0") != "0" or (
        "transfer-encoding" in request.headers
    )
    if not has_body:
        return
    error = NotJson(
        f"The request body is declared as '{printable(content_type, 80)}', not JSON; this "
        "API takes JSON only: send the body with 'Content-Type: application/json'.",
        "not declared JSON",
    )
    counters.reject(str(error.reason), error.message, where=f"{request.method} {request.url.path}")
    raise error


TokenDep = Annotated[None, Depends(require_token)]


def checked_well(
    well: Annotated[
        str, Path(description=f"well id: 1 to {WELL_ID_MAX} printable characters, no / * $ ? #")
    ],
) -> str:
    """The well id of the path, if it follows the one rule for ids (422 otherwise)."""
    problem = well_id_problem(well)
    if problem is not None:
        raise InvalidRequest(problem, "unparseable key")
    return well


WellPath = Annotated[str, Depends(checked_well)]


def known_well(well: WellPath, engine: MaybeEngineDep) -> str:
    """The well of the path, if this service knows it (404 otherwise)."""
    if engine is None or not engine.has_well(well):
        raise unknown_well(well)
    return well


KnownWell = Annotated[str, Depends(known_well)]
