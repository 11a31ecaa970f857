"""Planar rigid transforms between frames of calibrated parameters (pure functions).

A kinematic file's parameters are expressed in a frame (``frame:``).  Without motion
capture there is no tracked body to define R, and a calibration is expressed in the
``design-fit`` frame: the planar rigid transform (rotation ``phi`` and translation ``t``,
no scaling) that best aligns the calibrated steering axes ``P_s,i`` with the nominal ones
``P_nom,i`` in the least-squares sense::

    (phi, t) = argmin sum_i |R(phi) P_s,i + t - P_nom,i|^2

Two calibrations of one robot in different frames are compared the same way: the
transform that aligns one file's ``P_s`` with the other's (a 2-D Procrustes without
scaling) re-expresses the first in the frame of the second.

Re-expressing parameters in a frame rotated by ``phi`` and shifted by ``t``::

    P_s' = R(phi) P_s + t,   beta' = beta + phi,   b' = b,   r' = r

(a direction ``u(theta_hat + beta)`` of the old frame is ``u(theta_hat + beta + phi)`` in
the new one).

**base_link**, the frame a ROS 2 robot's description and controllers use, is given by the
robot config (:class:`BaseLinkPose`, or the rule ``centroid``; docs/ros2.md): with
base_link's pose ``(x, y, yaw)`` in R, a point ``P`` of R is ``R(-yaw) (P - (x, y))`` in
base_link, i.e. ``phi = -yaw`` and ``t = -R(-yaw) (x, y)`` above.  ``centroid`` puts
base_link's origin at the centroid ``c = (1/N) sum_i P_s,i`` of the calibrated steering
axes, its x axis along R's: ``phi = 0``, ``t = -c``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict

from swpc_hw.robot.model import PARAM_NAMES, Finite, RobotParams, rot, wrap_angle

FloatArray = NDArray[np.float64]

DESIGN_FIT = "design-fit"
"""The ``frame:`` of a calibration aligned to its nominal robot (no motion capture)."""
FILE_FIT = "file-fit"
"""The ``frame:`` of a check without motion capture: fitted to the file it checks (its
steering axes' centroid, rotation and length scale, its radii's sum), docs/check.md."""


def design_fit_transform(P_s_from: ArrayLike, P_s_to: ArrayLike) -> tuple[float, FloatArray]:
    """Least-squares planar rigid transform taking the points ``P_s_from`` onto ``P_s_to``.

    With the centroids ``c_f``, ``c_t`` and the centred points ``a_i = P_from,i - c_f``,
    ``d_i = P_to,i - c_t``::

        phi = atan2(sum_i a_i x d_i, sum_i a_i . d_i),    t = c_t - R(phi) c_f

    minimises ``sum_i |R(phi) P_from,i + t - P_to,i|^2`` (2-D Procrustes, no scaling).
    ``P_s_from``, ``P_s_to``: (N, 2), N >= 2.  Returns ``(phi, t)``.
    """
    A = np.asarray(P_s_from, dtype=float).reshape(-1, 2)
    D = np.asarray(P_s_to, dtype=float).reshape(-1, 2)
    if A.shape != D.shape or A.shape[0] < 2:
        raise ValueError(
            f"design_fit_transform: need two (N, 2) arrays, N >= 2 ({A.shape}, {D.shape})"
        )
    c_f, c_t = A.mean(axis=0), D.mean(axis=0)
    a, d = A - c_f, D - c_t
    cross = float(np.sum(a[:, 0] * d[:, 1] - a[:, 1] * d[:, 0]))
    dot = float(np.sum(a * d))
    phi = math.atan2(cross, dot)
    t = c_t - rot(phi) @ c_f
    return phi, np.asarray(t, dtype=float)


def transform_points(P: ArrayLike, phi: float, t: ArrayLike) -> FloatArray:
    """``R(phi) P + t`` for points ``P`` (..., 2)."""
    return np.asarray(
        np.einsum("ij,...j->...i", rot(phi), np.asarray(P, dtype=float)) + np.asarray(t),
        dtype=float,
    )


def transform_parameters(X: ArrayLike, phi: float, t: ArrayLike) -> FloatArray:
    """Re-express (N, 5) parameters ``x_s, y_s, beta, b, r`` in a frame rotated by ``phi``
    and shifted by ``t``: ``P_s' = R(phi) P_s + t``, ``beta' = wrap(beta + phi)``."""
    Y = np.array(X, dtype=float, copy=True).reshape(-1, 5)
    Y[:, 0:2] = transform_points(Y[:, 0:2], phi, t)
    Y[:, 2] = wrap_angle(Y[:, 2] + phi)
    return Y


def transform_covariance(
    cov: ArrayLike, phi: float, t_jacobian: ArrayLike | None = None
) -> FloatArray:
    """The (5N, 5N) covariance of parameters re-expressed by :func:`transform_parameters`:
    ``T C T^T`` with ``T`` the Jacobian of the re-expression.

    For a *fixed* transform ``T`` is block-diagonal, ``R(phi)`` on every module's
    ``(x_s, y_s)`` and 1 elsewhere.  A translation ``t`` that is itself a function of the
    steering axes (``t_jacobian``: ``d t / d P_s``, (2, 2N), ``P_s`` flattened as
    ``(x_1, y_1, x_2, ...)``; e.g. ``-I/N`` per module for the centroid) adds
    ``d P_s,j' / d P_s,i = d t / d P_s,i`` to every module ``j``'s rows: the uncertainty
    of the frame itself.
    """
    C = np.asarray(cov, dtype=float)
    n = C.shape[0] // 5
    T = np.eye(C.shape[0])
    R = rot(phi)
    for i in range(n):
        T[5 * i : 5 * i + 2, 5 * i : 5 * i + 2] = R
    if t_jacobian is not None:
        G = np.asarray(t_jacobian, dtype=float).reshape(2, 2 * n)
        for j in range(n):
            for i in range(n):
                T[5 * j : 5 * j + 2, 5 * i : 5 * i + 2] += G[:, 2 * i : 2 * i + 2]
    return np.asarray(T @ C @ T.T, dtype=float)


def transform_robot(params: RobotParams, phi: float, t: ArrayLike, frame: str) -> RobotParams:
    """``params`` re-expressed in the frame named ``frame`` (:func:`transform_parameters`).

    Standard deviations are dropped: rotating ``x_s``, ``y_s`` mixes their variances with
    their covariance, which a module's ``stddev`` does not hold; re-express the full
    covariance with :func:`transform_covariance` instead.
    """
    a = params.arrays()
    Y = transform_parameters(a.matrix(), phi, t)
    return RobotParams.from_matrix(a.ids, Y, robot=params.robot, frame=frame)


FRAME_FREE = frozenset({"b", "r"})
"""Parameters the same in every frame of R's rigid motions (``x_s``, ``y_s`` and ``beta``
move with the frame)."""


def frame_of_metrology(metrology: str | None) -> str:
    """The frame a calibration's result is in: design-fit without motion capture
    (metrology ``imu``: its frame R is not known), else R (the motion capture's body)."""
    return DESIGN_FIT if metrology == "imu" else "R"


def params_in_design_fit(
    params: RobotParams, nominal: RobotParams
) -> tuple[RobotParams, float, FloatArray]:
    """``params`` (with their std devs) re-expressed in the design-fit frame
    (:func:`design_fit_transform` of their steering axes onto the nominal ones, over the
    modules both have), and that transform ``(phi, t)``.  Std devs: ``beta``, ``b``, ``r``
    as they are (a rotation leaves them), ``x_s`` and ``y_s`` the larger of the two (a
    rotated coordinate's std dev is near it for the small angles of a fit)."""
    ids = [m for m in params.ids if m in nominal.ids]
    P = np.array([[params.module(m).x_s, params.module(m).y_s] for m in ids])
    Q = np.array([[nominal.module(m).x_s, nominal.module(m).y_s] for m in ids])
    phi, t = design_fit_transform(P, Q)
    moved = transform_robot(params, phi, t, DESIGN_FIT)
    mods = []
    for m, old in zip(moved.modules, params.modules, strict=True):
        sd = old.stddev
        if sd is not None:
            s = max(sd.x_s, sd.y_s)
            m = m.model_copy(update={"stddev": sd.model_copy(update={"x_s": s, "y_s": s})})
        mods.append(m)
    return moved.model_copy(update={"modules": mods}), phi, t


def design_fit_constraints(P_s: ArrayLike, P_nom: ArrayLike) -> FloatArray:
    """The three gauge conditions of the design-fit frame, zero when it holds::

        centroid(P_s) - centroid(P_nom)                      (2)
        sum_i (P_nom,i - c_nom) x (P_s,i - c_s)              (1)

    The second is the cross term of :func:`design_fit_transform` from ``P_s`` to
    ``P_nom`` (with the opposite sign): zero exactly when the best-fit rotation between
    the two point sets is 0.  Together, ``design_fit_transform(P_s, P_nom)`` is the
    identity.  Returns (3,): m, m, m^2.
    """
    P = np.asarray(P_s, dtype=float).reshape(-1, 2)
    Q = np.asarray(P_nom, dtype=float).reshape(-1, 2)
    c_s, c_n = P.mean(axis=0), Q.mean(axis=0)
    a, d = Q - c_n, P - c_s
    cross = float(np.sum(a[:, 0] * d[:, 1] - a[:, 1] * d[:, 0]))
    return np.array([c_s[0] - c_n[0], c_s[1] - c_n[1], cross])


def design_fit_constraint_jacobian(P_nom: ArrayLike) -> FloatArray:
    """Jacobian (3, 2N) of :func:`design_fit_constraints` with respect to ``P_s`` flattened
    as ``(x_1, y_1, x_2, ...)``; constant (the conditions are linear in ``P_s``):
    ``d c_s / d P_s,i = I / N`` and, since ``sum_i a_i = 0``, the rotation row is
    ``(-a_i,y, a_i,x)`` for module i."""
    Q = np.asarray(P_nom, dtype=float).reshape(-1, 2)
    n = Q.shape[0]
    a = Q - Q.mean(axis=0)
    A = np.zeros((3, 2 * n))
    A[0, 0::2] = 1.0 / n
    A[1, 1::2] = 1.0 / n
    A[2, 0::2] = -a[:, 1]
    A[2, 1::2] = a[:, 0]
    return A


BASE_LINK = "base_link"
"""The ``frame:`` of parameters re-expressed in the robot's base_link (docs/ros2.md)."""

CENTROID = "centroid"
"""The base_link rule: origin at the centroid of the calibrated steering axes, x along R's."""


class BaseLinkPose(BaseModel):
    """base_link's planar pose in R: its origin at ``(x, y)`` of R (m), its x axis at
    ``yaw`` (rad) from R's, counter-clockwise positive (the static transform whose parent
    is R and whose child is base_link)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    x: Finite = 0.0
    y: Finite = 0.0
    yaw: Finite = 0.0


BaseLink = BaseLinkPose | Literal["centroid"]
"""The robot config's ``base_link``: a pose in R or the rule ``centroid``."""

FRAMES_OF_R = ("R", DESIGN_FIT)
"""Frames that stand for R when re-expressed in base_link: R itself and design-fit (the
nominal robot's R, best aligned with the calibrated steering axes)."""


def base_link_transform(
    P_s: ArrayLike, base_link: BaseLink | None
) -> tuple[float, FloatArray, FloatArray | None]:
    """``(phi, t, d t / d P_s)`` taking points of R to base_link (module docstring).

    ``None`` is base_link = R (the identity).  ``d t / d P_s`` is (2, 2N) for
    ``centroid`` (``-I/N`` per module) and None for a fixed pose.
    """
    P = np.asarray(P_s, dtype=float).reshape(-1, 2)
    n = P.shape[0]
    if base_link is None:
        return 0.0, np.zeros(2), None
    if base_link == CENTROID:
        G = np.zeros((2, 2 * n))
        G[0, 0::2] = -1.0 / n
        G[1, 1::2] = -1.0 / n
        return 0.0, -P.mean(axis=0), G
    assert isinstance(base_link, BaseLinkPose)
    phi = -base_link.yaw
    t = -(rot(phi) @ np.array([base_link.x, base_link.y]))
    return phi, np.asarray(t, dtype=float), None


def to_base_link(
    params: RobotParams, covariance: ArrayLike | None, base_link: BaseLink | None
) -> tuple[RobotParams, FloatArray | None]:
    """``params`` (frame R or design-fit) and their (5N, 5N) covariance re-expressed in
    base_link (:func:`base_link_transform`, :func:`transform_covariance`).

    Standard deviations: the square roots of the new covariance's diagonal when it is
    known; without it a module's ``stddev`` is kept when base_link is R shifted by a fixed
    translation (unchanged by it) and dropped otherwise (a rotation or the centroid mixes
    parameters whose covariance the file does not hold).  Raises ``ValueError`` for a file
    in another frame.
    """
    if params.frame == BASE_LINK:
        cov = None if covariance is None else np.asarray(covariance, dtype=float)
        return params, cov
    if params.frame not in FRAMES_OF_R:
        raise ValueError(
            f"frame {params.frame!r}: the robot config gives base_link in R; a file in "
            f"{', '.join(FRAMES_OF_R)} or {BASE_LINK} can be exported"
        )
    if base_link is None:  # the identity: the values as they are, to the bit
        cov = None if covariance is None else np.asarray(covariance, dtype=float)
        return params.model_copy(update={"frame": BASE_LINK}), cov
    a = params.arrays()
    phi, t, G = base_link_transform(a.P_s, base_link)
    moved = transform_robot(params, phi, t, BASE_LINK)
    if covariance is not None:
        cov = transform_covariance(covariance, phi, G)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None)).reshape(-1, len(PARAM_NAMES))
        if any(m.stddev is None for m in params.modules):
            return moved, cov
        b = moved.arrays()
        return RobotParams.from_arrays(
            b.ids, b.P_s, b.beta, b.b, b.r, robot=params.robot, frame=BASE_LINK, stddev=sd
        ), cov
    if phi == 0.0 and G is None:  # a fixed translation: every module keeps its stddev
        modules = [
            m.model_copy(update={"stddev": old.stddev})
            for m, old in zip(moved.modules, params.modules, strict=True)
        ]
        return moved.model_copy(update={"modules": modules}), None
    return moved, None
