"""The particle kernels of MLS-MPM: P2G (stress and momentum to the grid), G2P (velocity, APIC affine matrix,
F_E update and the material's return mapping), fused in one kernel per substep (:func:`fused_kernel`,
:data:`FUSED`); the frame's first P2G and last G2P (with the frame statistics) stand alone.
"""
from __future__ import annotations

import functools
from typing import Any

import warp as wp

from ..constitutive import (
    MODEL_FIXED_COROTATED,
    MODEL_FLUID,
    MODEL_FOAM,
    MODEL_NEO_HOOKEAN,
    MODEL_VON_MISES,
    PlasticResult,
    area_normal,
    fluid_reset,
    hencky_plastic_return_warm,
    membrane_plastic_return,
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
from .contact import contact_velocity, pin_velocity
from .stencil import checked_grid_coord, gather_apic, raise_flag, scatter_apic
from .structs import (
    C_BULK,
    C_CRUSH,
    C_DAMPING,
    C_DENSITY,
    C_DILATION,
    C_GAMMA,
    C_HARDENING,
    C_LAMBDA,
    C_MU,
    C_PHYSICAL_DENSITY,
    C_VISCOSITY,
    C_YIELD,
    EXTREME_J,
    KERNEL_OPTIONS,
    NONFINITE,
    OUT_OF_GRID,
    Colliders,
    G2PResult,
    GridInfo,
    MaterialTable,
    Particles,
    StepParams,
)
from .walls import (
    membrane_particle,
    membrane_state,
    particle_stencil,
    wall_normal_energy,
    wall_normal_stress,
)

wp.set_module_options(KERNEL_OPTIONS)


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
    return-mapped F_E (used by the frame's first P2G; fixed-corotated refines q by Newton iteration; a thin wall's
    elastic particle as in the G2P: the plane-stress projection plus its normal stiffness)."""
    r = G2PResult()
    r.x = ps.x[p]
    r.v = ps.v[p]
    r.C = ps.C[p]
    r.F = ps.F[p]
    r.q = wp.quat_identity()
    mu = mats.par[mid, C_MU]
    lam = mats.par[mid, C_LAMBDA]
    if model == MODEL_FIXED_COROTATED:
        Fp = membrane_state(r.F, p, MODEL_FIXED_COROTATED, ps, mu, lam)
        r.q = polar_rotation_quat(Fp, ps.q[p], sp.polar_iters, sp.polar_tol)
        r.tau = tau_fixed_corotated(Fp, wp.quat_to_matrix(r.q), mu, lam) + wall_normal_stress(
            r.F, Fp, p, ps, sp, mu)
    elif model == MODEL_NEO_HOOKEAN:
        Fp = membrane_state(r.F, p, MODEL_NEO_HOOKEAN, ps, mu, lam)
        r.tau = tau_neo_hookean(Fp, mu, lam) + wall_normal_stress(r.F, Fp, p, ps, sp, mu)
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
def scatter_particle(r: G2PResult, p: int, mid: int, substep: int, ps: Particles, mats: MaterialTable,
                     gi: GridInfo, sp: StepParams, grid: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32),
                     bbox: wp.array(dtype=wp.int32), col: Colliders):
    """MLS-MPM P2G of particle p at r.x with velocity r.v, affine matrix r.C and Kirchhoff stress r.tau, over
    dt = ``sp.dt_p2g``: affine momentum A = -dt V0 4/dx^2 tau + m C (Hu et al. 2018, eq. 29).  Momentum m v plus the
    weight impulse dt m_phys ``sp.weight_g`` (selective mass scaling: each node then gains dt g sum w m_phys); with
    colliders, v after the surface contact (:func:`contact_velocity`).  ``grid`` is the particle's velocity field's
    grid (the kernel picks it from ``mats.field``)."""
    g = checked_grid_coord(r.x, gi, flags, OUT_OF_GRID, substep, p)
    vol = ps.vol[p]
    mass = particle_mass(p, mid, ps, mats)
    A = (-sp.dt_p2g * vol * 4.0 * gi.inv_dx * gi.inv_dx) * r.tau + mass * r.C
    mv = mass * r.v
    field = mats.field[mid]
    v = r.v
    if col.pins > 0:
        slot = col.pin_slot[p]
        if slot >= 0:
            pr = pin_velocity(col, slot, r.x, v, r.C, r.F, 0.5 * wp.pow(vol, 1.0 / 3.0), mass, sp.dt_p2g, gi.inv_dx)
            v = pr.v
            mv = mass * v
            A = A + pr.A
            if mats.par[mid, C_DAMPING] > 0.0:  # local damping damps the grid's change from the pinned velocity: from
                ps.v[p] = v  # the unpinned one it pumped energy (a held block in the gravity preload blew up)
    if col.count > 0 and ((col.fields >> field) & 1) != 0:
        cr = contact_velocity(col, r.x, v, r.C, r.F, r.tau, vol, ps.reach[p], mass, sp.dt_p2g, gi.inv_dx, field)
        mv = mass * cr.v
        A = A + cr.A
    if sp.weight_in_p2g != 0:
        mv = mv + (sp.dt_p2g * physical_mass(p, mid, ps, mats)) * sp.weight_g
    scatter_apic(grid, particle_stencil(g, p, ps, gi), gi.dx, mass, mv, A, bbox)


@wp.func
def round_off(x: Any, step: Any, x_new: Any):
    """The part of ``step`` that the float32 sum x_new = x + step lost to rounding, exactly, per component (Knuth's
    TwoSum: no multiplication, so no contraction into a fused multiply-add changes it); for a position (vec3, m) and
    for F_E's update (mat33).  A position near 0.1 m resolves 7.5e-9 m, so a substep that should move a particle
    less than half that moves it not at all: on the default grid's ~0.33 ms substeps anything slower than ~1.1e-5
    m/s stood still (a block drifting at 1e-5 m/s on 0.25 ms steps did not move, ``tests/physics/test_mpm_conservation.py``).  An entry
    of F_E near 1 resolves 1.2e-7, so strain increments below 6e-8 per substep were lost (a free stretch at 1e-4 /s
    on 0.25 ms steps kept F_E = I).  Carried into the next step, the lost parts add up.  A model that then projects
    F_E (a return mapping, a plane-stress wall's normal stretch, a fluid's reset) keeps a round-off of at most half
    a unit per entry, so it stays bounded."""
    bb = x_new - x
    return (x - (x_new - bb)) + (step - bb)


@wp.func
def g2p_begin(p: int, ps: Particles, gi: GridInfo, sp: StepParams, grid: wp.array3d(dtype=wp.vec4),
              flags: wp.array(dtype=wp.int32)) -> G2PResult:
    """First part of the G2P of particle p, common to every model: gather v (m/s) and C (1/s) from its velocity
    field's grid (``grid``, picked by the kernel), the advected position x + dt v (m) and the trial elastic
    deformation gradient (I + dt C) F_E, before the model's update."""
    xp = ps.x[p]
    g = checked_grid_coord(xp, gi, flags, OUT_OF_GRID, sp.substep, p)
    r = gather_apic(grid, particle_stencil(g, p, ps, gi), gi.inv_dx)
    F0 = ps.F[p]
    dF = sp.dt_g2p * (r.C @ F0) + ps.F_carry[p]
    r.F = F0 + dF
    r.F_carry = round_off(F0, dF, r.F)
    step = sp.dt_g2p * r.v + ps.x_carry[p]
    r.x = xp + step
    r.carry = round_off(xp, step, r.x)
    r.q = wp.quat_identity()
    r.alpha = 0.0
    return r


@wp.func
def g2p_end(r: G2PResult, p: int, ps: Particles, sp: StepParams, flags: wp.array(dtype=wp.int32)):
    """Last part of the G2P of particle p: guards on the new state, then store x and F_E."""
    check_particle(r, p, sp, flags)
    ps.x[p] = r.x
    ps.x_carry[p] = r.carry
    ps.F[p] = r.F
    ps.F_carry[p] = r.F_carry


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
    """Fixed-corotated part of the G2P: the trial F_E of a membrane particle projected to plane stress
    (:func:`membrane_state`), its rotation (warm-started from, and stored into, q[p]) and the Kirchhoff stress (Pa;
    mu, lam in Pa) of the projection plus the wall's normal stiffness (:func:`wall_normal_stress`; F_E keeps the
    grid's normal stretch, or with ``sp.wall_k`` = 0 becomes the projection)."""
    Fp = membrane_state(r.F, p, MODEL_FIXED_COROTATED, ps, mu, lam)
    r.q = rotation_update(Fp, ps.q[p], sp)
    r.tau = tau_fixed_corotated(Fp, wp.quat_to_matrix(r.q), mu, lam) + wall_normal_stress(
        r.F, Fp, p, ps, sp, mu)
    if sp.wall_k == 0.0:
        r.F = Fp
    ps.q[p] = r.q
    return r


@wp.func
def neo_hookean_update(r: G2PResult, p: int, ps: Particles, sp: StepParams, mu: float, lam: float) -> G2PResult:
    """Neo-Hookean part of the G2P: the Kirchhoff stress (Pa) of the trial F_E, a membrane particle's projected to
    plane stress (:func:`membrane_state`) plus its wall's normal stiffness (with ``sp.wall_k`` = 0 F_E becomes the
    projection)."""
    Fp = membrane_state(r.F, p, MODEL_NEO_HOOKEAN, ps, mu, lam)
    r.tau = tau_neo_hookean(Fp, mu, lam) + wall_normal_stress(r.F, Fp, p, ps, sp, mu)
    if sp.wall_k == 0.0:
        r.F = Fp
    return r


@wp.func
def fluid_update(r: G2PResult, mid: int, mats: MaterialTable) -> G2PResult:
    """Fluid part of the G2P: the Kirchhoff stress (Pa) of the Tait fluid ``mid``, then F_E reset to its volume."""
    r.tau = fluid_stress(r.F, r.C, mid, mats)
    r.F = fluid_reset(r.F)
    return r


@wp.func
def plastic_store(r: G2PResult, pr: PlasticResult, p: int, ps: Particles) -> G2PResult:
    """The returned state of a plastic particle p into ``r`` (F_E, tau, alpha) and its stored alpha and q."""
    r.F = pr.F
    r.tau = pr.tau
    r.alpha = pr.alpha
    ps.alpha[p] = r.alpha
    ps.q[p] = pr.q
    return r


@wp.func
def hencky_update(r: G2PResult, p: int, mid: int, model: int, ps: Particles, mats: MaterialTable, sp: StepParams,
                  mu: float, lam: float) -> G2PResult:
    """Von Mises / foam part of the G2P of a solid particle: the return mapping (eq. 5) in the warm-started
    eigenbasis (:func:`hencky_plastic_return_warm`) and its Kirchhoff stress."""
    return plastic_store(r, hencky_plastic_return_warm(
        r.F, ps.q[p], mu, lam, mats.par[mid, C_YIELD], mats.par[mid, C_HARDENING], ps.alpha[p],
        mats.par[mid, C_VISCOSITY], mats.par[mid, C_CRUSH], mats.par[mid, C_DILATION],
        int(model == MODEL_FOAM), sp.dt_g2p,
    ), p, ps)


@wp.func
def von_mises_membrane_update(r: G2PResult, p: int, mid: int, ps: Particles, mats: MaterialTable, sp: StepParams,
                              mu: float, lam: float) -> G2PResult:
    """Von Mises part of the G2P of a thin wall's particle: the wall's current normal, carried by this substep's
    velocity gradient (Nanson: cof(I + dt C) n; a degenerate or non-finite update keeps the last one, the particle
    stays a membrane), then the plane-stress return (:func:`membrane_plastic_return`)."""
    n = ps.normal[p]
    carried = area_normal(wp.identity(n=3, dtype=float) + sp.dt_g2p * r.C, n)
    size = wp.length(carried)
    if size > 1.0e-6:
        n = carried / size
    ps.normal[p] = n
    return plastic_store(r, membrane_plastic_return(r.F, n, ps.q[p], mu, lam, mats.par[mid, C_YIELD],
                                                    mats.par[mid, C_HARDENING], ps.alpha[p]), p, ps)


@wp.func
def g2p_update(p: int, mid: int, model: int, ps: Particles, mats: MaterialTable, gi: GridInfo, sp: StepParams,
               grid: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32)) -> G2PResult:
    """G2P of one particle, any model: gather v and C, F_E <- (I + dt C) F_E (a membrane's projected to plane
    stress, :func:`membrane_state`), return mapping (eq. 5), Kirchhoff
    stress of the new state (eq. 4), advection, guards, :func:`local_damping`; stores x, F_E and the model's state
    (rotation q of fixed-corotated, eigenbasis q and plastic strain alpha of von Mises / foam).  Velocity and C are returned, stored
    only for a damped particle's velocity.  The fused kernel runs the same parts, only those of its scene's models
    (:func:`fused_kernel`)."""
    r = g2p_begin(p, ps, gi, sp, grid, flags)
    mu = mats.par[mid, C_MU]
    lam = mats.par[mid, C_LAMBDA]
    if model == MODEL_FIXED_COROTATED:
        r = corotated_update(r, p, ps, sp, mu, lam)
    elif model == MODEL_NEO_HOOKEAN:
        r = neo_hookean_update(r, p, ps, sp, mu, lam)
    elif model == MODEL_FLUID:
        r = fluid_update(r, mid, mats)
    elif model == MODEL_VON_MISES and membrane_particle(p, ps):
        r = von_mises_membrane_update(r, p, mid, ps, mats, sp, mu, lam)
    else:
        r = hencky_update(r, p, mid, model, ps, mats, sp, mu, lam)
    g2p_end(r, p, ps, sp, flags)
    return local_damping(r, p, mid, ps, mats)


