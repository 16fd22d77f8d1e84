"""Warp kernels of the MLS-MPM solver (Hu et al. 2018, APIC transfers, quadratic B-splines, 3D).

One substep is   P2G -> grid update -> G2P.  To touch each particle once per substep, the G2P of substep n and
the P2G of substep n+1 are fused in :func:`k_g2p_p2g` (it reads grid buffer A and scatters into buffer B; the
grid update of B clears A); :func:`k_g2p_p2g_fc` is the same kernel specialised for scenes whose particles are
all fixed-corotated (no model branches).  The first P2G of a frame (:func:`k_p2g`) and the last G2P
(:func:`k_g2p`, which also accumulates the frame statistics) are separate kernels, so particle velocities and
affine matrices are stored only at frame boundaries.  Every P2G records the bounding box of the stencils it
touched (``bbox``) and the grid update runs only over the union of the current and previous boxes.

Kernel arguments are bundled in structs: :class:`Particles` (the per-particle state arrays),
:class:`MaterialTable` (model code and parameter row of each material), :class:`GridInfo` (grid geometry),
:class:`StepParams` (per-launch scalars of the particle kernels), :class:`GridStep` (per-launch scalars of the
grid update), :class:`GridConditions` (gravity, domain walls, floor), :class:`DirichletGrid` (the node arrays
of the Dirichlet constraints) and :class:`DirichletPointSet` (one set of constrained points).  A recorded launch
is updated through its one per-launch struct (``sp`` or ``gs``), by name.

Grid layout: ``wp.array3d(dtype=wp.vec4)``, node (i, j, k) at ``lo + (i, j, k) dx``; after P2G a node holds
(momentum, mass), after the grid update (velocity, mass).

Two velocity fields (multi-field MPM, Bardenhagen et al. 2000): each material belongs to field 0 (the body) or
field 1 (released material, fluids; ``MaterialTable.field``).  Field-1 particles scatter into and gather from a
second pair of grid buffers (``grid2_*``), updated by the same grid kernel (gravity, walls, floor; the Dirichlet
constraints and force patches act on the body field only) and coupled to the body only by the frictionless contact
of :func:`k_field_contact`.  While no particle is in field 1 the second grid is never touched (the solver passes a
one-node placeholder and skips its launches), so the single-field path is unchanged.

Index safety: every particle or point coordinate is checked against the safe band of the grid before any grid
access; an offending coordinate (including NaN) is clamped into the band and an error flag is raised in
``flags`` (read by the host, which raises :class:`~tasks.physics.mpm.solver.SimulationError`).  No kernel ever
writes outside the grid, in release or debug mode.

Flag layout (int32 array of length ``N_FLAGS``): for each code c in (OUT_OF_GRID, NONFINITE, EXTREME_J,
POINT_OUT): ``flags[c]`` = number of offences, ``flags[4 + c]`` = first substep index (atomic min),
``flags[8 + c]`` = an offending index (atomic max).
"""
from __future__ import annotations

import warp as wp

