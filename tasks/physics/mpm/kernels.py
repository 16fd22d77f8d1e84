"""Warp kernels of the MLS-MPM solver (Hu et al. 2018, APIC transfers, quadratic B-splines, 3D).

One substep is   P2G -> grid update -> G2P.  To touch each particle once per substep, the G2P of substep n and
the P2G of substep n+1 are fused in :func:`k_g2p_p2g` (it reads grid buffer A and scatters into buffer B; the
grid update of B clears A); :func:`k_g2p_p2g_fc` is the same kernel specialised for scenes whose particles are
all fixed-corotated (no model branches).  The first P2G of a frame (:func:`k_p2g`) and the last G2P
(:func:`k_g2p`, which also accumulates the frame statistics) are separate kernels, so particle velocities and
affine matrices are stored only at frame boundaries.  Every P2G records the bounding box of the stencils it
touched (``bbox``) and the grid update runs only over the union of the current and previous boxes.

Grid layout: ``wp.array3d(dtype=wp.vec4)``, node (i, j, k) at ``lo + (i, j, k) dx``; after P2G a node holds
(momentum, mass), after the grid update (velocity, mass).

Index safety: every particle or point coordinate is checked against the safe band of the grid before any grid
access; an offending coordinate (including NaN) is clamped into the band and an error flag is raised in
``flags`` (read by the host, which raises :class:`~tasks.physics.mpm.solver.SimulationError`).  No kernel ever writes
outside the grid, in release or debug mode.

Flag layout (int32 array of length ``N_FLAGS``): for each code c in (OUT_OF_GRID, NONFINITE, EXTREME_J,
TRACER_OUT): ``flags[c]`` = number of offences, ``flags[4 + c]`` = first substep index (atomic min),
``flags[8 + c]`` = an offending index (atomic max).
"""
from __future__ import annotations

import warp as wp

from . import materials as M
from .constitutive import (
    fluid_reset,
    hencky_plastic_return,
    polar_rotation_quat,
    polar_track_quat,
    psi_fixed_corotated,
    psi_fluid,
    psi_hencky,
    psi_neo_hookean,
    tau_fixed_corotated,
    tau_fluid,
    tau_hencky,
    tau_neo_hookean,
)

wp.set_module_options({"enable_backward": False, "optimization_level": 3})

OUT_OF_GRID = wp.constant(0)
NONFINITE = wp.constant(1)
EXTREME_J = wp.constant(2)
TRACER_OUT = wp.constant(3)
N_FLAGS = 12
NO_SUBSTEP = 2**31 - 1

# material table columns (see materials.py)
C_MU = wp.constant(M.COL_MU)
C_LAMBDA = wp.constant(M.COL_LAMBDA)
C_DENSITY = wp.constant(M.COL_DENSITY)
C_YIELD = wp.constant(M.COL_YIELD)
C_HARDENING = wp.constant(M.COL_HARDENING)
C_VISCOSITY = wp.constant(M.COL_VISCOSITY)
C_BULK = wp.constant(M.COL_BULK)
C_GAMMA = wp.constant(M.COL_GAMMA)
C_CRUSH = wp.constant(M.COL_CRUSH)


@wp.struct
class GridInfo:
    """Geometry of the background grid."""

    lo: wp.vec3  # world position of node (0, 0, 0), m
    dx: float  # node spacing, m
    inv_dx: float
    safe_lo: wp.vec3  # lowest allowed particle coordinate, in grid units
    safe_hi: wp.vec3  # highest allowed particle coordinate, in grid units


@wp.struct
class StepParams:
    """Per-launch scalars of the particle kernels."""

    dt_g2p: float  # dt of the G2P (advection, F update) part
    dt_p2g: float  # dt of the P2G (stress impulse) part
    substep: int  # global substep counter (error reports)
    j_min: float
    j_max: float
    polar_iters: int
    polar_tol: float
    polar_newton: int  # 1: Newton iteration to polar_tol (frame start/end); 0: one cheap tracking step per iter


@wp.struct
class G2PResult:
    x: wp.vec3
    v: wp.vec3
    C: wp.mat33
    F: wp.mat33
    q: wp.quat
    alpha: float
    tau: wp.mat33


# ============================================================================================ helpers
@wp.func
def raise_flag(flags: wp.array(dtype=wp.int32), code: int, substep: int, index: int):
    wp.atomic_add(flags, code, 1)
    wp.atomic_min(flags, 4 + code, substep)
    wp.atomic_max(flags, 8 + code, index)


@wp.func
def clamp_band(g: float, lo_b: float, hi_b: float) -> float:
    """Clamp g into [lo_b, hi_b]; NaN maps to lo_b."""
    if g >= lo_b:
        if g <= hi_b:
            return g
        return hi_b
    return lo_b


