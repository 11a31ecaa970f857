"""The same seed gives the same calibration, bit for bit.

Two fresh services on the in-process simulator (lockstep: simulated time, whatever the
host does), the same seed, the same run started through HTTP: the calibrated parameters
are identical to the last bit (the digest ``make demo`` prints) and so is every pose and
encoder sample the runs recorded.  A busy host can only slow the runs down.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from pydantic import SecretStr

from services.config.settings import ServiceSettings
from services.demo import parameters_digest
from services.http.app import create_app
from swpc_hw.robot.model import PARAM_NAMES
from tests.service_rig import AUTH, TOKEN, wait_state

# every module, two angles, the shortest spins the solver takes: the whole protocol but
# the fast part (the demo's digests hold a whole run with it to the bit)
PROTOCOL = {
    "sweep_deg": 15, "settle_time": 0.3, "stop_time": 0.3, "align_time": 0.3, "resteer_time": 1.0,
    "precheck": False,
}  # fmt: skip


def calibrate(data_dir: Path, seed: int) -> tuple[dict[str, Any], Path]:
    """One run on a fresh service: its result document and its dataset directory."""
    settings = ServiceSettings(data_dir=data_dir, token=SecretStr(TOKEN), sim_seed=seed)
    with TestClient(create_app(settings)) as client:
        r = client.post("/calibrations", json={"overrides": {"protocol": PROTOCOL}}, headers=AUTH)
        assert r.status_code == 202, r.text
        run_id = r.json()["id"]
        st = wait_state(client, run_id, {"DONE", "FAILED", "ABORTED"})
        assert st["state"] == "DONE", st["errors"]
        res: dict[str, Any] = client.get(f"/calibrations/{run_id}/result").json()
    return res, Path(res["dataset_dir"])


def test_the_same_seed_gives_the_same_parameters_bit_for_bit(tmp_path: Path) -> None:
    first, data1 = calibrate(tmp_path / "a", seed=7)
    second, data2 = calibrate(tmp_path / "b", seed=7)
    print(f"\nseed 7: digests {parameters_digest(first)} {parameters_digest(second)}")
    assert parameters_digest(first) == parameters_digest(second)
    for a, b in zip(first["modules"], second["modules"], strict=True):
        for k in PARAM_NAMES:
            assert float(a[k]).hex() == float(b[k]).hex(), (a["id"], k, a[k], b[k])
            assert float(a["stddev"][k]).hex() == float(b["stddev"][k]).hex()
    for name in ("poses.csv", "encoders.csv", "segments.csv"):
        assert (data1 / name).read_bytes() == (data2 / name).read_bytes(), name