from . import materials as M
from .constitutive import (
    MODEL_FIXED_COROTATED,
    MODEL_FLUID,
    MODEL_FOAM,
    MODEL_NEO_HOOKEAN,
    fluid_reset,
    hencky_plastic_return_warm,
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
POINT_OUT = wp.constant(3)
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
C_DILATION = wp.constant(M.COL_DILATION)
C_PHYSICAL_DENSITY = wp.constant(M.COL_PHYSICAL_DENSITY)
C_DAMPING = wp.constant(M.COL_DAMPING)


@wp.struct
class GridInfo:
    """Geometry of the background grid."""

    lo: wp.vec3  # world position of node (0, 0, 0), m
    dx: float  # node spacing, m
    inv_dx: float
    safe_lo: wp.vec3  # lowest allowed particle coordinate, in grid units
    safe_hi: wp.vec3  # highest allowed particle coordinate, in grid units


@wp.struct
class Particles:
    """Per-particle state, arrays of length N (``q``, ``alpha``: length 1 when no particle's model uses them)."""

    x: wp.array(dtype=wp.vec3)  # position, m
    v: wp.array(dtype=wp.vec3)  # velocity, m/s (stored at frame ends)
    C: wp.array(dtype=wp.mat33)  # APIC affine velocity matrix (velocity gradient), 1/s (stored at frame ends)
    F: wp.array(dtype=wp.mat33)  # elastic deformation gradient F_E
    q: wp.array(dtype=wp.quat)  # rotation of F_E (fixed-corotated); eigenbasis of F_E F_E^T (von Mises, foam)
    alpha: wp.array(dtype=float)  # equivalent plastic strain (von Mises, foam)
    vol: wp.array(dtype=float)  # initial volume, m^3
    mat_id: wp.array(dtype=wp.int32)  # row of the particle's material in the MaterialTable


@wp.struct
class MaterialTable:
    """Packed materials (see :func:`~tasks.physics.mpm.materials.pack_table`), one row per material."""

    model: wp.array(dtype=wp.int32)  # (material,) model code, one of the MODEL_* constants
    par: wp.array2d(dtype=float)  # (material, N_COLS) parameters, columns C_* (SI units)
    field: wp.array(dtype=wp.int32)  # (material,) velocity field: 0 the body's grid, 1 the released field's grid


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
    weight_g: wp.vec3  # m/s^2: gravity applied in P2G as the impulse dt_p2g m_phys g (mixed mass scales)
    weight_in_p2g: int  # 1: add that impulse (mixed scales); 0: the grid update adds g / s (uniform scale)


@wp.struct
class GridStep:
    """Per-launch scalars of the grid update."""

    origin: wp.vec3i  # lowest node of the active box (the launch covers origin + launch dims)
    dt: float  # substep, s
    has_bc: int  # 1: Dirichlet nodes are active this substep
    substep: int  # global substep counter (error reports of the boundary points and tracers)


@wp.struct
class GridConditions:
    """Body force and fixed boundaries of the grid update (constant while the solver's materials are)."""

    gravity: wp.vec3  # m/s^2 added to every node's velocity: g / s under a uniform mass scale s, else zero
    pad: int  # wall layer thickness, nodes
    wall_sticky: int  # 1: walls stop the whole velocity; 0: only the component into the wall (slip)
    floor_on: int
    floor_g: float  # floor height in grid units
    floor_mu: float  # Coulomb friction coefficient of the floor (0: frictionless slip)
    floor_sticky: int


@wp.struct
class DirichletGrid:
    """Node arrays of the Dirichlet constraints (grid-shaped, zero outside the constrained stencils)."""

    target: wp.array3d(dtype=wp.vec4)  # (sum w P v_target [m/s], sum w) over the points touching the node
    proj: wp.array3d(dtype=wp.mat33)  # sum w P, P = n n^T for a slip point (unit normal n), I for a sticky one
    reaction: wp.array3d(dtype=wp.vec4)  # (m (v_bc - v*) / (dt W) [N per unit weight], 0)


@wp.struct
class DirichletPointSet:
    """One set of constrained points: target velocities, optional slip normals, finger ids."""

    x: wp.array(dtype=wp.vec3)  # (point,) position, m
    v: wp.array(dtype=wp.vec3)  # (point,) target velocity, m/s
    n: wp.array(dtype=wp.vec3)  # (point,) unit slip normal, or zero
    finger: wp.array(dtype=wp.int32)  # (point,) finger id
    min_w: float  # stencil nodes with a B-spline weight <= min_w are left free
    advect: int  # 1: move the points by dt * target velocity every substep


COLLIDER_PLANE = wp.constant(0)
COLLIDER_SPHERE = wp.constant(1)
COLLIDER_CAPSULE = wp.constant(2)


@wp.struct
class Colliders:
    """Rigid colliders of the surface contact (``mpm.contact = surface``): signed distances acting on the particles
    that touch them (see :func:`contact_velocity`).  Arrays of length >= ``count`` (at least 1)."""

    count: int  # number of active colliders (0: no contact, nothing is evaluated)
    kind: wp.array(dtype=wp.int32)  # COLLIDER_PLANE / _SPHERE / _CAPSULE
    a: wp.array(dtype=wp.vec3)  # plane: a point on it; sphere: centre; capsule: segment end A (m)
    b: wp.array(dtype=wp.vec3)  # plane: unit normal towards the material; capsule: segment end B (m)
    radius: wp.array(dtype=float)  # sphere / capsule radius (m)
    vel: wp.array(dtype=wp.vec3)  # translation velocity (m/s)
    mu: wp.array(dtype=float)  # Coulomb friction coefficient (0: frictionless; < 0: no slip while touching)
    finger: wp.array(dtype=wp.int32)  # finger id whose reaction receives the impulses (< 0: not reported)
    impulse: wp.array(dtype=wp.vec3)  # (finger,) impulse the colliders applied to the material (N s)
    work: wp.array(dtype=wp.float64)  # [0]: work of those impulses, impulse . new velocity (J)


@wp.struct
class Stencil:
    """Quadratic B-spline stencil of a point: nodes base + (i, j, k), i, j, k in {0, 1, 2}."""

    base: wp.vec3i  # lowest node, floor(g - 0.5)
    f: wp.vec3  # g - base, in [0.5, 1.5) per axis (grid units)
    wx: wp.vec3  # weights of the nodes base + (0, 1, 2) along x
    wy: wp.vec3
    wz: wp.vec3


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
def checked_grid_coord(xp: wp.vec3, gi: GridInfo, flags: wp.array(dtype=wp.int32), code: int, substep: int,
                       index: int) -> wp.vec3:
    """Grid coordinate of the world point xp (m); outside the safe band it raises flag ``code`` and is clamped."""
    g = to_grid(xp, gi)
    if not in_band(g, gi):
        raise_flag(flags, code, substep, index)
        g = clamp_to_band(g, gi)
    return g


@wp.func
def clamped_grid_coord(xp: wp.vec3, gi: GridInfo) -> wp.vec3:
    """Grid coordinate of xp clamped into the safe band, without a flag (the point was checked earlier)."""
    return clamp_to_band(to_grid(xp, gi), gi)


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
def stencil_at(g: wp.vec3) -> Stencil:
    """Quadratic B-spline stencil (base node and per-axis weights) of the grid coordinate g (grid units)."""
    s = Stencil()
    s.base = base_index(g)
    s.f = frac(g, s.base)
    s.wx = bspline_w(s.f[0])
    s.wy = bspline_w(s.f[1])
    s.wz = bspline_w(s.f[2])
    return s


@wp.func
def stencil_weight(s: Stencil, i: int, j: int, k: int) -> float:
    """Weight of node base + (i, j, k): the product of the three axis weights."""
    return s.wx[i] * s.wy[j] * s.wz[k]


@wp.func
def point_stencil(xp: wp.vec3, gi: GridInfo, flags: wp.array(dtype=wp.int32), substep: int, idx: int) -> Stencil:
    """Stencil of a boundary or force point at xp (m); a point outside the safe band raises POINT_OUT."""
    return stencil_at(checked_grid_coord(xp, gi, flags, POINT_OUT, substep, idx))


@wp.func
def gather_apic(grid: wp.array3d(dtype=wp.vec4), s: Stencil, inv_dx: float) -> G2PResult:
    """Interpolate velocity and the APIC/MLS affine matrix C = 4/dx^2 sum_i w_i v_i (x_i - x_p)^T.

    Separable form: with offsets o = (i, j, k) and f = g - base, x_i - x_p = dx (o - f), so
    C = 4/dx (S - v f^T) with S[:, c] = sum_i w_i v_i o_c.  Sums run in vec4 (the 4th lane is unused).
    """
    b = s.base
    f = s.f
    wx = s.wx
    wy = s.wy
    wz = s.wz
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
    c = 4.0 * inv_dx
    # C[row, col] = 4/dx (s_col[row] - v[row] f[col]), built element by element (row-major scalars)
    r.C = wp.mat33(
        c * (s0[0] - v[0] * f[0]), c * (s1[0] - v[0] * f[1]), c * (s2[0] - v[0] * f[2]),
        c * (s0[1] - v[1] * f[0]), c * (s1[1] - v[1] * f[1]), c * (s2[1] - v[1] * f[2]),
        c * (s0[2] - v[2] * f[0]), c * (s1[2] - v[2] * f[1]), c * (s2[2] - v[2] * f[2]),
    )
    return r


@wp.func
def scatter_apic(grid: wp.array3d(dtype=wp.vec4), s: Stencil, dx: float, mass: float, mv: wp.vec3, A: wp.mat33,
                 bbox: wp.array(dtype=wp.int32)):
    """P2G: node i receives w_i (mv + A (x_i - x_p)) momentum (mv: the particle's momentum, kg m/s, plus any body
    impulse) and w_i m mass; records the stencil bounding box.

    A (x_i - x_p) = dx A (o - f) = p0 + i a0 + j a1 + k a2, evaluated in vec4 with the mass in the 4th lane.
    """
    b = s.base
    f = s.f
    a0 = dx * wp.vec4(A[0, 0], A[1, 0], A[2, 0], 0.0)
    a1 = dx * wp.vec4(A[0, 1], A[1, 1], A[2, 1], 0.0)
    a2 = dx * wp.vec4(A[0, 2], A[1, 2], A[2, 2], 0.0)
    p0 = wp.vec4(mv[0], mv[1], mv[2], mass) - (f[0] * a0 + f[1] * a1 + f[2] * a2)
    for i in range(3):
        for j in range(3):
            wij = s.wx[i] * s.wy[j]
            pij = p0 + float(i) * a0 + float(j) * a1
            for k in range(3):
                wp.atomic_add(grid, b[0] + i, b[1] + j, b[2] + k, (wij * s.wz[k]) * (pij + float(k) * a2))
    wp.atomic_min(bbox, 0, b[0])
    wp.atomic_min(bbox, 1, b[1])
    wp.atomic_min(bbox, 2, b[2])
    wp.atomic_max(bbox, 3, b[0])
    wp.atomic_max(bbox, 4, b[1])
    wp.atomic_max(bbox, 5, b[2])


@wp.func
def particle_mass(p: int, mid: int, ps: Particles, mats: MaterialTable) -> float:
    """Mass of particle p (kg): initial volume x (mass-scaled) density of its material ``mid``."""
    return ps.vol[p] * mats.par[mid, C_DENSITY]


@wp.func
def physical_mass(p: int, mid: int, ps: Particles, mats: MaterialTable) -> float:
    """Physical (unscaled) mass of particle p (kg): initial volume x physical density; its weight is m_phys g."""
    return ps.vol[p] * mats.par[mid, C_PHYSICAL_DENSITY]


@wp.func
def fluid_stress(F: wp.mat33, gradv: wp.mat33, mid: int, mats: MaterialTable) -> wp.mat33:
    """Kirchhoff stress (Pa) of the Tait fluid ``mid`` at F_E with velocity gradient gradv (1/s)."""
    return tau_fluid(wp.determinant(F), gradv, mats.par[mid, C_BULK], mats.par[mid, C_GAMMA],
                     mats.par[mid, C_VISCOSITY])


@wp.func
def stored_state(p: int, mid: int, model: int, ps: Particles, mats: MaterialTable, sp: StepParams) -> G2PResult:
    """Stored state of particle p (x, v, C, F_E, rotation q) and the Kirchhoff stress of its already
    return-mapped F_E (used by the frame's first P2G; fixed-corotated refines q by Newton iteration)."""
    r = G2PResult()
    r.x = ps.x[p]
    r.v = ps.v[p]
    r.C = ps.C[p]
    r.F = ps.F[p]
    r.q = wp.quat_identity()
    mu = mats.par[mid, C_MU]
    lam = mats.par[mid, C_LAMBDA]
    if model == MODEL_FIXED_COROTATED:
        r.q = polar_rotation_quat(r.F, ps.q[p], sp.polar_iters, sp.polar_tol)
        r.tau = tau_fixed_corotated(r.F, wp.quat_to_matrix(r.q), mu, lam)
    elif model == MODEL_NEO_HOOKEAN:
        r.tau = tau_neo_hookean(r.F, mu, lam)
    elif model == MODEL_FLUID:
        r.tau = fluid_stress(r.F, r.C, mid, mats)
    else:
        r.tau = tau_hencky(r.F, mu, lam)
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
def collider_distance(col: Colliders, c: int, x: wp.vec3) -> wp.vec4:
    """Signed distance (m, 4th lane; > 0 on the material's side) of x from collider c and the unit normal at the
    closest surface point pointing towards the material (first three lanes)."""
    kind = col.kind[c]
    a = col.a[c]
    if kind == COLLIDER_PLANE:
        n = col.b[c]
        return wp.vec4(n[0], n[1], n[2], wp.dot(x - a, n))
    centre = a
    if kind == COLLIDER_CAPSULE:
        ab = col.b[c] - a
        t = wp.clamp(wp.dot(x - a, ab) / wp.max(wp.dot(ab, ab), 1.0e-30), 0.0, 1.0)
        centre = a + t * ab
    d = x - centre
    ln = wp.length(d)
    n = wp.vec3(0.0, 0.0, 1.0)
    if ln > 0.0:
        n = d / ln
    return wp.vec4(n[0], n[1], n[2], ln - col.radius[c])


@wp.struct
class ContactResult:
    v: wp.vec3  # particle velocity after the contact impulses, m/s
    A: wp.mat33  # affine momentum (kg/s) placing each impulse at its contact point


@wp.func
def contact_velocity(col: Colliders, x: wp.vec3, v: wp.vec3, C: wp.mat33, F: wp.mat33, tau: wp.mat33, vol: float,
                     radius: float, mass: float, dt: float, inv_dx: float) -> ContactResult:
    """Surface contact of one particle (centre x, m; velocity v, m/s; velocity gradient C, 1/s; deformation
    gradient F; radius = half its undeformed spacing, m; mass, kg) with the colliders, before its P2G over the
    coming substep dt (s).

    The particle is the ellipsoid x + F X, |X| <= radius: towards collider c (normal n at the closest surface point,
    signed distance phi_c(x)) it reaches r = radius |F^T n|, so its surface point x - r n has the gap
    g = phi_c(x) - r and, by the particle's affine velocity field, the velocity u = v - r C n.  That point touches
    the collider when g would close within dt: the relative normal velocity u_n = (u - v_c) . n must satisfy
    g + dt (u_n - dt a) >= 0, so u_n is raised to -g / dt + dt a where it is lower (a particle that is not reached in
    this substep is left alone: no halo; one that penetrated is pushed back to the surface).  a = max(-n . tau n, 0)
    V0 / (m 2 r) is the push of the material behind it over the substep (its compressive normal Kirchhoff stress
    tau on its cross-section; without it the particle would settle a dt^2 = eps (c dt)^2 / h into the collider).  Constraining the surface point, not the
    centre, lets the material between the centre and the collider deform (the centre of a particle that touches a
    plate does not move with the plate).  The tangential relative velocity then loses at most mu |du_n| (Coulomb;
    mu = 0 frictionless, mu < 0 no slip).  The change du is added to v; the impulse J = m du enters the P2G
    momentum with the affine term 4/dx^2 J (x_c - x)^T (returned in ``A``), which moves its first moment on the
    grid, sum_i w_i J_i (x_i - x), from the particle centre to the contact point x_c = x - r n (the B-spline's
    second moment is dx^2/4 I) while its total stays J: the push enters the grid as a traction at the material's
    surface, not as a body force centred half a particle inside (which left the layers next to a plate
    under-strained).  J is added to the collider's finger reaction (N s) with its work J . v_new (J)."""
    vn = v
    A = wp.mat33(0.0)
    for c in range(col.count):
        dn = collider_distance(col, c, x)
        n = wp.vec3(dn[0], dn[1], dn[2])
        r = radius * wp.length(wp.transpose(F) @ n)
        gap = dn[3] - r
        vc = col.vel[c]
        rel = vn - r * (C @ n) - vc
        un = wp.dot(rel, n)
        # the material behind pushes the particle on with its normal stress over the coming substep
        push = wp.max(-wp.dot(n, tau @ n), 0.0) * vol / (mass * 2.0 * r)
        need = -gap / dt - un + dt * push
        if need > 0.0:
            vt = rel - un * n
            lt = wp.length(vt)
            mu = col.mu[c]
            keep = float(1.0)
            if mu < 0.0 or lt <= mu * need:
                keep = 0.0
            elif mu > 0.0:
                keep = 1.0 - mu * need / lt
            dv = need * n + (keep - 1.0) * vt
            new = vn + dv
            vn = new
            A = A - (4.0 * inv_dx * inv_dx * mass * r) * wp.outer(dv, n)
            k = col.finger[c]
            if k >= 0:
                wp.atomic_add(col.impulse, k, mass * dv)
            wp.atomic_add(col.work, 0, wp.float64(mass * wp.dot(dv, new)))
    res = ContactResult()
    res.v = vn
    res.A = A
    return res


@wp.func
def scatter_particle(r: G2PResult, p: int, mid: int, substep: int, ps: Particles, mats: MaterialTable,
                     gi: GridInfo, sp: StepParams, grid: wp.array3d(dtype=wp.vec4),
                     grid2: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32),
                     bbox: wp.array(dtype=wp.int32), col: Colliders):
    """MLS-MPM P2G of particle p at r.x with velocity r.v, affine matrix r.C and Kirchhoff stress r.tau, over
    dt = ``sp.dt_p2g``: affine momentum A = -dt V0 4/dx^2 tau + m C (Hu et al. 2018, eq. 29).  Momentum m v plus the
    weight impulse dt m_phys ``sp.weight_g`` (selective mass scaling: each node then gains dt g sum w m_phys); with
    colliders, v after the surface contact (:func:`contact_velocity`).  A particle of the released field
    (``mats.field``) scatters into ``grid2``, the others into ``grid``."""
    g = checked_grid_coord(r.x, gi, flags, OUT_OF_GRID, substep, p)
    vol = ps.vol[p]
    mass = particle_mass(p, mid, ps, mats)
    A = (-sp.dt_p2g * vol * 4.0 * gi.inv_dx * gi.inv_dx) * r.tau + mass * r.C
    mv = mass * r.v
    if col.count > 0:
        cr = contact_velocity(col, r.x, r.v, r.C, r.F, r.tau, vol, 0.5 * wp.pow(vol, 1.0 / 3.0), mass, sp.dt_p2g,
                              gi.inv_dx)
        mv = mass * cr.v
        A = A + cr.A
    if sp.weight_in_p2g != 0:
        mv = mv + (sp.dt_p2g * physical_mass(p, mid, ps, mats)) * sp.weight_g
    if mats.field[mid] == 0:
        scatter_apic(grid, stencil_at(g), gi.dx, mass, mv, A, bbox)
    else:
        scatter_apic(grid2, stencil_at(g), gi.dx, mass, mv, A, bbox)


