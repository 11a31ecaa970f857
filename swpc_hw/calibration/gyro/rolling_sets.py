"""The wheels of a spin or a straight drive at their nodes, and their rolling residuals.

A :class:`RollingSet` holds one segment's (or the straight drive's) wheel angles at its
nodes with the gyro's integrals; :class:`RollingStack` every set in one array.  Per node
the wheels roll as ``psi_jl = c_run(j,l) + (g_j / r_j) Y_l``: :func:`profiled_rolling`
profiles the yaw (or distance) ``Y`` and the runs' constants ``c`` out, :func:`arc_profile`
the straight drive's curvature as well (the ``spin`` and ``drive`` blocks of
:mod:`swpc_hw.calibration.gyro.problem`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from scipy import sparse

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class ProfileStructure:
    """Which samples :func:`profiled_rolling` uses, prepared once per ``present``/``run``:
    the present samples ``(rows, cols)`` and their runs, every pair of present samples of
    a node (``l, i, j``) and the sparse maps summing pairs and samples into runs."""

    rows: IntArray
    cols: IntArray
    runs: IntArray
    n_run: int
    pl: IntArray
    pi: IntArray
    pj: IntArray
    pairs: sparse.csr_matrix
    samples: sparse.csr_matrix
    counts: FloatArray
    pairs_t: sparse.csc_matrix = field(init=False, repr=False)
    samples_t: sparse.csc_matrix = field(init=False, repr=False)
    """The two maps transposed, once (a transpose is a new matrix at every use)."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "pairs_t", self.pairs.T)
        object.__setattr__(self, "samples_t", self.samples.T)

    @classmethod
    def of(cls, present: BoolArray, run: IntArray) -> ProfileStructure:
        from scipy import sparse  # at first use: see swpc_hw.calibration

        rows, cols = np.nonzero(present)
        runs = run[rows, cols]
        n_run = int(np.max(runs)) + 1 if runs.size else 0
        pr, pi, pj = [], [], []
        for i in range(present.shape[1]):
            for j in range(present.shape[1]):
                sel = np.flatnonzero(present[:, i] & present[:, j])
                pr.append(sel)
                pi.append(np.full(sel.size, i))
                pj.append(np.full(sel.size, j))
        l_, i_, j_ = np.concatenate(pr), np.concatenate(pi), np.concatenate(pj)
        pairs = sparse.csr_matrix(
            (np.ones(l_.size), (np.arange(l_.size), run[l_, i_] * n_run + run[l_, j_])),
            shape=(l_.size, n_run * n_run),
        )
        samples = sparse.csr_matrix(
            (np.ones(runs.size), (np.arange(runs.size), runs)), shape=(runs.size, n_run)
        )
        counts = np.bincount(runs, minlength=n_run).astype(float)
        return cls(rows, cols, runs, n_run, l_, i_, j_, pairs, samples, counts)


def profiled_rolling(
    z: FloatArray,
    g: FloatArray,
    present: BoolArray,
    run: IntArray,
    structure: ProfileStructure | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Residuals of ``z_jl = c_run(j,l) + g_j Y_l`` with ``Y`` and ``c`` profiled out.

    ``z`` (..., L, m) the wheels' readings and ``g`` their levers, broadcast together (any
    leading batch dimensions), ``present`` (L, m) the samples used, ``run`` (L, m) the
    constant's index of each (dense, any value where absent; ``structure``: the two
    prepared, :class:`ProfileStructure`).  Per node the least-squares
    ``Y_l = g_l^T (z_l - c) / |g_l|^2`` (``g_l``: ``g`` on the present modules) leaves
    ``P_l (z_l - c)`` with the projector ``P_l = I_l - g_l g_l^T / |g_l|^2``; ``c``
    minimises ``sum_l |P_l (z_l - C_l c)|^2``::

        (sum_l C_l^T P_l C_l) c = sum_l C_l^T P_l z_l,
        sum_l C_l^T P_l C_l = diag(samples per run) - Q^T Q,   Q_l,run(l,j) = g_lj / |g_l|

    (minimum norm: ``c`` along ``g`` is a shift of ``Y``); ``Q^T Q`` from the pairs of
    present samples of every node (a node has m: sparse).  Returns ``(residual (..., L,
    m), Y (..., L))``; the residual is 0 where absent.
    """
    st = structure or ProfileStructure.of(present, run)
    shape = np.broadcast_shapes(np.shape(z), np.shape(g))
    z = np.broadcast_to(z, shape)
    gP = np.where(present, np.broadcast_to(g, shape), 0.0)
    nrm = np.sum(gP * gP, axis=-1)
    inv = np.where(nrm > 0, 1.0 / np.where(nrm > 0, nrm, 1.0), 0.0)
    zp = np.where(present, z, 0.0)
    rows, cols, runs, n = st.rows, st.cols, st.runs, st.n_run
    batch = shape[:-2]
    flat = int(np.prod(batch, dtype=np.int64))
    outer = gP[..., st.pl, st.pi] * gP[..., st.pl, st.pj] * inv[..., st.pl]
    QtQ = np.asarray(st.pairs_t @ outer.reshape(flat, st.pl.size).T).T.reshape(*batch, n, n)
    A = np.diag(st.counts) - QtQ
    gz = np.sum(gP * zp, axis=-1) * inv
    Pz = zp[..., rows, cols] - gP[..., rows, cols] * gz[..., rows]
    rhs = np.asarray(st.samples_t @ Pz.reshape(flat, runs.size).T).T.reshape(*batch, n)
    c = (np.linalg.pinv(A, rcond=1e-12) @ rhs[..., None])[..., 0]
    e = zp.copy()
    e[..., rows, cols] -= c[..., runs]
    Y = np.sum(gP * e, axis=-1) * inv
    resid = np.where(present, e - gP * Y[..., None], 0.0)
    return np.asarray(resid, dtype=float), np.asarray(Y, dtype=float)


ARC_STEP = 1e-3
"""Curvature step (1/m) of :func:`arc_profile`'s derivative."""


