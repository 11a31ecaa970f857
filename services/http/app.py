"""The calibration service's HTTP API (FastAPI).

Operators start a calibration, watch it and read the result; motion and write
endpoints need the bearer token from the settings.  See :mod:`services.runtime.runtime` for what
is opened in the lifespan and :mod:`services.runs.protocol` for the protocol.

Before a request reaches a route, :class:`services.http.guard.RequestGuard` checks the
token of every request that may change something (before its body is read), the body's
size and that a JSON body is standard JSON.  Responses are standard JSON too: a
non-finite number is written ``null`` (:class:`FiniteJSONResponse`), and a validation
error never fails to render.  ``/docs`` and ``/redoc`` are served with their JavaScript
and CSS from this service (the ``fastapi-offline`` package's copies of Swagger UI and
ReDoc; its licence at ``/docs/assets/LICENSE``): they work in a lab without internet.
"""

from __future__ import annotations

import asyncio
import json
import math
import secrets
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from importlib import metadata
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, HTTPException, Request, Response, status
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import (
    get_redoc_html,
    get_swagger_ui_html,
    get_swagger_ui_oauth2_redirect_html,
)
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.config.robot import ConfigOverrides, OverrideError, RobotConfig
from services.config.settings import ServiceSettings
from services.http.console import console_router
from services.http.guard import RequestGuard
from services.http.imu import ReferenceIn, entries, imu_router, refused
from services.http.kinematics import UnreadableFileProblem, kinematics_router, unreadable_problem
from services.runs.imu import parse_references, reference_problems
from services.runs.protocol import RunStatus
from services.runtime.health import service_health
from services.runtime.runtime import (
    DiskSpaceError,
    NoResultError,
    RunConflictError,
    Runtime,
    StoreError,
)
from services.store.provenance import tool_version
from swpc_hw.errors import DatasetError, KinematicFileError
from swpc_hw.heap_freeze import freeze_startup_heap
from swpc_hw.references import Reference


class StartRequest(BaseModel):
    """Start a calibration; ``overrides`` are deep-merged into the robot config (limits and
    tolerances may only be tightened).  ``metrology``: ``mocap`` (motion capture) or
    ``imu`` (none: the robot's gyro, with ``references`` measured by tape; the straight
    drive's comes during the run); default ``imu`` when the service is set up without
    motion capture (``SWPC_METROLOGY=imu``), else ``mocap``."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    overrides: ConfigOverrides = Field(default_factory=ConfigOverrides)
    install: Literal["if-within-tolerance", "always", "never"] = "if-within-tolerance"
    metrology: Literal["mocap", "imu"] | None = None
    references: list[ReferenceIn] = Field(default_factory=list)


class Problem(BaseModel):
    detail: str


def _finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by ``None`` (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value


def _printable(value: Any) -> Any:
    """``value`` with every non-finite float as its name (``"inf"``, ``"nan"``): for the
    ``input`` of a validation error, which must say what was sent."""
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, dict):
        return {k: _printable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_printable(v) for v in value]
    return value


class FiniteJSONResponse(JSONResponse):
    """Standard JSON: non-finite numbers as ``null`` (never a 500 while rendering)."""

    def render(self, content: Any) -> bytes:
        return json.dumps(
            _finite(content), ensure_ascii=False, allow_nan=False, separators=(",", ":")
        ).encode("utf-8")


async def runtime(request: Request) -> Runtime:
    """The runtime opened in the lifespan (dependency; async: no threadpool hand-off for
    what is an attribute read, which an abort would wait behind)."""
    rt: Runtime = request.app.state.runtime
    return rt


Rt = Annotated[Runtime, Depends(runtime)]
_bearer = HTTPBearer(auto_error=False)


async def auth(
    request: Request,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Motion and write endpoints: the bearer token of the settings, else 401 (the guard
    has already refused such requests before reading their body; this documents it).
    Async: a constant-time compare needs no threadpool hand-off (an abort's path)."""
    token: str = request.app.state.token
    if creds is None or not secrets.compare_digest(creds.credentials.encode(), token.encode()):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or invalid bearer token",
            headers={"WWW-Authenticate": "Bearer"},
        )


