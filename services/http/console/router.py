"""The operator console's routes: the page, its event stream, a run's geometry and files.

* ``GET /`` the page (``static/``: hand-written HTML, CSS and JavaScript, no build step and
  nothing fetched from elsewhere).
* ``GET /events`` server-sent events: ``hello`` (the robot's nominal geometry and the
  protocol defaults), ``run`` (a run's status on every change of state, pushed by the
  state machine through :class:`services.runtime.events.EventBus`) and ``live`` (nodes, mocap age,
  the robot's pose, its trajectory since the last one, the fixed point of every spin done)
  every :data:`LIVE_PERIOD` s of host time while the stream is open.  ``?run=<id>``
  follows one run and ends after its final state.  ``live`` also carries ``drives``, the
  document of ``GET /drives`` (:mod:`services.http.drives`), for the Drives view.
  FastAPI's own server-sent events (``fastapi.sse``); every event has an id
  (:mod:`services.runtime.events`: increasing along a stream), so a client that
  reconnects with ``Last-Event-ID`` (a browser's EventSource does it itself) gets exactly
  the ``run`` events it missed, then ``live`` again; with an id too old, unknown or
  ``hello``'s, the stream starts over as a new one (``hello``, the run's status).
* ``GET /calibrations/{id}/geometry`` a finished run's spins for the top-down view.
* ``GET /calibrations/{id}/files`` and ``.../files/{name}`` its files for download.
* ``GET /calibrations/{id}/mcap`` what its ``run.mcap`` holds, read from the file's own
  summary (channels and schemas, metadata, attachments, the time base), for the page's
  Foxglove view.

The live period is host time on purpose: it is how often a person is shown the robot, not
a duration of the protocol (robot time runs faster than the host's against the in-process
simulator, slower under load).
"""

from __future__ import annotations

import asyncio
import io
import json
import math
import re
import zipfile
from collections import OrderedDict
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Header, HTTPException, Request
from fastapi.responses import FileResponse, Response
from fastapi.sse import EventSourceResponse, ServerSentEvent
from mcap.exceptions import McapError
from mcap.reader import make_reader
from pydantic import BaseModel, Field

from services.http.deps import Problem, Rt, done_result, problems
from services.http.drives import drives_view
from services.http.edge.guard import has_token
from services.http.edge.streams import StreamGate, StreamRefusedError, Ticket
from services.runs.mcap import MODULE_COLOURS
from services.runs.protocol import CalibrationRun
from services.runs.state import TERMINAL
from services.runtime.health import simulated_time_still
from services.runtime.runtime import Runtime
from swpc_hw.calibration import geometry as geo
from swpc_hw.errors import SwpcError
from swpc_hw.files.dataset import load_dataset
from swpc_hw.robot.model import PARAM_NAMES

STATIC = Path(__file__).parent / "static"
_ASSETS = {
    "console.css": "text/css; charset=utf-8",
    "console.js": "text/javascript; charset=utf-8",
}
LIVE_PERIOD = 0.25
"""s of host time between two ``live`` events of one stream."""
RETRY_MS = 1000
"""How long a browser waits before it reconnects a stream that broke, ms."""
HELLO = 0
"""The number in the id of ``hello``: before every event (a client resuming from it
starts over)."""
TRAIL_POINTS = 60
"""Most trajectory points in one ``live`` event (decimated evenly beyond)."""
FILES: dict[str, tuple[str, str]] = {
    "run.mcap": ("run.mcap", "application/octet-stream"),
    "can.log": ("dataset/can.log", "text/plain; charset=utf-8"),
    "kinematics.yaml": ("kinematics.yaml", "application/yaml"),
    "dataset.zip": ("dataset", "application/zip"),
}
"""Downloadable files of a run: name -> (path in the run's directory, media type)."""
FileName = Literal["run.mcap", "can.log", "kinematics.yaml", "dataset.zip"]


class Spin(BaseModel):
    """One spin: the fixed point ``C_R`` (robot frame), where it stayed ``C_W`` (world),
    the radius of the circle the robot's origin drew about it, the origin's path."""

    module: int
    start: float
    end: float
    c_r: tuple[float, float]
    c_w: tuple[float, float]
    radius: float
    path: list[tuple[float, float]] = []


class ModuleGeometry(BaseModel):
    id: int
    x_s: float
    y_s: float
    beta: float
    b: float
    r: float


class RunGeometry(BaseModel):
    run: str
    nominal: list[ModuleGeometry]
    calibrated: list[ModuleGeometry]
    spins: list[Spin]


