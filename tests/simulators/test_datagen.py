"""Simulated calibration experiment and the vectorised batch experiment."""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import pytest

from simulators.offline.datagen import (
    Experiment,
    ExperimentOptions,
    PartialSlip,
    generate_experiment,
)
from simulators.offline.random_robots import batch_experiment, random_robots
from swpc_hw.files.dataset import load_dataset
from swpc_hw.files.kinematic_file import load_robot
from swpc_hw.robot.model import rot, wrap_angle
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED, PAPER_NOMINAL

NOISELESS = ExperimentOptions(counts_per_rev=None)


@pytest.fixture(scope="module")
def clean() -> Experiment:
    return generate_experiment(PAPER_CALIBRATED, NOISELESS)


def _rows_in(e: Experiment, mid: int, start: float, end: float) -> np.ndarray:
    enc = e.dataset.encoders[mid]
    return enc[(enc[:, 0] >= start) & (enc[:, 0] <= end)]


def test_timeline_and_dataset_shape(clean: Experiment) -> None:
    ds = clean.dataset
    assert ds.robot == PAPER_NOMINAL  # the dataset carries the nominal, never the truth
    assert [s.static_module for s in ds.segments] == [1, 1, 2, 2, 3, 3, 4, 4]
    assert all(s.end - s.start == pytest.approx(12.0, abs=1e-6) for s in ds.segments)
    assert ds.poses[0, 0] == 0.0
    assert np.allclose(ds.poses[0, 1:], 0.0)
    assert np.allclose(np.diff(ds.poses[:, 0]), 0.01)
    assert np.all(np.abs(ds.poses[:, 3]) <= math.pi)
    for enc in ds.encoders.values():
        assert np.allclose(np.diff(enc[:, 0]), 0.005)
        assert np.all(np.abs(enc[:, 1]) <= math.pi)
    # starts at ramp + settle (>= 2 s) after the alignment
    assert ds.segments[0].start >= 1.0 + 1.0 + 2.0


def test_rotation_about_locked_contact_point(clean: Experiment) -> None:
    P = clean.true_poses
    for s in clean.segments:
        sel = (P[:, 0] >= s.start) & (P[:, 0] <= s.end)
        assert sel.sum() >= 1199
        p, yaw = P[sel, 1:3], P[sel, 3]
        C_W = p + np.einsum("kij,j->ki", rot(yaw), s.fixed_point)
        assert np.abs(C_W - s.fixed_point_world).max() < 1e-9
        # the fixed point is the true contact point of the locked module
        m = PAPER_CALIBRATED.module(s.static_module)
        th = s.theta_hat + m.beta
        expect = np.array([m.x_s + m.b * math.cos(th), m.y_s + m.b * math.sin(th)])
        assert np.allclose(s.fixed_point, expect, atol=1e-15)
        # re-steering about P_s,k keeps the pinned wheel on the same floor point
        first = next(g for g in clean.segments if g.static_module == s.static_module)
        assert np.allclose(s.fixed_point_world, first.fixed_point_world, atol=1e-12)
        # counter-clockwise at 0.5 rad/s
        dyaw = np.unwrap(yaw)
        assert (dyaw[-1] - dyaw[0]) == pytest.approx(0.5 * (P[sel, 0][-1] - P[sel, 0][0]))


def test_casters_settled_and_wheels_roll_d_dyaw(clean: Experiment) -> None:
    A = PAPER_CALIBRATED.arrays()
    P = clean.true_poses
    for s in clean.segments:
        k = A.ids.tolist().index(s.static_module)
        in_win = (clean.encoder_stamps >= s.start) & (clean.encoder_stamps <= s.end)
        err = wrap_angle(clean.true_theta[in_win] - s.settled_theta[None, :])
        assert np.abs(err).max() < 1e-9
        # static module: held angle, braked wheel
        st = _rows_in(clean, s.static_module, s.start, s.end)
        assert np.allclose(st[:, 1], s.theta_hat, atol=1e-12)
        assert np.ptp(st[:, 2]) == 0.0
        # dynamic wheels: r dpsi = -D dyaw on samples common to both clocks
        ta, tb = math.ceil(s.start * 100) / 100, math.floor(s.end * 100) / 100
        ia, ib = np.searchsorted(P[:, 0], [ta - 1e-9, tb - 1e-9])
        dyaw = float(np.unwrap(P[ia : ib + 1, 3])[-1] - P[ia, 3])
        for j in range(A.n):
            if j == k:
                continue
            enc = clean.dataset.encoders[int(A.ids[j])]
            ja, jb = np.searchsorted(enc[:, 0], [ta - 1e-9, tb - 1e-9])
            dpsi = enc[jb, 2] - enc[ja, 2]
            assert A.r[j] * dpsi == pytest.approx(-s.D[j] * dyaw, rel=1e-9)
            # the settled reported angle is in the encoder stream
            assert np.allclose(wrap_angle(enc[ja:jb, 1] - s.settled_theta_hat[j]), 0, atol=1e-9)


