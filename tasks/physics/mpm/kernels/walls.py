"""Thin walls (a wall thinner than the grid, sampled on Gauss layers through its thickness): membrane particles,
the shared mid-surface stencil of a wall's layers, the wall's normal stiffness, the plane-stress state, and
the normal-fibre kernel that keeps the layers at their rest distance.
"""
from __future__ import annotations

import warp as wp

from ..constitutive import (
    MODEL_FIXED_COROTATED,
    MODEL_NEO_HOOKEAN,
    membrane_F,
    wall_normal_psi,
    wall_normal_tau,
)
from .stencil import base_index, stencil_at, stencil_on
from .structs import C_LAMBDA, C_MU, KERNEL_OPTIONS, GridInfo, MaterialTable, Particles, Stencil, StepParams

wp.set_module_options(KERNEL_OPTIONS)


@wp.func
def membrane_particle(p: int, ps: Particles) -> bool:
    """Whether particle p belongs to a wall thinner than the grid, held in plane stress (a non-zero normal row
    ``ps.normal[p]``: rest or current, :class:`Particles`; the array has length 1 when no particle does)."""
    if ps.normal.shape[0] > 1:
        N = ps.normal[p]
        return wp.dot(N, N) > 0.5
    return False


@wp.func
def particle_stencil(g: wp.vec3, p: int, ps: Particles, gi: GridInfo) -> Stencil:
    """Stencil of particle p at grid coordinate g (its stored position; the P2G and the next G2P read the same
    state, so they use the same nodes).  A Gauss layer of a wall thinner than the grid (``ps.wall_offset[p]`` = d
    != 0, ``mpm.wall_stencil=shared``) takes the base node of its wall's mid-surface, x - d F_E N / |F_E N| (N its
    ``normal``), so both layers of the wall use the same 27 nodes (:func:`stencil_on`, weights at its own position;
    for a wall thinner than a cell they are positive).  With a stencil each, two layers on either side of a plane
    of cell centres spread over four node layers across the wall, and the grid gains velocity modes that move the
    particles but strain neither (a clamped strip whose mid-surface lay there crept under its weight, even as a
    solid)."""
    if ps.wall_offset.shape[0] > 1:
        d = ps.wall_offset[p]
        if d != 0.0 and membrane_particle(p, ps):
            fn = ps.F[p] @ ps.normal[p]
            ln = wp.length(fn)
            if ln > 1.0e-6:
                return stencil_on(g, base_index(g - (d * gi.inv_dx / ln) * fn))
    return stencil_at(g)


@wp.func
def wall_normal_stress(F: wp.mat33, Fp: wp.mat33, p: int, ps: Particles, sp: StepParams, mu: float) -> wp.mat33:
    """Kirchhoff stress (Pa) of particle p's normal stiffness ``sp.wall_k`` x 2 mu (mu in Pa) when it is a thin
    wall's (:func:`~tasks.physics.mpm.constitutive.wall_normal_tau`; F its F_E, Fp the plane-stress projection),
    else 0."""
    if sp.wall_k == 0.0 or not membrane_particle(p, ps):
        return wp.mat33(0.0)
    return wall_normal_tau(F, Fp, ps.normal[p], sp.wall_k * 2.0 * mu)


@wp.func
def wall_normal_energy(F: wp.mat33, Fp: wp.mat33, p: int, ps: Particles, sp: StepParams, mu: float) -> float:
    """Energy density (J/m^3) of particle p's normal stiffness ``sp.wall_k`` x 2 mu when it is a thin wall's
    (:func:`~tasks.physics.mpm.constitutive.wall_normal_psi`), else 0."""
    if sp.wall_k == 0.0 or not membrane_particle(p, ps):
        return 0.0
    return wall_normal_psi(F, Fp, ps.normal[p], sp.wall_k * 2.0 * mu)


@wp.func
def membrane_state(F: wp.mat33, p: int, model: int, ps: Particles, mu: float, lam: float) -> wp.mat33:
    """The elastic trial F_E of particle p with zero normal stress on its wall (:func:`membrane_F`; fixed-corotated
    with its previous substep's rotation ``ps.q[p]``) when p is a thin wall's particle
    (:func:`membrane_particle`), else unchanged."""
    if membrane_particle(p, ps):
        R = wp.identity(n=3, dtype=float)
        if model == MODEL_FIXED_COROTATED:
            R = wp.quat_to_matrix(ps.q[p])
        return membrane_F(F, ps.normal[p], R, model, mu, lam)
    return F


@wp.kernel
def k_plane_stress_F(ps: Particles, mats: MaterialTable, F_out: wp.array(dtype=wp.mat33)):
    """F_E of every particle, a thin wall's elastic particle's as its plane-stress projection (:func:`membrane_state`):
    the material's state, without the grid's normal stretch that its normal stiffness resists
    (``mpm.wall_normal_stiffness``)."""
    p = wp.tid()
    mid = int(ps.mat_id[p])
    model = mats.model[mid]
    F = ps.F[p]
    if model == MODEL_FIXED_COROTATED or model == MODEL_NEO_HOOKEAN:
        F = membrane_state(F, p, model, ps, mats.par[mid, C_MU], mats.par[mid, C_LAMBDA])
    F_out[p] = F


@wp.kernel
def k_wall_fibres(x: wp.array(dtype=wp.vec3), vol: wp.array(dtype=float), mat_id: wp.array(dtype=wp.int32),
                  first: wp.array(dtype=wp.int32), second: wp.array(dtype=wp.int32), rest: wp.array(dtype=float)):
    """The normal fibre of a wall thinner than the grid (Kirchhoff-Love's inextensible director): the particles of
    its two Gauss layers, ``first[k]`` and ``second[k]``, are put back at their rest distance ``rest[k]`` (m) along
    the line joining them, about their common centre of mass (same material: their volumes weigh them), so
    momentum and angular momentum are unchanged.  The grid cannot resolve the wall's thickness, so nothing else
    keeps it: its plane-stress particles carry no normal stress, and a contact on one face closes the layers, and
    with them the wall's bending lever arm (the ball between two flats: 11 % of it left under the flats at 4 mm).
    A pair whose particles no longer share a material (one released) is left alone."""
    k = wp.tid()
    i = first[k]
    j = second[k]
    if mat_id[i] != mat_id[j]:
        return
    d = x[i] - x[j]
    length = wp.length(d)
    if length < 1.0e-12:
        return
    corr = d * ((rest[k] - length) / length)
    wi = vol[j] / (vol[i] + vol[j])
    x[i] = x[i] + wi * corr
    x[j] = x[j] - (1.0 - wi) * corr
