"""A run's overrides of the robot config may only tighten its safety limits, and a run that
cannot succeed is refused before any motion (the config's own checks, and the state
machine's defence in depth).
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from services.config.robot import MotionLimits, RobotConfig, Tolerances
from services.runs.state import State
from tests.run_rig import Rig
from tests.service_rig import (
    PRE_MOTION_REFUSALS,
    overrides,
)


@pytest.mark.parametrize(
    ("group", "name"),
    [("limits", n) for n in MotionLimits.model_fields]
    + [("tolerances", n) for n in Tolerances.model_fields],
)
def test_every_safety_limit_in_an_override_can_only_tighten(group: str, name: str) -> None:
    from services.config.robot import RUN_FIXED_LIMITS, OverrideError

    base = RobotConfig()
    value = getattr(getattr(base, group), name)
    # a run may not loosen it, by any amount, nor remove it with Infinity
    with pytest.raises(OverrideError, match=rf"{group}\.{name}") as exc:
        base.for_run(overrides({group: {name: value * 2 if value else 1}}))
    assert all(f"{group}.{name}" in p for p in exc.value.problems), exc.value.problems
    with pytest.raises(ValidationError):
        overrides({group: {name: math.inf}})
    with pytest.raises(ValidationError):
        overrides({group: {name: math.nan}})
    # tightening is accepted and is what the run gets (the watchdog is the service's only)
    tighter = type(value)(value * 0.5) if not (group == "limits" and name == "spin_torque") else 0.3
    if name in RUN_FIXED_LIMITS:
        with pytest.raises(OverrideError, match="not per run"):
            base.for_run(overrides({group: {name: tighter}}))
    else:
        run = base.for_run(overrides({group: {name: tighter}}))
        assert getattr(getattr(run, group), name) == tighter < value


@pytest.mark.parametrize(("doc", "why"), PRE_MOTION_REFUSALS)
def test_each_pre_motion_check_refuses_the_run(doc: dict[str, Any], why: str) -> None:
    from services.config.robot import OverrideError

    with pytest.raises((OverrideError, ValidationError), match=re.escape(why)):
        RobotConfig().for_run(overrides(doc))


def test_a_refused_config_never_moves_the_robot(tmp_path: Path) -> None:
    """Defence in depth: a config that the API would refuse, given to the state machine
    directly, fails before CONNECT with no command sent."""
    rig = Rig(tmp_path, {"protocol": {"modules": [1]}})
    run = rig.run()
    assert run.status.state is State.FAILED and "before any motion" in (run.status.reason or "")
    assert [c[1] for c in rig.robot.log if c[1] not in ("stop_all", "release")] == []
