"""What every router of the API shares: the runtime and token dependencies, the problem
body, standard-JSON responses and the response tables of the OpenAPI document."""

from __future__ import annotations

import json
import math
import secrets
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request, status
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel

from services.config.robot import RunKind
from services.runtime.runtime import Runtime


class Problem(BaseModel):
    """An error's body (FastAPI's ``{"detail": ...}``)."""

    detail: str


def finite(value: Any) -> Any:
    """``value`` with every non-finite float replaced by ``None`` (JSON has no NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [finite(v) for v in value]
    return value


def printable(value: Any) -> Any:
    """``value`` with every non-finite float as its name (``"inf"``, ``"nan"``): for the
    ``input`` of a validation error, which must say what was sent."""
    if isinstance(value, float):
        return value if math.isfinite(value) else repr(value)
    if isinstance(value, dict):
        return {k: printable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [printable(v) for v in value]
    return value


class FiniteJSONResponse(JSONResponse):
    """Standard JSON: non-finite numbers as ``null`` (never a 500 while rendering)."""

    def render(self, content: Any) -> bytes:
        return json.dumps(
            finite(content), ensure_ascii=False, allow_nan=False, separators=(",", ":")
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


AUTH = [Depends(auth)]
"""The dependencies of a route that moves the robot or writes."""

Responses = dict[int | str, dict[str, Any]]


def problems(*codes: int, **described: str) -> Responses:
    """The OpenAPI responses of ``codes`` (a :class:`Problem` body each), and of the codes
    given as ``_<code>="description"``."""
    out: Responses = {code: {"model": Problem} for code in codes}
    for name, text in described.items():
        out[int(name.lstrip("_"))] = {"model": Problem, "description": text}
    return out


GUARDED = problems(401, 413)
"""What a guarded route may answer before its own work: no token, a body too large."""


def not_running(rt: Runtime, run_id: str, kind: RunKind = "calibration") -> HTTPException:
    """404 for a run of ``kind`` never seen, 409 for one that is over (the route wants it
    running)."""
    if rt.status(run_id, kind) is None:
        return HTTPException(404, f"no {kind} {run_id}")
    return HTTPException(409, f"{kind} {run_id} is not running")


def done_result(rt: Runtime, run_id: str, kind: RunKind = "calibration") -> dict[str, Any]:
    """A DONE run's result document: 404 for a run of ``kind`` never seen, 409 for one
    without a result."""
    got = rt.result(run_id, kind)
    if got is None:
        raise HTTPException(404, f"no {kind} {run_id}")
    state, doc = got
    if state != "DONE" or doc is None:
        raise HTTPException(409, f"{kind} {run_id} is {state}: no result")
    return doc
