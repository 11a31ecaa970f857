"""deploy/: scripts, systemd units, env file, robot config and zenoh configs.

The success paths of ``vcan-up.sh`` and ``can-up.sh`` need a kernel with SocketCAN: they
run in ``make test-vcan`` (deploy/vm/in-vm.sh).  Here: their error paths on this kernel,
``systemd-analyze verify`` of both units, and that every example file loads into the
real settings/config models and documents every key.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import BaseModel

from swpc_hw.robot.model import PARAM_NAMES
from tests.service_rig import ROOT

DEPLOY = ROOT / "deploy"
UNITS = (
    "swpc-service.service", "swpc-sim.service", "swpc-fleet.service", "swpc-mocap.service"
)


def run(*cmd: str | Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(c) for c in cmd], capture_output=True, text=True, timeout=30, env=env, check=False
    )


def kernel_has_vcan() -> bool:
    if Path("/sys/module/vcan").exists():
        return True
    return shutil.which("modprobe") is not None and run("modprobe", "-n", "vcan").returncode == 0


# ---------------------------------------------------------------------------- scripts
@pytest.mark.parametrize(
    "script",
    [
        "vcan-up.sh", "can-up.sh", "vm/setup.sh", "vm/run-in-vm.sh", "vm/in-vm.sh",
        "vm/robot-install.sh", "vm/robot-install-test.sh",
    ],
)
def test_scripts_are_executable_bash(script: str) -> None:
    path = DEPLOY / script
    assert os.access(path, os.X_OK)
    assert run("bash", "-n", path).returncode == 0


@pytest.mark.skipif(kernel_has_vcan(), reason="this kernel has vcan: make test-vcan covers it")
@pytest.mark.skipif(os.geteuid() != 0, reason="as non-root the script stops at the permission")
def test_vcan_up_without_vcan_is_a_clear_error() -> None:
    r = run(DEPLOY / "vcan-up.sh", "swpctest0")
    assert r.returncode == 3, r
    assert r.stdout == ""
    msg = r.stderr
    assert msg.startswith("vcan-up: error: the running kernel (") and "has no vcan support" in msg
    assert os.uname().release in msg
    assert "modprobe vcan failed" in msg
    assert "CONFIG_CAN_VCAN" in msg and "'virtual'" in msg
    assert not Path("/sys/class/net/swpctest0").exists()


def test_vcan_up_usage() -> None:
    r = run(DEPLOY / "vcan-up.sh", "--bogus")
    assert (r.returncode, r.stderr) == (2, "vcan-up: unknown option --bogus\n")
    h = run(DEPLOY / "vcan-up.sh", "--help")
    assert h.returncode == 0 and "Exit status" in h.stdout and "set -e" not in h.stdout


def test_can_up_errors() -> None:
    r = run(DEPLOY / "can-up.sh", "swpcnone0")
    assert r.returncode == 3
    assert r.stderr.startswith("can-up: error: no interface named swpcnone0.")
    lo = run(DEPLOY / "can-up.sh", "lo")
    assert (lo.returncode, lo.stderr) == (3, "can-up: error: lo is not a CAN interface\n")
    for args, text in (
        (["--bitrate", "2000000"], "--bitrate must be an integer in 1..1000000"),
        (["--bitrate"], "--bitrate needs a value"),
        (["--restart-ms", "-1"], "--restart-ms must be a non-negative integer"),
        (["--sample-point", "87.5"], "--sample-point must be a fraction"),
    ):
        bad = run(DEPLOY / "can-up.sh", "can0", *args)
        assert bad.returncode == 2 and text in bad.stderr, (args, bad)
    h = run(DEPLOY / "can-up.sh", "--help")
    assert h.returncode == 0 and "--restart-ms" in h.stdout and "set -e" not in h.stdout


# ---------------------------------------------------------------------------- systemd
def _unit_root(tmp_path: Path) -> Path:
    """A root with the host's unit tree, our units and stubs for the ExecStart paths."""
    root = tmp_path / "root"
    (root / "usr/lib/systemd").mkdir(parents=True)
    shutil.copytree("/usr/lib/systemd/system", root / "usr/lib/systemd/system", symlinks=True)
    units = root / "etc/systemd/system"
    units.mkdir(parents=True)
    for unit in UNITS:
        shutil.copy(DEPLOY / "systemd" / unit, units / unit)
    for exe in (".venv/bin/swpc", "deploy/can-up.sh", "deploy/vcan-up.sh"):
        stub = root / "opt/swpc" / exe
        stub.parent.mkdir(parents=True, exist_ok=True)
        stub.write_text("#!/bin/sh\n")
        stub.chmod(0o755)
    return root