@wp.func
def g2p_begin(p: int, mid: int, ps: Particles, mats: MaterialTable, gi: GridInfo, sp: StepParams,
              grid: wp.array3d(dtype=wp.vec4), grid2: wp.array3d(dtype=wp.vec4),
              flags: wp.array(dtype=wp.int32)) -> G2PResult:
    """First part of the G2P of particle p, common to every model: gather v (m/s) and C (1/s) from its velocity
    field's grid (``grid``, or ``grid2`` for the released field), the advected position x + dt v (m) and the trial
    elastic deformation gradient (I + dt C) F_E, before the model's update."""
    xp = ps.x[p]
    g = checked_grid_coord(xp, gi, flags, OUT_OF_GRID, sp.substep, p)
    r = G2PResult()
    if mats.field[mid] == 0:
        r = gather_apic(grid, stencil_at(g), gi.inv_dx)
    else:
        r = gather_apic(grid2, stencil_at(g), gi.inv_dx)
    r.F = (wp.identity(n=3, dtype=float) + sp.dt_g2p * r.C) @ ps.F[p]
    r.x = xp + sp.dt_g2p * r.v
    r.q = wp.quat_identity()
    r.alpha = 0.0
    return r


@wp.func
def g2p_end(r: G2PResult, p: int, ps: Particles, sp: StepParams, flags: wp.array(dtype=wp.int32)):
    """Last part of the G2P of particle p: guards on the new state, then store x and F_E."""
    check_particle(r, p, sp, flags)
    ps.x[p] = r.x
    ps.F[p] = r.F