@wp.func
def to_grid(x: wp.vec3, gi: GridInfo) -> wp.vec3:
    return (x - gi.lo) * gi.inv_dx


@wp.func
def in_band(g: wp.vec3, gi: GridInfo) -> bool:
    # written so that NaN compares as "outside"
    ok = g[0] >= gi.safe_lo[0] and g[0] <= gi.safe_hi[0]
    ok = ok and g[1] >= gi.safe_lo[1] and g[1] <= gi.safe_hi[1]
    ok = ok and g[2] >= gi.safe_lo[2] and g[2] <= gi.safe_hi[2]
    return ok


@wp.func
def clamp_to_band(g: wp.vec3, gi: GridInfo) -> wp.vec3:
    return wp.vec3(
        clamp_band(g[0], gi.safe_lo[0], gi.safe_hi[0]),
        clamp_band(g[1], gi.safe_lo[1], gi.safe_hi[1]),
        clamp_band(g[2], gi.safe_lo[2], gi.safe_hi[2]),
    )


@wp.func
def bspline_w(f: float) -> wp.vec3:
    """Quadratic B-spline weights of the 3 nodes base, base+1, base+2 for f = g - base in [0.5, 1.5)."""
    a = 1.5 - f
    b = f - 1.0
    c = f - 0.5
    return wp.vec3(0.5 * a * a, 0.75 - b * b, 0.5 * c * c)


@wp.func
def base_index(g: wp.vec3) -> wp.vec3i:
    """Lower stencil node: floor(g - 0.5) (floor, not truncation)."""
    return wp.vec3i(int(wp.floor(g[0] - 0.5)), int(wp.floor(g[1] - 0.5)), int(wp.floor(g[2] - 0.5)))


@wp.func
def frac(g: wp.vec3, b: wp.vec3i) -> wp.vec3:
    return wp.vec3(g[0] - float(b[0]), g[1] - float(b[1]), g[2] - float(b[2]))


@wp.func
def gather_apic(grid: wp.array3d(dtype=wp.vec4), g: wp.vec3, inv_dx: float) -> G2PResult:
    """Interpolate velocity and the APIC/MLS affine matrix C = 4/dx^2 sum_i w_i v_i (x_i - x_p)^T.

    Separable form: with offsets o = (i, j, k) and f = g - base, x_i - x_p = dx (o - f), so
    C = 4/dx (S - v f^T) with S[:, c] = sum_i w_i v_i o_c.  Sums run in vec4 (the 4th lane is unused).
    """
    b = base_index(g)
    f = frac(g, b)
    wx = bspline_w(f[0])
    wy = bspline_w(f[1])
    wz = bspline_w(f[2])
    v = wp.vec4(0.0)
    s0 = wp.vec4(0.0)  # sum w v i
    s1 = wp.vec4(0.0)  # sum w v j
    s2 = wp.vec4(0.0)  # sum w v k
    for i in range(3):
        for j in range(3):
            n0 = grid[b[0] + i, b[1] + j, b[2]]
            n1 = grid[b[0] + i, b[1] + j, b[2] + 1]
            n2 = grid[b[0] + i, b[1] + j, b[2] + 2]
            wij = wx[i] * wy[j]
            acc = wij * (wz[0] * n0 + wz[1] * n1 + wz[2] * n2)
            v = v + acc
            s2 = s2 + wij * (wz[1] * n1 + (2.0 * wz[2]) * n2)
            if i == 1:
                s0 = s0 + acc
            if i == 2:
                s0 = s0 + 2.0 * acc
            if j == 1:
                s1 = s1 + acc
            if j == 2:
                s1 = s1 + 2.0 * acc
    r = G2PResult()
    r.v = wp.vec3(v[0], v[1], v[2])
    s = 4.0 * inv_dx
    # C[row, col] = 4/dx (s_col[row] - v[row] f[col]), built element by element (row-major scalars)
    r.C = wp.mat33(
        s * (s0[0] - v[0] * f[0]), s * (s1[0] - v[0] * f[1]), s * (s2[0] - v[0] * f[2]),
        s * (s0[1] - v[1] * f[0]), s * (s1[1] - v[1] * f[1]), s * (s2[1] - v[1] * f[2]),
        s * (s0[2] - v[2] * f[0]), s * (s1[2] - v[2] * f[1]), s * (s2[2] - v[2] * f[2]),
    )
    return r