def start_references(
    config: RobotConfig, metrology: str, given: list[ReferenceIn]
) -> list[Reference]:
    """The references of a run to start, checked before any motion (422 otherwise)."""
    if metrology != "imu":
        if given:
            raise refused("references", ValueError("references are for metrology imu"))
        return []
    try:
        refs = parse_references(entries(given), config.nominal.ids)
    except DatasetError as exc:
        raise refused("references", ValueError(f"refused before any motion: {exc}")) from exc
    problems = reference_problems(config, refs)
    if problems:
        raise RequestValidationError(
            [
                {
                    "loc": ["body", "references"],
                    "msg": f"refused before any motion: {p}",
                    "type": "value_error",
                }
                for p in problems
            ]
        )
    return refs


def _offline_docs(app: FastAPI) -> None:
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


def create_app(
    settings: ServiceSettings | None = None,
    runtime_factory: Callable[[ServiceSettings], Runtime] | None = None,
) -> FastAPI:
    """The app; the runtime is ``runtime_factory(settings)`` in the lifespan (``swpc serve``
    and tests: one already open), else a new :class:`Runtime` opened there; it is closed
    when the lifespan ends."""
    cfg = settings or ServiceSettings()
    token = cfg.ensure_token()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        rt = runtime_factory(cfg) if runtime_factory else Runtime(cfg).open()
        app.state.runtime = rt
        freeze_startup_heap()  # no full-collection pause over the start-up heap mid-run
        try:
            yield
        finally:
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
    app.state.token = token
    app.add_middleware(
        RequestGuard,
        token=lambda: str(app.state.token),
        max_body=cfg.max_body_bytes,
    )
    _offline_docs(app)
    responses_run: dict[int | str, dict[str, Any]] = {404: {"model": Problem}}
    guarded: dict[int | str, dict[str, Any]] = {
        401: {"model": Problem},
        413: {"model": Problem},
    }

    @app.post(
        "/calibrations",
        status_code=202,
        response_model=RunStatus,
        dependencies=[Depends(auth)],
        responses={
            **guarded,
            409: {"model": Problem},
            503: {"model": Problem, "description": "the run store cannot be written"},
            507: {"model": Problem, "description": "no room on disk for a run"},
        },
    )
    def start(body: StartRequest, rt: Rt, response: Response) -> dict[str, Any]:
        """Start a run.  Overrides may only tighten the robot config's limits and
        tolerances, and everything that can be checked before motion is: 422 otherwise,
        before any CAN frame."""
        metrology = body.metrology or ("imu" if rt.settings.metrology == "imu" else "mocap")
        try:
            config: RobotConfig = rt.config.for_run(body.overrides.document(), metrology)
        except OverrideError as exc:
            raise RequestValidationError(
                [
                    {
                        "loc": ["body", "overrides"],
                        "msg": f"refused before any motion: {p}",
                        "type": "value_error",
                    }
                    for p in exc.problems
                ]
            ) from exc
        except (ValidationError, ValueError, TypeError) as exc:
            # same shape as FastAPI's own request-validation errors (one schema for 422)
            raise RequestValidationError(
                [
                    {
                        "loc": ["body", "overrides"],
                        "msg": f"invalid robot config override: {exc}",
                        "type": "value_error",
                    }
                ]
            ) from exc
        refs = start_references(config, metrology, body.references)
        try:
            run = rt.start_run(config, body.install, metrology, refs)
        except RunConflictError as exc:
            raise HTTPException(409, str(exc)) from exc
        except DiskSpaceError as exc:
            raise HTTPException(507, str(exc)) from exc
        except StoreError as exc:
            raise HTTPException(503, str(exc)) from exc
        response.headers["Location"] = f"/calibrations/{run.id}"
        return run.status.to_dict()

    @app.get("/calibrations", response_model=list[RunStatus])
    def list_runs(rt: Rt) -> list[dict[str, Any]]:
        return rt.list_runs()

    @app.get("/calibrations/{run_id}", response_model=RunStatus, responses=responses_run)
    def get_run(run_id: str, rt: Rt) -> dict[str, Any]:
        st = rt.status(run_id)
        if st is None:
            raise HTTPException(404, f"no calibration {run_id}")
        return st

    @app.get(
        "/calibrations/{run_id}/result",
        responses={404: {"model": Problem}, 409: {"model": Problem}},
    )
    def get_result(run_id: str, rt: Rt) -> dict[str, Any]:
        got = rt.result(run_id)
        if got is None:
            raise HTTPException(404, f"no calibration {run_id}")
        state, doc = got
        if state != "DONE" or doc is None:
            raise HTTPException(409, f"calibration {run_id} is {state}: no result")
        return doc

    @app.post(
        "/calibrations/{run_id}/abort",
        response_model=RunStatus,
        dependencies=[Depends(auth)],
        responses={**guarded, 404: {"model": Problem}, 409: {"model": Problem}},
    )
    async def abort(run_id: str, rt: Rt) -> dict[str, Any]:
        # async: runs on the event loop itself, so stop_all() is not queued behind a
        # threadpool hand-off; only the wait for the run's thread goes to a worker
        run = rt.runs.get(run_id)
        if run is None:
            if rt.status(run_id) is None:
                raise HTTPException(404, f"no calibration {run_id}")
            raise HTTPException(409, f"calibration {run_id} is not running")
        if run.finished:
            raise HTTPException(409, f"calibration {run_id} is {run.status.state}")
        run.abort()
        await asyncio.to_thread(run.join, 10.0)
        return run.status.to_dict()

    @app.get(
        "/calibrations/{run_id}/plot.png",
        responses={
            200: {"content": {"image/png": {}}},
            404: {"model": Problem},
            409: {"model": Problem},
        },
        response_class=Response,
    )
    def plot(run_id: str, rt: Rt) -> Response:
        """The run's plot: rendered once, then served from the run's directory."""
        try:
            path = rt.plot(run_id)
        except NoResultError as exc:
            raise HTTPException(409, str(exc)) from exc
        if path is None:
            raise HTTPException(404, f"no calibration {run_id}")
        return FileResponse(path, media_type="image/png")

    @app.get(
        "/kinematics",
        responses={
            404: {"model": Problem, "description": "no kinematic file installed"},
            500: {
                "model": UnreadableFileProblem,
                "description": "the file in force is on disk but does not load (damaged, "
                "not UTF-8, not a file): a fault of the server's data that lasts until a "
                "file is installed or rolled back, named with the backups that load; "
                "GET /health is then degraded",
            },
        },
    )
    def kinematics(rt: Rt) -> Any:
        """The kinematic file in force (docs/kinematic-file.md)."""
        try:
            doc = rt.kinematics_document()
        except KinematicFileError as exc:
            problem = unreadable_problem(rt.settings.kinematics_file, exc)
            return FiniteJSONResponse(problem.model_dump(), status_code=500)
        if doc is None:
            where = rt.settings.kinematics_file
            raise HTTPException(404, f"no kinematic file installed at {where}")
        return doc

    @app.get(
        "/health",
        responses={503: {"description": "failing: a calibration cannot start or go on"}},
    )
    def health(rt: Rt) -> FiniteJSONResponse:
        """``ok`` / ``degraded`` (200) or ``failing`` (503), with the problems."""
        state, doc = service_health(rt)
        return FiniteJSONResponse(doc, status_code=503 if state == "failing" else 200)

    @app.get("/metrics", response_class=PlainTextResponse)
    def metrics(rt: Rt) -> PlainTextResponse:
        from services.http.metrics import render_metrics

        body, content_type = render_metrics(rt)
        return PlainTextResponse(body, media_type=content_type)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
        detail = _printable(jsonable_encoder(exc.errors()))
        return FiniteJSONResponse({"detail": detail}, status_code=422)

    # Routers of other parts of the service (e.g. the operator console) go here, one
    # line each: app.include_router(<module>.router)
    app.include_router(kinematics_router(auth))  # the kinematic files: install, roll back
    # without motion capture: the operator's floor mark and tape (and the simulator's tape)
    app.include_router(imu_router(auth, in_process=cfg.in_process))
    app.include_router(console_router())  # GET /, its event stream, a run's geometry, files
    return app
