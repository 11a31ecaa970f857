"""The IMU dataset: imu.csv and references.yaml, their checks, the simulated run."""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from simulators.offline.datagen_imu import (
    IMU_PROTOCOL,
    ImuExperiment,
    ReferenceOptions,
    generate_imu_experiment,
    yaw_rate,
)
from swpc_hw.calibration.gyro.bias import rest_windows
from swpc_hw.errors import DatasetError
from swpc_hw.files.dataset import load_dataset, save_dataset
from swpc_hw.files.references import (
    AxisDistance,
    StraightDrive,
    WheelRadius,
    load_references,
    parse_references,
)
from swpc_hw.robot.frames import (
    design_fit_constraints,
    design_fit_transform,
    transform_covariance,
    transform_parameters,
)
from swpc_hw.robot.model import rot
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED
from swpc_hw.sensors.gyro import GyroOptions

FAST = dataclasses.replace(
    IMU_PROTOCOL, spin_duration=4.0, drive_length=2.0, encoder_rate=100.0
)


@pytest.fixture(scope="module")
def run() -> ImuExperiment:
    return generate_imu_experiment(
        PAPER_CALIBRATED, FAST, references=ReferenceOptions(wheel_radius_modules=(3,))
    )


@pytest.fixture(scope="module")
def saved(run: ImuExperiment, tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("imu") / "ds"
    run.save(d)
    return d


def copy_of(saved: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(saved, tmp_path / "ds"))


def test_round_trip_without_poses(run: ImuExperiment, saved: Path) -> None:
    assert not (saved / "poses.csv").exists()
    ds = load_dataset(saved)
    assert not ds.has_poses and ds.is_imu
    assert ds.imu is not None and run.dataset.imu is not None
    np.testing.assert_allclose(ds.imu, run.dataset.imu, atol=1e-6)
    assert [type(r) for r in ds.references] == [type(r) for r in run.dataset.references]
    for a, b in zip(ds.references, run.dataset.references, strict=True):
        assert a.kind == b.kind and a.stddev == b.stddev
        assert abs(a.value - b.value) < 1e-9
    assert ds.segments == run.dataset.segments


def test_poses_kept_when_asked_and_a_stale_one_removed(
    run: ImuExperiment, tmp_path: Path
) -> None:
    run.save(tmp_path / "ds", poses=True)
    both = load_dataset(tmp_path / "ds")
    assert both.has_poses and both.imu is not None and not both.is_imu
    save_dataset(tmp_path / "ds", run.imu_dataset)  # same directory, no poses
    assert not (tmp_path / "ds" / "poses.csv").exists()


def test_neither_poses_nor_imu_is_refused_naming_both(saved: Path, tmp_path: Path) -> None:
    d = copy_of(saved, tmp_path)
    (d / "imu.csv").unlink()
    with pytest.raises(DatasetError, match=r"poses\.csv: missing file \(and no imu\.csv"):
        load_dataset(d)


def test_imu_clock_jumping_back_is_refused(saved: Path, tmp_path: Path) -> None:
    d = copy_of(saved, tmp_path)
    path = d / "imu.csv"
    lines = path.read_text().splitlines()
    rows = lines[1:]
    half = len(rows) // 2
    path.write_text("\n".join([lines[0], *rows[:half], *rows[half - 2000 : half]]) + "\n")
    with pytest.raises(DatasetError, match=r"imu\.csv: t: the clock jumps back"):
        load_dataset(d)


GOOD = {"kind": "axis_distance", "modules": [1, 2], "value": 0.43, "stddev": 0.0005}
BAD = {
    "unknown kind": ({"kind": "laser", "value": 1.0, "stddev": 0.1}, "unknown kind 'laser'"),
    "missing key": (
        {"kind": "wheel_radius", "value": 0.05, "stddev": 1e-3}, "missing key(s) module"
    ),
    "extra key": ({**GOOD, "stdev": 0.1}, "unknown key(s) stdev"),
    "unknown module": ({**GOOD, "modules": [1, 9]}, "module 9 is not in robot.yaml"),
    "same module": ({**GOOD, "modules": [2, 2]}, "two different modules"),
    "three modules": ({**GOOD, "modules": [1, 2, 3]}, "a list of two module ids"),
    "zero stddev": ({**GOOD, "stddev": 0}, "must be > 0"),
    "text value": ({**GOOD, "value": "0.4"}, "value must be a finite number"),
    "nan value": ({**GOOD, "value": math.nan}, "value must be a finite number"),
    "end before start": (
        {"kind": "straight_drive", "start": 5.0, "end": 4.0, "value": 4.0, "stddev": 1e-3},
        "end 4 must be after start 5",
    ),
    "not a mapping": (["axis_distance", 1, 2], "must be a mapping"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_malformed_reference_is_one_line_naming_file_and_entry(case: str) -> None:
    entry, message = BAD[case]
    doc: dict[str, Any] = {"references": [GOOD, entry]}
    with pytest.raises(DatasetError) as exc:
        parse_references(doc, "ds/references.yaml", {1, 2, 3, 4})
    text = str(exc.value)
    assert text.startswith("ds/references.yaml: references[1]")
    assert message in text and "\n" not in text


def test_references_file_round_trip_and_kinds(tmp_path: Path) -> None:
    p = tmp_path / "references.yaml"
    p.write_text(
        "references:\n"
        "  - {kind: axis_distance, modules: [1, 2], value: 0.4301, stddev: 0.0005}\n"
        "  - {kind: wheel_radius, module: 3, value: 0.05500, stddev: 0.00002}\n"
        "  - {kind: straight_drive, start: 12.0, end: 30.0, value: 5.000, stddev: 0.001}\n"
    )
    refs = load_references(p, {1, 2, 3})
    assert refs == [
        AxisDistance((1, 2), 0.4301, 0.0005),
        WheelRadius(3, 0.055, 0.00002),
        StraightDrive(12.0, 30.0, 5.0, 0.001),
    ]
    p.write_text("references: {kind: axis_distance}\n")
    with pytest.raises(DatasetError, match="references must be a list"):
        load_references(p)


def test_an_unknown_kind_in_a_dataset_is_refused_on_load(saved: Path, tmp_path: Path) -> None:
    d = copy_of(saved, tmp_path)
    path = d / "references.yaml"
    path.write_text(path.read_text() + "  - {kind: gps_fix, value: 1.0, stddev: 0.1}\n")
    with pytest.raises(DatasetError, match=r"references\[8\]: unknown kind 'gps_fix'"):
        load_dataset(d)


def test_the_gyro_reads_scale_times_yaw_rate_plus_bias(run: ImuExperiment) -> None:
    clean = generate_imu_experiment(
        PAPER_CALIBRATED, FAST, GyroOptions(noise_density=0.0, bias_walk=0.0, scale_error=0.01)
    )
    imu = clean.dataset.imu
    assert imu is not None
    omega = yaw_rate(clean.experiment, imu[:, 0])
    np.testing.assert_allclose(imu[:, 1], 1.01 * omega + math.radians(0.1), atol=1e-9)
    assert omega.max() == pytest.approx(0.5, abs=1e-6)  # the spins' 0.5 rad/s
    # the noisy gyro: its scatter in a rest is the white noise, N sqrt(rate)
    g = run.gyro
    a, b = run.experiment.rests[0]
    noisy = run.dataset.imu
    assert noisy is not None
    sel = (noisy[:, 0] > a) & (noisy[:, 0] < b)
    assert np.std(noisy[sel, 1]) == pytest.approx(g.noise_density * math.sqrt(g.rate), rel=0.15)


def test_references_are_the_truth_within_their_stddev(run: ImuExperiment) -> None:
    exp = run.experiment
    P = PAPER_CALIBRATED.arrays().P_s
    z = []
    for ref in run.dataset.references:
        if isinstance(ref, AxisDistance):
            a, b = ref.modules
            z.append((ref.value - np.linalg.norm(P[a - 1] - P[b - 1])) / ref.stddev)
        elif isinstance(ref, WheelRadius):
            z.append((ref.value - PAPER_CALIBRATED.module(ref.module).r) / ref.stddev)
        else:  # module 1's steering axis between the rests around the drive
            poses = exp.poses_at(np.array([ref.start, ref.end]))
            q = [poses[k, :2] + rot(poses[k, 2]) @ P[0] for k in range(2)]
            assert poses[1, 2] == pytest.approx(poses[0, 2], abs=1e-12)  # a translation
            z.append((ref.value - np.linalg.norm(q[1] - q[0])) / ref.stddev)
            assert ref.value == pytest.approx(FAST.drive_length, abs=5 * ref.stddev)
    assert len(z) == 8 and np.abs(z).max() < 4.0
    assert np.std(z) > 0.2  # drawn, not copied


def test_rest_windows_are_the_runs_rests(run: ImuExperiment) -> None:
    found = rest_windows(run.dataset, 2 * math.pi / 2**17)
    truth = run.experiment.rests
    assert len(found) == len(truth)
    for (a, b), (ta, tb) in zip(found, truth, strict=True):
        assert ta <= a < b <= tb and b - a > 0.5 * (tb - ta)


def test_design_fit_transform_recovers_a_rigid_motion() -> None:
    rng = np.random.default_rng(4)
    P = rng.normal(0.0, 0.3, (5, 2))
    phi, t = 0.7, np.array([0.3, -1.2])
    Q = (rot(phi) @ P.T).T + t
    got_phi, got_t = design_fit_transform(P, Q)
    assert got_phi == pytest.approx(phi, abs=1e-12)
    np.testing.assert_allclose(got_t, t, atol=1e-12)
    # least squares with noise: the residual is orthogonal to the fitted motion's family
    Qn = Q + rng.normal(0.0, 1e-3, Q.shape)
    phi_n, t_n = design_fit_transform(P, Qn)
    X = np.column_stack([P, rng.normal(size=(5, 3))])
    moved = transform_parameters(X, phi_n, t_n)
    assert np.abs(design_fit_constraints(moved[:, :2], Qn)).max() < 1e-12
    np.testing.assert_allclose(moved[:, 2], (X[:, 2] + phi_n + np.pi) % (2 * np.pi) - np.pi)
    C = np.eye(25)
    C2 = transform_covariance(C, 0.3)
    np.testing.assert_allclose(C2, C, atol=1e-12)  # isotropic stays isotropic