@wp.func
def scatter_apic(grid: wp.array3d(dtype=wp.vec4), g: wp.vec3, dx: float, mass: float, v: wp.vec3, A: wp.mat33,
                 bbox: wp.array(dtype=wp.int32)):
    """P2G: node i receives w_i (m v + A (x_i - x_p)) momentum and w_i m mass; records the stencil bounding box.

    A (x_i - x_p) = dx A (o - f) = p0 + i a0 + j a1 + k a2, evaluated in vec4 with the mass in the 4th lane.
    """
    b = base_index(g)
    f = frac(g, b)
    wx = bspline_w(f[0])
    wy = bspline_w(f[1])
    wz = bspline_w(f[2])
    a0 = dx * wp.vec4(A[0, 0], A[1, 0], A[2, 0], 0.0)
    a1 = dx * wp.vec4(A[0, 1], A[1, 1], A[2, 1], 0.0)
    a2 = dx * wp.vec4(A[0, 2], A[1, 2], A[2, 2], 0.0)
    mv = mass * v
    p0 = wp.vec4(mv[0], mv[1], mv[2], mass) - (f[0] * a0 + f[1] * a1 + f[2] * a2)
    for i in range(3):
        for j in range(3):
            wij = wx[i] * wy[j]
            pij = p0 + float(i) * a0 + float(j) * a1
            for k in range(3):
                wp.atomic_add(grid, b[0] + i, b[1] + j, b[2] + k, (wij * wz[k]) * (pij + float(k) * a2))
    wp.atomic_min(bbox, 0, b[0])
    wp.atomic_min(bbox, 1, b[1])
    wp.atomic_min(bbox, 2, b[2])
    wp.atomic_max(bbox, 3, b[0])
    wp.atomic_max(bbox, 4, b[1])
    wp.atomic_max(bbox, 5, b[2])


@wp.func
def stress_from_state(
    model: int,
    F: wp.mat33,
    q: wp.quat,
    C: wp.mat33,
    mat_par: wp.array2d(dtype=float),
    mid: int,
    polar_iters: int,
    polar_tol: float,
) -> G2PResult:
    """Kirchhoff stress of an already return-mapped state (used by the frame's first P2G, Newton rotation)."""
    r = G2PResult()
    r.q = q
    mu = mat_par[mid, C_MU]
    lam = mat_par[mid, C_LAMBDA]
    if model == 0:
        qn = polar_rotation_quat(F, q, polar_iters, polar_tol)
        r.q = qn
        r.tau = tau_fixed_corotated(F, wp.quat_to_matrix(qn), mu, lam)
    elif model == 1:
        r.tau = tau_neo_hookean(F, mu, lam)
    elif model == 4:
        r.tau = tau_fluid(wp.determinant(F), C, mat_par[mid, C_BULK], mat_par[mid, C_GAMMA], mat_par[mid, C_VISCOSITY])
    else:
        r.tau = tau_hencky(F, mu, lam)
    return r


@wp.func
def rotation_update(F: wp.mat33, q: wp.quat, sp: StepParams) -> wp.quat:
    """Rotation of F for the fixed-corotated stress, from the particle's previous rotation q."""
    if sp.polar_newton != 0:
        return polar_rotation_quat(F, q, sp.polar_iters, sp.polar_tol)
    return polar_track_quat(F, q, sp.polar_iters)


@wp.func
def check_particle(r: G2PResult, p: int, sp: StepParams, flags: wp.array(dtype=wp.int32)):
    """Guards after G2P: non-finite state, then det(F_E) outside [j_min, j_max].

    Finiteness is tested on one sum of squares (a NaN or inf anywhere in x, v or F_E makes it NaN/inf, and no
    physical state comes near 1e30), which is much cheaper than 15 separate isfinite tests.
    """
    Jn = wp.determinant(r.F)
    s = wp.dot(r.x, r.x) + wp.dot(r.v, r.v) + wp.ddot(r.F, r.F)
    if not (s < 1.0e30):
        raise_flag(flags, NONFINITE, sp.substep, p)
    elif not (Jn >= sp.j_min and Jn <= sp.j_max):
        raise_flag(flags, EXTREME_J, sp.substep, p)


@wp.func
def gather_at(xp: wp.vec3, p: int, grid: wp.array3d(dtype=wp.vec4), gi: GridInfo, sp: StepParams,
              flags: wp.array(dtype=wp.int32)) -> G2PResult:
    g = to_grid(xp, gi)
    if not in_band(g, gi):
        raise_flag(flags, OUT_OF_GRID, sp.substep, p)
        g = clamp_to_band(g, gi)
    return gather_apic(grid, g, gi.inv_dx)


