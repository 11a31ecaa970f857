"""The fleet service's HTTP API and page (FastAPI), read-only.

* ``GET /`` the fleet page (``static/fleet.html`` and ``fleet.js``, styled by the operator
  console's own ``console.css``: one look for both).
* ``GET /robots`` every robot the fleet has heard, by name: status (live / stale, why,
  last seen), the file in force (created, run), the last check, health, and the drift of
  each module's parameters (first, last, change, per week).
* ``GET /robots/{name}`` one robot: the same with each parameter's series over its
  calibrations, and its last state document as published.
* ``GET /health`` the fleet service itself: robots live and stale, documents kept,
  messages received and rejected.

Nothing here changes anything: there is no token, and every request is a GET.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi import APIRouter, FastAPI, HTTPException, Request
from fastapi.responses import FileResponse

from services.fleet.service import FleetService
from services.http.console.router import STATIC as CONSOLE_STATIC
from services.http.deps import FiniteJSONResponse
from services.store.provenance import tool_version

STATIC = Path(__file__).parent / "static"
_ASSETS = {
    "fleet.js": (STATIC / "fleet.js", "text/javascript; charset=utf-8"),
    "console.css": (CONSOLE_STATIC / "console.css", "text/css; charset=utf-8"),
}
NO_CACHE = {"Cache-Control": "no-cache"}

router = APIRouter()


def _fleet(request: Request) -> FleetService:
    fleet: FleetService = request.app.state.fleet
    return fleet


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    return FileResponse(STATIC / "fleet.html", headers=NO_CACHE)


@router.get("/fleet/{name}", include_in_schema=False)
def asset(name: str) -> FileResponse:
    if name not in _ASSETS:
        raise HTTPException(404, f"no fleet page asset {name}")
    path, media = _ASSETS[name]
    return FileResponse(path, media_type=media, headers=NO_CACHE)


@router.get("/robots")
def robots(request: Request) -> FiniteJSONResponse:
    """Every robot heard, by name (module docstring)."""
    return FiniteJSONResponse(_fleet(request).robots())


@router.get("/robots/{name}", responses={404: {"description": "never heard of"}})
def robot(name: str, request: Request) -> FiniteJSONResponse:
    """One robot, with each parameter's series and its last state document."""
    got = _fleet(request).robot(name)
    if got is None:
        raise HTTPException(404, f"no robot {name} in the fleet")
    return FiniteJSONResponse(got)


@router.get("/health")
def health(request: Request) -> FiniteJSONResponse:
    counts: dict[str, Any] = _fleet(request).counts()
    return FiniteJSONResponse({"status": "ok", **counts})


def create_fleet_app(fleet: FleetService) -> FastAPI:
    """The fleet's app over ``fleet`` (opened and closed by its caller)."""
    app = FastAPI(
        title="swpc fleet",
        version=tool_version(),
        description="Every robot's file in force, last check, status and drift.",
        default_response_class=FiniteJSONResponse,
        docs_url=None,
        redoc_url=None,
    )
    app.state.fleet = fleet
    app.include_router(router)
    return app