@wp.func
def sign0(x: float) -> float:
    """-1, 0 or 1 (``wp.sign`` gives 1 at 0: a particle at rest would be pushed along its first acceleration)."""
    if x > 0.0:
        return 1.0
    if x < 0.0:
        return -1.0
    return 0.0


@wp.func
def local_damping(r: G2PResult, p: int, mid: int, ps: Particles, mats: MaterialTable) -> G2PResult:
    """Local non-viscous damping (Cundall 1987) of particle p with coefficient a = ``C_DAMPING`` of its material
    (0 <= a < 1): each component of the velocity change dv = v_new - v_old over the substep loses a |dv| against the
    old velocity's direction, i.e. the force m dv / dt becomes F - a |F| sign(v).  It vanishes where the net force
    does (a body at equilibrium or following a slowly varying load), so it damps vibration without a viscous lag.
    Damped particles store their velocity every substep (the next substep's v_old)."""
    a = mats.par[mid, C_DAMPING]
    if a > 0.0:
        v0 = ps.v[p]
        dv = r.v - v0
        r.v = r.v - a * wp.vec3(wp.abs(dv[0]) * sign0(v0[0]), wp.abs(dv[1]) * sign0(v0[1]),
                                wp.abs(dv[2]) * sign0(v0[2]))
        ps.v[p] = r.v
    return r


@wp.func
def corotated_update(r: G2PResult, p: int, ps: Particles, sp: StepParams, mu: float, lam: float) -> G2PResult:
    """Fixed-corotated part of the G2P: rotation of the trial F_E (warm-started from, and stored into, q[p]) and
    the Kirchhoff stress (Pa; mu, lam in Pa)."""
    r.q = rotation_update(r.F, ps.q[p], sp)
    r.tau = tau_fixed_corotated(r.F, wp.quat_to_matrix(r.q), mu, lam)
    ps.q[p] = r.q
    return r


