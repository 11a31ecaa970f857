"""The IMU least-squares problem: encoders, gyro and references, no poses.

Unknowns ``x = [X (N, 5) row by row, s, b_1 .. b_K, da_1 .. da_S]`` (:class:`ImuLayout`):
every module's ``x_s, y_s, beta, b, r``, the gyro's scale ``s = 1 + eps``, its bias at the
``K`` rest windows (:mod:`.bias`) and the reading error of every segment's locked
steering.  For every segment (a spin about the locked module k at reported steering
``a``, read with the error ``da``) the contact point is
``C = P_s,k + b_k u(a + da + beta_k)``.  Blocks of weighted residuals (names as in
:data:`BLOCKS`):

``settled``
    ``((P_s,j - C) . u(theta_hat_j + beta_j) + b_j) / sigma`` per segment and free caster
    (:func:`.geometry.settled_residual`), as with motion capture.
``spin``
    The wheels of one segment at its nodes ``t_l``: ``psi_jl = psi_j(t_l)`` rolls as
    ``psi_jl = c_j + (g_j / r_j) Y_l`` (``r dpsi = g dyaw``) with the lever of a settled
    caster
    ``g_j = (P_w,j - C) x u(theta_j) = -sign(omega) D_j``,
    ``D_j = sqrt(|P_s,j - C|^2 - b_j^2)`` (the settled right angle at ``P_w``: the
    paper's distance), and the yaw ``Y_l``, common to the modules.  The lever is the
    geometry's, not the reported steering's: a steering reading carries a quantization
    error that is constant over the segment, which the wheels' precise ratios would
    otherwise take for a lever (``dg = -b dtheta``).  ``Y_l`` and the constants ``c``
    (one per clean run of a wheel) are profiled out (:func:`profiled_rolling`): what is
    left is the part of every node's vector ``psi_l - c`` across ``g / r``, white encoder
    noise.  Neither the gyro nor its noise enters: these residuals hold the ratios
    ``r_j / g_j``.  In wheel angles (rad), not distances ``r psi``: scaling the radii or
    the layout then leaves them unchanged (in distances a smaller ``r`` shrinks every
    residual, a pull on the radii that cost a quarter of the straight drive's std dev).
``gyro``
    Per straight drive, the wheels' turn ``kappa (Y_end - Y_start)`` against the gyro's
    (``drive``).  Per chunk of connected nodes ``[l_a, l_b]`` of a segment: the yaw the
    wheels turned, ``Y_lb - Y_la``, against the gyro's::

        (int_{t_la}^{t_lb} wz dt - sum_i b_i int phi_i dt) / s

    with the std dev of the integrated white noise, the bias walk about the knots'
    line (:mod:`.bias`) and the wheels' own (the sum of the chunk's yaw increments: the
    gyro's noise telescopes into one term per chunk, shared by all its modules).
``rest``
    ``(mean wz of rest window i - b_i) / sigma_i``: the bias knots' observations.
``locked_angle``
    ``da_s / sigma_a``: the locked steering's reading error, a quantization of std dev
    ``sigma_a`` (it moves the contact point by ``b_k da``).
``drive``
    The straight drive's wheels as ``spin``, with the lever of a translation along the
    mean wheel direction ``phi``: ``g_j = cos(theta_j - phi)``, ``Y_l`` the distance; and
    its turn: wheels held at fixed angles a little apart (homing errors) move the robot on
    an arc, ``dyaw = kappa dY``, to first order in the turn::

        r_j dpsi_j = cos(theta_j - phi) dY + (P_s,j x u(theta_j)) dyaw
                   = (cos(theta_j - phi) + kappa P_s,j x u(theta_j)) dY

    (``P_w,j x u = P_s,j x u``): one lever per wheel still, the curvature ``kappa``
    profiled out with ``Y`` and ``c`` (:func:`arc_profile`), the gyro's turn over the
    drive its one observation in the ``gyro`` block (node by node the gyro's noise would
    blur the wheels' ratios).
``axis_distance``, ``wheel_radius``, ``straight_drive``
    ``(|P_s,a - P_s,b| - value) / stddev``, ``(r_m - value) / stddev`` and
    ``(|Y_end - Y_start| |1 + kappa P_s,1 x u(phi)| - value) / stddev`` of the drive: the
    distance the first module's steering axis travelled (``Y`` is R's origin's; the
    turn ``dyaw`` over the drive moves the axis by ``dyaw z x P_s,1`` more).
``gauge``
    The design-fit conditions (:func:`swpc_hw.robot.frames.design_fit_constraints`): the data
    do not see a planar rigid motion of the frame, these three residuals fix it (at the
    optimum they are exactly zero, whatever their weight).  A check without references
    (:func:`swpc_hw.calibration.gyro.solver.solve_imu_check`) fits to the file's layout
    (``P_nom`` the file's axes) and fixes the two scales the data do not see either
    (``scale_ref``)::

        sum_i a_i . (P_s,i - c_s) - sum_i |a_i|^2      (the layout's length scale, m^2)
        sum_i r_i - sum_i r_ref,i                     (the radii's common scale, m)

    with ``a_i = P_nom,i - c_nom``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from swpc_hw.calibration import geometry as geo
from swpc_hw.calibration.gyro.rolling_sets import (
    RollingSet,
    RollingStack,
    arc_profile,
    drive_structure,
    profiled_rolling,
    stack_sets,
)
from swpc_hw.calibration.parameters import BETA, N_PARAMS, P_S, R
from swpc_hw.calibration.parameters import B as B_COL
from swpc_hw.calibration.problem import SettledObservations
from swpc_hw.files.references import AxisDistance, StraightDrive, WheelRadius
from swpc_hw.robot.model import contact_point

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

BLOCKS = (
    "settled", "spin", "gyro", "rest", "locked_angle", "drive",
    "axis_distance", "wheel_radius", "straight_drive", "gauge",
)
"""Residual blocks, in the order of :meth:`ImuProblem.residuals`."""
Rolling = Callable[
    [FloatArray, FloatArray, FloatArray, FloatArray],
    tuple[FloatArray, FloatArray, FloatArray, FloatArray],
]
"""What profiles the wheels from their levers (:meth:`ImuProblem.rolling`)."""
GAUGE_SCALE = 1e-4
"""The gauge residuals' unit (m, m, m^2): weights near the data's, for the solver's steps."""


