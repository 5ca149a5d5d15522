"""The FastAPI application: one router per concern over a running service.

=======================================  =====================================================
``GET /health``                          counts of accepted and rejected inputs (by reason),
                                         queue depths, overflow count (:mod:`.health`)
``GET /wells``                           every well with its model version (:mod:`.wells`)
``GET /wells/{well}``                    model, method, physical parameters (value, unit),
                                         version, updates, last update, rolling MAPE, drift
``GET /wells/{well}/history``            samples, predictions and measurements in [start, end)
``GET /wells/{well}/history.csv``        the same as CSV in the observation format (streamed)
``POST /wells/{well}/well-tests``        a well-test result {time, q_total}: stored, then
                                         learned from; answers with the prediction before and
                                         after (bearer token; :mod:`.well_tests`)
``POST /wells/{well}/measurements/review``  accept or reject a well test held for review
                                         (bearer token; :mod:`.reviews`)
``PUT /wells/{well}/model``              replace the well's model (bearer token;
                                         :mod:`.model_changes`)
``DELETE /wells/{well}``                 retire a well, keeping or purging its data (bearer
                                         token; :mod:`.wells`)
``POST /wells/{well}/diagnosis``         start a diagnosis of the well's stored history
                                         (bearer token; :mod:`.diagnosis`)
``GET /diagnosis/{job}``                 its state, progress and, once done, the diagnosis
``GET /events``                          live events, server-sent (:mod:`.events`)
``GET /metrics``                         Prometheus text format (:mod:`.metrics`)
``GET /``, ``/docs``, ``/static/...``    the workbench page and the API docs, with every
                                         asset from the package (:mod:`.workbench`)
=======================================  =====================================================

Errors answer ``{"detail": "<a sentence>", "reason": "<counter key>"}`` with the status
of :data:`service.http.error_responses.STATUS`; a body above ``http.max_body_bytes`` gets 413. Dependencies (:mod:`.deps`) are injected with
``Annotated[..., Depends()]``, so tests override them.
"""

from __future__ import annotations

import threading

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from service.errors import REASONS
from service.http import (
    diagnosis,
    events,
    health,
    metrics,
    model_changes,
    reviews,
    separators,
    well_tests,
    wells,
    workbench,
)
from service.http.deps import ServiceView
from service.http.error_responses import BodyLimit, install_error_handlers

__all__ = ["create_app"]


def create_app(service: ServiceView) -> FastAPI:
    """The FastAPI app for a service (kept in ``app.state.service``)."""
    app = FastAPI(
        title="vfm: streaming virtual flow meter",
        version="1",
        description=(
            "Predicted rates for every sensor sample over Zenoh; model state, history and well tests over "
            "HTTP. Units: bar absolute, degC, fractions 0..1, Sm3/h; times ISO 8601 UTC. "
            "Rejection reasons: " + "; ".join(f"'{k}': {v}" for k, v in REASONS.items()) + "."
        ),
        # served from the package by workbench.docs (the default loads Swagger UI from a CDN)
        docs_url=None,
        redoc_url=None,
    )
    app.state.service = service
    app.state.metrics = metrics.registry_for(service)
    #: set when the HTTP server begins to shut down: live streams end at once
    app.state.closing = threading.Event()
    install_error_handlers(app)

    def count(message: str, where: str) -> None:
        service.counters.reject("payload too large", message, where=where)

    app.add_middleware(BodyLimit, limit=service.settings.http.max_body_bytes, count=count)
    app.include_router(health.router)
    app.include_router(wells.router)
    app.include_router(model_changes.router)
    app.include_router(well_tests.router)
    app.include_router(reviews.router)
    app.include_router(separators.router)
    app.include_router(diagnosis.router)
    app.include_router(events.router)
    app.include_router(metrics.router)
    app.include_router(workbench.router)
    app.mount("/static", StaticFiles(directory=workbench.STATIC), name="static")
    return app
