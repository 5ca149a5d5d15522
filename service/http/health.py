"""``GET /health``: counts of accepted and refused inputs, queues, Zenoh, the store."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from service.http.deps import ServiceDep
from service.http.schemas import HealthOut

__all__ = ["router"]

router = APIRouter(tags=["health"])


@router.get("/health", response_model=HealthOut, summary="Counters, queues and status")
def health(service: ServiceDep) -> dict[str, Any]:
    return service.health()