class RunFile(BaseModel):
    name: str
    size: int
    url: str


class McapChannel(BaseModel):
    topic: str
    schema_name: str
    encoding: str
    messages: int
    native: bool = Field(description="a schema Foxglove shows natively (foxglove.*, ROS 2)")


class McapSummary(BaseModel):
    """What a run's MCAP holds, from the file's summary section."""

    run: str
    size: int
    indexed: bool = Field(description="the file has a summary (False: cut short, unindexed)")
    channels: list[McapChannel] = []
    metadata: list[str] = []
    attachments: list[str] = []
    start_ns: int | None = None
    end_ns: int | None = None
    epoch_times: bool = Field(False, description="log times are Unix epoch nanoseconds")


EPOCH_2000_NS = 946_684_800 * 10**9
"""Log times from here on are taken for epoch times (2000-01-01T00:00:00Z)."""
MCAP_MAGIC = b"\x89MCAP0\r\n"
_ROS2_TYPE = re.compile(r"^\w+/msg/\w+$")


def mcap_summary(run_id: str, path: Path) -> McapSummary:
    """The summary of the MCAP at ``path`` (``indexed`` False if it has none)."""
    size = path.stat().st_size
    with path.open("rb") as fh:
        try:
            summary = make_reader(fh).get_summary()
        except McapError:  # no footer: a recording cut short, if it starts as an MCAP does
            fh.seek(0)
            if fh.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                raise
            summary = None
    if summary is None:
        return McapSummary(run=run_id, size=size, indexed=False)
    stats = summary.statistics
    counts = {} if stats is None else stats.channel_message_counts
    channels = []
    for cid, ch in sorted(summary.channels.items()):
        schema = summary.schemas.get(ch.schema_id)
        name = "" if schema is None else schema.name
        native = name.startswith("foxglove.") or bool(_ROS2_TYPE.match(name))
        channels.append(
            McapChannel(
                topic=ch.topic,
                schema_name=name,
                encoding=ch.message_encoding,
                messages=counts.get(cid, 0),
                native=native,
            )
        )
    start = None if stats is None or not stats.message_count else stats.message_start_time
    end = None if stats is None or not stats.message_count else stats.message_end_time
    return McapSummary(
        run=run_id,
        size=size,
        indexed=True,
        channels=channels,
        metadata=[m.name for m in summary.metadata_indexes],
        attachments=[a.name for a in summary.attachment_indexes],
        start_ns=start,
        end_ns=end,
        epoch_times=start is not None and start >= EPOCH_2000_NS,
    )




def spin_of(module: int, start: float, end: float, poses: np.ndarray[Any, Any]) -> Spin | None:
    """The spin in ``poses`` (rows t, x, y, yaw) within ``[start, end]``; None if fewer
    than 3 poses."""
    sel = (poses[:, 0] >= start) & (poses[:, 0] <= end)
    p = poses[sel, 1:4].copy()
    if p.shape[0] < 3:
        return None
    p[:, 2] = np.unwrap(p[:, 2])
    c_r, c_w = geo.fixed_point(p)
    path = p[:: max(1, math.ceil(p.shape[0] / 300)), :2]
    return Spin(
        module=module,
        start=start,
        end=end,
        c_r=(float(c_r[0]), float(c_r[1])),
        c_w=(float(c_w[0]), float(c_w[1])),
        radius=float(np.hypot(c_r[0], c_r[1])),
        path=[(float(x), float(y)) for x, y in path],
    )


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


_NO_ROWS = np.zeros((0, 6))


class _LiveCursor:
    """What one stream has sent of the current run's trajectory and spins."""

    def __init__(self) -> None:
        self.run: str | None = None
        self.last_t = -math.inf
        self.spins: dict[tuple[str, int], dict[str, Any]] = {}


def _nodes(rt: Runtime) -> list[dict[str, Any]]:
    """Each node's state; ``alive`` None (unknown) while no heartbeat is watched: the
    in-process simulator between runs, whose time stands still."""
    d = rt.drives
    if d is None:
        return []
    watched = not simulated_time_still(rt)
    out = []
    for m in d.modules():
        st = d.module_state(m)
        th = st.theta_hat
        out.append(
            {
                "module": m,
                "node": st.node,
                "alive": st.alive if watched else None,
                "errors": [int(e) for e in st.errors],
                "homed": st.homed,
                "steer_deg": _finite(math.degrees(th)),
                "modes": [str(getattr(x, "name", x)).lower() for x in st.modes],
            }
        )
    return out


