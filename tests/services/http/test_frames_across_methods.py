"""One frame per comparison (issue 45 item 2): a motion-capture result (frame R) over a file
in force from a calibration without motion capture (frame design-fit).

Their parameters differ by the two frames' rotation and offset as well as by the robot:
compared as they are, every ``beta`` moved by the frames' turn and was flagged; installed
by the default policy, odometry would have moved by that turn without anyone choosing it.
On the fake robot and a virtual clock (a whole run in about a second).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from services.config.robot import RobotConfig
from services.http.app import create_app
from services.runtime.history import Point, epoch, parameter_series
from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
from swpc_hw.robot.frames import DESIGN_FIT, design_fit_transform, transform_robot
from swpc_hw.robot.model import PARAM_NAMES, RobotParams
from tests.service_rig import AUTH
from tests.services.http.console_rig import NOMINAL, TRUTH, bare_runtime, new_run


def test_a_mocap_result_over_a_design_fit_file_is_held_and_compared_in_design_fit(
    tmp_path: Path,
) -> None:
    rt = bare_runtime(tmp_path)
    phi, t = design_fit_transform(TRUTH.arrays().P_s, NOMINAL.arrays().P_s)
    turn_deg, move_mm = math.degrees(phi), float(math.hypot(*t)) * 1e3
    assert abs(turn_deg) > 0.07 and move_mm > 0.6  # what a comparison as-is would flag
    in_force = transform_robot(TRUTH, phi, t, DESIGN_FIT)  # the truth, as the gyro gives it
    path = rt.settings.kinematics_file
    save_kinematics(path, in_force, created="2026-01-01T00:00:00Z")
    before = path.read_bytes()

    run = new_run(rt, install="if-within-tolerance")
    run.start()
    run.join(30)
    assert run.status.state == "DONE", run.status.errors
    # within tolerance, yet not installed: the file in force is of another frame
    doc = run.result_doc
    assert doc is not None and doc["within_tolerance"] and not run.status.installed
    assert doc["install_held"].startswith(
        "the file in force is in frame design-fit, this result in frame R"
    )
    assert path.read_bytes() == before

    with TestClient(create_app(rt.settings, runtime_factory=lambda _: rt)) as client:
        cmp = client.get(f"/calibrations/{run.id}/comparison").json()
        assert cmp["reference"] == "file in force" and cmp["frame"] == DESIGN_FIT
        assert cmp["install_held"] == doc["install_held"]
        assert cmp["frame_note"].startswith("this result (frame R) re-expressed in design-fit")
        rows = {(r["module"], r["param"]): r for r in cmp["rows"]}
        for m in TRUTH.modules:
            beta, x, y = (rows[(m.id, p)] for p in ("beta", "x_s", "y_s"))
            # in one frame the result is the truth: well under the frames' turn and offset
            assert abs(beta["change"]) < 0.1 * abs(turn_deg), beta
            assert math.hypot(x["change"], y["change"]) < 0.1 * move_mm, (x, y)
            assert not beta["significant"], beta
            # and the calibrated values shown are the result's, in design-fit
            assert beta["calibrated"] != rows[(m.id, "beta")]["nominal"]
        # the operator's explicit install puts it in force: R now, the gyro file kept
        r = client.post(f"/calibrations/{run.id}/install", headers=AUTH)
        assert r.status_code == 200, r.text
    assert load_kinematics(path).params.frame == "R"
    assert any(p.read_bytes() == before for p in path.parent.glob("kinematics.*.yaml"))


def point(run: str, day: int, params: RobotParams, frame: str) -> Point:
    sd = 0.1e-3
    return Point(
        run=run, kind="calibration", time=f"2026-11-{day:02d}T12:00:00Z", frame=frame,
        installed=None, verdict=None,
        modules={
            m.id: {k: (float(getattr(m, k)), sd) for k in PARAM_NAMES} for m in params.modules
        },
    )  # fmt: skip


def test_drift_draws_each_calibration_in_the_references_frame_or_not_at_all() -> None:
    """Two motion-capture calibrations (R) and one without (design-fit) of the same robot:
    Drift drew the design-fit one as an outlier by the frames' turn in every beta and
    position.  Against a design-fit file the R points are re-expressed in design-fit
    (they then agree with it); against an R file the design-fit point is not drawn and
    not in the trend (a design-fit result has no frame R)."""
    config = RobotConfig.model_validate({"nominal": NOMINAL.model_dump()})
    phi, t = design_fit_transform(TRUTH.arrays().P_s, NOMINAL.arrays().P_s)
    fitted = transform_robot(TRUTH, phi, t, DESIGN_FIT)
    pts = [point("a", 1, TRUTH, "R"), point("g", 2, fitted, DESIGN_FIT), point("b", 3, TRUTH, "R")]
    now = epoch("2026-11-04T12:00:00Z")

    def series(reference: RobotParams) -> dict[tuple[int, str], dict[str, Any]]:
        ref = {m.id: {k: float(getattr(m, k)) for k in PARAM_NAMES} for m in reference.modules}
        got = parameter_series(pts, ref, reference.frame, config, now)
        return {(s["module"], s["param"]): s for s in got}

    in_df = series(fitted)
    for m in TRUTH.modules:
        beta = in_df[(m.id, "beta")]
        by_run = {q["run"]: q for q in beta["points"]}
        assert by_run["a"]["re_expressed"] and not by_run["g"]["re_expressed"]
        assert not any(q["other_frame"] for q in beta["points"])
        for q in beta["points"]:  # all three are the truth in design-fit
            assert q["value"] == pytest.approx(beta["reference"], abs=1e-9), q
        assert beta["trend"]["points"] == 3
    in_r = series(TRUTH)
    for m in TRUTH.modules:
        for k in ("x_s", "y_s", "beta"):
            s = in_r[(m.id, k)]
            g = next(q for q in s["points"] if q["run"] == "g")
            assert g["other_frame"] and g["value"] is None, g
            assert s["trend"]["points"] == 2
        r = next(q for q in in_r[(m.id, "r")]["points"] if q["run"] == "g")
        assert not r["other_frame"] and r["value"] is not None  # r is the same in any frame
    # the turn the design-fit point would have shown as drift (what it drew before)
    assert abs(math.degrees(phi)) > 0.07
