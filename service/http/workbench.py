"""The workbench page at ``/`` and the API docs at ``/docs``, with every asset from the package.

The page (``service/static/index.html``, ``app.js``, ``app.css``) is plain HTML and
JavaScript with no build step; its charts use uPlot (MIT), and ``/docs`` uses Swagger UI
(``swagger-ui-dist``, Apache-2.0), both vendored under ``service/static/vendor/`` with their
licences, so neither needs the internet (a plant network has none).
"""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse

__all__ = ["router", "STATIC"]

#: the page and its vendored libraries (served under /static)
STATIC = Path(__file__).resolve().parents[1] / "static"

router = APIRouter(include_in_schema=False)


@router.get("/")
def index() -> FileResponse:
    return FileResponse(STATIC / "index.html", media_type="text/html")


@router.get("/docs")
def docs(request: Request) -> HTMLResponse:
    return get_swagger_ui_html(
        openapi_url=request.app.openapi_url,
        title=f"{request.app.title}: API",
        swagger_js_url="/static/vendor/swagger-ui-bundle.js",
        swagger_css_url="/static/vendor/swagger-ui.css",
        swagger_favicon_url="/static/favicon.svg",
    )