def test_negative_yaw_rate_and_more_angles() -> None:
    deg = math.pi / 180
    opt = ExperimentOptions(
        angles=(30 * deg, 100 * deg, -150 * deg), yaw_rate=-0.4, spin_duration=3.0,
        counts_per_rev=None,
    )
    e = generate_experiment(PAPER_CALIBRATED, opt)
    assert len(e.dataset.segments) == 12
    P = e.true_poses
    for s in e.segments:
        sel = (P[:, 0] >= s.start) & (P[:, 0] <= s.end)
        C_W = P[sel, 1:3] + np.einsum("kij,j->ki", rot(P[sel, 3]), s.fixed_point)
        assert np.abs(C_W - s.fixed_point_world).max() < 1e-9
        dyaw = np.unwrap(P[sel, 3])
        assert dyaw[-1] - dyaw[0] == pytest.approx(-0.4 * (P[sel, 0][-1] - P[sel, 0][0]))
        in_win = (e.encoder_stamps >= s.start) & (e.encoder_stamps <= s.end)
        assert np.abs(wrap_angle(e.true_theta[in_win] - s.settled_theta)).max() < 1e-9
        # trailing wheels still turn backwards
        psi = e.true_psi[in_win]
        assert np.all(psi[-1] - psi[0] <= 0.0)


def test_quantization_step() -> None:
    counts = 2**12
    e = generate_experiment(PAPER_CALIBRATED, ExperimentOptions(counts_per_rev=counts))
    step = 2 * math.pi / counts
    for enc in e.dataset.encoders.values():
        for col in (1, 2):
            ticks = enc[:, col] / step
            assert np.abs(ticks - np.round(ticks)).max() < 1e-6
            d = np.abs(np.diff(np.unique(enc[:, col])))
            assert d.min() == pytest.approx(step, rel=1e-9)
    # quantization error bounded by half a step
    for j, enc in enumerate(e.dataset.encoders.values()):
        assert np.abs(enc[:, 2] - e.true_psi[:, j]).max() <= step / 2 + 1e-12


def test_noise_dropout_outliers() -> None:
    opt = ExperimentOptions(
        pose_sigma_xy=0.001, pose_sigma_yaw=0.002, dropout_fraction=0.1,
        outlier_fraction=0.02, outlier_magnitude=0.05, seed=3,
    )
    e = generate_experiment(PAPER_CALIBRATED, opt)
    n_all = e.true_poses.shape[0]
    poses = e.dataset.poses
    assert poses.shape[0] == pytest.approx(0.9 * n_all, abs=2)
    assert e.dropped_times.size == n_all - poses.shape[0]
    truth = e.true_poses[np.searchsorted(e.true_poses[:, 0], poses[:, 0] - 1e-9)]
    assert np.allclose(truth[:, 0], poses[:, 0])
    dxy = np.hypot(*(poses[:, 1:3] - truth[:, 1:3]).T)
    outl = dxy > 0.025
    assert outl.sum() == pytest.approx(0.02 * poses.shape[0], rel=0.05)
    assert set(np.round(poses[outl, 0], 6)) == set(np.round(e.outlier_times, 6))
    good = ~np.isin(np.round(poses[:, 0], 6), np.round(e.outlier_times, 6))
    res = poses[good, 1:3] - truth[good, 1:3]
    assert res.std() == pytest.approx(0.001, rel=0.05)
    ryaw = wrap_angle(poses[good, 3] - truth[good, 3])
    assert ryaw.std() == pytest.approx(0.002, rel=0.05)
    big_yaw = np.abs(wrap_angle(poses[~good, 3] - truth[~good, 3]))
    assert np.allclose(big_yaw, 0.05 / 0.25, atol=0.02)


def test_clock_offset_shifts_encoder_stamps(clean: Experiment) -> None:
    off = 0.015  # three encoder periods
    opt = ExperimentOptions(counts_per_rev=None, clock_offset=off)
    e = generate_experiment(PAPER_CALIBRATED, opt)
    assert np.allclose(e.dataset.poses, clean.dataset.poses)
    for mid, enc in e.dataset.encoders.items():
        ref = clean.dataset.encoders[mid]
        # stamp t_e was sampled at pose-clock time t_e - offset
        assert enc[0, 0] == pytest.approx(off)
        assert np.allclose(enc[:, 0] - off, ref[: enc.shape[0], 0], atol=1e-12)
        assert np.allclose(enc[:, 1:], ref[: enc.shape[0], 1:], atol=1e-9)