@wp.func
def g2p_update(p: int, mid: int, model: int, ps: Particles, mats: MaterialTable, gi: GridInfo, sp: StepParams,
               grid: wp.array3d(dtype=wp.vec4), grid2: wp.array3d(dtype=wp.vec4),
               flags: wp.array(dtype=wp.int32)) -> G2PResult:
    """G2P of one particle, any model: gather v and C, F_E <- (I + dt C) F_E, return mapping (eq. 5), Kirchhoff
    stress of the new state (eq. 4), advection, guards, :func:`local_damping`; stores x, F_E and the model's state
    (rotation q of fixed-corotated, eigenbasis q and plastic strain alpha of von Mises / foam).  Velocity and C are returned, stored
    only for a damped particle's velocity."""
    r = g2p_begin(p, mid, ps, mats, gi, sp, grid, grid2, flags)
    mu = mats.par[mid, C_MU]
    lam = mats.par[mid, C_LAMBDA]
    if model == MODEL_FIXED_COROTATED:
        r = corotated_update(r, p, ps, sp, mu, lam)
    elif model == MODEL_NEO_HOOKEAN:
        r.tau = tau_neo_hookean(r.F, mu, lam)
    elif model == MODEL_FLUID:
        r.tau = fluid_stress(r.F, r.C, mid, mats)
        r.F = fluid_reset(r.F)
    else:
        pr = hencky_plastic_return_warm(
            r.F, ps.q[p], mu, lam, mats.par[mid, C_YIELD], mats.par[mid, C_HARDENING], ps.alpha[p],
            mats.par[mid, C_VISCOSITY], mats.par[mid, C_CRUSH], mats.par[mid, C_DILATION], int(model == MODEL_FOAM),
            sp.dt_g2p,
        )
        r.F = pr.F
        r.tau = pr.tau
        r.alpha = pr.alpha
        ps.alpha[p] = r.alpha
        ps.q[p] = pr.q
    g2p_end(r, p, ps, sp, flags)
    return local_damping(r, p, mid, ps, mats)


@wp.func
def g2p_update_fc(p: int, mid: int, ps: Particles, mats: MaterialTable, gi: GridInfo, sp: StepParams,
                  grid: wp.array3d(dtype=wp.vec4), grid2: wp.array3d(dtype=wp.vec4),
                  flags: wp.array(dtype=wp.int32)) -> G2PResult:
    """:func:`g2p_update` specialised for a fixed-corotated particle (the common fast path, no model branches)."""
    r = corotated_update(g2p_begin(p, mid, ps, mats, gi, sp, grid, grid2, flags), p, ps, sp, mats.par[mid, C_MU],
                         mats.par[mid, C_LAMBDA])
    g2p_end(r, p, ps, sp, flags)
    return local_damping(r, p, mid, ps, mats)


@wp.func
def elastic_energy_density(model: int, r: G2PResult, mid: int, mats: MaterialTable) -> float:
    """Psi(F_E) per unit reference volume of the returned state (fixed-corotated uses the tracked rotation)."""
    mu = mats.par[mid, C_MU]
    lam = mats.par[mid, C_LAMBDA]
    if model == MODEL_FIXED_COROTATED:
        return psi_fixed_corotated(r.F, wp.quat_to_matrix(r.q), mu, lam)
    elif model == MODEL_NEO_HOOKEAN:
        return psi_neo_hookean(r.F, mu, lam)
    elif model == MODEL_FLUID:
        return psi_fluid(wp.determinant(r.F), mats.par[mid, C_BULK], mats.par[mid, C_GAMMA])
    return psi_hencky(r.F, mu, lam)


# ============================================================================================ particle kernels
@wp.kernel
def k_p2g(gi: GridInfo, sp: StepParams, ps: Particles, mats: MaterialTable, grid_out: wp.array3d(dtype=wp.vec4),
          grid2_out: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32), bbox: wp.array(dtype=wp.int32),
          col: Colliders):
    """Stand-alone P2G (first substep of a frame), stress from the stored F_E (any model)."""
    p = wp.tid()
    mid = int(ps.mat_id[p])
    model = mats.model[mid]
    r = stored_state(p, mid, model, ps, mats, sp)
    if model == MODEL_FIXED_COROTATED:
        ps.q[p] = r.q
    scatter_particle(r, p, mid, sp.substep, ps, mats, gi, sp, grid_out, grid2_out, flags, bbox, col)


@wp.kernel
def k_g2p_p2g(gi: GridInfo, sp: StepParams, ps: Particles, mats: MaterialTable, grid_in: wp.array3d(dtype=wp.vec4),
              grid_out: wp.array3d(dtype=wp.vec4), grid2_in: wp.array3d(dtype=wp.vec4),
              grid2_out: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32), bbox: wp.array(dtype=wp.int32),
              col: Colliders):
    """Fused G2P (substep n, from ``grid_in`` / ``grid2_in``) + P2G (substep n+1, into ``grid_out`` /
    ``grid2_out``; the second grid of each pair is the released field's), any model."""
    p = wp.tid()
    mid = int(ps.mat_id[p])
    r = g2p_update(p, mid, mats.model[mid], ps, mats, gi, sp, grid_in, grid2_in, flags)
    scatter_particle(r, p, mid, sp.substep + 1, ps, mats, gi, sp, grid_out, grid2_out, flags, bbox, col)


@wp.kernel
def k_g2p_p2g_fc(gi: GridInfo, sp: StepParams, ps: Particles, mats: MaterialTable,
                 grid_in: wp.array3d(dtype=wp.vec4), grid_out: wp.array3d(dtype=wp.vec4),
                 grid2_in: wp.array3d(dtype=wp.vec4), grid2_out: wp.array3d(dtype=wp.vec4),
                 flags: wp.array(dtype=wp.int32), bbox: wp.array(dtype=wp.int32), col: Colliders):
    """Fused G2P + P2G when every particle is fixed-corotated (no model branches, no plastic state)."""
    p = wp.tid()
    mid = int(ps.mat_id[p])
    r = g2p_update_fc(p, mid, ps, mats, gi, sp, grid_in, grid2_in, flags)
    scatter_particle(r, p, mid, sp.substep + 1, ps, mats, gi, sp, grid_out, grid2_out, flags, bbox, col)


