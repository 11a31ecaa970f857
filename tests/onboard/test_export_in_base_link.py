"""Every export in base_link (docs/ros2.md): the re-expression with its covariance, the
URDF (loaded by yourdfpy, a URDF library swpc did not write, its wheel contact points
against swpc's model), the ROS 2 parameter file, the kinematic file, ``swpc export``'s
errors and the per-run download ``GET /calibrations/{id}/export``.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from swpc_hw.files.kinematic_file import (
    KinematicFile,
    kinematics_document,
    load_kinematics,
    parse_kinematics,
    save_kinematics,
)
from swpc_hw.onboard.export import make_export, render
from swpc_hw.onboard.export.ros2_params import render_ros2_params
from swpc_hw.onboard.export.urdf import render_urdf
from swpc_hw.robot.frames import BASE_LINK, BaseLinkPose, to_base_link, transform_parameters
from swpc_hw.robot.model import PARAM_NAMES, RobotParams, contact_point, true_steering_angle
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED

CREATED = "2026-11-01T10:00:00Z"
POSE = BaseLinkPose(x=0.03, y=-0.02, yaw=0.25)


def covariance(n: int, seed: int = 3) -> np.ndarray:
    """A dense, positive definite (5n, 5n) covariance of realistic size (~0.1-1 mm, mrad)."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(5 * n, 5 * n)) * 2e-4
    return np.asarray(A @ A.T / (5 * n) + np.eye(5 * n) * 1e-9)


def calibrated(cov: np.ndarray | None = None) -> KinematicFile:
    """The paper's calibrated robot as a kinematic file (frame R), std devs from ``cov``."""
    p = PAPER_CALIBRATED
    if cov is not None:
        a = p.arrays()
        p = RobotParams.from_arrays(
            a.ids, a.P_s, a.beta, a.b, a.r, stddev=np.sqrt(np.diag(cov)).reshape(-1, 5)
        )
    doc = kinematics_document(
        p,
        created=CREATED,
        covariance=cov,
        extra={"provenance": {"tool": "swpc service", "run": "r1"}},
    )
    return parse_kinematics(yaml.safe_load(yaml.safe_dump(doc)), "calibrated.yaml")


# ---------------------------------------------------------------- base_link re-expression


def test_a_pose_in_r_re_expresses_the_contact_points_as_a_rigid_motion() -> None:
    """The model's contact points in base_link are those in R seen from base_link:
    R(-yaw) (P_w - (x, y)), for any steering angles."""
    params, _ = to_base_link(PAPER_CALIBRATED, None, POSE)
    assert params.frame == BASE_LINK
    a, b = PAPER_CALIBRATED.arrays(), params.arrays()
    theta_hat = np.random.default_rng(1).uniform(-4, 4, size=(50, 4))
    in_r = contact_point(a.P_s, a.b, true_steering_angle(theta_hat, a.beta))
    in_bl = contact_point(b.P_s, b.b, true_steering_angle(theta_hat, b.beta))
    c, s = math.cos(POSE.yaw), math.sin(POSE.yaw)
    d = in_r - np.array([POSE.x, POSE.y])
    expected = np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], -1)
    assert np.abs(in_bl - expected).max() < 1e-15
    assert np.array_equal(b.b, a.b) and np.array_equal(b.r, a.r)


def test_unset_base_link_is_r_and_a_base_link_file_is_left_as_it_is() -> None:
    kf = calibrated(covariance(4))
    same, cov = to_base_link(kf.params, kf.covariance, None)
    assert same.model_dump(exclude={"frame"}) == kf.params.model_dump(exclude={"frame"})
    assert cov is not None and np.array_equal(cov, np.asarray(kf.covariance))
    again, _ = to_base_link(same, cov, POSE)  # already in base_link: the pose is not re-applied
    assert again == same
    exp = make_export(kf, None, "calibrated.yaml")
    assert "base_link = R, the identity: the robot config sets no base_link" in exp.header


