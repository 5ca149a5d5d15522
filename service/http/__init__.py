"""The HTTP API of the service (FastAPI): routers per concern, errors mapped in one table.

``create_app(service)`` (:mod:`service.http.app`) builds the application; the routers are
:mod:`~service.http.health`, :mod:`~service.http.wells`, :mod:`~service.http.well_tests`
and :mod:`~service.http.model_changes`; :mod:`~service.http.deps` holds what they depend
on and :mod:`~service.http.error_responses` the status of each domain error. This package never
imports :mod:`service.app`: the service is handed in.
"""

from service.http.app import create_app

__all__ = ["create_app"]
