"""What the HTTP API checks before a request reaches a route: host, token, size, JSON.

:class:`RequestGuard` is a pure ASGI middleware, so it decides before the body is read:

0. the ``Host`` header must name this service: an IP address (v4 or v6), or one of the
   names it answers to (this host's names, ``localhost`` and ``SWPC_ALLOWED_HOSTS``);
   any other is answered 400.  A web page on another site whose name an attacker points at
   the robot's address (DNS rebinding) sends its own name: it reads nothing;
1. a request that may change something (any method but GET, HEAD, OPTIONS) without the
   bearer token is answered 401 at once: its body is never read or parsed.  An abort
   (``POST /calibrations/{id}/abort``, ``/checks/{id}/abort``, ``/commissions/{id}/abort``:
   :data:`STOP_PATH`)
   passes without it: stopping the robot is never refused for want of a token, as anyone
   beside the robot may press its emergency stop (it only ever stops motion);
2. a body over ``max_body`` bytes (by its ``Content-Length``, or counted as it arrives when
   chunked) is answered 413 without reading the rest;
3. a JSON body must be standard JSON (RFC 8259): ``NaN``, ``Infinity``, ``-Infinity``
   (which Python's parser accepts), numbers too large for a float (``1e400`` parses as
   infinity) or an integer of more than :data:`MAX_INT_DIGITS` digits, nesting deeper than
   :data:`MAX_DEPTH`, and text that is not UTF-8 are answered 422 with FastAPI's
   validation-error shape, naming what and where.

What passes is handed to the app unchanged.
"""

from __future__ import annotations

import ipaddress
import json
import math
import re
import secrets
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
STOP_PATH = re.compile(r"/(?:calibrations|checks|commissions)/[^/]+/abort")
"""The requests that stop a run: no token needed (module docstring, item 1)."""
MAX_DEPTH = 32
MAX_INT_DIGITS = 40


class JsonBodyError(ValueError):
    """A JSON body the service does not accept; ``pos`` is its character offset."""

    def __init__(self, msg: str, pos: int = 0) -> None:
        super().__init__(msg)
        self.msg, self.pos = msg, pos


def _constant(name: str) -> Any:
    raise JsonBodyError(f"{name} is not JSON (RFC 8259 has no NaN or Infinity)")


def _float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise JsonBodyError(f"number {text[:40]} is too large for a float")
    return value


def _int(text: str) -> int:
    if len(text.lstrip("-")) > MAX_INT_DIGITS:
        raise JsonBodyError(f"integer of {len(text)} digits (at most {MAX_INT_DIGITS})")
    return int(text)


def _depth_problem(text: str) -> JsonBodyError | None:
    """Nesting deeper than :data:`MAX_DEPTH` (outside strings), found before parsing (the
    parser itself would recurse that deep)."""
    depth, in_string, escaped = 0, False, False
    for i, c in enumerate(text):
        if in_string:
            if escaped:
                escaped = False
            elif c == "\\":
                escaped = True
            elif c == '"':
                in_string = False
        elif c == '"':
            in_string = True
        elif c in "[{":
            depth += 1
            if depth > MAX_DEPTH:
                return JsonBodyError(f"nesting deeper than {MAX_DEPTH} levels", i)
        elif c in "]}":
            depth -= 1
    return None


def check_json(body: bytes) -> JsonBodyError | None:
    """Why ``body`` is not acceptable JSON (module docstring), or ``None``."""
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as exc:
        return JsonBodyError(f"body is not UTF-8 (byte 0x{body[exc.start]:02x})", exc.start)
    deep = _depth_problem(text)
    if deep is not None:
        return deep
    try:
        json.loads(text, parse_constant=_constant, parse_float=_float, parse_int=_int)
    except JsonBodyError as exc:
        return exc
    except json.JSONDecodeError as exc:
        return JsonBodyError(exc.msg, exc.pos)
    except (ValueError, RecursionError) as exc:
        return JsonBodyError(str(exc).splitlines()[0])
    return None