@wp.func
def g2p_update_fc(p: int, mid: int, ps: Particles, mats: MaterialTable, gi: GridInfo, sp: StepParams,
                  grid: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32)) -> G2PResult:
    """:func:`g2p_update` specialised for a fixed-corotated particle (the common fast path, no model branches)."""
    r = corotated_update(g2p_begin(p, ps, gi, sp, grid, flags), p, ps, sp, mats.par[mid, C_MU],
                         mats.par[mid, C_LAMBDA])
    g2p_end(r, p, ps, sp, flags)
    return local_damping(r, p, mid, ps, mats)


@wp.func
def elastic_energy_density(model: int, r: G2PResult, p: int, mid: int, ps: Particles, mats: MaterialTable,
                           sp: StepParams) -> float:
    """Psi(F_E) per unit reference volume of the returned state (fixed-corotated uses the tracked rotation; a thin
    wall's elastic particle: its plane-stress projection's plus its normal stiffness's, :func:`wall_normal_energy`)."""
    mu = mats.par[mid, C_MU]
    lam = mats.par[mid, C_LAMBDA]
    if model == MODEL_FIXED_COROTATED:
        Fp = membrane_state(r.F, p, MODEL_FIXED_COROTATED, ps, mu, lam)
        return psi_fixed_corotated(Fp, wp.quat_to_matrix(r.q), mu, lam) + wall_normal_energy(
            r.F, Fp, p, ps, sp, mu)
    elif model == MODEL_NEO_HOOKEAN:
        Fp = membrane_state(r.F, p, MODEL_NEO_HOOKEAN, ps, mu, lam)
        return psi_neo_hookean(Fp, mu, lam) + wall_normal_energy(r.F, Fp, p, ps, sp, mu)
    elif model == MODEL_FLUID:
        return psi_fluid(wp.determinant(r.F), mats.par[mid, C_BULK], mats.par[mid, C_GAMMA])
    return psi_hencky(r.F, mu, lam)


