"""The calibration service's HTTP API (FastAPI).

Operators start a calibration, watch it and read the result; motion and write
endpoints need the bearer token from the settings.  See :mod:`services.runtime` for what
is opened in the lifespan and :mod:`services.calibration_run` for the protocol.
"""

from __future__ import annotations

import asyncio
import io
import math
import secrets
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Annotated, Any, Literal

from fastapi import Depends, FastAPI, HTTPException, Request, Response, status
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from services.calibration_run import RunStatus
from services.robot_config import ConfigOverrides, RobotConfig
from services.runtime import RunConflictError, Runtime
from services.settings import ServiceSettings
from swpc_hw.errors import KinematicFileError
from swpc_hw.heap_freeze import freeze_startup_heap
from swpc_hw.kinematic_file import load_kinematics


class StartRequest(BaseModel):
    """Start a calibration; ``overrides`` are deep-merged into the robot config."""

    model_config = ConfigDict(extra="forbid")

    overrides: ConfigOverrides = Field(default_factory=ConfigOverrides)
    install: Literal["if-within-tolerance", "always", "never"] = "if-within-tolerance"


class Problem(BaseModel):
    detail: str


def runtime(request: Request) -> Runtime:
    """The runtime opened in the lifespan (dependency)."""
    rt: Runtime = request.app.state.runtime
    return rt


Rt = Annotated[Runtime, Depends(runtime)]
_bearer = HTTPBearer(auto_error=False)


def auth(
    request: Request,
    creds: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    """Motion and write endpoints: the bearer token of the settings, else 401."""
    token: str = request.app.state.token
    if creds is None or not secrets.compare_digest(creds.credentials.encode(), token.encode()):
        raise HTTPException(
            status.HTTP_401_UNAUTHORIZED,
            "missing or invalid bearer token",
            headers={"WWW-Authenticate": "Bearer"},
        )


def create_app(
    settings: ServiceSettings | None = None,
    runtime_factory: Callable[[ServiceSettings], Runtime] | None = None,
) -> FastAPI:
    """The app; the runtime is opened in the lifespan (``runtime_factory`` for tests)."""
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
            rt.close()

    app = FastAPI(
        title="swpc calibration service",
        version="0.1.0",
        lifespan=lifespan,
        description="Calibrates SWPC robots: start / watch / abort runs, read results.",
    )
    app.state.token = token
    responses_run: dict[int | str, dict[str, Any]] = {404: {"model": Problem}}

    @app.post(
        "/calibrations",
        status_code=202,
        response_model=RunStatus,
        dependencies=[Depends(auth)],
        responses={401: {"model": Problem}, 409: {"model": Problem}},
    )
    def start(body: StartRequest, rt: Rt, response: Response) -> dict[str, Any]:
        try:
            config: RobotConfig = rt.config.with_overrides(body.overrides.document())
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
        try:
            run = rt.start_run(config, body.install)
        except RunConflictError as exc:
            raise HTTPException(409, str(exc)) from exc
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
        responses={401: {"model": Problem}, 404: {"model": Problem}, 409: {"model": Problem}},
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
        run = rt.runs.get(run_id)
        if run is None or run.result is None:
            if rt.status(run_id) is None:
                raise HTTPException(404, f"no calibration {run_id}")
            raise HTTPException(409, f"calibration {run_id} has no result in memory to plot")
        from services.plots import calibration_plot

        png = calibration_plot(run.dataset(), run.result)
        return Response(content=png, media_type="image/png")

    @app.get("/kinematics", responses={404: {"model": Problem}})
    def kinematics(rt: Rt) -> dict[str, Any]:
        path = rt.settings.kinematics_file
        if not path.exists():
            raise HTTPException(404, f"no kinematic file installed at {path}")
        try:
            k = load_kinematics(path)
        except KinematicFileError as exc:
            raise HTTPException(500, str(exc)) from exc
        import yaml

        doc: dict[str, Any] = yaml.safe_load(path.read_text(encoding="utf-8"))
        doc["path"] = str(path)
        doc["robot"] = k.params.robot
        return doc

    @app.get("/health")
    def health(rt: Rt) -> dict[str, Any]:
        d = rt.driver
        age = rt.mocap.age()
        nodes = {}
        if d is not None:
            for m in d.modules():
                st = d.module_state(m)
                nodes[str(m)] = {"alive": st.alive, "errors": list(st.errors), "homed": st.homed}
        return {
            "status": "ok",
            "can": None if d is None else d.state.name.lower(),
            "nodes": nodes,
            "mocap_age_s": age if math.isfinite(age) else None,
            "mocap_stale": rt.mocap.is_stale(),
            "running": rt.running(),
            "in_process_simulator": rt.simulator is not None,
        }

    @app.get("/metrics", response_class=PlainTextResponse)
    def metrics(rt: Rt) -> PlainTextResponse:
        from services.metrics import render_metrics

        body, content_type = render_metrics(rt)
        return PlainTextResponse(body, media_type=content_type)

    @app.exception_handler(KinematicFileError)
    async def _kin_error(request: Request, exc: KinematicFileError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=500)

    _ = io  # plots are rendered in services.plots
    return app