def test_slip_bursts_turn_the_encoder_only(clean: Experiment) -> None:
    opt = ExperimentOptions(counts_per_rev=None, slip_burst_rate=0.05, seed=5)
    e = generate_experiment(PAPER_CALIBRATED, opt)
    assert np.array_equal(e.dataset.poses, clean.dataset.poses)  # body unaffected
    assert len(e.slip_bursts) >= 5
    ids = PAPER_CALIBRATED.ids
    for j, mid in enumerate(ids):
        extra = e.dataset.encoders[mid][:, 2] - e.true_psi[:, j]
        t = e.encoder_stamps
        in_burst = np.zeros(t.size, dtype=bool)
        dtrue = np.diff(e.true_psi[:, j])
        d = np.diff(extra)
        for sb in (b for b in e.slip_bursts if b.module == mid):
            assert 0.2 - 1e-9 <= sb.end - sb.start <= 0.5 + 1e-9 or sb.end == e.duration
            assert 0.3 <= sb.factor <= 1.0
            inside = (t > sb.start) & (t < sb.end)
            in_burst |= inside
            both = inside[1:] & inside[:-1]
            # the encoder turns (1 + factor) x the rolling rotation
            assert np.allclose(d[both], sb.factor * dtrue[both], rtol=0, atol=1e-12)
        # outside bursts the extra rotation stays constant
        assert np.abs(d[~in_burst[1:] & ~in_burst[:-1]]).max() < 1e-12
    total = sum(abs(e.dataset.encoders[m][-1, 2] - e.true_psi[-1, ids.index(m)]) for m in ids)
    assert total > 0.1


def test_save_and_load_roundtrip(tmp_path: Path) -> None:
    e = generate_experiment(PAPER_CALIBRATED, ExperimentOptions(spin_duration=3.0))
    e.save(tmp_path / "run")
    ds = load_dataset(tmp_path / "run")
    assert ds.robot == PAPER_NOMINAL
    assert load_robot(tmp_path / "run" / "truth.yaml") == PAPER_CALIBRATED
    assert ds.segments == e.dataset.segments
    assert np.allclose(ds.poses, e.dataset.poses, atol=1e-6)
    for mid, enc in e.dataset.encoders.items():
        assert np.allclose(ds.encoders[mid], enc, atol=1e-6)


def test_default_run_reports_its_generation_time() -> None:
    """How long it takes is a benchmark's figure (make bench: [datagen]), not a test's."""
    t0 = time.perf_counter()
    e = generate_experiment(PAPER_CALIBRATED)
    elapsed = time.perf_counter() - t0
    assert 0.0 < e.generation_seconds <= elapsed


def test_batch_agrees_with_generator() -> None:
    rng = np.random.default_rng(7)
    robots = random_robots(50, rng)
    T, n = robots.beta.shape
    assert robots.P_s.shape == (T, n, 2)
    design = PAPER_NOMINAL.arrays()
    assert np.all(np.abs(robots.P_s / design.P_s[None] - 1) <= 0.3)
    assert np.all(np.abs(robots.beta) <= math.radians(30))
    assert np.all(np.abs(robots.b / 0.020 - 1) <= 0.1)
    assert np.all(np.abs(robots.r / 0.055 - 1) <= 0.1)
    bx = batch_experiment(*robots, n_poses=36, seed=1)
    assert bx.poses.shape == (T, n, 2, 36, 3)
    # exact rigid rotations about the fixed points
    p, yaw = bx.poses[..., :2], bx.poses[..., 2]
    C_W = p + np.einsum("...ij,...j->...i", rot(yaw), bx.fixed_points[..., None, :])
    assert np.abs(C_W - bx.fixed_points_world[..., None, :]).max() < 1e-12
    assert np.allclose(bx.dyaw, 2 * math.pi)

    for i in (0, 1):
        robot = robots.robot(i)
        e = generate_experiment(robot, ExperimentOptions(counts_per_rev=None, spin_duration=4.0))
        A = robot.arrays()
        for s in e.segments:
            k = A.ids.tolist().index(s.static_module)
            m = s.angle_index
            assert np.allclose(s.fixed_point, bx.fixed_points[i, k, m], atol=1e-15)
            d_th = wrap_angle(s.settled_theta_hat - bx.theta_hat[i, k, m])
            assert np.allclose(d_th, 0, atol=1e-12)
            assert bx.static_theta_hat[i, k, m] == s.theta_hat
            # wheel increments per radian of yaw agree with the integrated experiment
            # (times on both the 100 Hz pose and 200 Hz encoder grids)
            P = e.true_poses
            pa, pb = np.searchsorted(P[:, 0], [s.start - 1e-9, s.end + 1e-9])
            pb -= 1
            ea, eb = np.searchsorted(e.encoder_stamps, P[[pa, pb], 0] - 1e-9)
            assert np.allclose(e.encoder_stamps[[ea, eb]], P[[pa, pb], 0], atol=1e-12)
            dyaw = float(np.unwrap(P[pa : pb + 1, 3])[-1] - P[pa, 3])
            dpsi = e.true_psi[eb] - e.true_psi[ea]
            ratio = bx.dpsi[i, k, m] / bx.dyaw[i, k, m]
            assert np.allclose(dpsi / dyaw, ratio, rtol=1e-9, atol=0)


