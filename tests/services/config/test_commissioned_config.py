"""The robot config a commissioning found (services.config.commission.corrected_config):
each finding becomes the key its fix needs on each drive kind, or is said to be outside
the config; every key the operator wrote stays as written."""

from __future__ import annotations

import math
from typing import Any

import pytest
import yaml

from services.config.commission import corrected_config
from services.config.robot import RobotConfig
from swpc_hw.calibration.commission.analysis import Commissioning, Finding

KINDS = ("swpc", "cia402", "odrive")


def commissioned(kind: str, *findings: Finding) -> tuple[dict[str, Any], list[str]]:
    text = f"robot: swpc\ndrives:\n  kind: {kind}\nlimits:\n  spin_torque: 0.5\n"
    config = RobotConfig.model_validate(yaml.safe_load(text))
    doc, diff, rest = corrected_config(config, text, Commissioning(findings=list(findings)))
    assert doc["limits"] == {"spin_torque": 0.5}  # the operator's own keys stay
    assert (diff == "") == (doc == yaml.safe_load(text))
    return doc, rest


@pytest.mark.parametrize("kind", KINDS)
def test_swapped_motors_are_left_to_their_connectors_on_every_kind(kind: str) -> None:
    """Each drive is set up for its own motor: exchanging nodes in the config would leave
    each motor on the other's tuning, gear and homing input."""
    swapped = Finding(3, "module", "swapped", 1.0, "module 3's steering drive turns a wheel")
    doc, rest = commissioned(kind, swapped)
    assert "drives" not in doc or "modules" not in doc["drives"], doc
    assert rest == [swapped.text]


@pytest.mark.parametrize("kind", KINDS)
def test_crossed_nodes_polarity_and_zero_are_written(kind: str) -> None:
    doc, rest = commissioned(
        kind,
        Finding(1, "module", "crossed", 2.0, "module 2's drives move module 1"),
        Finding(2, "module", "crossed", 1.0, "module 1's drives move module 2"),
        Finding(4, "wheel", "polarity", -1.0, "module 4's wheel rolls backwards"),
        Finding(3, "steer", "zero", math.radians(91.0), "module 3 reads 0 at 91 deg"),
    )
    assert rest == []
    mods = doc["drives"]["modules"]
    default = RobotConfig.model_validate({"drives": {"kind": kind}}).to_document()
    nodes = default["drives"]["modules"]
    assert mods[1] == nodes["2"] and mods[2] == nodes["1"] and mods[3] == nodes["3"]
    assert doc["polarity"] == {4: {"wheel": -1}}
    beta = {m["id"]: m["beta"] for m in doc["nominal"]["modules"]}
    assert beta[3] == pytest.approx(math.radians(91.0), abs=1e-6)


@pytest.mark.parametrize(("kind", "written"), [("odrive", True), ("cia402", False),
                                               ("swpc", False)])  # fmt: skip
def test_a_ratio_is_written_only_where_the_config_alone_holds_it(kind: str, written: bool) -> None:
    ratio = Finding(4, "wheel", "ratio", 2.0, "module 4's wheel gear x resolution is 2x")
    doc, rest = commissioned(kind, ratio)
    if written:
        gear = doc["drives"]["modules"][4]["wheel"]["gear_ratio"]
        default = RobotConfig.model_validate({"drives": {"kind": kind}}).to_document()
        assert gear == pytest.approx(2.0 * default["drives"]["modules"]["4"]["wheel"]["gear_ratio"])
        assert rest == []
    else:
        assert rest == [ratio.text]
