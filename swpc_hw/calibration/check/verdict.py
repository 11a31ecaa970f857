"""Does the robot still match its kinematic file?  A check's test (pure functions).

A *check* (docs/check.md) is a short run of the calibration protocol whose data are
solved by the joint solver started from the file in force
(:func:`swpc_hw.calibration.mocap.solver.solve` with ``start``): an estimate ``p_check`` of
every parameter with its covariance ``C_check``, independent of the file's estimate
``p_file`` (covariance ``C_file``, as the file states it).  Both are in the frame R of
the motion capture's rigid body
(:func:`~swpc_hw.calibration.check.dataset_check.check_dataset` refuses a file in another
frame): a change of the robot shows as a change of its parameters, nothing else does.  A check
without motion capture compares the robot's shape instead
(:mod:`swpc_hw.calibration.check.shape`).

**The change** of every parameter and its covariance (the two estimates come from
independent data)::

    d = p_check - p_file            (beta: wrapped to (-pi, pi])
    Cov(d) = C_check + C_file + diag(s_rep^2)

``s_rep`` is the robot's *repeatability* (a std dev per parameter kind, the robot
config's ``check.repeatability``): how much an unchanged robot differs from one day to
the next beyond what the two runs' noise explains (the floor, the tyres, temperature,
the solver's small-sample covariance of short spins).  Zero gives the bare statistic.

**Per parameter** ``z_i = d_i / sqrt(Cov(d)_ii)``: standard normal when nothing changed.

**Per module** k, its five parameters together::

    chi2_k = d_k^T Cov(d)_kk^-1 d_k        (chi-square with 5 degrees of freedom
                                             when module k is unchanged)

module k has *drifted* when ``chi2_k > q``, ``q`` the chi-square quantile for a per-module
false-alarm rate ``alpha_m``, chosen by **Sidak's correction** so that an unchanged robot
of N modules raises a false alarm with probability ``false_alarm``::

    alpha_m = 1 - (1 - false_alarm)^(1/N),    q = F^-1_chi2(5)(1 - alpha_m)

(exact when the modules' statistics are independent; they share the check's spins, and
the measured false-alarm rate, docs/figures.md, is the judge).  Sidak rather than
Bonferroni (``alpha_m = false_alarm / N``): the same guarantee, slightly less
conservative.

**Which parameters**: in a drifted module, those with ``|z_i| > z_m``, the two-sided
normal quantile of ``alpha_m / 5`` (Bonferroni over the module's five); when none
passes it alone, the largest ``|z_i|``.

**The verdict**: ``consistent`` (no module drifted), else ``drifted`` with the action
``recalibrate module k`` (the drifted modules named) or, when at least ``whole_robot``
(a fraction, default half) of the modules drifted, ``recalibrate the whole robot``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration.parameters import BETA, N_PARAMS
from swpc_hw.calibration.report import DISPLAY
from swpc_hw.errors import CalibrationError
from swpc_hw.robot.model import PARAM_NAMES, RobotParams, wrap_angle

FloatArray = NDArray[np.float64]

CONSISTENT = "consistent"
DRIFTED = "drifted"
WHOLE_ROBOT = "recalibrate the whole robot"


def sidak(false_alarm: float, n_modules: int) -> float:
    """Per-module false-alarm rate for ``false_alarm`` over ``n_modules`` (Sidak):
    ``1 - (1 - false_alarm)^(1/N)``."""
    if not 0.0 < false_alarm < 1.0 or n_modules < 1:
        raise ValueError("need 0 < false_alarm < 1 and at least one module")
    return float(-math.expm1(math.log1p(-false_alarm) / n_modules))


@functools.lru_cache(maxsize=64)
def thresholds(false_alarm: float, n_modules: int) -> tuple[float, float, float]:
    """``(alpha_m, q, z_m)``: the per-module rate, its chi-square threshold (5 degrees of
    freedom) and the per-parameter two-sided normal threshold (module docstring).  Kept
    per ``(false_alarm, n_modules)``: scipy.stats' quantiles cost 0.1 ms a call, and every
    verdict asks twice."""
    from scipy.stats import chi2, norm  # on first use: scipy.stats costs 0.8 s to import

    alpha_m = sidak(false_alarm, n_modules)
    return (
        alpha_m,
        float(chi2.isf(alpha_m, N_PARAMS)),
        float(norm.isf(alpha_m / (2 * N_PARAMS))),
    )


def in_order(
    params: RobotParams, covariance: Any, ids: list[int]
) -> tuple[FloatArray, FloatArray | None]:
    """``params`` as an (N, 5) matrix in the module order ``ids``, and its (5N, 5N)
    ``covariance`` (None: not stated) permuted alike; a missing module is a
    :class:`~swpc_hw.errors.CalibrationError`."""
    missing = sorted(set(ids) - set(params.ids))
    if missing:
        raise CalibrationError(f"the file has no module {missing[0]} (it has {params.ids})")
    X = np.array([params.module(m).values() for m in ids])
    if covariance is None:
        return X, None
    C = np.asarray(covariance, dtype=float)
    where = [params.index(m) for m in ids]
    idx = np.array([N_PARAMS * i + c for i in where for c in range(N_PARAMS)])
    return X, C[np.ix_(idx, idx)]


def stated_covariance(params: RobotParams, covariance: Any, ids: list[int]) -> FloatArray:
    """The covariance a file states, in the order ``ids``: its ``covariance``, else its
    std devs (no correlation), else zero (the file taken as exact: a check then judges
    its own noise only, and says so, :attr:`CheckVerdict.notes`)."""
    X, C = in_order(params, covariance, ids)
    if C is not None and np.all(np.isfinite(C)):
        return C
    sd = np.zeros_like(X)
    for i, m in enumerate(ids):
        s = params.module(m).stddev
        if s is not None:
            sd[i] = s.values()
    return np.diag(sd.ravel() ** 2)


@dataclass
class ParameterChange:
    """One parameter of one module: the file's value, the check's, the change (SI)."""

    module: int
    param: str
    file: float
    check: float
    change: float
    stddev: float
    """Std dev of the change, ``sqrt(Cov(d)_ii)``."""
    z: float
    drifted: bool
    """Named as a drifted parameter of a drifted module."""

    def row(self) -> dict[str, Any]:
        """In display units (:data:`DISPLAY`)."""
        unit, f = DISPLAY[self.param]
        return {
            "module": self.module,
            "param": self.param,
            "unit": unit,
            "file": self.file * f,
            "check": self.check * f,
            "change": self.change * f,
            "stddev": self.stddev * f,
            "z": self.z,
            "drifted": self.drifted,
        }


@dataclass
class ModuleCheck:
    """One module: its chi-square against the threshold."""

    id: int
    chi2: float
    dof: int
    p_value: float
    drifted: bool
    parameters: list[str]
    """The parameters named as drifted (empty when the module has not)."""


@dataclass
class CheckVerdict:
    """A check's verdict (module docstring)."""

    verdict: str
    """``consistent`` or ``drifted``."""
    action: str
    """``none``, ``recalibrate module k`` (or ``modules j, k``) or ``recalibrate the whole
    robot``."""
    drifted: list[int]
    modules: list[ModuleCheck]
    changes: list[ParameterChange]
    false_alarm: float
    alpha_module: float
    threshold: float
    """The chi-square threshold ``q`` of a module (5 degrees of freedom)."""
    z_threshold: float
    whole_robot: float
    notes: list[str] = field(default_factory=list)

    @property
    def summary(self) -> str:
        """One line for people: the verdict, the action and, per drifted module, its
        parameter that drifted most (in its std devs) and by how much."""
        if self.verdict == CONSISTENT:
            worst = max(self.modules, key=lambda m: m.chi2 / self.threshold)
            return (
                f"consistent: every module matches the file (largest chi2 {worst.chi2:.1f} "
                f"of {self.threshold:.1f}, module {worst.id})"
            )
        parts = []
        for mid in self.drifted:
            named = [c for c in self.changes if c.module == mid and c.drifted]
            c = max(named, key=lambda c: abs(c.z))
            unit, f = DISPLAY[c.param]
            more = f" and {len(named) - 1} more" if len(named) > 1 else ""
            parts.append(
                f"module {mid} {c.param} {c.change * f:+.3f} {unit} ({c.z:+.1f} sd){more}"
            )
        return f"drifted: {self.action} ({'; '.join(parts)})"

    def document(self) -> dict[str, Any]:
        return {
            "verdict": self.verdict,
            "action": self.action,
            "summary": self.summary,
            "drifted_modules": list(self.drifted),
            "false_alarm": self.false_alarm,
            "alpha_module": self.alpha_module,
            "chi2_threshold": self.threshold,
            "z_threshold": self.z_threshold,
            "whole_robot": self.whole_robot,
            "modules": [
                {
                    "id": m.id,
                    "chi2": m.chi2,
                    "dof": m.dof,
                    "p_value": m.p_value,
                    "drifted": m.drifted,
                    "parameters": list(m.parameters),
                }
                for m in self.modules
            ],
            "table": [c.row() for c in self.changes],
            "notes": list(self.notes),
        }


