"""The default protocol is stated once (swpc_hw.protocol.DEFAULT_PROTOCOL): the robot
config, the example robot config, the offline generator, the planner and ``swpc datagen``
read it (the generator with two shorter pauses of its own)."""

from __future__ import annotations

import dataclasses
import math

from services.config.robot import ProtocolConfig, load_robot_config
from simulators.offline.datagen import ExperimentOptions
from simulators.offline.datagen_imu import IMU_PROTOCOL
from swpc_hw.calibration.plan.plan import ANGLE_SETS
from swpc_hw.protocol import DEFAULT_PROTOCOL
from tests.service_rig import ROOT

EXAMPLE = ROOT / "deploy" / "robot.example.yaml"


def protocol_of(config: ProtocolConfig) -> dict[str, object]:
    """The fields of ``config`` that DEFAULT_PROTOCOL states, as its types."""
    got = {f.name: getattr(config, f.name) for f in dataclasses.fields(DEFAULT_PROTOCOL)}
    got["angles_deg"] = tuple(got["angles_deg"])  # type: ignore[arg-type]
    return got


def test_the_robot_config_and_its_example_state_the_default_protocol() -> None:
    assert protocol_of(ProtocolConfig()) == dataclasses.asdict(DEFAULT_PROTOCOL)
    assert protocol_of(load_robot_config(EXAMPLE).protocol) == dataclasses.asdict(
        DEFAULT_PROTOCOL
    )


def test_the_generator_and_the_planner_start_from_it() -> None:
    opt = ExperimentOptions()
    assert opt.angles == tuple(math.radians(a) for a in DEFAULT_PROTOCOL.angles_deg)
    assert opt.align_time == DEFAULT_PROTOCOL.align_time
    # the generator's own pauses, shorter: its timelines (and what was measured on them)
    assert opt.settle_time <= DEFAULT_PROTOCOL.settle_time
    assert opt.resteer_time <= DEFAULT_PROTOCOL.resteer_time
    assert (IMU_PROTOCOL.rest_time, IMU_PROTOCOL.drive_length) == (
        DEFAULT_PROTOCOL.rest_time,
        DEFAULT_PROTOCOL.drive_length,
    )
    assert ANGLE_SETS[0] == DEFAULT_PROTOCOL.angles_deg
