"""``GET /health``: can a calibration start, or go on, now?

:func:`service_health` judges the service's runtime (:class:`services.runtime.runtime.Runtime`):
``failing`` when a calibration cannot start or go on (CAN not open or faulted, a node
lost, a sensor the calibration needs not live or its clock off, the disk full, the store
unwritable), ``degraded`` when it can but something needs attention (node errors, a CAN
log stopped, the kinematic file in force unreadable, zenoh linked to none of its connect
endpoints while the sensors are live through another), else ``ok``.  ``zenoh_links`` counts
the zenoh sessions linked; none while connect endpoints are configured is a problem of its
own, named with the endpoints: zenoh retries them quietly, so a wrong address or a
refused user/password would otherwise look like a silent mocap PC.

The sensors judged: while a run goes, those of its metrology (motion capture, or the
gyro without motion capture); between runs, those of ``SWPC_METROLOGY`` (``mocap``,
``imu`` or ``both``).  Both sensors' ages are in the document either way (the gyro's is
null on a service set up for motion capture until its first run without it: only then does
it subscribe to the gyro).  The in-process
simulator's nodes and sensors are not judged between runs: its time stands still then.
"""

from __future__ import annotations

import math
import os
import shutil
from pathlib import Path
from typing import Any

from services.runtime.runtime import Runtime
from services.store.disk import run_reserve
from swpc_hw.drives.types import Lifecycle
from swpc_hw.errors import KinematicFileError
from swpc_hw.files.kinematic_file import module_mismatch
from swpc_hw.sensors.zenoh_session import linked_sessions

MIB = 1 << 20


def judged_sensors(rt: Runtime) -> set[str]:
    """``{"mocap"}``, ``{"imu"}`` or both: the running run's metrology, else the setting's."""
    run = rt.current
    if run is not None and rt.running():
        return {run.metrology.name}
    m = rt.settings.metrology
    return {"mocap", "imu"} if m == "both" else {m}


def run_files_problems(data_dir: Path) -> list[str]:
    """Why a run could not make its directory and files in ``data_dir`` (empty: it can):
    ``runs`` not a writable directory, or no inodes left on the file system."""
    out = []
    runs = data_dir / "runs"
    where = runs if runs.exists() else data_dir
    if runs.exists() and not runs.is_dir():
        out.append(f"data dir: {runs} is not a directory: a run cannot keep its files")
    elif not os.access(where, os.W_OK | os.X_OK):
        out.append(f"data dir: {where} is not writable: a run cannot keep its files")
    st = os.statvfs(data_dir)
    if st.f_files and st.f_favail == 0:
        out.append(
            "data dir: no inodes left on its file system: a run cannot make its files "
            f"({data_dir})"
        )
    return out


def _age(age: float) -> float | None:
    return age if math.isfinite(age) else None


def simulated_time_still(rt: Runtime) -> bool:
    """The in-process simulator between runs: simulated time stands still (it flows only
    while someone waits on it, docs/time.md), so no heartbeat, pose or gyro sample is
    late, and none is watched: a node's liveness is unknown; the run's PRECHECK judges
    them once time flows."""
    return rt.simulator is not None and not rt.running()


def start_problems(rt: Runtime) -> list[str]:
    """Why a run started now would fail at CONNECT or PRECHECK: what ``GET /health``
    calls failing about the robot and its sensors (the CAN driver, the nodes, the
    sensors, zenoh), but a fault the driver stopped on (the next run's CONNECT clears it;
    a cause that lasts, a node lost, is a problem of its own).  ``POST /calibrations``
    refuses a run with these (409); the disk and the run store it judges itself (507,
    503)."""
    return _robot_health(rt, simulated_time_still(rt), past_fault=False)[0]