def _exec_paths(unit: str) -> set[str]:
    text = (DEPLOY / "systemd" / unit).read_text()
    return {m.lstrip("+-@!:") for m in re.findall(r"^Exec\w+=(\S+)", text, re.M)}


@pytest.fixture(scope="module")
def systemd_analyze() -> str:
    exe = shutil.which("systemd-analyze")
    if exe is None:
        pytest.skip("systemd-analyze missing: apt-get install systemd")
    return exe


def test_units_verify(systemd_analyze: str, tmp_path: Path) -> None:
    root = _unit_root(tmp_path)
    for unit in UNITS:
        assert _exec_paths(unit) <= {
            "/opt/swpc/.venv/bin/swpc",
            "/opt/swpc/deploy/can-up.sh",
            "/opt/swpc/deploy/vcan-up.sh",
        }
    r = run(systemd_analyze, "verify", f"--root={root}", *UNITS)
    assert (r.returncode, r.stdout, r.stderr) == (0, "", "")


def test_units_verify_catches_mistakes(systemd_analyze: str, tmp_path: Path) -> None:
    """The check above is live: a typo or a missing executable is reported."""
    root = _unit_root(tmp_path)
    unit = root / "etc/systemd/system" / UNITS[0]
    unit.write_text(unit.read_text().replace("ProtectSystem=strict", "ProtectSystem=strickt"))
    r = run(systemd_analyze, "verify", f"--root={root}", UNITS[0])
    assert "Failed to parse protect system value" in r.stderr
    (root / "opt/swpc/.venv/bin/swpc").unlink()
    r = run(systemd_analyze, "verify", f"--root={root}", UNITS[0])
    assert r.returncode != 0 and "/opt/swpc/.venv/bin/swpc is not executable" in r.stderr


def _directives(unit: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for line in (DEPLOY / "systemd" / unit).read_text().splitlines():
        if "=" in line and not line.startswith(("#", "[")):
            key, value = line.split("=", 1)
            out.setdefault(key, []).append(value)
    return out


@pytest.mark.parametrize("unit", UNITS)
def test_units_are_hardened(unit: str) -> None:
    d = _directives(unit)
    assert d["User"] == ["swpc"] and d["Restart"] == ["on-failure"]
    assert d["ProtectSystem"] == ["strict"] and d["NoNewPrivileges"] == ["yes"]
    assert d["CapabilityBoundingSet"] == [""]
    # the fleet view and the mocap bridge need no CAN socket
    can = unit not in ("swpc-fleet.service", "swpc-mocap.service")
    assert ("AF_CAN" in d["RestrictAddressFamilies"][0].split()) == can
    assert all(v.startswith("+/opt/swpc/deploy/") for v in d.get("ExecStartPre", []))
    if unit == "swpc-fleet.service":
        # the fleet store is the only writable path
        assert d["StateDirectory"] == ["swpc-fleet"] and "ReadWritePaths" not in d
        assert d["Environment"] == ["SWPC_FLEET_DATA_DIR=/var/lib/swpc-fleet"]
        assert d["ExecStart"] == ["/opt/swpc/.venv/bin/swpc fleet --data-dir /var/lib/swpc-fleet"]
    elif unit == "swpc-service.service":
        # the data dir is the only writable path: the state dir, nothing else
        assert d["StateDirectory"] == ["swpc"] and "ReadWritePaths" not in d
        assert d["Environment"] == ["SWPC_DATA_DIR=/var/lib/swpc"]
        assert d["ExecStart"] == ["/opt/swpc/.venv/bin/swpc serve --data-dir /var/lib/swpc"]
        # what it writes is 0640 in the odometry's group, with no setgid bit (refused by
        # RestrictSUIDSGID=); file descriptors for every HTTP connection and more
        assert d["EnvironmentFile"] == ["/etc/swpc/swpc.env"]
        assert d["Group"] == ["swpc-data"] and d["UMask"] == ["0027"]
        assert d["RestrictSUIDSGID"] == ["yes"]
        from services.config.settings import ServiceSettings

        assert int(d["LimitNOFILE"][0]) >= 4 * ServiceSettings().max_connections
    elif unit == "swpc-mocap.service":
        # writes nothing; its command line is one `swpc mocap` takes, with the password in
        # a file (never on the command line: `ps` shows it)
        assert "StateDirectory" not in d and "ReadWritePaths" not in d
        from services.cli import build_parser

        argv = d["ExecStart"][0].split()
        assert argv[0] == "/opt/swpc/.venv/bin/swpc"
        args = build_parser("mocap").parse_args(argv[1:])
        assert args.zenoh_user == "mocap" and str(args.zenoh_password_file).startswith("/etc/")
    else:
        assert "StateDirectory" not in d and "ReadWritePaths" not in d
        assert "EnvironmentFile" not in d  # `swpc sim` reads no SWPC_* setting
        assert d["ExecStart"] == [
            "/opt/swpc/.venv/bin/swpc sim --interface socketcan --channel vcan0 "
            "--zenoh-listen tcp/127.0.0.1:7447 "
            "--zenoh-config /opt/swpc/deploy/zenoh/mocap-peer.json5"
        ]


# ---------------------------------------------------------------------------- env + config
def test_env_example_loads_and_names_every_setting() -> None:
    from services.config.settings import ServiceSettings

    path = DEPLOY / "swpc.env.example"
    text = path.read_text()
    for name in ServiceSettings.model_fields:
        assert re.search(rf"^#?SWPC_{name.upper()}=", text, re.M), name
    s = ServiceSettings(_env_file=str(path))
    assert s.can_interface == "socketcan" and s.can_channel == "can0"
    assert s.can_bitrate == 1_000_000 and s.zenoh_mode == "peer"
    assert s.data_dir == Path("/var/lib/swpc") and s.host == "127.0.0.1"
    assert s.zenoh_config_file == "/etc/swpc/zenoh.json5"  # its copy of robot-peer.json5


def _keys(model: type[BaseModel], prefix: str = "") -> list[str]:
    keys = []
    for name, field in model.model_fields.items():
        keys.append(prefix + name)
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel) and name != "nominal":
            keys += _keys(ann, prefix + name + ".")
    return keys


