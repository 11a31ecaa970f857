"""The calibration service's HTTP API (FastAPI): the app, its lifespan and its routers.

Operators start a calibration, watch it and read the result; motion and write
endpoints need the bearer token from the settings.  One router per resource:

* :mod:`.calibrations` (start, list, result, plot, abort), :mod:`.checks` (a check of
  the file in force, the robot's history), :mod:`.answers` (the
  operator's answers to a run that waits for them), :mod:`.kinematics` (the file in force,
  its backups, install and roll back), :mod:`.drives` (``/drives``: each axis' drive as
  the driver knows it), :mod:`.health` (``/health``, ``/metrics``), the
  operator console (:mod:`.console`) and, with the in-process simulator only,
  :mod:`.simulator` (its tape measure);
* what they share: :mod:`.deps` (the runtime and token dependencies, problem bodies,
  standard-JSON responses); ``/docs`` and ``/redoc`` offline: :mod:`.docs`.

Before a request reaches a route, :class:`services.http.edge.guard.RequestGuard` checks the
token of every request that may change something (before its body is read), the body's
size and that a JSON body is standard JSON.  Responses are standard JSON too: a
non-finite number is written ``null`` (:class:`~services.http.deps.FiniteJSONResponse`),
and a validation error never fails to render.  See :mod:`services.runtime.runtime` for
what is opened in the lifespan and :mod:`services.runs.protocol` for the protocol.
"""

from __future__ import annotations

import errno
import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from services.config.settings import ServiceSettings
from services.http import (
    answers,
    calibrations,
    checks,
    commissions,
    drives,
    health,
    kinematics,
    simulator,
)
from services.http.console import router as console
from services.http.deps import FiniteJSONResponse, printable
from services.http.docs import offline_docs
from services.http.edge.control import limit_route_threads
from services.http.edge.guard import RequestGuard
from services.http.edge.streams import StreamGate
from services.runtime.fleet import FleetPublisher
from services.runtime.runtime import Runtime
from services.store.provenance import tool_version
from swpc_hw.heap_freeze import freeze_startup_heap

log = logging.getLogger("swpc.service")


def create_app(
    settings: ServiceSettings | None = None,
    runtime_factory: Callable[[ServiceSettings], Runtime] | None = None,
) -> FastAPI:
    """The app; the runtime is ``runtime_factory(settings)`` in the lifespan (``swpc serve``
    and tests: one already open), else a new :class:`Runtime` opened there; it is closed
    when the lifespan ends."""
    cfg = settings or ServiceSettings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        limit_route_threads()
        rt = runtime_factory(cfg) if runtime_factory else Runtime(cfg).open()
        app.state.runtime = rt
        fleet: FleetPublisher | None = None
        try:
            # SWPC_FLEET_PUBLISH: this robot's state to the fleet (its own zenoh session)
            fleet = FleetPublisher.open(rt) if cfg.fleet_publish else None
            app.state.fleet = fleet
            freeze_startup_heap()  # no full-collection pause over the start-up heap mid-run
            yield
        finally:
            if fleet is not None:
                fleet.close()
            signal_name = getattr(app.state, "stop_signal", None)
            how = f" ({signal_name})" if signal_name else ""
            rt.close(f"the service was stopped{how} during the run")

    app = FastAPI(
        title="swpc calibration service",
        version=tool_version(),
        lifespan=lifespan,
        description="Calibrates SWPC robots: start / watch / abort runs, read results.",
        default_response_class=FiniteJSONResponse,
        docs_url=None,
        redoc_url=None,
    )
    app.state.token = cfg.ensure_token()
    app.state.streams = StreamGate(cfg.max_streams, cfg.streams_per_client)
    app.add_middleware(
        RequestGuard,
        token=lambda: str(app.state.token),
        max_body=cfg.max_body_bytes,
        hosts=cfg.host_names(),
    )
    offline_docs(app)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        detail = printable(jsonable_encoder(exc.errors()))
        return FiniteJSONResponse({"detail": detail}, status_code=422)

    @app.exception_handler(OSError)
    async def _os_error(request: Request, exc: OSError) -> JSONResponse:
        """A file the request needed could not be written or read: 507 when the disk (or
        a quota) is full, else 500; the reason without a traceback (that goes to the log)."""
        full = exc.errno in (errno.ENOSPC, errno.EDQUOT)
        log.error("%s %s: %s", request.method, request.url.path, exc, exc_info=not full)
        what = "no room on disk" if full else "a file could not be written or read"
        return FiniteJSONResponse(
            {"detail": f"{what}: {exc.strerror or exc}"}, status_code=507 if full else 500
        )

    for module in (calibrations, checks, commissions, answers, kinematics, drives, health):
        app.include_router(module.router)
    if cfg.in_process:  # never against a robot
        app.include_router(simulator.router)
    app.include_router(console.router)  # GET /, its event stream, a run's geometry, files
    return app
