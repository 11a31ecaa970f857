"""How the service is: ``GET /health`` for operators, systemd and the console, ``GET
/metrics`` for Prometheus (:mod:`services.runtime.health` judges, :mod:`.metrics`
renders)."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from services.http.deps import FiniteJSONResponse, Rt
from services.http.edge.control import HEALTH, run_in
from services.http.metrics import render_metrics
from services.runtime.health import service_health

router = APIRouter()


@router.get(
    "/health",
    responses={503: {"description": "failing: a calibration cannot start or go on"}},
)
async def health(rt: Rt) -> FiniteJSONResponse:
    """``ok`` / ``degraded`` (200) or ``failing`` (503), with the problems (judged in
    threads of its own: :mod:`services.http.edge.control`)."""
    state, doc = await run_in(HEALTH, service_health, rt)
    return FiniteJSONResponse(doc, status_code=503 if state == "failing" else 200)


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(rt: Rt, request: Request) -> PlainTextResponse:
    body, content_type = render_metrics(rt, request.app.state.streams)
    return PlainTextResponse(body, media_type=content_type)