def test_a_frame_not_of_r_is_refused() -> None:
    other = PAPER_CALIBRATED.model_copy(update={"frame": "odom"})
    with pytest.raises(ValueError, match="frame 'odom': the robot config gives base_link in R"):
        to_base_link(other, None, POSE)


@pytest.mark.parametrize("base_link", [POSE, "centroid"], ids=["pose", "centroid"])
def test_the_covariance_in_base_link_is_the_jacobian_sandwich(base_link: Any) -> None:
    """``J C J^T`` with J the re-expression's Jacobian, taken here by central differences of
    the parameters' map (the centroid moves with the steering axes); figures that do not
    depend on the frame keep their std dev."""
    kf = calibrated(covariance(4))
    C = np.asarray(kf.covariance)
    params, cov = to_base_link(kf.params, C, base_link)
    assert cov is not None
    X = np.column_stack(
        [
            kf.params.arrays().P_s,
            kf.params.arrays().beta,
            kf.params.arrays().b,
            kf.params.arrays().r,
        ]
    ).reshape(-1)

    def f(x: np.ndarray) -> np.ndarray:
        p = RobotParams.from_arrays(
            [1, 2, 3, 4],
            x.reshape(-1, 5)[:, :2],
            x.reshape(-1, 5)[:, 2],
            x.reshape(-1, 5)[:, 3],
            x.reshape(-1, 5)[:, 4],
        )
        q = to_base_link(p, None, base_link)[0].arrays()
        return np.column_stack([q.P_s, q.beta, q.b, q.r]).reshape(-1)

    h = 1e-6
    J = np.column_stack([(f(X + h * e) - f(X - h * e)) / (2 * h) for e in np.eye(X.size)])
    assert np.abs(cov - J @ C @ J.T).max() < 1e-8 * np.abs(C).max()  # differences: ~1e-10
    for m, row in zip(params.modules, np.sqrt(np.diag(cov)).reshape(-1, 5), strict=True):
        assert m.stddev is not None
        assert [getattr(m.stddev, k) for k in PARAM_NAMES] == pytest.approx(row, rel=1e-12)
    # the distance vector between two steering axes, rotated back, and b, r: as before
    g = np.zeros(20)
    g[[0, 5]] = [1.0, -1.0]  # x_1 - x_2
    var_r = g @ C @ g + 0.0
    gy = np.zeros(20)
    gy[[1, 6]] = [1.0, -1.0]
    var_bl = (g @ cov @ g) + (gy @ cov @ gy)
    assert var_bl == pytest.approx(var_r + gy @ C @ gy, rel=1e-12)
    for k in (3, 4, 8, 9):
        assert cov[k, k] == pytest.approx(C[k, k], rel=1e-12)


def test_std_devs_without_a_covariance_survive_only_a_translation() -> None:
    kf = calibrated(covariance(4))
    bare = kf.params  # the file's stddev, no covariance
    shifted, _ = to_base_link(bare, None, BaseLinkPose(x=0.1, y=0.2))
    assert [m.stddev for m in shifted.modules] == [m.stddev for m in bare.modules]
    for base_link in (POSE, "centroid"):
        moved, cov = to_base_link(bare, None, base_link)
        assert cov is None and all(m.stddev is None for m in moved.modules)


# ---------------------------------------------------------------- URDF


def small_robot() -> KinematicFile:
    doc = {
        "format": "swpc-kinematics/1", "robot": "bot", "frame": "R", "created": CREATED,
        "modules": [
            {"id": 7, "x_s": 0.25, "y_s": 0.125, "beta": 0.5, "b": 0.03, "r": 0.0625,
             "stddev": {"x_s": 1e-4, "y_s": 2e-4, "beta": 3e-3, "b": 5e-5, "r": 2e-5}},
            {"id": 9, "x_s": -0.25, "y_s": -0.125, "beta": -0.25, "b": 0.02, "r": 0.05},
        ],
    }  # fmt: skip
    return parse_kinematics(doc, "small.yaml")