def test_sysctl_makes_room_for_the_drivers_receive_buffer() -> None:
    """The robot's sysctl file lets an unprivileged service get the receive buffer the
    driver asks for (SO_RCVBUF is capped at net.core.rmem_max)."""
    from swpc_hw.drives.bus import CanConfig

    path = DEPLOY / "sysctl" / "60-swpc-can.conf"
    lines = [ln.strip() for ln in path.read_text().splitlines()]
    values = dict(
        (k.strip(), v.strip())
        for k, v in (ln.split("=", 1) for ln in lines if ln and not ln.startswith("#"))
    )
    assert set(values) == {"net.core.rmem_max"}
    assert int(values["net.core.rmem_max"]) >= CanConfig().rx_buffer_bytes
    assert "deploy/sysctl/60-swpc-can.conf /etc/sysctl.d/" in (DEPLOY / "README.md").read_text()


def test_robot_example_loads_and_documents_every_key() -> None:
    from services.config.robot import RobotConfig, load_robot_config
    from swpc_hw.robot.paper_robot import PAPER_NOMINAL

    path = DEPLOY / "robot.example.yaml"
    cfg = load_robot_config(path)
    assert cfg == RobotConfig()  # the example spells out the defaults (the paper's robot)
    assert cfg.nominal == PAPER_NOMINAL and cfg.pose_key == "mocap/swpc/pose"
    doc: dict[str, Any] = yaml.safe_load(path.read_text())
    lines = path.read_text().splitlines()
    for key in _keys(RobotConfig):
        node: Any = doc
        for part in key.split("."):
            assert part in node, f"{key} missing from {path.name}"
            node = node[part]
        leaf = key.split(".")[-1]
        found = [ln for ln in lines if re.match(rf"^\s*{leaf}:", ln)]
        assert found and all("#" in ln for ln in found), f"{key} has no comment"
    for field in ("id", *PARAM_NAMES):
        assert any(re.match(rf"^\s*-? ?{field}: .*#", ln) for ln in lines), field


# ---------------------------------------------------------------------------- zenoh
ZENOH_FILES = ("robot-peer.json5", "mocap-peer.json5", "lab-router.json5", "fleet-router.json5")


@pytest.mark.parametrize("name", ZENOH_FILES)
def test_zenoh_configs_load_with_scouting_off(name: str) -> None:
    import zenoh

    cfg = zenoh.Config.from_file(str(DEPLOY / "zenoh" / name))
    assert json.loads(cfg.get_json("scouting/multicast/enabled")) is False
    assert json.loads(cfg.get_json("scouting/gossip/enabled")) is False
    mode = json.loads(cfg.get_json("mode"))
    assert mode == ("router" if name.endswith("-router.json5") else "peer")