def change_and_covariance(
    check: FloatArray,
    C_check: FloatArray,
    file: FloatArray,
    C_file: FloatArray,
    n: int,
    repeatability: Any = None,
) -> tuple[FloatArray, FloatArray]:
    """``(d (N, 5), Cov(d) (5N, 5N))`` of the module docstring (``beta`` wrapped); a
    covariance that is not finite is a :class:`~swpc_hw.errors.CalibrationError`."""
    if check.shape != (n, N_PARAMS) or file.shape != (n, N_PARAMS):
        raise ValueError(f"estimates must be ({n}, {N_PARAMS})")
    C = np.asarray(C_check, dtype=float) + np.asarray(C_file, dtype=float)
    if repeatability is not None:
        rep = np.asarray(repeatability, dtype=float).reshape(N_PARAMS)
        C = C + np.diag(np.tile(rep**2, n))
    if C.shape != (N_PARAMS * n, N_PARAMS * n) or not np.all(np.isfinite(C)):
        raise CalibrationError(
            "the check's data do not determine every parameter (its covariance is unknown): "
            "a longer check, or one that locks every module, is needed"
        )
    d = check - file
    d[:, BETA] = wrap_angle(d[:, BETA])
    return d, C


def chi2_of(e: FloatArray, Ce: FloatArray, what: str) -> float:
    """``e^T Ce^-1 e``; a ``Ce`` that is not positive definite is a
    :class:`~swpc_hw.errors.CalibrationError` naming ``what``."""
    w, V = np.linalg.eigh(0.5 * (Ce + Ce.T))
    if not w[0] > 1e-12 * max(float(w[-1]), 0.0) or w[-1] <= 0:
        raise CalibrationError(
            f"{what}: the change's covariance is not positive definite (the check does not "
            "determine every parameter of it)"
        )
    a = V.T @ e
    return float(np.sum(a * a / w))


