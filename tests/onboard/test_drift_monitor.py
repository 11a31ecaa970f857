"""The drift monitor (swpc_hw.onboard.drift): running estimate of each module's r and beta error
from the odometry of normal driving, and the calibration suspect it raises.

Readings: :mod:`simulators.offline.drift_path` (exact no-slip casters on a true robot, a mixed path
of straights, arcs, strafes, spins and stops, 200 Hz); "noiseless" has no quantization,
slip or jitter, "noisy" the defaults (2^17 counts, 0.2 % slip, slip bursts).  The file is
the paper's calibrated robot.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest

from services.cli.offline.odometry import log_suspect
from simulators.offline.drift_path import (
    PathNoise,
    drive_readings,
    mixed_segments,
    observe_drive,
    with_error,
)
from swpc_hw.files.kinematic_file import save_kinematics
from swpc_hw.onboard.drift import (
    DriftError,
    DriftMonitor,
    DriftOptions,
    SuspectChange,
    median_contrast,
    residual_maker,
)
from swpc_hw.onboard.odometry import OdometryStep
from swpc_hw.onboard.ros2.messages import DIAGNOSTIC_ARRAY
from swpc_hw.onboard.ros2.stream import DIAGNOSTICS_TOPIC, Ros2OdometryStream
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.mocap import ros2_typestore

FILE = PAPER_CALIBRATED
NOISELESS = PathNoise(counts=0, slip_std=0.0, bursts_per_minute=0.0, jitter=0.0)


def _estimate(run_monitor: DriftMonitor, module: int) -> tuple[float, float, float, float]:
    e = next(e for e in run_monitor.estimates if e.module == module)
    return e.r, e.r_std, e.beta, e.beta_std


def test_residual_maker_removes_rigid_fields_and_keeps_the_rest() -> None:
    rng = np.random.default_rng(3)
    Qx, Qy = rng.normal(0, 0.3, 4).tolist(), rng.normal(0, 0.3, 4).tolist()
    w = rng.uniform(0.2, 1.0, 4).tolist()
    vx, vy, om = 0.3, -0.1, 0.7
    rigid = np.array([[vx - om * Qy[i], vy + om * Qx[i]][c] for i in range(4) for c in (0, 1)])
    other = rng.normal(0, 1, 8)
    out = residual_maker(Qx, Qy, w, np.column_stack([rigid, other]))
    assert np.abs(out[:, 0]).max() < 1e-12  # (I - H) A = 0
    again = residual_maker(Qx, Qy, w, out[:, 1:])  # a projector: (I - H)^2 = I - H
    np.testing.assert_allclose(again[:, 0], out[:, 1], atol=1e-12)
    assert np.abs(out[:, 1]).max() > 0.1


def test_median_contrast() -> None:
    eps = np.array([0.1, -3.0, 0.3, 0.2])  # middle two: 0.1, 0.2
    assert float(median_contrast(eps, 1) @ eps) == pytest.approx(-3.15)
    assert float(median_contrast(eps, 0) @ eps) == pytest.approx(-0.05)
    assert float(median_contrast(eps[:3], 1) @ eps[:3]) == pytest.approx(-3.1)
    assert median_contrast(eps, 2).sum() == pytest.approx(0.0)  # blind to a common scale


@pytest.mark.parametrize(("dr", "dbeta"), [(-0.3e-3, 0.0), (0.0, math.radians(0.3)),
                                           (0.2e-3, math.radians(-0.2))])
def test_recovers_a_known_error_on_noiseless_data(dr: float, dbeta: float) -> None:
    truth = with_error(FILE, 3, dr=dr, dbeta=dbeta)
    run = observe_drive(truth, FILE, mixed_segments(120.0, 5), noise=NOISELESS)
    assert run.metres > 25.0
    # not pulled towards zero: the model is first order in the error and blind to the
    # common radius scale, whose faint trace in the swivels is left out; the remainder
    # (measured 0.42 um and 6 urad at these errors, beyond the std of noiseless data) stays
    # under 1 um / 10 urad
    for e in run.monitor.estimates:
        true_r, true_beta = (dr, dbeta) if e.module == 3 else (0.0, 0.0)
        assert abs(e.r - true_r) <= 3.0 * e.r_std + 1e-6
        assert abs(e.beta - true_beta) <= 3.0 * e.beta_std + 10e-6
    r, _, _, _ = _estimate(run.monitor, 3)
    assert abs(r - dr) <= 0.005 * max(abs(dr), 0.2e-3)
    raised = {(c.suspect.module, c.suspect.parameter) for c in run.changes if c.raised}
    assert raised == {(3, p) for p, d in (("r", dr), ("beta", dbeta)) if d != 0.0}


def test_a_common_radius_scale_is_not_a_suspect() -> None:
    """Every wheel 0.5 % larger: the odometry cannot see it (docstring), nothing is flagged."""
    mods = [m.model_copy(update={"r": m.r * 1.005}) for m in FILE.modules]
    truth = FILE.model_copy(update={"modules": mods})
    run = observe_drive(truth, FILE, mixed_segments(120.0, 6), noise=NOISELESS)
    assert run.changes == []
    assert max(abs(e.r) for e in run.monitor.estimates) < 1e-6  # of a 0.27 mm scale


def test_a_common_beta_on_straight_drives_only_is_not_observable_nor_flagged() -> None:
    mods = [m.model_copy(update={"beta": m.beta + math.radians(0.5)}) for m in FILE.modules]
    truth = FILE.model_copy(update={"modules": mods})
    run = observe_drive(truth, FILE, [(120.0, (0.4, 0.0, 0.0))], noise=PathNoise())
    assert run.monitor.estimates and run.changes == []
    assert min(e.beta_std for e in run.monitor.estimates) > math.radians(0.5)


def test_flags_the_drifted_wheel_on_a_noisy_path() -> None:
    truth = with_error(FILE, 2, dr=-0.3e-3)
    run = observe_drive(truth, FILE, mixed_segments(400.0, 11), seed=11, stop_at_first=True)
    (change,) = run.changes
    s = change.suspect
    assert change.raised and (s.module, s.parameter) == (2, "r")
    assert 10.0 < s.metres < 60.0
    assert abs(s.estimate + 0.3e-3) < 0.05e-3 and s.std < 0.02e-3


def test_a_correct_robot_is_not_flagged_over_a_long_noisy_path() -> None:
    run = observe_drive(FILE, FILE, mixed_segments(900.0, 21), seed=21)
    assert run.metres > 200.0 and run.monitor.dropped > 0  # slip bursts were seen
    assert run.changes == []
    o = run.monitor.options
    assert max(abs(e.r) for e in run.monitor.estimates) < 0.5 * o.min_r
    assert max(abs(e.beta) for e in run.monitor.estimates) < 0.5 * o.min_beta


def test_the_evidence_is_what_is_logged_and_published(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    kin = tmp_path / "kinematics.yaml"
    save_kinematics(kin, FILE)
    sent: list[tuple[str, bytes]] = []
    changes: list[SuspectChange] = []

    def on_suspect(c: SuspectChange) -> None:
        changes.append(c)
        log_suspect(c)

    stream = Ros2OdometryStream(kin, lambda topic, _ty, _st, b: sent.append((topic, b)),
                                drift=DriftOptions(), on_suspect=on_suspect)
    truth = with_error(FILE, 4, dr=-0.3e-3)
    with caplog.at_level(logging.INFO, logger="swpc.odometry"):
        for t, th, ps in drive_readings(truth, mixed_segments(200.0, 7), seed=7):
            for k in range(t.size):
                stream.update(float(t[k]), th[k].tolist(), ps[k].tolist())
            if changes:
                break
    (c,) = changes
    assert c.raised and (c.suspect.module, c.suspect.parameter) == (4, "r")
    (rec,) = [r for r in caplog.records if r.name == "swpc.odometry"]
    assert rec.levelno == logging.WARNING
    ev = c.suspect.fields()
    assert rec.getMessage() == (
        f"event=calibration_suspect module=4 parameter=r estimate_mm={ev['estimate_mm']} "
        f"std_mm={ev['std_mm']} metres={ev['metres']}")
    assert -0.35 < float(str(ev["estimate_mm"])) < -0.25
    (diag,) = [b for topic, b in sent if topic == DIAGNOSTICS_TOPIC]
    msg = ros2_typestore().deserialize_cdr(diag, DIAGNOSTIC_ARRAY)
    (status,) = msg.status
    assert status.level == 1 and status.name == "swpc: calibration"
    assert {kv.key: kv.value for kv in status.values} == {f"0.{k}": str(v) for k, v in ev.items()}
    assert stream.published > 0  # /odom and /tf as before


def test_bad_options_and_mismatched_steps_are_refused() -> None:
    with pytest.raises(DriftError, match="z_on >= z_off"):
        DriftOptions(z_on=2.0, z_off=3.0)
    with pytest.raises(DriftError, match="window"):
        DriftOptions(window=0.0)
    mon = DriftMonitor(FILE)
    step = OdometryStep(t=0.01, dt=0.01, twist=(0.1, 0.0, 0.0), residuals=(0.0,) * 3,
                        filtered_residuals=(0.0,) * 3, weights=(1.0,) * 3, sigma=0.003,
                        iterations=1)
    rows = [(0.2, 0.1, 0.0, 0.02, 0.055, 0.055 / 0.24)] * 3
    with pytest.raises(DriftError, match="expected 4 modules"):
        mon.observe(rows, [0.0] * 3, [0.0] * 3, [0.0] * 3, [0.1] * 3, step)
    assert mon.blocks == 0 and mon.metres == 0.0  # nothing taken in
