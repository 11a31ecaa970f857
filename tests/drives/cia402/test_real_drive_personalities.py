"""The set-up against the object dictionaries real drives publish (issue 42, item 2 and
the table of real drives): eight EDS files of seven makers (``tests/drives/cia402/eds/``,
their sources in its README), each given as ``object_dictionary`` the way docs/drives.md
tells a user to, the virtual drive serving only what that EDS declares (its 0x6502, its
objects, its mapping objects' types).  Each comes up with the modes it has and says once
what it skipped, or is refused before any motion naming node, object and why; never a
``KeyError``.  A whole calibration on the ones that come up:
``tests/services/whole_runs/test_calibration_on_real_drives.py``."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import Any

import canopen
import pytest

from firmware_protocol import cia402
from firmware_protocol.cia402 import Mode
from firmware_protocol.codec import Axis
from simulators.options import SimOptions
from simulators.virtual_robot import VirtualRobot
from swpc_hw.clock import SimClock
from swpc_hw.drives.bus import CanConfig
from swpc_hw.drives.cia402.config import Cia402Drives
from swpc_hw.drives.cia402.driver import Cia402Driver
from swpc_hw.drives.cia402.setup import place
from swpc_hw.drives.errors import NodeError
from swpc_hw.drives.types import DriverEvent, EventKind
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

EDS = Path(__file__).with_name("eds")


def personality(eds: Path) -> dict[str, Any]:
    """A robot config's ``drives:`` for drives of this EDS, as a technician would write it:
    ``rated_torque`` from the data sheet where the drive has no 0x6076, ``homing:
    absolute`` where it has no homing method 0x6098."""
    od = canopen.import_od(str(eds), 1)
    steer: dict[str, Any] = {"rated_torque": 0.1}
    if cia402.HOMING_METHOD not in od:
        steer["homing"] = "absolute"
    return {"kind": "cia402", "object_dictionary": str(eds), "modules": {
        m: {"steer": {"node": 2 * m - 1, **steer}, "wheel": {"node": 2 * m, "rated_torque": 0.1}}
        for m in PAPER_CALIBRATED.ids}}  # fmt: skip


EXPECTED: dict[str, str | tuple[Mode, Mode | None]] = {
    "elmo_gold": (Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_TORQUE),
    "yiyou_euservo": (Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_TORQUE),
    "faulhaber_mcdc300_co": (Mode.PROFILE_POSITION, None),
    "pilz_prbt": "the drive has no homing mode swpc can use (0x6502 = 0x00000043",
    "schunk_prl120": "the drive has no position mode swpc can use (0x6502 = 0x00000060",
    "technosoft_idm_iscm": (Mode.PROFILE_POSITION, None),
    "technosoft_ipos": (Mode.PROFILE_POSITION, None),
    "wittenstein_simco": (Mode.CYCLIC_SYNC_POSITION, Mode.CYCLIC_SYNC_TORQUE),
}
"""What each comes to: (steering's position mode, wheel's torque mode: None, it spins the
robot by velocity), or the refusal."""


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_each_real_drive_comes_up_with_its_modes_or_is_refused_naming_why(name: str) -> None:
    cfg = Cia402Drives.model_validate(personality(EDS / f"{name}.eds"))
    clock = SimClock()
    ch = f"cia402-real-{uuid.uuid4().hex[:8]}"
    host = Cia402Driver(cfg, CanConfig(channel=ch, feedback_rate_hz=50), clock=clock)
    events: list[DriverEvent] = []
    host.add_event_callback(events.append)
    host.configure()
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, clock=clock,
                            options=SimOptions(drives=cfg, physics_dt=0.01))  # fmt: skip
    sim.start()
    expected = EXPECTED[name]
    try:
        with clock.participant():
            if isinstance(expected, str):
                with pytest.raises(NodeError) as err:
                    host.activate()
                assert "module 1 steer (node 1): " in str(err.value)
                assert expected in str(err.value), str(err.value)
                outcome = f"refused: {str(err.value).split(': ', 1)[1]}"
            else:
                host.activate()
                steer, wheel = host.axis_track(1, Axis.STEER), host.axis_track(1, Axis.WHEEL)
                assert (steer.position_mode, wheel.torque_mode) == expected
                skipped = [e.message for e in events if e.kind is EventKind.SET_UP]
                assert len(skipped) == len(set(skipped))  # each said once
                torque = expected[1].name if expected[1] else "no torque mode"
                outcome = f"up: {expected[0].name}, {torque}; skipped: " + "; ".join(
                    sorted({m.split(': ', 1)[1] for m in skipped})
                )
    finally:
        sim.stop()
        host.shutdown()
        clock.close()
    print(f"\n{name}: {outcome}")


def edited_eds(
    tmp_path: Path, drop: tuple[str, ...] = (), edit: dict[str, tuple[str, str]] | None = None
) -> Path:
    """The project's EDS without the sections ``drop`` and with ``edit``: section ->
    (line start, new line)."""
    out: list[str] = []
    section = ""
    for line in cia402.EDS_PATH.read_text().splitlines():
        if line.startswith("["):
            section = line.strip("[]")
        if section in drop:
            continue
        if edit and section in edit and line.startswith(edit[section][0]):
            line = edit[section][1]
        out.append(line)
    path = tmp_path / "edited.eds"
    path.write_text("\n".join(out) + "\n")
    return path


@pytest.mark.parametrize(
    ("drop", "edit", "expected"),
    [
        ((), {"6061": ("PDOMapping=", "PDOMapping=0")},
         "0x6061 (Modes of operation display) is not PDO-mappable on this drive (its object "
         "dictionary): swpc reads the mode in force back"),
        (tuple(f"1600sub{k}" for k in range(3, 9)), None,
         "RPDO 1's mapping 0x1600 has room for 2 entries, swpc maps 3 (0x6040, 0x6060, 0x6071); "
         "spread over its RPDOs (1: 2, 2: 8 entries), swpc's 2 groups of 3 and 2 entries, each "
         "in PDOs of its own, do not fit"),
        (("6098",), None,
         "the drive has no 0x6098 (homing method): the steering's homing method; with an "
         "absolute encoder, set its `homing: absolute`"),
    ],
)  # fmt: skip
def test_an_object_or_a_map_the_drive_cannot_give_is_refused_naming_it(
    tmp_path: Path, drop: tuple[str, ...], edit: dict[str, tuple[str, str]] | None, expected: str
) -> None:
    """The real drives' table: objects not PDO-mappable (Schunk PRL120's 0x6060/0x6061),
    mapping records with fewer entries than swpc's maps (canopen only logs a warning and
    maps less), a homing method missing: refused before any motion, naming it."""
    eds = edited_eds(tmp_path, drop, edit)
    cfg = Cia402Drives(object_dictionary=eds).for_modules(PAPER_CALIBRATED.ids)
    clock = SimClock()
    ch = f"cia402-map-{uuid.uuid4().hex[:8]}"
    host = Cia402Driver(cfg, CanConfig(channel=ch, feedback_rate_hz=50), clock=clock)
    host.configure()
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, clock=clock,
                            options=SimOptions(drives=cfg, physics_dt=0.01))  # fmt: skip
    sim.start()
    try:
        with clock.participant(), pytest.raises(NodeError) as err:
            host.activate()
        assert str(err.value) == f"module 1 steer (node 1): {expected}"
    finally:
        sim.stop()
        host.shutdown()
        clock.close()


def test_a_drive_without_homing_is_refused_unless_the_steering_is_absolute() -> None:
    """Yiyou's EuServo has neither homing mode nor 0x6098: with the default homing (19) it
    is refused naming the way out; ``homing: absolute`` brings it up (the test above)."""
    drives = personality(EDS / "yiyou_euservo.eds")
    for m in drives["modules"].values():
        m["steer"].pop("homing")
    cfg = Cia402Drives.model_validate(drives)
    clock = SimClock()
    ch = f"cia402-hm-{uuid.uuid4().hex[:8]}"
    host = Cia402Driver(cfg, CanConfig(channel=ch, feedback_rate_hz=50), clock=clock)
    host.configure()
    sim = VirtualRobot.open(PAPER_CALIBRATED, channel=ch, clock=clock,
                            options=SimOptions(drives=cfg, physics_dt=0.01))  # fmt: skip
    sim.start()
    try:
        with clock.participant(), pytest.raises(NodeError) as err:
            host.activate()
        assert "module 1 steer (node 1): the drive has no homing mode" in str(err.value)
        assert "and homing unless the encoder is absolute" in str(err.value)
    finally:
        sim.stop()
        host.shutdown()
        clock.close()


def test_swpcs_pdo_groups_go_each_to_pdos_of_its_own_spread_where_a_map_is_small() -> None:
    rpdo = [list(entries) for entries in cia402.RPDO_MAP.values()]  # 3 and 2 entries
    assert place(rpdo, {1: 8, 2: 8, 3: 8, 4: 8}) == [[(1, rpdo[0])], [(2, rpdo[1])]]
    # Technosoft IDM/ISCM: 1, 2, 2, 2
    assert place(rpdo, {1: 1, 2: 2, 3: 2, 4: 2}) == [
        [(1, rpdo[0][:1]), (2, rpdo[0][1:])], [(3, rpdo[1])]
    ]
    assert place(rpdo, {1: 2, 2: 8}) is None  # the targets would share RPDO 2
    assert place(rpdo, {1: 0, 2: 3, 3: 2}) == [[(2, rpdo[0])], [(3, rpdo[1])]]