@wp.kernel
def k_g2p(gi: GridInfo, sp: StepParams, ps: Particles, mats: MaterialTable, grid_in: wp.array3d(dtype=wp.vec4),
          grid2_in: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32), sums: wp.array(dtype=wp.float64), ext: wp.array(dtype=float),
          g_phys: wp.vec3, mat_energy: wp.array2d(dtype=wp.float64)):
    """Stand-alone G2P (last substep of a frame): stores x, v, C, F_E and the plastic state, and accumulates the
    frame statistics: sums = [KE, IE, px, py, pz, mass] (float64), ext = [J min, J max, max speed], and per material
    ``mat_energy[material] = [KE, IE, gravitational PE = -m_phys g_phys . x]`` (J; ``g_phys`` the physical gravity,
    m/s^2)."""
    p = wp.tid()
    mid = int(ps.mat_id[p])
    model = mats.model[mid]
    r = g2p_update(p, mid, model, ps, mats, gi, sp, grid_in, grid2_in, flags)
    ps.v[p] = r.v
    ps.C[p] = r.C
    mass = particle_mass(p, mid, ps, mats)
    psi = elastic_energy_density(model, r, mid, mats)
    J = wp.determinant(r.F)
    vp = r.v
    ke = wp.float64(0.5 * mass * wp.dot(vp, vp))
    ie = wp.float64(ps.vol[p] * psi)
    wp.atomic_add(sums, 0, ke)
    wp.atomic_add(sums, 1, ie)
    wp.atomic_add(sums, 2, wp.float64(mass * vp[0]))
    wp.atomic_add(sums, 3, wp.float64(mass * vp[1]))
    wp.atomic_add(sums, 4, wp.float64(mass * vp[2]))
    wp.atomic_add(sums, 5, wp.float64(mass))
    wp.atomic_add(mat_energy, mid, 0, ke)
    wp.atomic_add(mat_energy, mid, 1, ie)
    wp.atomic_add(mat_energy, mid, 2, wp.float64(-physical_mass(p, mid, ps, mats) * wp.dot(g_phys, r.x)))
    wp.atomic_min(ext, 0, J)
    wp.atomic_max(ext, 1, J)
    wp.atomic_max(ext, 2, wp.length(vp))


# ============================================================================================ grid kernel
@wp.func
def dirichlet_velocity(v: wp.vec3, b: wp.vec3, A: wp.mat33, W: float) -> wp.vec3:
    """Node velocity (m/s) under the constraints projected on it: the least-squares solution of the constrained
    components, v + A^+ (b - A v), with A = sum w P and b = sum w P v_target over the constraint points (P = n n^T
    for a slip point, I for a sticky one).  One normal: v's component along n becomes the weighted mean target
    component, the tangential part stays free; two orthogonal normals (a plate against a wall) keep each normal's
    own component, e.g. normal x with target 0 and normal z with target -0.05 give (0, v_y, -0.05); all sticky
    (A = W I): the weighted mean target b / W.  Directions A does not constrain (singular values <= 1e-6 W) are
    left free."""
    if A[0, 1] == 0.0 and A[0, 2] == 0.0 and A[1, 2] == 0.0 and A[0, 0] == W and A[1, 1] == W and A[2, 2] == W:
        return b / W
    U = wp.mat33()
    sig = wp.vec3()
    V = wp.mat33()
    wp.svd3(A, U, sig, V)
    r = wp.transpose(U) @ (b - A @ v)
    for c in range(3):
        if sig[c] > 1.0e-6 * W:
            r[c] = r[c] / sig[c]
        else:
            r[c] = 0.0
    return v + V @ r


@wp.func
def fixed_boundaries(v_in: wp.vec3, i: int, j: int, k: int, cond: GridConditions, nx: int, ny: int,
                     nz: int) -> wp.vec3:
    """Velocity (m/s) of node (i, j, k) of an (nx, ny, nz) grid after the domain walls and the floor (see
    :func:`k_grid_update`)."""
    pad = cond.pad
    v = v_in
    # 1. domain walls
    if cond.wall_sticky != 0:
        if i < pad or i >= nx - pad or j < pad or j >= ny - pad or k < pad or k >= nz - pad:
            v = wp.vec3(0.0)
    else:
        if (i < pad and v[0] < 0.0) or (i >= nx - pad and v[0] > 0.0):
            v = wp.vec3(0.0, v[1], v[2])
        if (j < pad and v[1] < 0.0) or (j >= ny - pad and v[1] > 0.0):
            v = wp.vec3(v[0], 0.0, v[2])
        if (k < pad and v[2] < 0.0) or (k >= nz - pad and v[2] > 0.0):
            v = wp.vec3(v[0], v[1], 0.0)
    # 2. floor plane z = floor, normal +z
    if cond.floor_on != 0 and float(k) <= cond.floor_g + 1.0e-4:
        if cond.floor_sticky != 0:
            v = wp.vec3(0.0)
        elif v[2] < 0.0:
            vn = -v[2]
            vt = wp.vec3(v[0], v[1], 0.0)
            lt = wp.length(vt)
            mu = cond.floor_mu
            if mu > 0.0:
                if lt <= mu * vn:
                    vt = wp.vec3(0.0)
                else:
                    vt = vt * (1.0 - mu * vn / lt)
            v = vt
    return v


@wp.kernel
def k_grid_update(gs: GridStep, cond: GridConditions, grid: wp.array3d(dtype=wp.vec4),
                  other: wp.array3d(dtype=wp.vec4), bc: DirichletGrid, gstats: wp.array(dtype=float),
                  work: wp.array(dtype=wp.float64)):
    """Momentum -> velocity, gravity, domain walls, floor, Dirichlet nodes (+ reaction), clear ``other``.

    Launched over the active box only (``gs.origin`` + launch dims): the union of the node boxes touched by the
    current and the previous P2G, so ``other`` (the previous substep's buffer) is fully cleared.
    Walls: nodes within ``pad`` nodes of the grid faces; the velocity component into the wall is removed
    (slip) or the whole velocity (sticky).  Floor: nodes at or below the plane z = floor (``floor_g`` in grid
    units); the normal component is removed only when moving into the floor, the tangential part gets Coulomb
    friction |dv_t| <= mu |v_n| (``floor_mu`` = 0: frictionless slip) or is zeroed (sticky).
    Dirichlet nodes (``bc.target.w`` > 0): velocity <- :func:`dirichlet_velocity` (each constraint's prescribed
    components, sticky or slip, several normals combined); the reaction m (v_bc - v*) / dt is stored per node
    divided by the node's total weight, to be split among the fingers by :func:`k_bc_reaction`, and the work the
    constraint did on the node, impulse . new velocity = m (v_bc - v*) . v_bc (J; the discrete work of symplectic
    Euler, where a force does work on the velocity it leaves), is added to ``work[0]`` (energy guard).
    """
    ti, tj, tk = wp.tid()
    i = ti + gs.origin[0]
    j = tj + gs.origin[1]
    k = tk + gs.origin[2]
    dt = gs.dt
    other[i, j, k] = wp.vec4(0.0)
    n = grid[i, j, k]
    m = n[3]
    if m <= 0.0:
        return
    v = fixed_boundaries(wp.vec3(n[0], n[1], n[2]) / m + dt * cond.gravity, i, j, k, cond, grid.shape[0],
                         grid.shape[1], grid.shape[2])
    # Dirichlet nodes
    if gs.has_bc != 0:
        b = bc.target[i, j, k]
        W = b[3]
        if W > 0.0:
            vnew = dirichlet_velocity(v, wp.vec3(b[0], b[1], b[2]), bc.proj[i, j, k], W)
            r = (m / (dt * W)) * (vnew - v)
            bc.reaction[i, j, k] = wp.vec4(r[0], r[1], r[2], 0.0)
            wp.atomic_add(work, 0, wp.float64(m * wp.dot(vnew - v, vnew)))
            v = vnew
    grid[i, j, k] = wp.vec4(v[0], v[1], v[2], m)
    wp.atomic_max(gstats, 0, wp.length(v))