def test_urdf_exact_content_of_a_small_robot() -> None:
    text = render_urdf(make_export(small_robot(), BaseLinkPose(x=0.25), "small.yaml"))
    assert text.startswith('<?xml version="1.0"?>\n<!--\n  swpc calibration of robot bot, ')
    assert "  source: small.yaml, created 2026-11-01T10:00:00Z\n" in text
    assert "base_link's pose in R (robot config): x 0.25 m, y 0.0 m, yaw 0.0 rad" in text
    assert '<robot name="bot">\n  <link name="base_link"/>\n' in text
    module_7 = (
        "  <!-- module 7: std devs x_s 0.0001 m, y_s 0.0002 m, beta 0.003 rad, b 5e-05 m, "
        "r 2e-05 m -->\n"
        '  <joint name="steer_7" type="continuous">\n'
        '    <parent link="base_link"/>\n'
        '    <child link="steer_7_link"/>\n'
        '    <origin xyz="0.0 0.125 0.0" rpy="0.0 0.0 0.5"/>\n'
        '    <axis xyz="0 0 1"/>\n'
        "  </joint>\n"
        '  <link name="steer_7_link"/>\n'
        '  <joint name="wheel_7" type="continuous">\n'
        '    <parent link="steer_7_link"/>\n'
        '    <child link="wheel_7_link"/>\n'
        '    <origin xyz="0.03 0.0 0.0625" rpy="0.0 0.0 0.0"/>\n'
        '    <axis xyz="0 1 0"/>\n'
        "  </joint>\n"
    )
    assert module_7 in text
    assert '<origin xyz="-0.5 -0.125 0.0" rpy="0.0 0.0 -0.25"/>' in text  # module 9
    assert "  <!-- module 9: std devs unknown -->" in text
    assert '<cylinder radius="0.0625" length="0.02"/>' in text
    assert text.endswith("</robot>\n")


def urdf_contact_error(text: str, params: RobotParams, tmp_path: Path, samples: int = 200) -> float:
    """Largest distance between yourdfpy's wheel contact points (wheel centre less r along
    base_link's z) and swpc's model's ``P_s + b u(theta_hat + beta)`` on the floor, over
    random steering and wheel angles."""
    import yourdfpy

    path = tmp_path / "robot.urdf"
    path.write_text(text)
    robot = yourdfpy.URDF.load(str(path))
    a = params.arrays()
    rng = np.random.default_rng(7)
    worst = 0.0
    for _ in range(samples):
        theta_hat = rng.uniform(-2 * math.pi, 2 * math.pi, a.n)
        psi = rng.uniform(-50.0, 50.0, a.n)
        cfg = {f"steer_{int(i)}": float(t) for i, t in zip(a.ids, theta_hat, strict=True)}
        cfg.update({f"wheel_{int(i)}": float(p) for i, p in zip(a.ids, psi, strict=True)})
        robot.update_cfg(cfg)
        model = contact_point(a.P_s, a.b, true_steering_angle(theta_hat, a.beta))
        for k, mid in enumerate(a.ids):
            T = robot.get_transform(f"wheel_{int(mid)}_link", "base_link")
            contact = T[:3, 3] - np.array([0.0, 0.0, a.r[k]])
            worst = max(worst, float(np.linalg.norm(contact - [*model[k], 0.0])))
    return worst


@pytest.mark.parametrize("base_link", [None, POSE, "centroid"], ids=["R", "pose", "centroid"])
def test_urdf_loaded_by_yourdfpy_puts_the_wheels_where_swpcs_model_does(
    base_link: Any, tmp_path: Path
) -> None:
    exp = make_export(calibrated(covariance(4)), base_link, "calibrated.yaml")
    worst = urdf_contact_error(render_urdf(exp), exp.params, tmp_path)
    assert worst <= 1e-9, f"largest contact-point difference {worst:.3e} m"
    print(f"largest contact-point difference ({base_link}): {worst:.3e} m")