def judged_module(
    mid: int, stat: float, file: FloatArray, change: FloatArray, sd: FloatArray,
    drifted: bool, z_m: float,
) -> tuple[ModuleCheck, list[ParameterChange]]:  # fmt: skip
    """One module's line and table rows: its statistic, the parameters named when it
    drifted (``|z| > z_m``, else the largest), per parameter the file's value, the check's
    (``file + change``), the change, its std dev and z."""
    from scipy.special import chdtrc  # scipy.stats' chi2.sf, without its argument checks

    z = change / sd
    named: list[str] = []
    if drifted:
        named = [p for p, zp in zip(PARAM_NAMES, z, strict=True) if abs(zp) > z_m]
        named = named or [PARAM_NAMES[int(np.argmax(np.abs(z)))]]
    module = ModuleCheck(mid, stat, N_PARAMS, float(chdtrc(N_PARAMS, stat)), drifted, named)
    rows = [
        ParameterChange(
            mid, p, float(file[c]), float(file[c] + change[c]), float(change[c]), float(sd[c]),
            float(z[c]), p in named,
        )
        for c, p in enumerate(PARAM_NAMES)
    ]
    return module, rows


def verdict_of(
    modules: list[ModuleCheck],
    changes: list[ParameterChange],
    false_alarm: float,
    whole_robot: float,
) -> CheckVerdict:
    """The verdict and action from the judged modules (module docstring)."""
    alpha_m, q, z_m = thresholds(false_alarm, len(modules))
    drifted_ids = [m.id for m in modules if m.drifted]
    if not drifted_ids:
        verdict, action = CONSISTENT, "none"
    elif len(drifted_ids) >= whole_robot * len(modules):
        verdict, action = DRIFTED, WHOLE_ROBOT
    else:
        verdict = DRIFTED
        word = "module" if len(drifted_ids) == 1 else "modules"
        action = f"recalibrate {word} {', '.join(map(str, drifted_ids))}"
    return CheckVerdict(
        verdict, action, drifted_ids, modules, changes, false_alarm, alpha_m, q, z_m, whole_robot
    )