@wp.func
def node_mass(grid: wp.array3d(dtype=wp.vec4), i: int, j: int, k: int) -> float:
    """Mass (kg) of node (i, j, k), indices clamped into the grid."""
    return grid[wp.clamp(i, 0, grid.shape[0] - 1), wp.clamp(j, 0, grid.shape[1] - 1),
                wp.clamp(k, 0, grid.shape[2] - 1)][3]


@wp.func
def mass_gradient(grid: wp.array3d(dtype=wp.vec4), i: int, j: int, k: int) -> wp.vec3:
    """Central-difference gradient of the nodal mass at node (i, j, k) (kg per node spacing)."""
    return wp.vec3(node_mass(grid, i + 1, j, k) - node_mass(grid, i - 1, j, k),
                   node_mass(grid, i, j + 1, k) - node_mass(grid, i, j - 1, k),
                   node_mass(grid, i, j, k + 1) - node_mass(grid, i, j, k - 1))


@wp.kernel
def k_field_contact(gs: GridStep, cond: GridConditions, body: wp.array3d(dtype=wp.vec4),
                    free: wp.array3d(dtype=wp.vec4)):
    """Frictionless contact of the two velocity fields (multi-field MPM: Bardenhagen et al. 2000, sec. 3; normals
    as discussed by Homel & Herbold 2017), after both grid updates, over the active box (``gs.origin`` + launch
    dims).  At a node where both the body field (``body``) and the released field (``free``) carry mass (after the
    update: (velocity m/s, mass kg) per node), n is the unit contact normal from the body towards the released
    material: the body's outward normal -grad m_body / |grad m_body| (central differences of the nodal masses)
    unless it opposes the direction into the released material, grad m_free (more than 120 degrees apart), else
    that direction grad m_free / |grad m_free|.  The body's normal is the accurate one next to a solid body (spray
    falling past it is tangential to it, whatever the spray's own shape), but it flips sign across a shell one
    particle thick (a can's wall): fluid pressing on such a wall from inside reaches nodes beyond it, where the
    body's normal would call the fluid separating and let it through, while the fluid's mass gradient still
    points from the wall into the fluid (there the two are opposite; at the edge of a fluid sheet sliding along a
    wall they are ~90 degrees apart and the wall's normal must stay, or the sheet's own edge would brake it).  If the fields approach, (v_free - v_body) . n < 0, both normal components
    become the centre-of-mass normal velocity (m_b v_b + m_f v_f) . n / (m_b + m_f), which conserves the node's
    momentum and stops the interpenetration while the tangential components stay free (no friction); separating
    fields are left independent (no sticking).  The domain walls and the floor are applied again to the corrected
    velocities."""
    ti, tj, tk = wp.tid()
    i = ti + gs.origin[0]
    j = tj + gs.origin[1]
    k = tk + gs.origin[2]
    a = body[i, j, k]
    b = free[i, j, k]
    mb = a[3]
    mf = b[3]
    if mb <= 0.0 or mf <= 0.0:
        return
    gb = -mass_gradient(body, i, j, k)
    gf = mass_gradient(free, i, j, k)
    lb = wp.length(gb)
    lf = wp.length(gf)
    if lb <= 0.0 and lf <= 0.0:
        return
    n = wp.vec3(0.0)
    if lf <= 0.0 or (lb > 0.0 and wp.dot(gb, gf) >= -0.5 * lb * lf):
        n = gb / lb
    else:
        n = gf / lf
    vb = wp.vec3(a[0], a[1], a[2])
    vf = wp.vec3(b[0], b[1], b[2])
    if wp.dot(vf - vb, n) >= 0.0:
        return
    vn = (mb * wp.dot(vb, n) + mf * wp.dot(vf, n)) / (mb + mf)
    nx = body.shape[0]
    ny = body.shape[1]
    nz = body.shape[2]
    vb = fixed_boundaries(vb + (vn - wp.dot(vb, n)) * n, i, j, k, cond, nx, ny, nz)
    vf = fixed_boundaries(vf + (vn - wp.dot(vf, n)) * n, i, j, k, cond, nx, ny, nz)
    body[i, j, k] = wp.vec4(vb[0], vb[1], vb[2], mb)
    free[i, j, k] = wp.vec4(vf[0], vf[1], vf[2], mf)


# ============================================================================================ boundary points
@wp.kernel
def k_bc_scatter(gi: GridInfo, pts: DirichletPointSet, bc: DirichletGrid, flags: wp.array(dtype=wp.int32),
                 gs: GridStep):
    """Project constrained points (target velocity, optional slip normal) onto the nodes of their stencils: the
    node accumulates w P v_target and w P (P = n n^T for a slip point, I for a sticky one), see
    :func:`dirichlet_velocity`."""
    p = wp.tid()
    s = point_stencil(pts.x[p], gi, flags, gs.substep, p)
    b = s.base
    vt = pts.v[p]
    nt = pts.n[p]
    P = wp.identity(n=3, dtype=float)
    slip = wp.dot(nt, nt) > 0.0
    if slip:
        P = wp.outer(nt, nt)
        vt = P @ vt
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = stencil_weight(s, i, j, k)
                if w > pts.min_w:
                    wp.atomic_add(bc.target, b[0] + i, b[1] + j, b[2] + k,
                                  wp.vec4(w * vt[0], w * vt[1], w * vt[2], w))
                    wp.atomic_add(bc.proj, b[0] + i, b[1] + j, b[2] + k, w * P)


