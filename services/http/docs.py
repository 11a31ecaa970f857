"""``/docs`` and ``/redoc`` with their JavaScript and CSS served by this service (the
``fastapi-offline`` package's copies of Swagger UI and ReDoc; its licence at
``/docs/assets/LICENSE``): they work in a lab without internet."""

from __future__ import annotations

from importlib import metadata
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import HTMLResponse, PlainTextResponse
from fastapi.staticfiles import StaticFiles


def offline_docs(app: FastAPI) -> None:
    """``/docs`` and ``/redoc`` with their assets served here (module docstring)."""
    import fastapi_offline

    static = Path(fastapi_offline.__file__).parent / "static"
    openapi_url = app.openapi_url or "/openapi.json"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_swagger_ui_html(
            openapi_url=f"{root}{openapi_url}",
            title=f"{app.title} - Swagger UI",
            oauth2_redirect_url=f"{root}/docs/oauth2-redirect",
            swagger_js_url=f"{root}/docs/assets/swagger-ui-bundle.js",
            swagger_css_url=f"{root}/docs/assets/swagger-ui.css",
            swagger_favicon_url=f"{root}/docs/assets/favicon.png",
        )

    @app.get("/docs/oauth2-redirect", include_in_schema=False)
    async def swagger_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_redoc_html(
            openapi_url=f"{root}{openapi_url}",
            title=f"{app.title} - ReDoc",
            redoc_js_url=f"{root}/docs/assets/redoc.standalone.js",
            redoc_favicon_url=f"{root}/docs/assets/favicon.png",
            with_google_fonts=False,
        )

    @app.get("/docs/assets/LICENSE", include_in_schema=False)
    async def docs_licence() -> PlainTextResponse:
        dist = metadata.distribution("fastapi_offline")
        text = next(
            (f.read_text() for f in dist.files or [] if f.name.startswith("LICENSE")), ""
        )
        note = (
            "The documentation pages are served from the fastapi-offline package "
            f"{dist.version}, which bundles Swagger UI (Apache License 2.0, SmartBear "
            "Software) and ReDoc (MIT licence, Redocly); its own licence:\n\n"
        )
        return PlainTextResponse(note + text)

    # after the licence route: the mount would otherwise answer its path (404)
    app.mount("/docs/assets", StaticFiles(directory=static), name="docs-assets")