def _robot_health(
    rt: Runtime, still: bool, past_fault: bool = True
) -> tuple[list[str], list[str], dict[str, Any], set[str], int | None]:
    """``(failing, degraded, nodes, sensors judged, zenoh links)`` of the robot and its
    sensors."""
    failing: list[str] = []
    degraded: list[str] = []
    d = rt.drives
    nodes: dict[str, Any] = {}
    if d is None or d.state in (Lifecycle.UNCONFIGURED, Lifecycle.FINALIZED):
        failing.append("CAN driver not open")
    else:
        if d.fault_cause is not None and past_fault:
            failing.append(f"CAN driver stopped on a fault: {d.fault_cause}")
        for m in d.modules():
            st = d.module_state(m)
            nodes[str(m)] = {"alive": st.alive, "errors": list(st.errors), "homed": st.homed}
            if not st.alive and not still:
                failing.append(f"module {m} (node {st.node}): no heartbeat")
            elif any(st.errors):
                degraded.append(f"module {m} (node {st.node}): active errors {st.errors}")
        err = d.log_error()
        if err is not None:
            degraded.append(f"CAN log stopped: {err}")
    sensors = judged_sensors(rt)
    age, gyro_age = rt.mocap.age(), rt.gyro.age()
    if "mocap" in sensors:
        if rt.mocap.is_stale() and not still:
            failing.append(
                "motion capture stale: "
                + ("no pose yet" if not math.isfinite(age) else f"no pose for {age:.2f} s")
            )
        clock = rt.mocap.clock_problem()
        if clock is not None:
            failing.append(clock)
        src = rt.mocap_source.latest()
        if src is not None and not src["seen"]:
            has = ", ".join(map(str, src.get("bodies") or [])) or "no bodies"
            failing.append(
                f"motion capture: {src['source']} does not see the body {src['body']!r} "
                f"(it has: {has}): put the robot in the volume, or name its body "
                "(swpc mocap --body)"
            )
    if "imu" in sensors:
        if rt.gyro.is_stale() and not still:
            failing.append(
                "gyro stale: "
                + (
                    "no sample yet"
                    if not math.isfinite(gyro_age)
                    else f"no sample for {gyro_age:.2f} s"
                )
            )
        clock = rt.gyro.clock_problem()
        if clock is not None:
            failing.append(clock)
    links = None if rt.session is None else linked_sessions(rt.session)
    if links == 0 and rt.zenoh_connect:
        # zenoh retries its connect endpoints quietly: a wrong address, a peer not
        # listening, or a user/password it refused all look like silent sensors
        problem = (
            f"zenoh: no link to {', '.join(rt.zenoh_connect)}: check the address, that the "
            "peer listens there, and this robot's zenoh user/password (deploy/README.md, "
            "Motion capture over zenoh)"
        )
        stale = ("mocap" in sensors and rt.mocap.is_stale()) or (
            "imu" in sensors and rt.gyro.is_stale()
        )
        (failing if stale and not still else degraded).append(problem)
    return failing, degraded, nodes, sensors, links


def service_health(rt: Runtime) -> tuple[str, dict[str, Any]]:
    """``(status, document)`` (module docstring)."""
    still = simulated_time_still(rt)
    failing, degraded, nodes, sensors, links = _robot_health(rt, still)
    d = rt.drives
    age, gyro_age = rt.mocap.age(), rt.gyro.age()
    if rt._unsaved:
        rt._save_unsaved()
    if rt.store_error is not None:
        failing.append(f"run store not writable: {rt.store_error}")
    disk: dict[str, Any] = {}
    try:
        free = shutil.disk_usage(rt.data_dir).free
        disk = {"free_bytes": free, "budget_bytes": int(rt.settings.disk_budget)}
        if free < int(rt.settings.min_free):
            failing.append(
                f"disk nearly full: {free / MIB:.1f} MiB free, below SWPC_MIN_FREE "
                f"{int(rt.settings.min_free) / MIB:.1f} MiB"
            )
        elif not rt.running():
            # what POST /calibrations asks of the file system (after pruning old runs'
            # recordings, which may still make the room: degraded, not failing)
            reserve = run_reserve(int(rt.settings.disk_budget))
            if free < int(rt.settings.min_free) + reserve:
                degraded.append(
                    f"disk: {free / MIB:.1f} MiB free, a run needs {reserve / MIB:.1f} MiB "
                    f"above SWPC_MIN_FREE {int(rt.settings.min_free) / MIB:.1f} MiB (507 "
                    "unless pruning old recordings makes the room)"
                )
        failing += run_files_problems(rt.data_dir)
    except OSError as exc:
        failing.append(f"data dir: {exc}")
    try:
        in_force = rt.kinematics_document()
    except KinematicFileError as exc:
        degraded.append(f"kinematic file in force unreadable: {exc}")
    else:
        ids = [] if in_force is None else [int(m["id"]) for m in in_force["modules"]]
        mismatch = None if in_force is None else module_mismatch(ids, rt.config.nominal.ids)
        if mismatch is not None:
            degraded.append(
                f"kinematic file in force does not match the robot: {mismatch} (a check is "
                "refused; a calibration replaces it)"
            )
    status = "failing" if failing else ("degraded" if degraded else "ok")
    doc = {
        "status": status,
        "problems": failing + degraded,
        "can": None if d is None else d.state.name.lower(),
        "nodes": nodes,
        "mocap_age_s": _age(age),
        "mocap_stale": rt.mocap.is_stale(),
        "mocap_source": rt.mocap_source.latest(),
        "gyro_age_s": _age(gyro_age),
        "gyro_stale": rt.gyro.is_stale(),
        "sensors": sorted(sensors),
        "running": rt.running(),
        "in_process_simulator": rt.simulator is not None,
        "simulated_time_still": still,
        "disk": disk,
        "zenoh_links": links,
    }
    return status, doc