@wp.func
def scatter_at(xp: wp.vec3, p: int, substep: int, grid: wp.array3d(dtype=wp.vec4), gi: GridInfo, dt: float,
               vol: float, mass: float, v: wp.vec3, C: wp.mat33, tau: wp.mat33, flags: wp.array(dtype=wp.int32),
               bbox: wp.array(dtype=wp.int32)):
    """MLS-MPM P2G of one particle: affine momentum A = -dt V0 4/dx^2 tau + m C (Hu et al. 2018, eq. 29)."""
    g = to_grid(xp, gi)
    if not in_band(g, gi):
        raise_flag(flags, OUT_OF_GRID, substep, p)
        g = clamp_to_band(g, gi)
    A = (-dt * vol * 4.0 * gi.inv_dx * gi.inv_dx) * tau + mass * C
    scatter_apic(grid, g, gi.dx, mass, v, A, bbox)


@wp.func
def g2p_begin(
    p: int,
    grid: wp.array3d(dtype=wp.vec4),
    gi: GridInfo,
    sp: StepParams,
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    flags: wp.array(dtype=wp.int32),
) -> G2PResult:
    """First part of the G2P of particle p, common to every model: gather v (m/s) and C (1/s), the advected position
    x + dt v (m) and the trial elastic deformation gradient (I + dt C) F_E, before the model's update."""
    xp = x[p]
    r = gather_at(xp, p, grid, gi, sp, flags)
    r.F = (wp.identity(n=3, dtype=float) + sp.dt_g2p * r.C) @ F[p]
    r.x = xp + sp.dt_g2p * r.v
    r.q = wp.quat_identity()
    r.alpha = 0.0
    return r


@wp.func
def g2p_end(r: G2PResult, p: int, sp: StepParams, x: wp.array(dtype=wp.vec3), F: wp.array(dtype=wp.mat33),
            flags: wp.array(dtype=wp.int32)):
    """Last part of the G2P of particle p: guards on the new state, then store x and F_E."""
    check_particle(r, p, sp, flags)
    x[p] = r.x
    F[p] = r.F


@wp.func
def corotated_update(r: G2PResult, p: int, q: wp.array(dtype=wp.quat), sp: StepParams, mu: float,
                     lam: float) -> G2PResult:
    """Fixed-corotated part of the G2P: rotation of the trial F_E (warm-started from, and stored into, q[p]) and
    the Kirchhoff stress (Pa; mu, lam in Pa)."""
    r.q = rotation_update(r.F, q[p], sp)
    r.tau = tau_fixed_corotated(r.F, wp.quat_to_matrix(r.q), mu, lam)
    q[p] = r.q
    return r


@wp.func
def g2p_update(
    p: int,
    grid: wp.array3d(dtype=wp.vec4),
    gi: GridInfo,
    sp: StepParams,
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    q: wp.array(dtype=wp.quat),
    alpha: wp.array(dtype=float),
    mid: int,
    model: int,
    mat_par: wp.array2d(dtype=float),
    flags: wp.array(dtype=wp.int32),
) -> G2PResult:
    """G2P of one particle, any model: gather v and C, F_E <- (I + dt C) F_E, return mapping (eq. 5), Kirchhoff
    stress of the new state (eq. 4), advection, guards; stores x, F_E and the model's state (rotation q of
    fixed-corotated, plastic strain alpha of von Mises / foam).  Velocity and C are returned, not stored."""
    r = g2p_begin(p, grid, gi, sp, x, F, flags)
    mu = mat_par[mid, C_MU]
    lam = mat_par[mid, C_LAMBDA]
    if model == 0:
        r = corotated_update(r, p, q, sp, mu, lam)
    elif model == 1:
        r.tau = tau_neo_hookean(r.F, mu, lam)
    elif model == 4:
        r.tau = tau_fluid(wp.determinant(r.F), r.C, mat_par[mid, C_BULK], mat_par[mid, C_GAMMA],
                          mat_par[mid, C_VISCOSITY])
        r.F = fluid_reset(r.F)
    else:
        pr = hencky_plastic_return(
            r.F, mu, lam, mat_par[mid, C_YIELD], mat_par[mid, C_HARDENING], alpha[p],
            mat_par[mid, C_VISCOSITY], mat_par[mid, C_CRUSH], int(model == 3), sp.dt_g2p,
        )
        r.F = pr.F
        r.tau = pr.tau
        r.alpha = pr.alpha
        alpha[p] = r.alpha
    g2p_end(r, p, sp, x, F, flags)
    return r


@wp.func
def g2p_update_fc(
    p: int,
    grid: wp.array3d(dtype=wp.vec4),
    gi: GridInfo,
    sp: StepParams,
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    q: wp.array(dtype=wp.quat),
    mu: float,
    lam: float,
    flags: wp.array(dtype=wp.int32),
) -> G2PResult:
    """:func:`g2p_update` specialised for a fixed-corotated particle (the common fast path, no model branches)."""
    r = corotated_update(g2p_begin(p, grid, gi, sp, x, F, flags), p, q, sp, mu, lam)
    g2p_end(r, p, sp, x, F, flags)
    return r