def test_urdf_wheel_joint_rolls_the_way_the_model_does(tmp_path: Path) -> None:
    """A positive wheel angle turns the wheel's lowest point backwards (along -u) about its
    centre, so rolling without slip carries the centre along +u by r dpsi: the model's
    ``r psi_dot u``."""
    import yourdfpy

    exp = make_export(small_robot(), None, "small.yaml")
    path = tmp_path / "small.urdf"
    path.write_text(render_urdf(exp))
    robot = yourdfpy.URDF.load(str(path))
    m = exp.params.modules[0]
    theta_hat, dpsi = 0.4, 1e-4
    bottom = np.array([0.0, 0.0, -m.r, 1.0])
    robot.update_cfg({"steer_7": theta_hat, "wheel_7": 0.0})
    before = robot.get_transform("wheel_7_link", "base_link") @ bottom
    robot.update_cfg({"steer_7": theta_hat, "wheel_7": dpsi})
    after = robot.get_transform("wheel_7_link", "base_link") @ bottom
    u = np.array([math.cos(theta_hat + m.beta), math.sin(theta_hat + m.beta), 0.0])
    assert np.allclose((after - before)[:3] / (m.r * dpsi), -u, atol=1e-4)


# ---------------------------------------------------------------- ROS 2 parameters


def test_ros2_params_in_the_swerve_drive_controller_layout() -> None:
    cov = covariance(4)
    exp = make_export(calibrated(cov), "centroid", "calibrated.yaml")
    text = render_ros2_params(exp)
    doc = yaml.safe_load(text)
    sw = doc["swerve_drive_controller"]["ros__parameters"]
    assert {k: v for k, v in sw.items() if k.endswith("_joint")} == {
        "front_left_wheel_joint": "wheel_1", "front_right_wheel_joint": "wheel_2",
        "rear_left_wheel_joint": "wheel_4", "rear_right_wheel_joint": "wheel_3",
        "front_left_axle_joint": "steer_1", "front_right_axle_joint": "steer_2",
        "rear_left_axle_joint": "steer_4", "rear_right_axle_joint": "steer_3",
    }  # fmt: skip
    p = exp.params.arrays()
    assert sw["wheelbase"] == pytest.approx(
        (p.P_s[0, 0] + p.P_s[1, 0] - p.P_s[2, 0] - p.P_s[3, 0]) / 2, abs=1e-15
    )
    assert sw["trackwidth"] == pytest.approx(
        (p.P_s[0, 1] + p.P_s[3, 1] - p.P_s[1, 1] - p.P_s[2, 1]) / 2, abs=1e-15
    )
    assert sw["wheel_radius"] == pytest.approx(float(np.mean(p.r)), abs=1e-15)
    # the radius' std dev comment: sqrt(g C g), g = 1/4 on every r (the frame leaves r alone)
    g = np.zeros(20)
    g[4::5] = 0.25
    assert f"mean of the 4 radii; std dev {math.sqrt(g @ cov @ g):.3g} m" in text
    assert "ros-controls/ros2_controllers pull request 1694" in text
    assert "swerve_drive_controller/src/swerve_drive_controller_parameter.yaml" in text
    kin = doc["swpc_kinematics"]["ros__parameters"]
    assert kin["frame_id"] == "base_link" and kin["module_ids"] == [1, 2, 3, 4]
    assert kin["steer_joints"] == ["steer_1", "steer_2", "steer_3", "steer_4"]
    for name in PARAM_NAMES:  # exact: repr round-trips
        assert kin[name] == [getattr(m, name) for m in exp.params.modules], name
    sd = exp.params.modules[2].stddev
    assert sd is not None and f"{sd.beta:.3g}" in text.split("    beta:")[1].splitlines()[1]


def test_ros2_params_refuses_a_robot_the_layout_cannot_hold() -> None:
    with pytest.raises(ValueError, match="layout has four modules \\(this robot has 2\\)"):
        render_ros2_params(make_export(small_robot(), None, "small.yaml"))
    a = PAPER_CALIBRATED.arrays()
    P = a.P_s.copy()
    P[3] = [0.3, 0.2]  # two front-left modules
    odd = RobotParams.from_arrays(a.ids, P, a.beta, a.b, a.r)
    kf = parse_kinematics(kinematics_document(odd), "odd.yaml")
    with pytest.raises(ValueError, match="one module in each quadrant"):
        render_ros2_params(make_export(kf, None, "odd.yaml"))


