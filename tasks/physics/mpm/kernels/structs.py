"""The structs the MLS-MPM kernels take (grid geometry, particle state, material table, per-launch scalars,
grid conditions, Dirichlet arrays, colliders, stencils), the error-flag codes and the material table's
columns; and the compile options every kernel module of the engine sets (:data:`KERNEL_OPTIONS`).
"""
from __future__ import annotations

import warp as wp

from .. import materials as M

# CPU: Warp's host flags plus -ffp-contract=fast.  Warp emits one statement per operation, so the compiler's default
# contraction (within a statement) never forms a fused multiply-add; across statements it does (the fused kernel:
# 0 -> 87 FMAs, 1406 -> 1364 instructions, ~10 % less CPU time per particle; results change at float32 round-off).
# Every kernel module of the engine sets them (``wp.set_module_options(KERNEL_OPTIONS)``).
KERNEL_OPTIONS = {"enable_backward": False, "optimization_level": 3,
                  "cpu_compiler_flags": f"{wp.config.cpu_compiler_flags or '-march=native'} -ffp-contract=fast"}

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
    normal: wp.array(dtype=wp.vec3)  # unit normal of a thin wall's particle (plane-stress membrane), zero for a
    # solid one; length 1 when no particle is a membrane.  Elastic models: the rest normal (:func:`membrane_state`;
    # F_E is the whole deformation); von Mises: the current one, updated every substep (plastic flow moves F_E's
    # reference, :func:`membrane_plastic_return`)
    reach: wp.array(dtype=float)  # radius (m) with which the particle's surface reaches a collider (contact_reach)
    x_carry: wp.array(dtype=wp.vec3)  # m: the advection's round-off, the part of dt v that the float32 position could
    # not take, carried into the next substep's step (compensated summation, :func:`round_off`)
    F_carry: wp.array(dtype=wp.mat33)  # the same for F_E's update F_E + dt C F_E (:func:`round_off`)
    wall_offset: wp.array(dtype=float)  # m: a thin wall's Gauss layer's signed rest distance from the wall's


    # mid-surface along ``normal`` (:func:`particle_stencil`), 0 for any other particle; length 1 when none shares


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
    first: int  # index of the launch's first particle (the fused kernel: a thread's share is first + tid)
    wall_k: float  # mpm.wall_normal_stiffness: a thin wall's normal stiffness / 2 mu (0: F_E stored in plane stress)


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
    field_cohesion: float  # N/kg, the released field's only: cohesion / (2 rho dx) (k_field_contact; 0 = none)


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
    fields: int  # bit f set: some collider acts on velocity field f (a particle of another field skips the contact)
    kind: wp.array(dtype=wp.int32)  # COLLIDER_PLANE / _SPHERE / _CAPSULE
    a: wp.array(dtype=wp.vec3)  # plane: a point on it; sphere: centre; capsule: segment end A (m)
    b: wp.array(dtype=wp.vec3)  # plane: unit normal towards the material; capsule: segment end B (m)
    radius: wp.array(dtype=float)  # sphere / capsule radius (m)
    vel: wp.array(dtype=wp.vec3)  # translation velocity (m/s)
    mu: wp.array(dtype=float)  # Coulomb friction coefficient (0: frictionless; < 0: no slip while touching)
    finger: wp.array(dtype=wp.int32)  # finger id whose reaction receives the impulses (< 0: not reported)
    field: wp.array(dtype=wp.int32)  # velocity field it acts on (MaterialTable.field; < 0: every particle)
    impulse: wp.array(dtype=wp.vec3)  # (finger,) impulse the colliders applied to the material (N s)
    work: wp.array(dtype=wp.float64)  # [0]: work of those impulses, impulse . new velocity (J)
    # particle pins (:func:`pin_velocity`): the surface points of some particles driven along prescribed paths
    pins: int  # number of pinned particles (0: none)
    pin_slip: int  # 1: only the normal component of the surface point's velocity is prescribed
    pin_slot: wp.array(dtype=wp.int32)  # (particle,) its pin, or -1 (length 1 when there are none)
    pin_y: wp.array(dtype=wp.vec3)  # (pin,) where its surface point is to be now (m; advanced every substep)
    pin_v: wp.array(dtype=wp.vec3)  # (pin,) the path's velocity (m/s)
    pin_n: wp.array(dtype=wp.vec3)  # (pin,) outward unit normal of the surface at the particle
    pin_arm: wp.array(dtype=float)  # (pin,) where along n it acts, in half spacings: 1 its surface, 0 its centre
    pin_finger: wp.array(dtype=wp.int32)  # (pin,) finger id whose reaction receives its impulses (< 0: none)
    pin_free: wp.array(dtype=wp.int32)  # (pin,) 1: its point may move out along n faster than its path (a hold)


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
    carry: wp.vec3  # m, the advection's round-off after this substep (Particles.x_carry)
    F_carry: wp.mat33  # F_E's update's round-off after this substep (Particles.F_carry)