@wp.kernel
def k_p2g(gi: GridInfo, sp: StepParams, ps: Particles, mats: MaterialTable, grid_out: wp.array3d(dtype=wp.vec4),
          grid2_out: wp.array3d(dtype=wp.vec4), flags: wp.array(dtype=wp.int32), bbox: wp.array(dtype=wp.int32),
          col: Colliders):
    """Stand-alone P2G (first substep of a frame), stress from the stored F_E (any model); a particle of the
    released field (``mats.field``) scatters into ``grid2_out``."""
    p = wp.tid()
    mid = int(ps.mat_id[p])
    model = mats.model[mid]
    r = stored_state(p, mid, model, ps, mats, sp)
    if model == MODEL_FIXED_COROTATED:
        ps.q[p] = r.q
    dst = grid_out
    if mats.field[mid] != 0:
        dst = grid2_out
    scatter_particle(r, p, mid, sp.substep, ps, mats, gi, sp, dst, flags, bbox, col)


@functools.cache
def fused_kernel(models: frozenset, two_fields: bool) -> wp.Kernel:
    """The fused G2P (substep n, from ``grid_in``) + P2G (substep n+1, into ``grid_out``) kernel of a scene whose
    particles take only the material ``models`` (codes, :data:`~tasks.physics.mpm.materials.MODEL_CODES`), specialised
    at code generation (``wp.static``): the G2P parts of :func:`g2p_update` of those models and no others (a von Mises
    membrane's only with von Mises; all fixed-corotated: :func:`g2p_update_fc`, no model lookup and no branches).
    Code for models a scene does not have costs time even when no particle runs it: on the benchmark's
    fixed-corotated cube the all-models kernel took 268 ns per particle-substep against 190 ns for this one.
    ``two_fields`` for scenes with a released velocity field (a particle of field 1, ``mats.field``, gathers from
    ``grid2_in`` and scatters into ``grid2_out``); without it the second pair is never read (the one-node
    placeholder) and the kernel carries no per-particle field lookup.  Every variant has one signature, so the solver
    records whichever it needs with the same inputs; each is generated and compiled once (its own Warp module,
    cached on disk).  A launch covers the particles ``sp.first`` + tid: with ``mpm.threads`` > 1 each thread runs
    its own share, scattering into its own ``grid_out`` (summed by :func:`k_grid_accumulate`), ``flags`` and
    ``bbox``."""
    corotated = models == frozenset({MODEL_FIXED_COROTATED})
    has_fc, has_nh, has_fluid = (MODEL_FIXED_COROTATED in models, MODEL_NEO_HOOKEAN in models, MODEL_FLUID in models)
    has_vm, has_foam = MODEL_VON_MISES in models, MODEL_FOAM in models

    @wp.kernel(module="unique", module_options=KERNEL_OPTIONS)
    def k_g2p_p2g(gi: GridInfo, sp: StepParams, ps: Particles, mats: MaterialTable,
                  grid_in: wp.array3d(dtype=wp.vec4), grid_out: wp.array3d(dtype=wp.vec4),
                  grid2_in: wp.array3d(dtype=wp.vec4), grid2_out: wp.array3d(dtype=wp.vec4),
                  flags: wp.array(dtype=wp.int32), bbox: wp.array(dtype=wp.int32), col: Colliders):
        p = wp.tid() + sp.first
        mid = int(ps.mat_id[p])
        src = grid_in
        dst = grid_out
        if wp.static(two_fields):
            if mats.field[mid] != 0:
                src = grid2_in
                dst = grid2_out
        r = G2PResult()
        if wp.static(corotated):
            r = g2p_update_fc(p, mid, ps, mats, gi, sp, src, flags)
        else:
            model = mats.model[mid]
            r = g2p_begin(p, ps, gi, sp, src, flags)
            mu = mats.par[mid, C_MU]
            lam = mats.par[mid, C_LAMBDA]
            if wp.static(has_fc):
                if model == MODEL_FIXED_COROTATED:
                    r = corotated_update(r, p, ps, sp, mu, lam)
            if wp.static(has_nh):
                if model == MODEL_NEO_HOOKEAN:
                    r = neo_hookean_update(r, p, ps, sp, mu, lam)
            if wp.static(has_fluid):
                if model == MODEL_FLUID:
                    r = fluid_update(r, mid, mats)
            if wp.static(has_vm):
                if model == MODEL_VON_MISES:
                    if membrane_particle(p, ps):
                        r = von_mises_membrane_update(r, p, mid, ps, mats, sp, mu, lam)
                    else:
                        r = hencky_update(r, p, mid, model, ps, mats, sp, mu, lam)
            if wp.static(has_foam):
                if model == MODEL_FOAM:
                    r = hencky_update(r, p, mid, model, ps, mats, sp, mu, lam)
            g2p_end(r, p, ps, sp, flags)
            r = local_damping(r, p, mid, ps, mats)
        scatter_particle(r, p, mid, sp.substep + 1, ps, mats, gi, sp, dst, flags, bbox, col)

    return k_g2p_p2g


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
    src = grid_in
    if mats.field[mid] != 0:
        src = grid2_in
    r = g2p_update(p, mid, model, ps, mats, gi, sp, src, flags)
    ps.v[p] = r.v
    ps.C[p] = r.C
    mass = particle_mass(p, mid, ps, mats)
    psi = elastic_energy_density(model, r, p, mid, ps, mats, sp)
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