@dataclass(frozen=True)
class ImuLayout:
    """Where the unknowns sit in the flat vector: ``5N`` module parameters, the gyro
    scale ``s``, ``K`` bias knots, ``S`` locked-angle reading errors."""

    n: int
    n_knots: int
    n_segments: int

    @property
    def size(self) -> int:
        return N_PARAMS * self.n + 1 + self.n_knots + self.n_segments

    @property
    def scale(self) -> int:
        """Index of the gyro scale ``s``."""
        return N_PARAMS * self.n

    @property
    def knots(self) -> slice:
        return slice(N_PARAMS * self.n + 1, N_PARAMS * self.n + 1 + self.n_knots)

    @property
    def angles(self) -> slice:
        return slice(self.size - self.n_segments, self.size)

    def split(self, x: FloatArray) -> tuple[FloatArray, float, FloatArray]:
        """``(X (N, 5), s, knots (K,))``."""
        return (
            x[: N_PARAMS * self.n].reshape(self.n, N_PARAMS),
            float(x[self.scale]),
            x[self.knots],
        )


@dataclass
class ImuProblem:
    """All observations of an IMU run; weighted residuals of the active blocks."""

    layout: ImuLayout
    settled: SettledObservations
    seg_static: IntArray
    seg_angle: FloatArray
    seg_sign: FloatArray
    angle_sigma: float
    spins: list[RollingSet]
    drives: list[RollingSet]
    knot_mean: FloatArray
    knot_sigma: FloatArray
    refs: list[AxisDistance | WheelRadius | StraightDrive]
    ids: list[int]
    P_nom: FloatArray
    active: frozenset[str] = frozenset(BLOCKS)
    _stack: RollingStack | None = field(default=None, repr=False)
    scale_ref: FloatArray | None = None
    """A check's reference radii (N,): the two scale conditions join the gauge (module
    docstring); None for a calibration (its references fix the scales)."""
    _rolled: (
        tuple[RollingStack, frozenset[str], tuple[FloatArray, ...], tuple[FloatArray, ...]]
        | None
    ) = field(default=None, repr=False)
    """The last single point :meth:`rolling` profiled: its inputs (the stack with them)
    and its outputs (the solver's Jacobian comes at the point of its last residuals)."""

    def stack(self) -> RollingStack:
        """The rolling sets stacked (built at first use; :meth:`restack` after changing a
        set's runs, noise scale or chunks)."""
        if self._stack is None:
            self._stack = stack_sets(self.spins, self.drives, self.layout.n_knots)
        return self._stack

    def restack(self) -> None:
        self._stack = None

    def contact_points(self, x: FloatArray) -> FloatArray:
        """``C_s = P_s,k + b_k u(a_s + da_s + beta_k)`` of every segment, (S, 2)."""
        X = self.layout.split(x)[0]
        k = self.seg_static
        a = self.seg_angle + x[self.layout.angles]
        return contact_point(X[k, P_S], X[k, B_COL], a + X[k, BETA])

    def spin_levers(self, X: FloatArray, C: FloatArray, rs: RollingSet, seg: int) -> FloatArray:
        """``g_j = -sign(omega_s) D_j`` of a segment's modules (m, :func:`settled_lever`)."""
        return geo.settled_lever(X[rs.mods, P_S], X[rs.mods, B_COL], C[seg], self.seg_sign[seg])

    @staticmethod
    def drive_levers(X: FloatArray, rs: RollingSet) -> FloatArray:
        """``cos(theta_j - phi)``, ``phi`` the direction of ``sum_j u(theta_j)``."""
        th = rs.theta + X[rs.mods, BETA]
        phi = math.atan2(float(np.sin(th).sum()), float(np.cos(th).sum()))
        return np.asarray(np.cos(th - phi), dtype=float)

    def drive_arc(
        self, x: FloatArray, rs: RollingSet
    ) -> tuple[FloatArray, FloatArray, float, float]:
        """A drive on its arc (:func:`arc_profile`): ``(levers g + kappa k (m,), residuals
        (L, m) rad, kappa (1/m), the wheels' turn kappa (Y_end - Y_start) (rad))``."""
        X = self.layout.split(x)[0]
        g = self.drive_levers(X, rs)
        th = rs.theta + X[rs.mods, BETA]
        k = X[rs.mods, 0] * np.sin(th) - X[rs.mods, 1] * np.cos(th)
        r = X[rs.mods, R]
        st = drive_structure(rs)
        e0, y0 = profiled_rolling(rs.psi, g / r, rs.present, rs.run, st)
        sigma_g = float(rs.gyro_sigma[0]) if rs.gyro_sigma.size else 1.0
        e, y, kappa, _ = arc_profile(
            rs.psi, g[None], k[None], r[None], rs.present, rs.run, st, e0[None], y0[None],
            rs.sigma, np.array([self.drive_turn(x, rs)]), sigma_g,
        )
        kap = float(kappa[0])
        return g + kap * k, e[0], kap, kap * float(y[0, -1] - y[0, 0])

    def drive_turn(self, x: FloatArray, rs: RollingSet) -> float:
        """The gyro's turn (rad) over a drive, first node to last."""
        _, s, knots = self.layout.split(x)
        L = rs.t.size - 1
        return float(rs.gyro_yaw(s, knots, np.array([0]), np.array([L]))[0])

    def rolled(self, X: FloatArray, rs: RollingSet, g: FloatArray) -> tuple[FloatArray, FloatArray]:
        """:func:`profiled_rolling` of ``psi`` with the levers ``g / r``: ``(residual (L, m)
        in rad, Y (L,))``."""
        return profiled_rolling(rs.psi, g / X[rs.mods, R], rs.present, rs.run)

    def unpack(
        self, xb: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """A batch ``xb`` (B, p) as ``X`` (B, N, 5), ``s`` (B,), the knots (B, K), the angle
        errors (B, S) and every segment's contact point ``C`` (B, S, 2)."""
        n, Bn = self.layout.n, xb.shape[0]
        X = xb[:, : N_PARAMS * n].reshape(Bn, n, N_PARAMS)
        s = xb[:, self.layout.scale]
        knots = xb[:, self.layout.knots]
        k = self.seg_static
        da = xb[:, self.layout.angles]
        C = contact_point(X[:, k, P_S], X[:, k, B_COL], self.seg_angle + da + X[:, k, BETA])
        return X, s, knots, da, C

    def levers(
        self, X: FloatArray, s: FloatArray, knots: FloatArray, C: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """What the rolling sets' wheels depend on (a batch, :meth:`unpack`): the levers
        ``g`` (B, sets, m) (:func:`settled_lever` for a spin, ``cos(theta_j - phi)`` for a
        drive), the drives' turn levers ``k = P_s,j x u(theta_j)`` (0 for a spin), the radii
        ``r`` (B, sets, m), the gyro's turn over every drive ``gamma`` (B, D) and the first
        axis' lever ``P_s,1 x u(phi)`` of every drive (B, D)."""
        st = self.stack()
        Bn = X.shape[0]
        n_sets, S = len(st.set_mods), st.n_spin
        G = np.zeros((Bn, n_sets, st.set_mods.shape[1]))
        if S:
            jm = st.set_mods[:S]
            G[:, :S] = geo.settled_lever(
                X[:, jm, P_S], X[:, jm, B_COL], C[:, :, None, :], self.seg_sign[:, None]
            )
        K = np.zeros_like(G)
        lever1 = np.zeros((Bn, n_sets - S))
        for d in range(S, n_sets):  # a translation along the mean wheel direction
            jm, mask = st.set_mods[d], st.set_mask[d]
            th = st.set_theta[d] + X[:, jm, BETA]
            phi = np.arctan2(np.sin(th[:, mask]).sum(axis=-1), np.cos(th[:, mask]).sum(axis=-1))
            G[:, d] = np.where(mask, np.cos(th - phi[:, None]), 0.0)
            # ... on an arc: the turn's lever P_s,j x u_j, and the first axis' P_s,1 x u_phi
            K[:, d] = np.where(mask, X[:, jm, 0] * np.sin(th) - X[:, jm, 1] * np.cos(th), 0.0)
            p1 = X[:, 0, P_S]
            lever1[:, d - S] = p1[:, 0] * np.sin(phi) - p1[:, 1] * np.cos(phi)
        r_set = X[:, st.set_mods, R]
        gamma = np.zeros((Bn, n_sets - S))
        for d in range(S, n_sets):  # the gyro's turn over every drive
            a0, a1 = int(st.set_first[d]), int(st.set_last[d])
            gamma[:, d - S] = (
                (st.I_wz[a1] - st.I_wz[a0]) - knots @ (st.W_bias[a1] - st.W_bias[a0])
            ) / s
        return G, K, r_set, gamma, lever1

    def drive_gyro_sigma(self, d: int) -> float:
        """The std dev (rad) of the gyro's turn over drive ``d`` (infinite without the
        ``gyro`` block: the drive's wheels alone)."""
        return float(self.stack().drive_gyro_sigma[d]) if "gyro" in self.active else math.inf

    def rolling(
        self, G: FloatArray, K: FloatArray, r_set: FloatArray, gamma: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        """Every rolling set's wheels profiled from their levers (:meth:`levers`, a batch
        B): the spins' by :func:`profiled_rolling` with ``h = g / r``, the drives' on their
        arcs (:func:`arc_profile`).  Returns the residuals (B, L, m) in rad, ``Y`` (B, L),
        every drive's weighted turn residual (B, D) and its wheels' turn ``kappa (Y_end -
        Y_start)`` (B, D)."""
        st = self.stack()
        Bn = G.shape[0]
        if Bn == 1 and self._rolled is not None:
            stack, active, inputs, out = self._rolled
            if stack is st and active == self.active and all(
                np.array_equal(a, b) for a, b in zip(inputs, (G, K, r_set, gamma), strict=True)
            ):
                return out[0].copy(), out[1].copy(), out[2].copy(), out[3].copy()
        n_sets, S = len(st.set_mods), st.n_spin
        H = G / r_set
        resid, Y = profiled_rolling(st.psi, H[:, st.row_set], st.present, st.run, st.structure)
        turn_res = np.zeros((Bn, n_sets - S))
        arc_turn = np.zeros((Bn, n_sets - S))
        for d in range(S, n_sets):
            rows = slice(int(st.set_first[d]), int(st.set_last[d]) + 1)
            e, y, kappa, turn_res[:, d - S] = arc_profile(
                st.psi[rows], G[:, d], K[:, d], r_set[:, d], st.present[rows],
                st.run[rows], st.drive_structures[d - S], resid[:, rows], Y[:, rows],
                float(st.row_sigma[rows.start]), gamma[:, d - S], self.drive_gyro_sigma(d - S),
            )
            resid[:, rows], Y[:, rows] = e, y
            arc_turn[:, d - S] = kappa * (y[:, -1] - y[:, 0])
        if Bn == 1:
            self._rolled = (
                st, self.active, (G.copy(), K.copy(), r_set.copy(), gamma.copy()),
                (resid.copy(), Y.copy(), turn_res.copy(), arc_turn.copy()),
            )
        return resid, Y, turn_res, arc_turn

    def linear_rolling(self, x: FloatArray, rel_step: float = 1e-7) -> Rolling:
        """:meth:`rolling` to first order about ``x``, for :meth:`jacobian`.

        A spin's wheels depend on the unknowns only through their ``m`` levers
        ``h_j = g_j / r_j``; a drive's through ``g_j / r_j``, ``k_j / r_j`` and ``gamma``
        (:func:`arc_profile`); the sets share nothing.  The derivatives in those few
        values are central differences (step ``rel_step max(1, |v|)``), every spin's
        ``h_j`` at once; the unknowns' then follow by the chain rule::

            d resid / d x_i = sum_v (d resid / d v) (d v / d x_i)

        (``d v / d x_i`` is :meth:`jacobian`'s difference of the levers: ``2 m`` profiles
        of the spins and ``2 (2 m + 1)`` of a drive instead of two per unknown)."""
        st = self.stack()
        n_sets, S = len(st.set_mods), st.n_spin
        X, s, knots, _, C = self.unpack(np.atleast_2d(x))
        G0, K0, r0, gamma0, _ = self.levers(X, s, knots, C)
        resid0, Y0, turn0, arc0 = self.rolling(G0, K0, r0, gamma0)
        H0 = (G0 / r0)[0]
        sp = slice(0, int(np.sum(st.spin_rows)))  # the spins' rows come first
        sp_set = st.row_set[sp]
        cols = [j for j in range(H0.shape[1]) if S and bool(st.set_mask[:S, j].any())]
        nj = len(cols)
        if nj:
            hs = rel_step * np.maximum(1.0, np.abs(H0[:S][:, cols]))  # (S, nj)
            Hb = np.repeat(H0[None], 2 * nj, axis=0)
            for i, j in enumerate(cols):
                Hb[i, :S, j] += hs[:, i]
                Hb[nj + i, :S, j] -= hs[:, i]
            rb, yb = profiled_rolling(
                st.psi[sp], Hb[:, sp_set], st.present[sp], st.run[sp], st.spin_structure
            )
            step = 2.0 * hs[sp_set].T  # (nj, rows)
            d_res = (rb[:nj] - rb[nj:]) / step[..., None]
            d_y = (yb[:nj] - yb[nj:]) / step
        drives = []
        for d in range(S, n_sets):
            rows = slice(int(st.set_first[d]), int(st.set_last[d]) + 1)
            mask = st.set_mask[d]
            w = int(mask.sum())
            v0 = np.concatenate([H0[d, mask], (K0 / r0)[0, d, mask], gamma0[0, d - S : d - S + 1]])
            nv = v0.size
            hv = rel_step * np.maximum(1.0, np.abs(v0))
            V = np.repeat(v0[None], 2 * nv, axis=0)
            V[np.arange(nv), np.arange(nv)] += hv
            V[nv + np.arange(nv), np.arange(nv)] -= hv
            A, Q = np.zeros((2 * nv, mask.size)), np.zeros((2 * nv, mask.size))
            A[:, mask], Q[:, mask] = V[:, :w], V[:, w : 2 * w]
            ds = st.drive_structures[d - S]
            z, pres, run = st.psi[rows], st.present[rows], st.run[rows]
            e0, y0 = profiled_rolling(z, A[:, None, :], pres, run, ds)
            e, y, kappa, turn = arc_profile(
                z, A, Q, np.ones_like(A), pres, run, ds, e0, y0, float(st.row_sigma[rows.start]),
                V[:, -1], self.drive_gyro_sigma(d - S),
            )
            arc = kappa * (y[:, -1] - y[:, 0])
            dv = 2.0 * hv
            drives.append((
                d, rows, mask, v0,
                (e[:nv] - e[nv:]) / dv[:, None, None], (y[:nv] - y[nv:]) / dv[:, None],
                (turn[:nv] - turn[nv:]) / dv, (arc[:nv] - arc[nv:]) / dv,
            ))  # fmt: skip

        def linear(
            G: FloatArray, K: FloatArray, r_set: FloatArray, gamma: FloatArray
        ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
            Bn = G.shape[0]
            H = G / r_set
            resid = np.repeat(resid0, Bn, axis=0)
            Y = np.repeat(Y0, Bn, axis=0)
            turn_res, arc_turn = np.repeat(turn0, Bn, axis=0), np.repeat(arc0, Bn, axis=0)
            if nj:
                dH = (H[:, :S][:, :, cols] - H0[:S][:, cols])[:, sp_set]  # (B, rows, nj)
                resid[:, sp] += np.einsum("blj,jlm->blm", dH, d_res, optimize=True)
                Y[:, sp] += np.einsum("blj,jl->bl", dH, d_y)
            for d, rows, mask, v0, de, dy, dt, da in drives:
                v = np.concatenate(
                    [H[:, d][:, mask], (K[:, d] / r_set[:, d])[:, mask], gamma[:, d - S, None]],
                    axis=1,
                )
                dv = v - v0
                resid[:, rows] += (dv @ de.reshape(de.shape[0], -1)).reshape(Bn, *de.shape[1:])
                Y[:, rows] += dv @ dy
                turn_res[:, d - S] += dv @ dt
                arc_turn[:, d - S] += dv @ da
            return resid, Y, turn_res, arc_turn

        return linear

    def blocks(self, x: FloatArray, rolling: Rolling | None = None) -> dict[str, FloatArray]:
        """Weighted residuals of every active block (dimensionless).

        ``x`` (p,) or a batch (B, p) (one call for a whole finite-difference Jacobian:
        :meth:`jacobian`); every block is then (B, k).  ``rolling``: what profiles the
        wheels given their levers (:meth:`rolling`, the default; :meth:`jacobian` passes
        its first-order expansion).
        """
        xb = np.atleast_2d(x)
        Bn = xb.shape[0]
        X, s, knots, da, C = self.unpack(xb)
        act = self.active
        out: dict[str, list[FloatArray]] = {b: [] for b in BLOCKS}
        if "settled" in act:
            j, sg = self.settled.mod, self.settled.seg
            res = geo.settled_residual(
                X[:, j, P_S], X[:, j, B_COL], self.settled.theta + X[:, j, BETA], C[:, sg]
            )
            out["settled"].append(res / self.settled.sigma)
        lengths = np.zeros((Bn, 0))
        if act & {"spin", "gyro", "drive", "straight_drive"}:
            st = self.stack()
            G, K, r_set, gamma, lever1 = self.levers(X, s, knots, C)
            resid, Y, turn_res, arc_turn = (rolling or self.rolling)(G, K, r_set, gamma)
            turned = arc_turn * lever1
            w = resid / st.row_sigma[:, None]
            if "spin" in act:
                out["spin"].append(w[:, st.present & st.spin_rows[:, None]])
            if "drive" in act:
                out["drive"].append(w[:, st.present & ~st.spin_rows[:, None]])
            if "gyro" in act and st.chunk_a.size:
                a_, b_ = st.chunk_a, st.chunk_b
                dW = st.W_bias[b_] - st.W_bias[a_]
                dyaw = ((st.I_wz[b_] - st.I_wz[a_])[None, :] - knots @ dW.T) / s[:, None]
                out["gyro"].append((Y[:, b_] - Y[:, a_] - dyaw) / st.chunk_sigma)
            if "gyro" in act:
                out["gyro"].append(turn_res)  # the drives' turn: the wheels' against the gyro's
            S = st.n_spin
            lengths = np.abs(Y[:, st.set_last[S:]] - Y[:, st.set_first[S:]] + turned)
        if "rest" in act:
            out["rest"].append((self.knot_mean - knots) / self.knot_sigma)
        if "locked_angle" in act:
            out["locked_angle"].append(da / self.angle_sigma)
        drive = iter(range(lengths.shape[1]))
        for ref in self.refs:
            if ref.kind not in act:
                continue
            if isinstance(ref, AxisDistance):
                a, b = (self.ids.index(m) for m in ref.modules)
                pred = np.linalg.norm(X[:, a, P_S] - X[:, b, P_S], axis=-1)
            elif isinstance(ref, WheelRadius):
                pred = X[:, self.ids.index(ref.module), R]
            else:  # the drives in the order of the straight_drive references
                pred = lengths[:, next(drive)]
            out[ref.kind].append(((pred - ref.value) / ref.stddev)[:, None])
        if "gauge" in act:
            P = X[:, :, P_S]
            arm = self.P_nom - self.P_nom.mean(axis=0)
            dev = P - P.mean(axis=1, keepdims=True)
            cross = np.sum(arm[:, 0] * dev[..., 1] - arm[:, 1] * dev[..., 0], axis=-1)
            c_s = P.mean(axis=1) - self.P_nom.mean(axis=0)
            out["gauge"].append(np.column_stack([c_s, cross]) / GAUGE_SCALE)
            if self.scale_ref is not None:
                dot = np.sum(arm[:, 0] * dev[..., 0] + arm[:, 1] * dev[..., 1], axis=-1)
                rsum = X[:, :, R].sum(axis=1) - float(self.scale_ref.sum())
                scales = np.column_stack([dot - float(np.sum(arm * arm)), rsum])
                out["gauge"].append(scales / GAUGE_SCALE)
        blocks = {
            b: np.concatenate(v, axis=1) if v else np.zeros((Bn, 0))
            for b, v in out.items()
            if b in act
        }
        return blocks if np.ndim(x) == 2 else {b: v[0] for b, v in blocks.items()}

    def jacobian(self, x: FloatArray, rel_step: float = 1e-7) -> FloatArray:
        """Jacobian of :meth:`residuals`: central differences (step
        ``rel_step max(1, |x_i|)``, every perturbed point in one batched evaluation) for
        the geometry and the angle errors (and, with a straight drive, whose arc takes the
        gyro's turn, for the gyro's scale and knots too), the wheels' profiles in the
        batch to first order in their levers (:meth:`linear_rolling`: the chain rule);
        the spins' ``gyro`` rows and the ``rest`` block exact in those (linear in the
        knots and ``1 / s``)::

            d gyro_c / d b_i = dW_ci / (s sigma_c)
            d gyro_c / d s = (dI_c - dW_c . b) / (s^2 sigma_c)
            d rest_i / d b_i = -1 / sigma_i
        """
        lay = self.layout
        lin = np.zeros(x.size, dtype=bool)
        if not self.drives:  # a drive's arc takes the gyro's turn: differences for all
            lin[lay.scale] = True
            lin[lay.knots] = True
        idx = np.flatnonzero(~lin)
        h = rel_step * np.maximum(1.0, np.abs(x[idx]))
        E = np.zeros((idx.size, x.size))
        E[np.arange(idx.size), idx] = h
        rolling = None
        if self.active & {"spin", "gyro", "drive", "straight_drive"}:
            rolling = self.linear_rolling(x, rel_step)
        blocks = self.blocks(np.vstack([x + E, x - E]), rolling)
        F = np.concatenate([blocks[b] for b in BLOCKS if b in blocks], axis=-1)
        p = idx.size
        J = np.zeros((F.shape[1], x.size))
        J[:, idx] = ((F[:p] - F[p:]) / (2.0 * h[:, None])).T
        start = 0
        _, s, knots = lay.split(x)
        for name in (b for b in BLOCKS if b in blocks):
            size = blocks[name].shape[1]
            rows = slice(start, start + size)
            start += size
            if name == "rest":
                J[rows, lay.knots] = np.diag(-1.0 / self.knot_sigma)
            elif name == "gyro" and size:
                st = self.stack()
                rows = slice(rows.start, rows.start + st.chunk_a.size)  # the spins' chunks
                dW = st.W_bias[st.chunk_b] - st.W_bias[st.chunk_a]
                dI = st.I_wz[st.chunk_b] - st.I_wz[st.chunk_a]
                J[rows, lay.knots] = dW / (s * st.chunk_sigma[:, None])
                J[rows, lay.scale] = (dI - dW @ knots) / (s * s * st.chunk_sigma)
        return J

    def residuals(self, x: FloatArray) -> FloatArray:
        """All weighted residuals of the active blocks, in :data:`BLOCKS` order ((B, k) for
        a batch ``x`` (B, p))."""
        blocks = self.blocks(x)
        return np.concatenate([blocks[b] for b in BLOCKS if b in blocks], axis=-1)

    def block_slices(self, x: FloatArray) -> dict[str, slice]:
        """Where each active block sits in :meth:`residuals`."""
        out, i = {}, 0
        for b, v in self.blocks(x).items():
            out[b] = slice(i, i + v.shape[-1])
            i += v.shape[-1]
        return out

    def with_refs(self, refs: list[AxisDistance | WheelRadius | StraightDrive]) -> ImuProblem:
        """The same problem with other axis_distance / wheel_radius references (the
        straight drives are tied to their wheels' sets and stay)."""
        drives = [r for r in self.refs if isinstance(r, StraightDrive)]
        kept = [r for r in refs if not isinstance(r, StraightDrive)]
        out = self.with_blocks(self.active)
        out.refs = kept + drives
        return out

    def with_blocks(self, active: set[str] | frozenset[str]) -> ImuProblem:
        """The same observations with only the blocks ``active``."""
        unknown = set(active) - set(BLOCKS)
        if unknown:
            raise ValueError(f"unknown block(s) {sorted(unknown)}")
        return ImuProblem(
            self.layout, self.settled, self.seg_static, self.seg_angle, self.seg_sign,
            self.angle_sigma, self.spins, self.drives,
            self.knot_mean, self.knot_sigma, self.refs, self.ids, self.P_nom, frozenset(active),
            self._stack, self.scale_ref,
        )

    def gauge_jacobian(self) -> FloatArray:
        """Jacobian (3 or 5, p) of the gauge conditions (constant: they are linear in the
        unknowns): the design-fit rows
        (:func:`swpc_hw.robot.frames.design_fit_constraint_jacobian`) and, for a check, the
        scale rows ``d/dP_s,i = a_i`` and ``d/dr_i = 1``."""
        from swpc_hw.robot.frames import design_fit_constraint_jacobian

        n = self.layout.n
        rows = 3 if self.scale_ref is None else 5
        A = np.zeros((rows, self.layout.size))
        cols = np.array([N_PARAMS * i + c for i in range(n) for c in (0, 1)])
        A[:3, cols] = design_fit_constraint_jacobian(self.P_nom)
        if self.scale_ref is not None:
            arm = self.P_nom - self.P_nom.mean(axis=0)
            A[3, cols] = arm.ravel()
            A[4, N_PARAMS * np.arange(n) + R] = 1.0
        return A