def compare(
    check: FloatArray,
    C_check: FloatArray,
    file: FloatArray,
    C_file: FloatArray,
    ids: list[int],
    *,
    false_alarm: float = 0.05,
    whole_robot: float = 0.5,
    repeatability: Any = None,
) -> CheckVerdict:
    """The check's verdict (module docstring) from the (N, 5) estimates ``check`` and
    ``file`` (modules in the order ``ids``, SI), their (5N, 5N) covariances and the
    ``repeatability`` std devs (5,) of ``x_s, y_s, beta, b, r`` (None: zero).

    A covariance that is not finite, or a module whose ``Cov(d)`` block is not positive
    definite, is a :class:`~swpc_hw.errors.CalibrationError`: the check cannot judge."""
    n = len(ids)
    d, C = change_and_covariance(check, C_check, file, C_file, n, repeatability)
    _, q, z_m = thresholds(false_alarm, n)
    modules: list[ModuleCheck] = []
    changes: list[ParameterChange] = []
    for i, mid in enumerate(ids):
        sl = slice(N_PARAMS * i, N_PARAMS * (i + 1))
        stat = chi2_of(d[i], C[sl, sl], f"module {mid}")
        sd = np.sqrt(np.diag(C[sl, sl]))
        module, rows = judged_module(mid, stat, file[i], d[i], sd, stat > q, z_m)
        modules.append(module)
        changes += rows
    return verdict_of(modules, changes, false_alarm, whole_robot)


def check_estimates(
    check: RobotParams,
    C_check: FloatArray | None,
    file: RobotParams,
    file_covariance: Any,
    *,
    false_alarm: float = 0.05,
    whole_robot: float = 0.5,
    repeatability: Any = None,
) -> CheckVerdict:
    """:func:`compare` of a check's parameters against a file's, after the gauge checks:
    the same robot frame (a file in another frame, e.g. ``design-fit``, cannot be compared
    with a check in R) and the same modules.  The file's covariance as it states it
    (:func:`stated_covariance`)."""
    if check.frame != file.frame:
        raise CalibrationError(
            f"the file is in frame {file.frame!r}, the check in {check.frame!r}: parameters "
            "in two frames cannot be compared (a calibration with motion capture makes a "
            "file in R)"
        )
    ids = check.ids
    X_check, _ = in_order(check, None, ids)
    X_file, _ = in_order(file, None, ids)
    C_f = stated_covariance(file, file_covariance, ids)
    C_c = (
        np.full((N_PARAMS * len(ids),) * 2, np.nan)
        if C_check is None
        else np.asarray(C_check, dtype=float)
    )
    out = compare(
        X_check, C_c, X_file, C_f, ids,
        false_alarm=false_alarm, whole_robot=whole_robot, repeatability=repeatability,
    )  # fmt: skip
    out.notes += file_notes(file, file_covariance, ids)
    return out


def file_notes(file: RobotParams, file_covariance: Any, ids: list[int]) -> list[str]:
    """What a verdict says of the file's uncertainty when it states no covariance."""
    if file_covariance is not None:
        return []
    stated = all(file.module(m).stddev is not None for m in ids)
    return [
        "The file states std devs but no covariance: its parameters are taken as "
        "uncorrelated."
        if stated
        else "The file states no uncertainty: it is taken as exact (only the check's "
        "noise and the repeatability are judged)."
    ]