def test_batch_of_10000_trials_is_finite_and_shaped() -> None:
    """Its speed is make bench's figure ([table3] data ... s), not a test's."""
    rng = np.random.default_rng(0)
    bx = batch_experiment(*random_robots(10_000, rng))
    assert bx.poses.shape == (10_000, 4, 2, 36, 3)
    assert np.isfinite(bx.poses).all()


@pytest.mark.parametrize("name", ["datagen", "simulate"])  # simulate: its old name
def test_datagen_command_writes_a_loadable_dataset(tmp_path: Path, name: str) -> None:
    import argparse

    from services.cli.offline import datagen

    parser = argparse.ArgumentParser()
    datagen.register(parser.add_subparsers())
    out = tmp_path / "sim"
    args = parser.parse_args(
        [name, str(out), "--spin-duration", "3", "--pose-sigma-xy", "0.5",
         "--angles", "30", "120", "200", "--seed", "2"]
    )
    assert args.func(args) == 0
    ds = load_dataset(out)
    assert len(ds.segments) == 12
    assert ds.robot == PAPER_NOMINAL
    assert load_robot(out / "truth.yaml") == PAPER_CALIBRATED
    seg = ds.segments[2]  # module 1, third angle
    enc = ds.encoders[seg.static_module]
    held = enc[(enc[:, 0] >= seg.start) & (enc[:, 0] <= seg.end), 1]
    assert np.allclose(held, wrap_angle(math.radians(200)), atol=1e-4)


def test_ar1_pose_noise_keeps_its_size_and_is_correlated_frame_to_frame() -> None:
    sig_xy, sig_yaw = 0.5e-3, math.radians(0.05)
    base = ExperimentOptions(pose_sigma_xy=sig_xy, pose_sigma_yaw=sig_yaw, spin_duration=3.0)
    for rho in (0.0, 0.8):
        e = generate_experiment(PAPER_CALIBRATED, dataclasses.replace(base, pose_noise_rho=rho))
        n = e.dataset.poses[:, 1:3] - e.true_poses[:, 1:3]
        n_yaw = wrap_angle(e.dataset.poses[:, 3] - e.true_poses[:, 3])
        assert n.std() == pytest.approx(sig_xy, rel=0.08)
        assert n_yaw.std() == pytest.approx(sig_yaw, rel=0.08)
        for x in (n[:, 0], n[:, 1], n_yaw):
            assert np.corrcoef(x[1:], x[:-1])[0, 1] == pytest.approx(rho, abs=0.05)
    with pytest.raises(ValueError, match="pose_noise_rho"):
        generate_experiment(PAPER_CALIBRATED, dataclasses.replace(base, pose_noise_rho=1.0))


def test_partial_slip_turns_one_wheel_more_over_part_of_one_window(clean: Experiment) -> None:
    slip = PartialSlip(module=2, segment=4, start=0.25, end=0.75, factor=0.004)
    e = generate_experiment(
        PAPER_CALIBRATED, dataclasses.replace(NOISELESS, partial_slips=(slip,))
    )
    s = e.segments[4]
    (burst,) = e.slip_bursts
    w = s.end - s.start
    assert (burst.module, burst.start, burst.end) == (2, s.start + 0.25 * w, s.start + 0.75 * w)
    j = PAPER_CALIBRATED.ids.index(2)
    psi = e.dataset.encoders[2][:, 2]
    extra = psi - e.true_psi[:, j]  # wheel angle beyond rolling
    t = e.encoder_stamps
    inside = (t > burst.start) & (t < burst.end)
    rolled = e.true_psi[inside, j] - np.interp(burst.start, t, e.true_psi[:, j])
    np.testing.assert_allclose(extra[inside], 0.004 * rolled, atol=1e-12)
    assert np.all(extra[t < burst.start] == 0.0)
    for mid, rows in e.dataset.encoders.items():  # the other wheels are untouched
        if mid != 2:
            np.testing.assert_array_equal(rows, clean.dataset.encoders[mid])