def _is_json(scope: Scope) -> bool:
    for k, v in scope.get("headers", []):
        if k == b"content-type":
            ct: str = v.decode("latin-1").split(";")[0].strip().lower()
            return ct == "application/json" or ct.endswith("+json")
    return True  # FastAPI reads a body without a content type as JSON


def has_token(scope: Scope, token: str) -> bool:
    """The request's ``Authorization`` is ``Bearer <token>`` (compared in constant time)."""
    for k, v in scope.get("headers", []):
        if k == b"authorization":
            scheme, _, cred = v.decode("latin-1").partition(" ")
            return scheme.lower() == "bearer" and bool(
                secrets.compare_digest(cred.strip().encode(), token.encode())
            )
    return False


async def _reply(send: Send, status: int, doc: Any, headers: dict[str, str] | None = None) -> None:
    body = json.dumps(doc).encode()
    raw = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    raw += [(k.lower().encode(), v.encode()) for k, v in (headers or {}).items()]
    await send({"type": "http.response.start", "status": status, "headers": raw})
    await send({"type": "http.response.body", "body": body})


class RequestGuard:
    """The middleware of the module docstring; ``token`` is read per request."""

    def __init__(
        self,
        app: ASGIApp,
        token: Callable[[], str],
        max_body: int,
        hosts: frozenset[str] = frozenset(),
    ) -> None:
        self.app = app
        self.token = token
        self.max_body = max_body
        self.hosts = hosts

    def _host_refused(self, scope: Scope) -> str | None:
        """The Host header when it names no host this service answers to (else None)."""
        for k, v in scope.get("headers", []):
            if k == b"host":
                host: str = v.decode("latin-1").strip().lower()
                break
        else:
            return None  # HTTP/1.0 without Host: nothing to rebind
        name = host[1:].split("]", 1)[0] if host.startswith("[") else host.rsplit(":", 1)[0]
        if name.rstrip(".") in self.hosts:
            return None
        try:
            ipaddress.ip_address(name)
        except ValueError:
            return host
        return None

    def _authorised(self, scope: Scope) -> bool:
        return has_token(scope, self.token())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        refused = self._host_refused(scope)
        if refused is not None:
            await _reply(
                send,
                400,
                {"detail": f"Host {refused!r} is not a name of this service (SWPC_ALLOWED_HOSTS)"},
            )
            return
        stop = scope["method"] == "POST" and STOP_PATH.fullmatch(scope.get("path", ""))
        if scope["method"] not in SAFE_METHODS and not stop and not self._authorised(scope):
            await _reply(
                send,
                401,
                {"detail": "missing or invalid bearer token"},
                {"WWW-Authenticate": "Bearer"},
            )
            return
        length = None
        for k, v in scope.get("headers", []):
            if k == b"content-length":
                try:
                    length = int(v)
                except ValueError:
                    await _reply(send, 400, {"detail": "invalid Content-Length"})
                    return
        if length is not None and length > self.max_body:
            await _reply(send, 413, {"detail": f"request body over {self.max_body} bytes"})
            return
        if scope["method"] in SAFE_METHODS and not length:
            await self.app(scope, receive, send)
            return
        # read the (bounded) body, check it, then replay it to the app
        chunks, size = [], 0
        while True:
            msg = await receive()
            if msg["type"] == "http.disconnect":
                return
            data = msg.get("body", b"")
            size += len(data)
            if size > self.max_body:
                await _reply(send, 413, {"detail": f"request body over {self.max_body} bytes"})
                return
            chunks.append(data)
            if not msg.get("more_body", False):
                break
        body = b"".join(chunks)
        if body and _is_json(scope):
            problem = check_json(body)
            if problem is not None:
                await _reply(
                    send,
                    422,
                    {
                        "detail": [
                            {
                                "type": "json_invalid",
                                "loc": ["body", problem.pos],
                                "msg": f"JSON decode error: {problem.msg}",
                                "input": {},
                                "ctx": {"error": problem.msg},
                            }
                        ]
                    },
                )
                return
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)