def arc_profile(
    z: FloatArray,
    g: FloatArray,
    k: FloatArray,
    r: FloatArray,
    present: BoolArray,
    run: IntArray,
    structure: ProfileStructure,
    e0: FloatArray,
    y0: FloatArray,
    sigma_w: float,
    gamma: FloatArray,
    sigma_g: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """A straight drive's wheels on an arc of curvature ``kappa``, profiled out.

    Wheels steered at fixed angles move a rigid robot on a circle: its turn is
    proportional to the distance, ``dyaw = kappa dY``, so every wheel still rolls in
    proportion to ``Y`` with the lever ``(g_j + kappa k_j) / r_j`` (``g = cos(theta -
    phi)``, ``k = P_s x u(theta)``; :data:`BLOCKS`' ``drive``).  ``kappa`` minimises::

        |E(kappa)|^2 / sigma_w^2 + ((kappa (Y_end - Y_start) - gamma) / sigma_g)^2

    ``E`` the profiled residuals (wheel angles of std dev ``sigma_w``), ``gamma`` the
    gyro's turn over the drive (std dev ``sigma_g``): without the gyro a radius error
    could pass for a curvature.  Two Gauss-Newton steps from 0, ``dE/dkappa`` a
    difference over :data:`ARC_STEP`.  ``z`` (L, m), ``g``, ``k``, ``r`` (B, m), ``e0``,
    ``y0``: the residuals (B, L, m) and ``Y`` (B, L) at ``kappa = 0``; ``gamma`` (B,).
    Returns the residuals, ``Y``, ``kappa`` (B,) and the turn's weighted residual (B,).
    ``sigma_g`` infinite: the wheels alone (the gyro's block left out).
    """
    kappa = np.zeros(g.shape[0])
    e, y = e0, y0
    wg = sigma_w / sigma_g
    for _ in range(2):
        h = (g + (kappa + ARC_STEP)[:, None] * k) / r
        e1, y1 = profiled_rolling(z, h[:, None, :], present, run, structure)
        de, dy = (e1 - e) / ARC_STEP, (y1 - y) / ARC_STEP
        D = y[:, -1] - y[:, 0]
        t = kappa * D - gamma
        num = np.sum(e * de, axis=(1, 2)) + wg * wg * t * D
        den = np.sum(de * de, axis=(1, 2)) + wg * wg * D * D
        step = np.where(den > 0, -num / np.where(den > 0, den, 1.0), 0.0)
        kappa = kappa + step
        e, y = e + step[:, None, None] * de, y + step[:, None] * dy
    h = (g + kappa[:, None] * k) / r
    e, y = profiled_rolling(z, h[:, None, :], present, run, structure)
    turn = (kappa * (y[:, -1] - y[:, 0]) - gamma) / sigma_g
    return e, y, kappa, turn


@dataclass
class RollingSet:
    """The wheels of one segment's spin (or of the straight drive) at their nodes.

    ``mods`` (m,) module indices; ``theta`` (m,) their reported steering (the settled
    median; held while driving); ``t`` (L,) node times; ``psi`` (L, m) wheel angles;
    ``present`` / ``run`` (L, m) the samples used and the clean run of each; ``sigma``
    (m) the noise of ``r psi`` at a node.  Gyro: ``I_wz`` (L,) ``int wz`` and ``W_bias``
    (L, K) ``int phi_i`` from a common origin to every node; ``chunks`` the connected node
    ranges ``(l_a, l_b)`` and ``gyro_sigma`` the std dev (rad) of each chunk's gyro yaw.
    ``static``, ``angle``: the locked module and its reported steering (-1 for a drive).
    """

    mods: IntArray
    theta: FloatArray
    t: FloatArray
    psi: FloatArray
    present: BoolArray
    run: IntArray
    I_wz: FloatArray
    W_bias: FloatArray
    static: int = -1
    angle: float = 0.0
    sigma: float = 1.0
    chunks: list[tuple[int, int]] = field(default_factory=list)
    gyro_sigma: FloatArray = field(default_factory=lambda: np.zeros(0))

    def gyro_yaw(self, s: float, knots: FloatArray, la: IntArray, lb: IntArray) -> FloatArray:
        """The gyro's yaw from node ``la`` to ``lb``: ``(dI - dW . b) / s`` (rad)."""
        return np.asarray(
            ((self.I_wz[lb] - self.I_wz[la]) - (self.W_bias[lb] - self.W_bias[la]) @ knots) / s,
            dtype=float,
        )


@dataclass(frozen=True)
class RollingStack:
    """Every rolling set in one array, spins first, for one :func:`profiled_rolling`.

    Rows are nodes (``row_set``: the set of each), columns a set's modules padded to the
    widest set (``mods`` 0 and ``present`` False in the padding).  ``run`` is dense over
    all sets; ``set_*`` (sets, m) each set's modules, reported steering and which columns
    are real; the gyro's chunks as row pairs ``chunk_a``/``chunk_b`` with their std dev.
    """

    psi: FloatArray
    present: BoolArray
    run: IntArray
    mods: IntArray
    row_set: IntArray
    row_sigma: FloatArray
    spin_rows: BoolArray
    I_wz: FloatArray
    W_bias: FloatArray
    set_mods: IntArray
    set_theta: FloatArray
    set_mask: BoolArray
    set_first: IntArray
    set_last: IntArray
    n_spin: int
    chunk_a: IntArray
    chunk_b: IntArray
    chunk_sigma: FloatArray
    structure: ProfileStructure
    spin_structure: ProfileStructure
    """The spins' rows alone (they come first)."""
    drive_structures: list[ProfileStructure]
    drive_gyro_sigma: FloatArray


def stack_sets(spins: list[RollingSet], drives: list[RollingSet], n_knots: int) -> RollingStack:
    """The :class:`RollingStack` of ``spins`` then ``drives``."""
    sets = [*spins, *drives]
    m = max((rs.mods.size for rs in sets), default=1)
    L = sum(rs.t.size for rs in sets)
    psi, mods, theta = np.zeros((L, m)), np.zeros((L, m), np.int64), np.zeros((len(sets), m))
    present, run = np.zeros((L, m), bool), np.zeros((L, m), np.int64)
    set_mods, set_mask = np.zeros((len(sets), m), np.int64), np.zeros((len(sets), m), bool)
    row_set, row_sigma = np.zeros(L, np.int64), np.ones(L)
    I_wz, W_bias = np.zeros(L), np.zeros((L, n_knots))
    first, last, ca, cb, csig = [], [], [], [], []
    row, run0 = 0, 0
    for k, rs in enumerate(sets):
        rows = slice(row, row + rs.t.size)
        w = rs.mods.size
        psi[rows, :w], present[rows, :w] = rs.psi, rs.present
        mods[rows, :w] = rs.mods[None, :]
        _, dense = np.unique(rs.run[rs.present], return_inverse=True)
        block = np.zeros((rs.t.size, w), np.int64)
        block[rs.present] = run0 + dense
        run[rows, :w] = block
        run0 += int(np.max(dense)) + 1 if dense.size else 0
        set_mods[k, :w], set_mask[k, :w], theta[k, :w] = rs.mods, True, rs.theta
        row_set[rows], row_sigma[rows] = k, rs.sigma
        I_wz[rows], W_bias[rows] = rs.I_wz, rs.W_bias
        first.append(row)
        last.append(row + rs.t.size - 1)
        if k < len(spins):
            for (la, lb), sg in zip(rs.chunks, rs.gyro_sigma, strict=False):
                ca.append(row + la)
                cb.append(row + lb)
                csig.append(sg)
        row += rs.t.size
    spin_rows = row_set < len(spins)
    return RollingStack(
        psi, present, run, mods, row_set, row_sigma, spin_rows, I_wz, W_bias,
        set_mods, theta, set_mask, np.array(first, np.int64), np.array(last, np.int64),
        len(spins), np.array(ca, np.int64), np.array(cb, np.int64), np.array(csig),
        ProfileStructure.of(present, run),
        ProfileStructure.of(present[spin_rows], run[spin_rows]),
        [drive_structure(rs) for rs in drives],
        np.array([float(rs.gyro_sigma[0]) if rs.gyro_sigma.size else 1.0 for rs in drives]),
    )


def drive_structure(rs: RollingSet) -> ProfileStructure:
    """The :class:`ProfileStructure` of one rolling set alone (dense runs)."""
    run = np.zeros_like(rs.run)
    _, dense = np.unique(rs.run[rs.present], return_inverse=True)
    run[rs.present] = dense
    return ProfileStructure.of(rs.present, run)


def connected_chunks(present: BoolArray, run: IntArray) -> list[tuple[int, int]]:
    """Maximal node ranges ``(l_a, l_b)`` (inclusive, >= 2 nodes) in which consecutive
    nodes share a module in the same run: ``Y`` is tied from one node to the next."""
    L = present.shape[0]
    linked = np.any(present[1:] & present[:-1] & (run[1:] == run[:-1]), axis=1)
    out, start = [], 0
    for k in range(1, L + 1):
        if k == L or not linked[k - 1]:
            if k - 1 > start:
                out.append((start, k - 1))
            start = k
    return out