# ============================================================================================ particle kernels
@wp.kernel
def k_p2g(
    gi: GridInfo,
    sp: StepParams,
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    q: wp.array(dtype=wp.quat),
    vol: wp.array(dtype=float),
    mat_id: wp.array(dtype=wp.int32),
    mat_model: wp.array(dtype=wp.int32),
    mat_par: wp.array2d(dtype=float),
    grid_out: wp.array3d(dtype=wp.vec4),
    flags: wp.array(dtype=wp.int32),
    bbox: wp.array(dtype=wp.int32),
):
    """Stand-alone P2G (first substep of a frame), stress from the stored F_E (any model)."""
    p = wp.tid()
    mid = int(mat_id[p])
    model = mat_model[mid]
    qp = wp.quat_identity()
    if model == 0:
        qp = q[p]
    r = stress_from_state(model, F[p], qp, C[p], mat_par, mid, sp.polar_iters, sp.polar_tol)
    if model == 0:
        q[p] = r.q
    scatter_at(x[p], p, sp.substep, grid_out, gi, sp.dt_p2g, vol[p], vol[p] * mat_par[mid, C_DENSITY], v[p], C[p],
               r.tau, flags, bbox)


@wp.kernel
def k_g2p_p2g(
    gi: GridInfo,
    sp: StepParams,
    grid_in: wp.array3d(dtype=wp.vec4),
    grid_out: wp.array3d(dtype=wp.vec4),
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    q: wp.array(dtype=wp.quat),
    alpha: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mat_id: wp.array(dtype=wp.int32),
    mat_model: wp.array(dtype=wp.int32),
    mat_par: wp.array2d(dtype=float),
    flags: wp.array(dtype=wp.int32),
    bbox: wp.array(dtype=wp.int32),
):
    """Fused G2P (substep n, from ``grid_in``) + P2G (substep n+1, into ``grid_out``), any model."""
    p = wp.tid()
    mid = int(mat_id[p])
    r = g2p_update(p, grid_in, gi, sp, x, F, q, alpha, mid, mat_model[mid], mat_par, flags)
    scatter_at(r.x, p, sp.substep + 1, grid_out, gi, sp.dt_p2g, vol[p], vol[p] * mat_par[mid, C_DENSITY], r.v, r.C,
               r.tau, flags, bbox)


@wp.kernel
def k_g2p_p2g_fc(
    gi: GridInfo,
    sp: StepParams,
    grid_in: wp.array3d(dtype=wp.vec4),
    grid_out: wp.array3d(dtype=wp.vec4),
    x: wp.array(dtype=wp.vec3),
    F: wp.array(dtype=wp.mat33),
    q: wp.array(dtype=wp.quat),
    vol: wp.array(dtype=float),
    mat_id: wp.array(dtype=wp.int32),
    mat_par: wp.array2d(dtype=float),
    flags: wp.array(dtype=wp.int32),
    bbox: wp.array(dtype=wp.int32),
):
    """Fused G2P + P2G when every particle is fixed-corotated (no model branches, no plastic state)."""
    p = wp.tid()
    mid = int(mat_id[p])
    r = g2p_update_fc(p, grid_in, gi, sp, x, F, q, mat_par[mid, C_MU], mat_par[mid, C_LAMBDA], flags)
    scatter_at(r.x, p, sp.substep + 1, grid_out, gi, sp.dt_p2g, vol[p], vol[p] * mat_par[mid, C_DENSITY], r.v, r.C,
               r.tau, flags, bbox)


@wp.func
def elastic_energy_density(model: int, r: G2PResult, mat_par: wp.array2d(dtype=float), mid: int) -> float:
    """Psi(F_E) per unit reference volume of the returned state (fixed-corotated uses the tracked rotation)."""
    mu = mat_par[mid, C_MU]
    lam = mat_par[mid, C_LAMBDA]
    if model == 0:
        return psi_fixed_corotated(r.F, wp.quat_to_matrix(r.q), mu, lam)
    elif model == 1:
        return psi_neo_hookean(r.F, mu, lam)
    elif model == 4:
        return psi_fluid(wp.determinant(r.F), mat_par[mid, C_BULK], mat_par[mid, C_GAMMA])
    return psi_hencky(r.F, mu, lam)