@wp.kernel
def k_bc_reaction(gi: GridInfo, pts: DirichletPointSet, gs: GridStep, bc: DirichletGrid,
                  finger_impulse: wp.array(dtype=wp.vec3)):
    """finger_impulse[k] += dt * sum over the finger's points and stencil nodes of w * reaction/W."""
    p = wp.tid()
    s = stencil_at(clamped_grid_coord(pts.x[p], gi))
    b = s.base
    acc = wp.vec3(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                w = stencil_weight(s, i, j, k)
                if w > pts.min_w:
                    r = bc.reaction[b[0] + i, b[1] + j, b[2] + k]
                    acc = acc + w * wp.vec3(r[0], r[1], r[2])
    wp.atomic_add(finger_impulse, int(pts.finger[p]), gs.dt * acc)


@wp.kernel
def k_bc_clear_advance(gi: GridInfo, pts: DirichletPointSet, gs: GridStep, bc: DirichletGrid):
    """Clear the boundary arrays at the stencil nodes, then move the points by dt * target velocity."""
    p = wp.tid()
    b = base_index(clamped_grid_coord(pts.x[p], gi))
    for i in range(3):
        for j in range(3):
            for k in range(3):
                bc.target[b[0] + i, b[1] + j, b[2] + k] = wp.vec4(0.0)
                bc.proj[b[0] + i, b[1] + j, b[2] + k] = wp.mat33(0.0)
                bc.reaction[b[0] + i, b[1] + j, b[2] + k] = wp.vec4(0.0)
    if pts.advect != 0:
        pts.x[p] = pts.x[p] + gs.dt * pts.v[p]


@wp.kernel
def k_force_weights(gi: GridInfo, px: wp.array(dtype=wp.vec3), pfinger: wp.array(dtype=wp.int32),
                    grid: wp.array3d(dtype=wp.vec4), finger_w: wp.array(dtype=float),
                    flags: wp.array(dtype=wp.int32), substep: int):
    """Total mass-weighted B-spline weight sum(w m_i) of each finger's points (force-mode normaliser)."""
    p = wp.tid()
    s = point_stencil(px[p], gi, flags, substep, p)
    b = s.base
    acc = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                m = grid[b[0] + i, b[1] + j, b[2] + k][3]
                if m > 0.0:
                    acc += stencil_weight(s, i, j, k) * m
    wp.atomic_add(finger_w, int(pfinger[p]), acc)


@wp.func
def patch_impulse_per_weight(finger_force: wp.array(dtype=wp.vec3), finger_w: wp.array(dtype=float), kf: int,
                             dt: float) -> wp.vec3:
    """dt F_k / W_k (N s / kg): finger k's impulse per unit of its patch weight W_k = sum w m; zero for a finger
    whose patch touches no mass (W_k = 0)."""
    W = finger_w[kf]
    if W <= 0.0:
        return wp.vec3(0.0)
    return finger_force[kf] * (dt / W)


@wp.kernel
def k_force_apply(gi: GridInfo, px: wp.array(dtype=wp.vec3), pfinger: wp.array(dtype=wp.int32),
                  finger_force: wp.array(dtype=wp.vec3), finger_w: wp.array(dtype=float), dt: float,
                  grid: wp.array3d(dtype=wp.vec4), finger_impulse: wp.array(dtype=wp.vec3)):
    """Add dt F_k w m_i / W_k momentum to the stencil nodes (W_k = sum w m): the total impulse per finger is
    exactly F_k dt, whatever the number of points or particles, and every node under the patch gets the same
    acceleration (a light fringe node is not flung away, as it would be with a weight-only split).  Its work is
    counted by :func:`k_force_work` once every point has pushed."""
    p = wp.tid()
    kf = int(pfinger[p])
    Fk = patch_impulse_per_weight(finger_force, finger_w, kf, dt)
    if wp.length_sq(Fk) == 0.0:
        return
    s = stencil_at(clamped_grid_coord(px[p], gi))
    b = s.base
    acc = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                m = grid[b[0] + i, b[1] + j, b[2] + k][3]
                if m > 0.0:
                    w = stencil_weight(s, i, j, k) * m
                    wp.atomic_add(grid, b[0] + i, b[1] + j, b[2] + k, wp.vec4(w * Fk[0], w * Fk[1], w * Fk[2], 0.0))
                    acc += w
    wp.atomic_add(finger_impulse, kf, acc * Fk)


@wp.kernel
def k_force_work(gi: GridInfo, px: wp.array(dtype=wp.vec3), pfinger: wp.array(dtype=wp.int32),
                 finger_force: wp.array(dtype=wp.vec3), finger_w: wp.array(dtype=float), dt: float,
                 grid: wp.array3d(dtype=wp.vec4), work: wp.array(dtype=wp.float64)):
    """The work of the pushes of :func:`k_force_apply`, impulse . node velocity after all of them (J, added to
    ``work[0]``): the discrete work of symplectic Euler, F . displacement, as for the Dirichlet nodes.  Read after
    every point has pushed: a node under many points is accelerated by their sum.  (Counting each point's impulse
    against the node velocity before the later points' pushes missed O(dt F^2 / W) per substep, the more the less
    mass scaling: the force-driven tomato at mass scale 26 was credited 0.0256 J for 0.0346 J of work by frame 34,
    and stopped on the energy guard.)"""
    p = wp.tid()
    kf = int(pfinger[p])
    Fk = patch_impulse_per_weight(finger_force, finger_w, kf, dt)
    if wp.length_sq(Fk) == 0.0:
        return
    s = stencil_at(clamped_grid_coord(px[p], gi))
    b = s.base
    power = float(0.0)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                n = grid[b[0] + i, b[1] + j, b[2] + k]
                if n[3] > 0.0:
                    power += stencil_weight(s, i, j, k) * wp.dot(Fk, wp.vec3(n[0], n[1], n[2]))
    wp.atomic_add(work, 0, wp.float64(power))


# ============================================================================================ colliders
@wp.kernel
def k_collider_advance(col: Colliders, dt: float):
    """Move every collider by dt times its velocity (rigid translation, m)."""
    c = wp.tid()
    d = dt * col.vel[c]
    col.a[c] = col.a[c] + d
    if col.kind[c] == COLLIDER_CAPSULE:
        col.b[c] = col.b[c] + d


# ============================================================================================ tracers
@wp.kernel
def k_tracer_embed(x: wp.array(dtype=wp.vec3), F: wp.array(dtype=wp.mat33), anchor: wp.array2d(dtype=wp.int32),
                   weight: wp.array2d(dtype=float), offset: wp.array2d(dtype=wp.vec3), tx: wp.array(dtype=wp.vec3),
                   tF: wp.array(dtype=wp.mat33)):
    """Tracers (surface Gaussians) embedded in the material: tracer t, bound at rest to particles k with weights
    w_tk (sum 1) and rest offsets r_tk = X_t - X_k (m), sits at x_t = sum_k w_tk (x_k + F_k r_tk) with
    F_t = sum_k w_tk F_k.  Exact for any affine motion of its anchors (x = A X + b, F = A), and never farther from
    the material than its anchors' deformed offsets: no drift, unlike a massless point advected by the grid."""
    t = wp.tid()
    xt = wp.vec3(0.0)
    Ft = wp.mat33(0.0)
    for j in range(anchor.shape[1]):
        k = anchor[t, j]
        w = weight[t, j]
        xt = xt + w * (x[k] + F[k] @ offset[t, j])
        Ft = Ft + w * F[k]
    tx[t] = xt
    tF[t] = Ft
