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

from fastapi.testclient import TestClient

from services.http.app import create_app
from swpc_hw.files.kinematic_file import load_kinematics, save_kinematics
from swpc_hw.robot.frames import DESIGN_FIT, design_fit_transform, transform_robot
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