@wp.kernel
def k_g2p(
    gi: GridInfo,
    sp: StepParams,
    grid_in: wp.array3d(dtype=wp.vec4),
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    C: wp.array(dtype=wp.mat33),
    F: wp.array(dtype=wp.mat33),
    q: wp.array(dtype=wp.quat),
    alpha: wp.array(dtype=float),
    vol: wp.array(dtype=float),
    mat_id: wp.array(dtype=wp.int32),
    mat_model: wp.array(dtype=wp.int32),
    mat_par: wp.array2d(dtype=float),
    flags: wp.array(dtype=wp.int32),
    sums: wp.array(dtype=wp.float64),
    ext: wp.array(dtype=float),
):
    """Stand-alone G2P (last substep of a frame): stores x, v, C, F_E and the plastic state, and accumulates the
    frame statistics: sums = [KE, IE, px, py, pz, mass] (float64), ext = [J min, J max, max speed]."""
    p = wp.tid()
    mid = int(mat_id[p])
    model = mat_model[mid]
    r = g2p_update(p, grid_in, gi, sp, x, F, q, alpha, mid, model, mat_par, flags)
    v[p] = r.v
    C[p] = r.C
    mass = vol[p] * mat_par[mid, C_DENSITY]
    psi = elastic_energy_density(model, r, mat_par, mid)
    J = wp.determinant(r.F)
    vp = r.v
    wp.atomic_add(sums, 0, wp.float64(0.5 * mass * wp.dot(vp, vp)))
    wp.atomic_add(sums, 1, wp.float64(vol[p] * psi))
    wp.atomic_add(sums, 2, wp.float64(mass * vp[0]))
    wp.atomic_add(sums, 3, wp.float64(mass * vp[1]))
    wp.atomic_add(sums, 4, wp.float64(mass * vp[2]))
    wp.atomic_add(sums, 5, wp.float64(mass))
    wp.atomic_min(ext, 0, J)
    wp.atomic_max(ext, 1, J)
    wp.atomic_max(ext, 2, wp.length(vp))


# ============================================================================================ grid kernel
@wp.kernel
def k_grid_update(
    grid: wp.array3d(dtype=wp.vec4),
    other: wp.array3d(dtype=wp.vec4),
    origin: wp.vec3i,
    dt: float,
    gravity: wp.vec3,
    pad: int,
    wall_sticky: int,
    floor_on: int,
    floor_g: float,
    floor_mu: float,
    floor_sticky: int,
    has_bc: int,
    bc_v: wp.array3d(dtype=wp.vec4),
    bc_n: wp.array3d(dtype=wp.vec4),
    react: wp.array3d(dtype=wp.vec4),
    gstats: wp.array(dtype=float),
):
    """Momentum -> velocity, gravity, domain walls, floor, Dirichlet nodes (+ reaction), clear ``other``.

    Launched over the active box only (``origin`` + launch dims): the union of the node boxes touched by the
    current and the previous P2G, so ``other`` (the previous substep's buffer) is fully cleared.
    Walls: nodes within ``pad`` nodes of the grid faces; the velocity component into the wall is removed
    (slip) or the whole velocity (sticky).  Floor: nodes at or below the plane z = floor (``floor_g`` in grid
    units); the normal component is removed only when moving into the floor, the tangential part gets Coulomb
    friction |dv_t| <= mu |v_n| (``floor_mu`` = 0: frictionless slip) or is zeroed (sticky).
    Dirichlet nodes (``bc_v.w`` > 0): velocity <- weighted mean target (full vector, or only its component along
    the mean normal when ``bc_n`` carries one); the reaction m (v_bc - v*) / dt is stored per node divided by the
    node's total weight, to be split among the fingers by :func:`k_bc_reaction`.
    """
    ti, tj, tk = wp.tid()
    i = ti + origin[0]
    j = tj + origin[1]
    k = tk + origin[2]
    other[i, j, k] = wp.vec4(0.0)
    n = grid[i, j, k]
    m = n[3]
    if m <= 0.0:
        return
    v = wp.vec3(n[0], n[1], n[2]) / m + dt * gravity
    nx = grid.shape[0]
    ny = grid.shape[1]
    nz = grid.shape[2]
    # --- domain walls
    if wall_sticky != 0:
        if i < pad or i >= nx - pad or j < pad or j >= ny - pad or k < pad or k >= nz - pad:
            v = wp.vec3(0.0)
    else:
        if (i < pad and v[0] < 0.0) or (i >= nx - pad and v[0] > 0.0):
            v = wp.vec3(0.0, v[1], v[2])
        if (j < pad and v[1] < 0.0) or (j >= ny - pad and v[1] > 0.0):
            v = wp.vec3(v[0], 0.0, v[2])
        if (k < pad and v[2] < 0.0) or (k >= nz - pad and v[2] > 0.0):
            v = wp.vec3(v[0], v[1], 0.0)
    # --- floor plane z = floor, normal +z
    if floor_on != 0 and float(k) <= floor_g + 1.0e-4:
        if floor_sticky != 0:
            v = wp.vec3(0.0)
        elif v[2] < 0.0:
            vn = -v[2]
            vt = wp.vec3(v[0], v[1], 0.0)
            lt = wp.length(vt)
            if floor_mu > 0.0:
                if lt <= floor_mu * vn:
                    vt = wp.vec3(0.0)
                else:
                    vt = vt * (1.0 - floor_mu * vn / lt)
            v = vt
    # --- Dirichlet nodes
    if has_bc != 0:
        b = bc_v[i, j, k]
        W = b[3]
        if W > 0.0:
            vt = wp.vec3(b[0], b[1], b[2]) / W
            bn = bc_n[i, j, k]
            nn = wp.vec3(bn[0], bn[1], bn[2])
            vnew = vt
            ln = wp.length(nn)
            if ln > 1.0e-6 * W:
                nh = nn / ln
                vnew = v + nh * (wp.dot(nh, vt) - wp.dot(nh, v))
            r = (m / (dt * W)) * (vnew - v)
            react[i, j, k] = wp.vec4(r[0], r[1], r[2], 0.0)
            v = vnew
    grid[i, j, k] = wp.vec4(v[0], v[1], v[2], m)
    wp.atomic_max(gstats, 0, wp.length(v))


