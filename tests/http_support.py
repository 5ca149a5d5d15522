"""A GET of a running in-process service's HTTP app, through ASGI (no socket), shared by the
tests that start a :class:`service.app.Service` on the in-memory transport."""

from __future__ import annotations

import asyncio
from typing import Any

import httpx


def http_get(service: Any, path: str) -> dict[str, Any]:
    """The JSON body of ``GET path`` on ``service``'s HTTP app."""
    from service.http import create_app

    async def go() -> httpx.Response:
        transport = httpx.ASGITransport(app=create_app(service))
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            return await client.get(path)

    out: dict[str, Any] = asyncio.run(go()).json()
    return out