def test_mocap_bridge_maps_ros_pose_topics_to_our_key_space() -> None:
    import zenoh

    cfg = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "mocap-peer.json5"))
    ros = json.loads(cfg.get_json("plugins/ros2dds"))
    assert ros["namespace"] == "/mocap"  # /robot1/pose -> mocap/robot1/pose
    (pattern,) = ros["allow"]["publishers"]
    assert re.fullmatch(pattern, "/robot1/pose") and not re.fullmatch(pattern, "/tf")


def test_lab_router_routes_each_robot_its_poses_and_denies_the_rest(tmp_path: Path) -> None:
    """The router file on loopback: mocap PC and robot connect to it as in the README."""
    import zenoh

    from swpc_hw.sensors.zenoh_session import free_tcp_endpoint, zenoh_config

    ep = free_tcp_endpoint()
    rcfg = zenoh.Config.from_file(str(DEPLOY / "zenoh" / "lab-router.json5"))
    rcfg.insert_json5("listen/endpoints", json.dumps([ep]))
    mcfg = zenoh_config(config_file=str(DEPLOY / "zenoh" / "mocap-peer.json5"), connect=[ep])
    mcfg.insert_json5("listen/endpoints", "[]")
    mcfg.insert_json5("plugins", "{}")
    robots = tmp_path / "robots.txt"  # the mocap PC's dictionary of robots (none here)
    robots.write_text("")
    mcfg.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(robots)))
    got: dict[str, list[str]] = {"robot1": [], "other": []}
    sessions = [zenoh.open(rcfg)]
    try:
        robot = zenoh.open(zenoh_config(mode="client", connect=[ep]))
        other = zenoh.open(zenoh_config(mode="client", connect=[ep]))
        mocap = zenoh.open(mcfg)
        sessions += [robot, other, mocap]
        robot.declare_subscriber(
            "mocap/robot1/pose", lambda s: got["robot1"].append(str(s.payload.to_bytes()))
        )
        other.declare_subscriber("other/**", lambda s: got["other"].append(str(s.key_expr)))
        deadline = time.monotonic() + 5.0
        while not got["robot1"] and time.monotonic() < deadline:
            mocap.put("mocap/robot1/pose", b"p1")
            mocap.put("mocap/robot2/pose", b"p2")
            mocap.put("other/key", b"x")
            time.sleep(0.1)
        time.sleep(0.2)
    finally:
        for s in reversed(sessions):
            s.close()  # type: ignore[no-untyped-call]
    assert got["robot1"] and set(got["robot1"]) == {"b'p1'"}
    assert got["other"] == []  # denied by the router's access control


# ---------------------------------------------------------------------------- VM comparison
def _result_doc(values: dict[str, float], std: dict[str, float] | None) -> dict[str, Any]:
    modules = [{"id": 1, **values, "stddev": std}]
    status = {"state": "DONE", "poses": 10, "encoder_samples": 20}
    return {"status": status, "wall_s": 1.0, "overrides": {}, "result": {"modules": modules}}


@pytest.mark.parametrize(
    ("shift", "std_b", "status", "needle"),
    [
        (2.9e-4, 1e-4, 0, "largest |A-B| / combined std dev: 2.05 (limit 3)"),
        (4.3e-4, 1e-4, 1, "MISMATCH module 1 x_s: |A-B| = 0.00043 > 3 x 0.000141"),
        (0.0, None, 1, "MISMATCH module 1 x_s: std dev unknown"),
    ],
)
def test_vm_calibration_comparison(
    tmp_path: Path, shift: float, std_b: float | None, status: int, needle: str
) -> None:
    """deploy/vm/sim_calibration.py compare: |A - B| <= 3 sqrt(sA^2 + sB^2) per parameter."""
    vals = {"x_s": 0.1, "y_s": 0.2, "beta": 0.3, "b": 0.02, "r": 0.05}
    std_a = dict.fromkeys(vals, 1e-4)
    a = tmp_path / "a.json"
    b = tmp_path / "b.json"
    a.write_text(json.dumps(_result_doc(vals, std_a)))
    std = None if std_b is None else dict.fromkeys(vals, std_b)
    b.write_text(json.dumps(_result_doc({**vals, "x_s": vals["x_s"] - shift}, std)))
    r = run(sys.executable, DEPLOY / "vm/sim_calibration.py", "compare", a, b)
    assert r.returncode == status, r.stdout + r.stderr
    assert needle in r.stdout