# ============================================================================================ boundary points
@wp.func
def point_stencil(xp: wp.vec3, gi: GridInfo, flags: wp.array(dtype=wp.int32), substep: int, idx: int) -> wp.vec3:
    g = to_grid(xp, gi)
    if not in_band(g, gi):
        raise_flag(flags, TRACER_OUT, substep, idx)
        g = clamp_to_band(g, gi)
    return g


@wp.kernel
def k_bc_scatter(
    gi: GridInfo,
    px: wp.array(dtype=wp.vec3),
    pv: wp.array(dtype=wp.vec3),
    pn: wp.array(dtype=wp.vec3),
    min_w: float,
    bc_v: wp.array3d(dtype=wp.vec4),
    bc_n: wp.array3d(dtype=wp.vec4),
    flags: wp.array(dtype=wp.int32),
    substep: int,
):
    """Project constrained points (target velocity, optional slip normal) onto the nodes of their stencils."""
    p = wp.tid()
    g = point_stencil(px[p], gi, flags, substep, p)
    b = base_index(g)
    f = frac(g, b)
    wx = bspline_w(f[0])
    wy = bspline_w(f[1])
    wz = bspline_w(f[2])
    vt = pv[p]
    nt = pn[p]
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                if w > min_w:
                    wp.atomic_add(bc_v, b[0] + i, b[1] + j, b[2] + k, wp.vec4(w * vt[0], w * vt[1], w * vt[2], w))
                    wp.atomic_add(bc_n, b[0] + i, b[1] + j, b[2] + k, wp.vec4(w * nt[0], w * nt[1], w * nt[2], 0.0))


@wp.kernel
def k_bc_reaction(
    gi: GridInfo,
    px: wp.array(dtype=wp.vec3),
    pfinger: wp.array(dtype=wp.int32),
    min_w: float,
    dt: float,
    react: wp.array3d(dtype=wp.vec4),
    finger_impulse: wp.array(dtype=wp.vec3),
):
    """finger_impulse[k] += dt * sum over the finger's points and stencil nodes of w * reaction/W."""
    p = wp.tid()
    g = clamp_to_band(to_grid(px[p], gi), gi)
    b = base_index(g)
    f = frac(g, b)
    wx = bspline_w(f[0])
    wy = bspline_w(f[1])
    wz = bspline_w(f[2])
    acc = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = wx[i] * wy[j] * wz[k]
                if w > min_w:
                    r = react[b[0] + i, b[1] + j, b[2] + k]
                    acc = acc + w * wp.vec3(r[0], r[1], r[2])
    wp.atomic_add(finger_impulse, int(pfinger[p]), dt * acc)


@wp.kernel
def k_bc_clear_advance(
    gi: GridInfo,
    px: wp.array(dtype=wp.vec3),
    pv: wp.array(dtype=wp.vec3),
    dt: float,
    advance: int,
    bc_v: wp.array3d(dtype=wp.vec4),
    bc_n: wp.array3d(dtype=wp.vec4),
    react: wp.array3d(dtype=wp.vec4),
):
    """Clear the boundary arrays at the stencil nodes, then move the points by dt * target velocity."""
    p = wp.tid()
    g = clamp_to_band(to_grid(px[p], gi), gi)
    b = base_index(g)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                bc_v[b[0] + i, b[1] + j, b[2] + k] = wp.vec4(0.0)
                bc_n[b[0] + i, b[1] + j, b[2] + k] = wp.vec4(0.0)
                react[b[0] + i, b[1] + j, b[2] + k] = wp.vec4(0.0)
    if advance != 0:
        px[p] = px[p] + dt * pv[p]