def _delays(rt: Runtime) -> list[float] | None:
    """The poses' delays at receipt, median and 99th percentile (ms; the transport's in
    clock mode wall, above the smallest in source: :meth:`MocapIngest.stats`)."""
    st = rt.mocap.stats()
    if "latency_p50_s" not in st:
        return None
    return [round(st["latency_p50_s"] * 1e3, 2), round(st["latency_p99_s"] * 1e3, 2)]


def live_snapshot(rt: Runtime, cur: _LiveCursor) -> dict[str, Any]:
    """The ``live`` event: what changes continuously (see the module docstring)."""
    latest = rt.mocap.latest()
    age = rt.mocap.age()
    run: CalibrationRun | None = rt.current
    out: dict[str, Any] = {
        "can": None if rt.drives is None else rt.drives.state.name.lower(),
        "nodes": _nodes(rt),
        "drives": drives_view(rt).model_dump(mode="json"),
        "mocap": {
            "age_s": _finite(age),
            "stale": rt.mocap.is_stale(),
            "pose": None if latest is None else [latest.x, latest.y, latest.yaw],
            "source": rt.mocap_source.latest(),
            "delay_ms": _delays(rt),
        },
        "run": None if run is None else run.status.to_dict(),
    }
    if run is None:
        return out
    reset = cur.run != run.id and run.status.started is not None
    if reset:  # from the run's start (on its clock) on
        cur.run, cur.last_t = run.id, run.clock_start
    trail: list[list[float]] = []
    rows = rt.mocap.samples(since_host=cur.last_t) if cur.run == run.id else _NO_ROWS
    if rows.shape[0]:
        cur.last_t = float(rows[-1, 2]) + 1e-9
        step = max(1, math.ceil(rows.shape[0] / TRAIL_POINTS))
        picked = rows[::step]
        if (rows.shape[0] - 1) % step:
            picked = np.vstack([picked, rows[-1:]])
        trail = [[round(float(x), 5), round(float(y), 5)] for x, y in picked[:, 3:5]]
    spins = []
    for i, sg in enumerate(list(run.segments)):
        key = (run.id, i)
        if key not in cur.spins:
            p = rt.mocap.samples(since_host=sg.start)
            s = spin_of(sg.static_module, sg.start, sg.end, p[:, 2:6])
            cur.spins[key] = {} if s is None else s.model_dump(exclude={"path"})
        if cur.spins[key]:
            spins.append(cur.spins[key])
    out["trail"] = {"run": run.id, "reset": reset, "points": trail}
    out["spins"] = spins
    return out


def _stopping(request: Request) -> bool:
    """The service is stopping (SIGTERM, SIGINT): an open stream then ends within
    :data:`LIVE_PERIOD`, since the server waits for every open response before it stops
    the runtime, and with it a run in progress."""
    return getattr(request.app.state, "stop_signal", None) is not None


def hello(rt: Runtime) -> dict[str, Any]:
    cfg = rt.config
    return {
        "robot": cfg.robot,
        "modules": [
            {k: getattr(m, k) for k in ("id", *PARAM_NAMES)}
            for m in cfg.nominal.modules
        ],
        "protocol": cfg.protocol.model_dump(),
        "check": cfg.check_config().protocol.model_dump(),
        "in_process_simulator": rt.simulator is not None,
        "kinematics_path": str(rt.settings.kinematics_file),
        "metrology": rt.settings.run_metrology,
    }


router = APIRouter()
_geometry_cache: OrderedDict[tuple[str, str], RunGeometry] = OrderedDict()
"""Finished runs' geometry by (data dir, run id): computed once from the run's dataset."""


@router.get("/", include_in_schema=False)
def index() -> FileResponse:
    return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

@router.get("/console/palette.js", include_in_schema=False)
def palette() -> Response:
    """The modules' colours of the run's plot (:data:`services.runs.mcap.MODULE_COLOURS`),
    for the page: one module, one colour on both."""
    body = f"const COLORS = {json.dumps(list(MODULE_COLOURS))};\n"
    return Response(
        body, media_type="text/javascript; charset=utf-8", headers={"Cache-Control": "no-cache"}
    )


@router.get("/console/{name}", include_in_schema=False)
def asset(name: str) -> FileResponse:
    if name not in _ASSETS:
        raise HTTPException(404, f"no console asset {name}")
    return FileResponse(
        STATIC / name, media_type=_ASSETS[name], headers={"Cache-Control": "no-cache"}
    )