def test_vm_calibration_comparison_refuses_different_protocols(tmp_path: Path) -> None:
    """The reference runs from the environment, the VM from its own copy: same overrides."""
    vals = {"x_s": 0.1, "y_s": 0.2, "beta": 0.3, "b": 0.02, "r": 0.05}
    docs = [_result_doc(vals, dict.fromkeys(vals, 1e-4)) for _ in range(2)]
    docs[1]["overrides"] = {"protocol": {"sweep_deg": 45}}
    paths = [tmp_path / "a.json", tmp_path / "b.json"]
    for p, d in zip(paths, docs, strict=True):
        p.write_text(json.dumps(d))
    r = run(sys.executable, DEPLOY / "vm/sim_calibration.py", "compare", *paths)
    assert r.returncode == 1 and "not the same protocol" in r.stdout, r.stdout + r.stderr


def _vm_speed_module() -> Any:
    import importlib.util

    spec = importlib.util.spec_from_file_location("vm_speed", DEPLOY / "vm/speed.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize(
    ("loop_s", "factor", "time_scale", "deadman"),
    [
        (0.5, 8.0, 0.3, 2.0),  # the reference speed: the values that passed
        (1.0, 16.0, 0.15, 4.0),  # half as fast: twice the periods, half the simulated speed
        (0.75, 12.0, 0.2, 3.0),
        (0.625, 10.0, 0.24, 2.5),
        (0.25, 8.0, 0.3, 1.0),  # faster: never less margin than at the reference
        (0.1, 8.0, 0.3, 0.5),  # the dead-man never below the robot's own
        (5.0, 24.0, 0.1, 8.0),  # far too slow: clamped, the run then takes its time
    ],
)
def test_vm_speed_scales_time_factor_and_time_scale(
    loop_s: float, factor: float, time_scale: float, deadman: float
) -> None:
    """deploy/vm/speed.py: F = 8 s, k = 0.3 / s and D = 2 s with s = loop / 0.5 s,
    clamped."""
    sp = _vm_speed_module()
    s = sp.slowness(loop_s)
    assert sp.time_factor(s) == pytest.approx(factor)
    assert sp.sim_time_scale(s) == pytest.approx(time_scale)
    assert sp.deadman(s) == pytest.approx(deadman)
    with pytest.raises(ValueError, match="must be > 0"):
        sp.slowness(0.0)


def test_vm_speed_prints_shell_assignments() -> None:
    r = run(sys.executable, "-S", DEPLOY / "vm/speed.py", "--repeat", "1", "--ref-loop", "1e-6")
    assert r.returncode == 0, r.stderr
    got = dict(kv.split("=") for kv in r.stdout.split())
    assert set(got) == {"LOOP_S", "SLOWNESS", "TIME_FACTOR", "SIM_TIME_SCALE", "DEADMAN_S"}
    # any real loop is far slower than 1 us: the slowest settings
    assert float(got["TIME_FACTOR"]) == 24.0 and float(got["SIM_TIME_SCALE"]) == 0.1
    assert float(got["DEADMAN_S"]) == 8.0


@pytest.mark.parametrize(
    ("passed", "before", "loop_after", "fixed", "deadman"),
    [
        (False, 0.56, 0.51, False, 2.1),  # 2026-11: 0.56 before, 1.02 after: held again
        (False, 1.0, 0.55, False, None),  # as slow as before: the failure stands
        (False, 0.56, 0.51, True, None),  # SWPC_VM_DEADMAN_D fixed it: never resized
        (True, 0.56, 0.51, False, None),  # a passed hold is not held again
    ],
)
def test_vm_deadman_step_is_judged_against_the_speed_it_had(
    monkeypatch: pytest.MonkeyPatch,
    passed: bool,
    before: float,
    loop_after: float,
    fixed: bool,
    deadman: float | None,
) -> None:
    """The deadman step failed once when the host slowed down during it (slowness 0.56
    before it, 1.02 before the next step): its dead-man had been sized for 0.56."""
    import argparse

    monkeypatch.syspath_prepend(str(DEPLOY / "vm"))
    import deadman as step
    import speed

    monkeypatch.setattr(speed, "loaded_loop_seconds", lambda *a, **k: loop_after)
    monkeypatch.setattr(step, "passed", lambda args, k: passed)
    args = argparse.Namespace(speed=f"LOOP_S=0.28 SLOWNESS={before}", fixed_deadman=fixed)
    got = step.slowed_down(args, {})
    if deadman is None:
        assert got is None
    else:
        assert got is not None and got["deadman"] == pytest.approx(deadman)
        assert f"slowness {before:.2f} before the step, 1.02 after" in got["why"]