# ---------------------------------------------------------------- kinematic file


def test_kinematics_export_round_trips_in_base_link(tmp_path: Path) -> None:
    kf = calibrated(covariance(4))
    exp = make_export(kf, POSE, "calibrated.yaml")
    text = render(exp, "kinematics")
    path = tmp_path / "bl.yaml"
    path.write_text(text)
    back = load_kinematics(path)
    assert back.params == exp.params and back.params.frame == "base_link"
    assert back.created == CREATED and back.covariance is not None
    assert np.array_equal(np.asarray(back.covariance), exp.covariance)
    assert back.extra["exported"][2].startswith("base_link's pose in R (robot config): x 0.03 m")
    # exporting it again changes nothing: it is in base_link already
    again = make_export(back, POSE, str(path))
    assert again.params == exp.params
    X = np.column_stack(
        [
            kf.params.arrays().P_s,
            kf.params.arrays().beta,
            kf.params.arrays().b,
            kf.params.arrays().r,
        ]
    )
    Y = transform_parameters(
        X,
        -POSE.yaw,
        -np.array(
            [[math.cos(POSE.yaw), math.sin(POSE.yaw)], [-math.sin(POSE.yaw), math.cos(POSE.yaw)]]
        )
        @ [POSE.x, POSE.y],
    )
    assert np.abs(Y[:, :2] - back.params.arrays().P_s).max() < 1e-15


# ---------------------------------------------------------------- swpc export


