"""After a restart: a corrupt kinematic file in force is a clear error and degraded health."""

from __future__ import annotations

from pathlib import Path

from fastapi.testclient import TestClient

from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.robot.paper_robot import PAPER_NOMINAL
from tests.service_rig import (
    AUTH,
    app_without_robot,
)


def test_corrupt_kinematic_file_is_a_clear_error_and_degraded_health(tmp_path: Path) -> None:
    """A file in force that does not load is a fault of the server's data, not of the
    request: a JSON 500 (not 503, which /health keeps for "cannot calibrate") that says
    why and which backup to roll back to; /health names it (degraded on a service that
    can calibrate: tests/services/http/test_health_and_metrics.py).  It was a bare 500."""
    kin = tmp_path / "kinematics.yaml"
    good = tmp_path / "kinematics.20260101T000000000000Z.yaml"
    save_kinematics(good, PAPER_NOMINAL, created="2026-01-01T00:00:00Z")
    (tmp_path / "kinematics.20260201T000000000000Z.yaml").write_text("format: nope\n")
    kin.write_bytes(b"format: swpc-kinematics/1\nrobot: \xff\xfe\n")
    with TestClient(app_without_robot(tmp_path)) as client:
        r = client.get("/kinematics")
        health = client.get("/health").json()
        files = client.get("/kinematics/files").json()
        assert r.status_code == 500 and r.headers["content-type"] == "application/json"
        body = r.json()
        reason = f"{kin}: not UTF-8 text (byte 0xff at offset 33): a damaged or foreign file"
        assert body == {
            "detail": f"the kinematic file in force cannot be loaded: {reason}; roll back to "
            f'a backup: POST /kinematics/rollback {{"backup": "{good.name}"}} '
            "(GET /kinematics/files lists them)",
            "path": str(kin),
            "reason": reason,
            "backups": [good.name],  # the newer backup does not load: not offered
        }
        assert f"kinematic file in force unreadable: {reason}" in health["problems"]
        assert files["in_force"]["valid"] is False and files["in_force"]["error"] == reason
        # what it says to do works
        r = client.post("/kinematics/rollback", json={"backup": good.name}, headers=AUTH)
        assert r.status_code == 200, r.text
        assert client.get("/kinematics").json()["modules"][0]["id"] == 1
        # a directory or a dangling link where the file should be: the same, not a 404
        # "none installed" (and /kinematics/files was a bare 500 on the directory)
        kin.unlink()
        kin.mkdir()
        r = client.get("/kinematics")
        reason = f"{kin}: not a regular file (a directory)"
        assert r.status_code == 500 and r.json()["reason"] == reason
        assert client.get("/kinematics/files").json()["in_force"]["sha256"] is None
        kin.rmdir()
        kin.symlink_to(tmp_path / "gone.yaml")
        r = client.get("/kinematics")
        assert r.status_code == 500 and r.json()["reason"].endswith("No such file or directory")
        assert client.get("/kinematics/files").json()["in_force"]["valid"] is False