def _followed(rt: Rt, run: str | None = None) -> str | None:
    """``?run=<id>``: a run this service knows (404 before the stream begins)."""
    if run is not None and rt.status(run) is None:
        raise HTTPException(404, f"no calibration {run}")
    return run


async def _admitted(request: Request) -> Ticket:
    """A place for the stream (:class:`services.http.edge.streams.StreamGate`), else 429."""
    gate: StreamGate = request.app.state.streams
    client = request.client.host if request.client else "unknown"
    try:
        return gate.admit(client, has_token(request.scope, str(request.app.state.token)))
    except StreamRefusedError as exc:
        raise HTTPException(429, str(exc), headers={"Retry-After": str(RETRY_MS // 1000)}) from None


@router.get("/events", include_in_schema=False, response_class=EventSourceResponse)
async def events(
    request: Request,
    rt: Rt,
    run: Annotated[str | None, Depends(_followed)],
    ticket: Annotated[Ticket, Depends(_admitted)],
    last_event_id: Annotated[str | None, Header()] = None,
) -> AsyncIterator[ServerSentEvent]:
    try:
        async for ev in _stream(request, rt, run, last_event_id, ticket):
            yield ev
    finally:
        ticket.release()


class _Sender:
    """One stream's events: numbered by the bus, :data:`RETRY_MS` on the first."""

    def __init__(self, rt: Runtime, only: str | None) -> None:
        self.rt, self.only = rt, only
        self.last = 0  # the number of the newest event this stream stands for
        self.ended = False  # ?run=<id>: its final state was sent
        self._retry: int | None = RETRY_MS

    def event(self, name: str, data: Any, seq: int) -> ServerSentEvent:
        ev = ServerSentEvent(
            event=name, data=data, id=self.rt.events.event_id(seq), retry=self._retry
        )
        self._retry = None
        self.last = max(self.last, seq)
        return ev

    def status(self) -> dict[str, Any] | None:
        """The followed run's status now (the current run's without ``?run``)."""
        rt = self.rt
        if self.only:
            return rt.status(self.only)
        return None if rt.current is None else rt.current.status.to_dict()

    def run(self, st: dict[str, Any], seq: int) -> list[ServerSentEvent]:
        """``run`` for ``st`` (numbered ``seq``) if this stream follows it."""
        self.last = max(self.last, seq)
        if self.ended or (self.only is not None and st["id"] != self.only):
            return []
        self.ended = self.only is not None and st["state"] in TERMINAL
        return [self.event("run", st, seq)]

    def snapshot(self, with_hello: bool) -> list[ServerSentEvent]:
        """``hello`` and the followed run's status, numbered before it is read: every
        change published after it comes next.  ``hello`` stands for nothing published
        (:data:`HELLO`): a client that reconnects with its id starts over."""
        seq = self.rt.events.mark()
        st = self.status()
        out = [self.event("hello", hello(self.rt), HELLO)] if with_hello else []
        self.last = seq
        return out + ([] if st is None else self.run(st, seq))

    def catch_up(self, news: list[tuple[int, dict[str, Any]]] | None) -> list[ServerSentEvent]:
        """The run events published since :attr:`last` (``news``), or the status now when
        the bus no longer has them all."""
        if news is None:
            return self.snapshot(with_hello=False)
        out: list[ServerSentEvent] = []
        for seq, ev in news:
            out += self.run(ev["run"], seq)
        return out


async def _stream(
    request: Request, rt: Runtime, only: str | None, last_event_id: str | None, ticket: Ticket
) -> AsyncIterator[ServerSentEvent]:
    loop = asyncio.get_running_loop()
    cur = _LiveCursor()
    bus = rt.events
    send = _Sender(rt, only)
    with bus.subscribe() as sub:
        resume = bus.number(last_event_id) or HELLO
        news = None if resume == HELLO else bus.since(resume)
        if news is None:  # a new client, or one whose id is too old or unknown
            first = send.snapshot(with_hello=True)
        else:  # exactly what it missed
            send.last = resume
            first = send.catch_up(news)
        for ev in first:
            yield ev
        next_live = loop.time()
        while not send.ended and not _stopping(request) and not ticket.evicted:
            await sub.wait(timeout=max(0.0, next_live - loop.time()))
            for ev in send.catch_up(bus.since(send.last)):
                yield ev
            if send.ended or loop.time() < next_live:
                continue
            if only is not None:  # its end, even if missed
                st = rt.status(only)
                if st is not None and st["state"] in TERMINAL:
                    for ev in send.catch_up(bus.since(send.last)):
                        yield ev
                    if not send.ended:
                        for ev in send.run(st, bus.mark()):
                            yield ev
                    return
            seq = bus.mark()
            for ev in send.catch_up(bus.since(send.last)):  # published before the mark
                yield ev
            yield send.event("live", live_snapshot(rt, cur), seq)
            next_live = loop.time() + LIVE_PERIOD
            if await request.is_disconnected():
                return


@router.get(
    "/calibrations/{run_id}/geometry",
    response_model=RunGeometry,
    responses=problems(404, 409),
)
def geometry(run_id: str, rt: Rt) -> RunGeometry:
    key = (str(rt.data_dir), run_id)
    if key in _geometry_cache:
        return _geometry_cache[key]
    doc = done_result(rt, run_id)
    try:
        ds = load_dataset(Path(rt.settings.data_dir) / "runs" / run_id / "dataset")
    except SwpcError as exc:
        raise HTTPException(409, f"calibration {run_id}: dataset unreadable: {exc}") from exc
    spins = [spin_of(s.static_module, s.start, s.end, ds.poses) for s in ds.segments]
    keys = ("id", *PARAM_NAMES)
    out = RunGeometry(
        run=run_id,
        nominal=[ModuleGeometry(**{k: getattr(m, k) for k in keys}) for m in ds.robot.modules],
        calibrated=[ModuleGeometry(**{k: m[k] for k in keys}) for m in doc["modules"]],
        spins=[s for s in spins if s is not None],
    )
    _geometry_cache[key] = out
    while len(_geometry_cache) > 16:
        _geometry_cache.popitem(last=False)
    return out

def run_dir(rt: Runtime, run_id: str) -> Path:
    """A calibration's directory (404 for anything else: a check's files are its own)."""
    if rt.status(run_id, "calibration") is None:
        raise HTTPException(404, f"no calibration {run_id}")
    return Path(rt.settings.data_dir) / "runs" / run_id

@router.get(
    "/calibrations/{run_id}/files",
    response_model=list[RunFile],
    responses=problems(404),
)
def list_files(run_id: str, rt: Rt) -> list[RunFile]:
    d = run_dir(rt, run_id)
    out = []
    for name, (rel, _) in FILES.items():
        p = d / rel
        if name == "dataset.zip":
            if not any((p / f).is_file() for f in ("poses.csv", "imu.csv")):
                continue  # no motion recorded (with or without motion capture)
            size = sum(f.stat().st_size for f in p.iterdir() if f.is_file())
        elif p.is_file():
            size = p.stat().st_size
        else:
            continue
        out.append(RunFile(name=name, size=size, url=f"/calibrations/{run_id}/files/{name}"))
    return out

@router.get(
    "/calibrations/{run_id}/files/{name}",
    response_class=Response,
    responses={
        200: {"content": {media: {} for _, media in FILES.values()}},
        404: {"model": Problem},
    },
)
def download(run_id: str, name: FileName, rt: Rt) -> Response:
    d = run_dir(rt, run_id)
    rel, media = FILES[name]
    p = d / rel
    disposition = {"Content-Disposition": f'attachment; filename="{run_id}-{name}"'}
    if name == "dataset.zip":
        if not p.is_dir():
            raise HTTPException(404, f"calibration {run_id} has no dataset")
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
            for f in sorted(p.iterdir()):
                if f.is_file():
                    z.write(f, f"{run_id}/dataset/{f.name}")
        return Response(buf.getvalue(), media_type=media, headers=disposition)
    if not p.is_file():
        raise HTTPException(404, f"calibration {run_id} has no {name}")
    return FileResponse(p, media_type=media, headers=disposition)

@router.get(
    "/calibrations/{run_id}/mcap",
    response_model=McapSummary,
    responses=problems(404, 409),
)
def mcap(run_id: str, rt: Rt) -> McapSummary:
    p = run_dir(rt, run_id) / FILES["run.mcap"][0]
    if not p.is_file():
        raise HTTPException(404, f"calibration {run_id} has no run.mcap")
    try:
        return mcap_summary(run_id, p)
    except (McapError, OSError, ValueError) as exc:
        raise HTTPException(409, f"calibration {run_id}: run.mcap unreadable: {exc}") from exc