@wp.kernel
def k_force_weights(
    gi: GridInfo,
    px: wp.array(dtype=wp.vec3),
    pfinger: wp.array(dtype=wp.int32),
    grid: wp.array3d(dtype=wp.vec4),
    finger_w: wp.array(dtype=float),
    flags: wp.array(dtype=wp.int32),
    substep: int,
):
    """Total mass-weighted B-spline weight sum(w m_i) of each finger's points (force-mode normaliser)."""
    p = wp.tid()
    g = point_stencil(px[p], gi, flags, substep, p)
    b = base_index(g)
    f = frac(g, b)
    wx = bspline_w(f[0])
    wy = bspline_w(f[1])
    wz = bspline_w(f[2])
    acc = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                m = grid[b[0] + i, b[1] + j, b[2] + k][3]
                if m > 0.0:
                    acc += wx[i] * wy[j] * wz[k] * m
    wp.atomic_add(finger_w, int(pfinger[p]), acc)


@wp.kernel
def k_force_apply(
    gi: GridInfo,
    px: wp.array(dtype=wp.vec3),
    pfinger: wp.array(dtype=wp.int32),
    finger_force: wp.array(dtype=wp.vec3),
    finger_w: wp.array(dtype=float),
    dt: float,
    grid: wp.array3d(dtype=wp.vec4),
    finger_impulse: wp.array(dtype=wp.vec3),
):
    """Add dt F_k w m_i / W_k momentum to the stencil nodes (W_k = sum w m): the total impulse per finger is
    exactly F_k dt, whatever the number of points or particles, and every node under the patch gets the same
    acceleration (a light fringe node is not flung away, as it would be with a weight-only split)."""
    p = wp.tid()
    kf = int(pfinger[p])
    W = finger_w[kf]
    if W <= 0.0:
        return
    Fk = finger_force[kf] * (dt / W)
    g = clamp_to_band(to_grid(px[p], gi), gi)
    b = base_index(g)
    f = frac(g, b)
    wx = bspline_w(f[0])
    wy = bspline_w(f[1])
    wz = bspline_w(f[2])
    acc = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                m = grid[b[0] + i, b[1] + j, b[2] + k][3]
                if m > 0.0:
                    w = wx[i] * wy[j] * wz[k] * m
                    wp.atomic_add(grid, b[0] + i, b[1] + j, b[2] + k, wp.vec4(w * Fk[0], w * Fk[1], w * Fk[2], 0.0))
                    acc += w
    wp.atomic_add(finger_impulse, kf, acc * Fk)


# ============================================================================================ tracers
@wp.kernel
def k_tracer_g2p(
    gi: GridInfo,
    grid: wp.array3d(dtype=wp.vec4),
    dt: float,
    tx: wp.array(dtype=wp.vec3),
    tF: wp.array(dtype=wp.mat33),
    flags: wp.array(dtype=wp.int32),
    substep: int,
):
    """Massless tracers (surface Gaussians): advect with the grid velocity, F <- (I + dt grad v) F.

    Interpolation is normalised over the stencil nodes that carry mass, so a tracer slightly outside the
    particle cloud follows the nearest material instead of being slowed by empty nodes.
    """
    p = wp.tid()
    g = point_stencil(tx[p], gi, flags, substep, p)
    b = base_index(g)
    f = frac(g, b)
    wx = bspline_w(f[0])
    wy = bspline_w(f[1])
    wz = bspline_w(f[2])
    v = wp.vec3(0.0)
    B = wp.mat33(0.0)
    dbar = wp.vec3(0.0)
    wsum = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                n = grid[b[0] + i, b[1] + j, b[2] + k]
                if n[3] > 0.0:
                    w = wx[i] * wy[j] * wz[k]
                    gv = wp.vec3(n[0], n[1], n[2])
                    d = wp.vec3(float(i) - f[0], float(j) - f[1], float(k) - f[2])
                    v = v + w * gv
                    B = B + w * wp.outer(gv, d)
                    dbar = dbar + w * d
                    wsum += w
    if wsum > 1.0e-6:
        v = v / wsum
        # normalised MLS velocity gradient: 4/dx sum w (v_i - v) d^T / W  (= 4/dx sum w v_i d^T for a full stencil)
        Cm = (4.0 * gi.inv_dx / wsum) * (B - wp.outer(v, dbar))
        tx[p] = tx[p] + dt * v
        tF[p] = (wp.identity(n=3, dtype=float) + dt * Cm) @ tF[p]
