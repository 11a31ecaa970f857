"""The rig of the console's endpoint tests (``test_console_run_and_install.py``,
``test_console_event_stream.py``): a runtime not opened, on a virtual clock, and real
runs of the state machine on the fake robot of ``tests/services/runs/test_state_machine.py``
(a whole run in about a second), made as the runtime makes them (its store, its event bus).
"""

from __future__ import annotations

from pathlib import Path

from pydantic import SecretStr

from services.config.robot import RobotConfig
from services.config.settings import ServiceSettings
from services.runs.check import CheckRun
from services.runs.metrology.mocap import MocapMetrology
from services.runs.protocol import CalibrationRun
from services.runtime.runtime import Runtime
from services.sensors.mocap import MocapIngest
from swpc_hw.clock import VirtualClock
from swpc_hw.files.kinematic_file import load_kinematics
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL
from tests.fake_robot import FakeRobot
from tests.service_rig import TOKEN

TRUTH = RobotParams(robot="swpc", modules=PAPER_CALIBRATED.modules[:3])
NOMINAL = RobotParams(robot="swpc", modules=PAPER_NOMINAL.modules[:3])
PROTOCOL = {"angles_deg": [30, 150], "sweep_deg": 90, "settle_time": 0.5, "stop_time": 0.3,
            "align_time": 0.3, "resteer_time": 0.5}  # fmt: skip


def bare_runtime(data: Path) -> Runtime:
    """A runtime not opened (no bus, no zenoh, no simulator) on a virtual clock."""
    settings = ServiceSettings(data_dir=data, token=SecretStr(TOKEN), can_interface="virtual")
    config = RobotConfig.model_validate({"nominal": NOMINAL.model_dump(), "protocol": PROTOCOL})
    rt = Runtime(settings, config)
    rt.clock = VirtualClock(start=1000.0)
    rt.mocap = MocapIngest(clock=rt.clock, clock_mode="wall", stale_after=0.5)
    return rt


def new_run(rt: Runtime, install: str = "never", seen: list[str] | None = None) -> CalibrationRun:
    """A run of the fake robot as the runtime makes one (its store and event bus); every
    state the runtime is told of goes to ``seen``."""

    def on_change(run: CalibrationRun) -> None:
        if seen is not None:
            seen.append(run.status.state)
        rt._persist(run)

    robot = FakeRobot(TRUTH, rt.clock, rt.mocap, dt=0.01, pose_every=1)  # type: ignore[arg-type]
    run = CalibrationRun(
        robot,
        MocapMetrology(rt.mocap, rt.config.pose_key),
        rt.config,
        clock=rt.clock,
        data_dir=rt.data_dir,
        kinematics_path=rt.settings.kinematics_file,
        install=install,
        on_change=on_change,
    )
    rt.runs[run.id] = run
    rt.current = run
    on_change(run)
    return run


def new_check(rt: Runtime) -> CheckRun:
    """A check of the file in force on the fake robot, as the runtime makes one."""
    robot = FakeRobot(TRUTH, rt.clock, rt.mocap, dt=0.01, pose_every=1)  # type: ignore[arg-type]
    path = rt.settings.kinematics_file
    run = CheckRun(
        robot,
        MocapMetrology(rt.mocap, rt.config.pose_key),
        rt.config.check_config().with_overrides({"protocol": {"sweep_deg": 90}}),  # quick
        file=load_kinematics(path),
        file_info={"name": path.name},
        clock=rt.clock,
        data_dir=rt.data_dir,
        kinematics_path=path,
        on_change=rt._persist,
    )
    rt.runs[run.id] = run
    rt.current = run
    rt._persist(run)
    return run
