"""Kinematic file: round trip, every validation error, atomic save."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from swpc_hw.errors import KinematicFileError
from swpc_hw.files.kinematic_file import (
    MAX_BYTES,
    kinematics_document,
    load_kinematics,
    parse_kinematics,
    save_kinematics,
)
from swpc_hw.robot.model import RobotParams
from swpc_hw.robot.paper_robot import PAPER_CALIBRATED


def doc() -> dict[str, Any]:
    return kinematics_document(PAPER_CALIBRATED, created="2026-01-01T00:00:00Z")


def test_round_trip_is_exact(tmp_path: Path) -> None:
    stds = [[1e-5, 2e-5, 3e-4, 4e-6, 5e-6]] * 4
    a = PAPER_CALIBRATED.arrays()
    params = RobotParams.from_arrays(
        a.ids, a.P_s, a.beta, a.b, a.r, robot="lab-7", frame="R", stddev=stds
    )
    path = tmp_path / "k.yaml"
    save_kinematics(path, params, extra={"quality": {"rms": 1.5e-4}})
    loaded = load_kinematics(path)
    assert loaded.params == params
    assert loaded.extra["quality"]["rms"] == 1.5e-4
    text = path.read_text()
    assert text.startswith("format: swpc-kinematics/1\n")


def test_unknown_keys_are_ignored() -> None:
    d = doc()
    d["modules"][0]["colour"] = "red"
    d["operator"] = "kim"
    assert parse_kinematics(d).params == PAPER_CALIBRATED


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda d: d.pop("modules"), "missing key 'modules'"),
        (lambda d: d.pop("format"), "missing key 'format'"),
        (lambda d: d.update(format="other/2"), "format: expected"),
        (lambda d: d["modules"][1].pop("r"), r"missing key 'modules\[1\].r'"),
        (lambda d: d["modules"][2].pop("id"), r"missing key 'modules\[2\].id'"),
        (lambda d: d["modules"][0].update(x_s=float("nan")), r"modules\[0\].x_s: must be finite"),
        (lambda d: d["modules"][0].update(beta=float("inf")), r"modules\[0\].beta: must be finite"),
        (lambda d: d["modules"][3].update(b=0.0), r"modules\[3\].b: must be within \[0.0001, 1\]"),
        (lambda d: d["modules"][3].update(r=-0.05), r"modules\[3\].r: must be within \[0.001, 1\]"),
        (
            lambda d: d["modules"][2].update(x_s=1e300),
            r"modules\[2\].x_s: must be within \[-50, 50\]",
        ),
        (lambda d: d["modules"][1].update(b=1e-300), r"modules\[1\].b: must be within"),
        (lambda d: d["modules"][1].update(r=1e-300), r"modules\[1\].r: must be within"),
        (lambda d: d["modules"][0].update(beta=7.0), r"modules\[0\].beta: must be within"),
        (lambda d: d["modules"][1].update(id=1), r"modules\[1\].id: duplicate module id 1"),
        (lambda d: d.update(modules=d["modules"][:1]), "N >= 2"),
        (lambda d: d["modules"][0].update(y_s="abc"), r"modules\[0\].y_s: must be a number"),
        (
            lambda d: d["modules"][0].update(stddev={"x_s": 1.0}),
            r"missing key 'modules\[0\].stddev.y_s'",
        ),
    ],
)
def test_validation_errors_name_the_key(mutate: Any, message: str, tmp_path: Path) -> None:
    d = doc()
    mutate(d)
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(KinematicFileError, match=message) as info:
        load_kinematics(path)
    assert str(path) in str(info.value)


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(KinematicFileError, match="cannot read"):
        load_kinematics(tmp_path / "nope.yaml")
    p = tmp_path / "broken.yaml"
    p.write_text("format: [unclosed\n")
    with pytest.raises(KinematicFileError, match="not valid YAML"):
        load_kinematics(p)


def test_only_a_regular_file_of_at_most_1_mib_is_read_and_never_waited_on(
    tmp_path: Path,
) -> None:
    """A FIFO (its open waits for a writer), a link to /dev/zero (endless), a directory
    and a file past MAX_BYTES are refused at once, naming what they are; a link to a
    regular file is followed."""
    good = tmp_path / "good.yaml"
    save_kinematics(good, PAPER_CALIBRATED)
    (tmp_path / "link.yaml").symlink_to(good)
    assert load_kinematics(tmp_path / "link.yaml").params == PAPER_CALIBRATED
    os.mkfifo(tmp_path / "fifo.yaml")
    (tmp_path / "zero.yaml").symlink_to("/dev/zero")
    big = tmp_path / "big.yaml"
    big.write_text(good.read_text() + "#" * MAX_BYTES)
    for name, reason in [
        ("fifo.yaml", "not a regular file (a FIFO)"),
        ("zero.yaml", "not a regular file (a character device)"),
        (".", "not a regular file (a directory)"),
        ("big.yaml", f"a kinematic file is at most {MAX_BYTES} bytes"),
    ]:
        with pytest.raises(KinematicFileError, match=re.escape(reason)):
            load_kinematics(tmp_path / name)


def test_a_yaml_alias_is_refused_before_it_grows(tmp_path: Path) -> None:
    """An alias bomb of a few kB (9 levels of 9 references: 387 million nodes once
    expanded) is refused where its first alias stands; a valid file needs none."""
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 9)}]" for i in range(1, 9)]
    p = tmp_path / "bomb.yaml"
    p.write_text(yaml.safe_dump(doc()) + "\n".join(lines) + "\n")
    assert p.stat().st_size < 5000
    with pytest.raises(KinematicFileError, match=r"YAML alias at line \d+: a kinematic"):
        load_kinematics(p)


def test_save_is_atomic_and_never_leaves_a_partial_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "k.yaml"
    save_kinematics(path, PAPER_CALIBRATED)
    before = path.read_bytes()

    def failing_fsync(fd: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", failing_fsync)
    other = PAPER_CALIBRATED.model_copy(update={"robot": "changed"})
    with pytest.raises(KinematicFileError, match="cannot write"):
        save_kinematics(path, other)
    assert path.read_bytes() == before  # previous file intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["k.yaml"]  # no temp file left


def test_save_into_missing_directory_is_a_clear_error(tmp_path: Path) -> None:
    with pytest.raises(KinematicFileError, match="cannot write"):
        save_kinematics(tmp_path / "no" / "k.yaml", PAPER_CALIBRATED)


def _with_covariance() -> tuple[RobotParams, np.ndarray]:
    """The paper robot with a covariance whose betas move together, and matching stddevs."""
    n = len(PAPER_CALIBRATED.modules)
    rng = np.random.default_rng(4)
    A = rng.normal(size=(5 * n, 5 * n)) * 1e-5
    cov = A @ A.T
    beta = [5 * i + 2 for i in range(n)]
    cov[np.ix_(beta, beta)] += 1e-8  # a common homing error: beta correlation ~1
    a = PAPER_CALIBRATED.arrays()
    params = RobotParams.from_arrays(
        a.ids, a.P_s, a.beta, a.b, a.r, stddev=np.sqrt(np.diag(cov)).reshape(n, 5)
    )
    return params, cov


def test_covariance_round_trip_and_validation(tmp_path: Path) -> None:
    params, cov = _with_covariance()
    path = tmp_path / "k.yaml"
    save_kinematics(path, params, covariance=cov)
    loaded = load_kinematics(path)
    np.testing.assert_array_equal(np.array(loaded.covariance), cov)
    assert "covariance" not in loaded.extra
    assert load_kinematics(path).params == params
    d = kinematics_document(params, covariance=cov)
    bad = {
        "not symmetric": lambda m: m[0].__setitem__(1, m[0][1] * 2 + 1e-9),
        "not positive semi-definite": lambda m: (
            m[7].__setitem__(2, 10.0) or m[2].__setitem__(7, 10.0)
        ),
        "must be 20 rows": lambda m: m.pop(),
        "must be finite": lambda m: m[3].__setitem__(3, float("nan")),
        r"module 1 y_s gives a std dev": lambda m: m[1].__setitem__(1, m[1][1] * 4),
    }
    for message, mutate in bad.items():
        dd = yaml.safe_load(yaml.safe_dump(d))
        mutate(dd["covariance"]["matrix"])
        with pytest.raises(KinematicFileError, match=message):
            parse_kinematics(dd, "k.yaml")
    dd = yaml.safe_load(yaml.safe_dump(d))
    dd["covariance"]["order"] = ["r", "b", "beta", "y_s", "x_s"]
    with pytest.raises(KinematicFileError, match=r"covariance.order: expected"):
        parse_kinematics(dd, "k.yaml")