def test_swpc_export_writes_each_target_and_fails_on_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from services.cli import main

    src = tmp_path / "kinematics.yaml"
    kf = calibrated(covariance(4))
    save_kinematics(src, kf.params, created=CREATED, covariance=kf.covariance)
    config = tmp_path / "robot.yaml"
    config.write_text("base_link: centroid\npolarity: {2: {wheel: -1}, 3: {steer: -1}}\n")
    texts = {}
    for target in ("urdf", "ros2-params", "kinematics"):
        out = tmp_path / f"out.{target}"
        assert (
            main(
                ["export", str(src), "--to", target, "-o", str(out), "--robot-config", str(config)]
            )
            == 0
        )
        exp = make_export(load_kinematics(src), "centroid", str(src), {2: (1, -1), 3: (-1, 1)})
        texts[target] = out.read_text()
        assert texts[target] == render(exp, target)
        assert f"wrote {out} ({target}, frame base_link)" in capsys.readouterr().err
    # the config's polarity beside the joints (the kinematic file holds the geometry only)
    node = yaml.safe_load(texts["ros2-params"])["swpc_kinematics"]["ros__parameters"]
    assert node["steer_polarity"] == [1, 1, -1, 1] and node["wheel_polarity"] == [1, -1, 1, 1]
    assert "#   wheel_2: polarity -1" in texts["ros2-params"]
    assert "#   steer_3: polarity -1" in texts["ros2-params"]
    assert texts["urdf"].count("polarity -1") == 2
    assert "polarity" not in texts["kinematics"]
    assert main(["export", str(src), "--to", "urdf"]) == 0  # stdout, base_link = R
    assert "base_link = R, the identity" in capsys.readouterr().out
    assert main(["export", str(src), "--to", "ros2-params"]) == 0  # no config: unknown
    unknown = capsys.readouterr().out
    assert "# polarity: no robot config given" in unknown and "_polarity:" not in unknown

    bad_yaml = tmp_path / "bad.yaml"
    bad_yaml.write_text("modules: [1, 2\n")
    other = tmp_path / "odom.yaml"
    save_kinematics(other, PAPER_CALIBRATED.model_copy(update={"frame": "odom"}))
    two = tmp_path / "two.yaml"
    save_kinematics(two, small_robot().params)
    bad_config = tmp_path / "bad-robot.yaml"
    bad_config.write_text("base_link: {x: 0.1, z: 2}\n")
    cases = [
        ([str(tmp_path / "none.yaml"), "--to", "urdf"], "none.yaml: cannot read"),
        ([str(bad_yaml), "--to", "urdf"], "bad.yaml: not valid YAML"),
        ([str(other), "--to", "urdf"], "frame 'odom': the robot config gives base_link in R"),
        ([str(two), "--to", "ros2-params"], "layout has four modules (this robot has 2)"),
        ([str(src), "--to", "urdf", "--robot-config", str(bad_config)], "bad-robot.yaml: "),
    ]
    for argv, what in cases:
        out = tmp_path / "never.out"
        assert main(["export", *argv, "-o", str(out)]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("swpc export: error: ") and what in err[0], err
        assert not out.exists()


# ---------------------------------------------------------------- GET /calibrations/{id}/export


def test_the_per_run_download(tmp_path: Path) -> None:
    from fastapi.testclient import TestClient
    from pydantic import SecretStr

    from services.config.robot import RobotConfig
    from services.config.settings import ServiceSettings
    from services.http.app import create_app
    from services.runtime.runtime import Runtime
    from tests.service_rig import TOKEN

    settings = ServiceSettings(data_dir=tmp_path, token=SecretStr(TOKEN))
    rt = Runtime(settings, RobotConfig.model_validate({"base_link": "centroid"}))
    kf = calibrated(covariance(4))
    for rid, state in (
        ("done1", "DONE"),
        ("failed1", "FAILED"),
        ("done2", "DONE"),
        ("two", "DONE"),
    ):
        rt.store.upsert(rid, "2026-11-01T10:00:00Z", {"id": rid, "state": state})
        if state == "DONE":
            rt.store.set_result(rid, {"id": rid})
    (tmp_path / "runs" / "done1").mkdir(parents=True)
    save_kinematics(
        tmp_path / "runs" / "done1" / "kinematics.yaml",
        kf.params,
        created=CREATED,
        covariance=kf.covariance,
        extra={"provenance": {"run": "done1"}},
    )
    (tmp_path / "runs" / "done2").mkdir(parents=True)
    (tmp_path / "runs" / "done2" / "kinematics.yaml").write_text("format: [\n")
    (tmp_path / "runs" / "two").mkdir(parents=True)
    save_kinematics(tmp_path / "runs" / "two" / "kinematics.yaml", small_robot().params)
    with TestClient(create_app(settings, runtime_factory=lambda _: rt)) as client:
        got = client.get("/calibrations/done1/export", params={"to": "urdf"})
        assert got.status_code == 200, got.text
        assert got.headers["content-type"].startswith("application/xml")
        assert got.headers["content-disposition"] == 'attachment; filename="swpc-done1.urdf"'
        exp = make_export(
            load_kinematics(tmp_path / "runs" / "done1" / "kinematics.yaml"),
            "centroid",
            "run done1",
            {},  # the service's robot config: no axis turned
        )
        assert got.text == render(exp, "urdf")
        assert "base_link: centroid: origin at the centroid" in got.text
        params = client.get("/calibrations/done1/export", params={"to": "ros2-params"})
        assert params.status_code == 200 and params.text == render(exp, "ros2-params")
        assert params.headers["content-type"].startswith("application/yaml")
        assert client.get("/calibrations/nope/export?to=urdf").status_code == 404
        assert client.get("/calibrations/failed1/export?to=urdf").status_code == 409
        broken = client.get("/calibrations/done2/export?to=urdf")
        assert broken.status_code == 409 and "not valid YAML" in broken.json()["detail"]
        assert client.get("/calibrations/done1/export?to=sdf").status_code == 422
        refused = client.get("/calibrations/two/export?to=ros2-params")
        assert refused.status_code == 422
        assert "layout has four modules" in refused.json()["detail"][0]["msg"]
