"""The grid update (momentum to velocity, gravity, domain walls, floor, Dirichlet nodes with their reactions),
the contact of the two velocity fields, and the sum of the threads' P2G shares.
"""
from __future__ import annotations

import warp as wp

from .structs import KERNEL_OPTIONS, DirichletGrid, GridConditions, GridStep

wp.set_module_options(KERNEL_OPTIONS)


@wp.kernel
def k_grid_accumulate(origin: wp.vec3i, grid: wp.array3d(dtype=wp.vec4), part: wp.array3d(dtype=wp.vec4)):
    """Add a thread's P2G share ``part`` (momentum kg m/s, mass kg per node) into ``grid`` and clear it, over the
    node box ``origin`` + launch dims that the thread's particles touched (``mpm.threads`` > 1)."""
    ti, tj, tk = wp.tid()
    i = ti + origin[0]
    j = tj + origin[1]
    k = tk + origin[2]
    grid[i, j, k] = grid[i, j, k] + part[i, j, k]
    part[i, j, k] = wp.vec4(0.0)


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
def k_field_contact(gs: GridStep, cond: GridConditions, cond_free: GridConditions, body: wp.array3d(dtype=wp.vec4),
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
    fields are left independent (no sticking) unless the released field is cohesive (``cond_free.field_cohesion`` =
    c / (2 rho dx) > 0, ``Material.cohesion`` c in Pa, rho its density): then the normal impulse that would stop the
    separation, m_b m_f / (m_b + m_f) (v_free - v_body) . n, is applied up to c A dt, A = |grad m_free| / (2 rho dx)
    being the node's share of the interface (m^2: the central difference of a sharp interface's nodal masses sums
    to 2 rho dx^3 across it, so the shares along a line through it add up to dx^2); both fields' momenta change by
    opposite amounts.  Each field's fixed boundaries are applied again to its corrected
    velocity: ``cond`` the body's (walls, floor), ``cond_free`` the released field's (walls; the table acts on
    that field's particles as a plane collider, see the solver's ``_upload_colliders``)."""
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
    w = wp.dot(vf - vb, n)  # m/s, > 0: separating
    if w >= 0.0 and cond_free.field_cohesion <= 0.0:
        return
    nx = body.shape[0]
    ny = body.shape[1]
    nz = body.shape[2]
    if w < 0.0:  # approaching: both normal components become the centre-of-mass one
        vn = (mb * wp.dot(vb, n) + mf * wp.dot(vf, n)) / (mb + mf)
        vb = fixed_boundaries(vb + (vn - wp.dot(vb, n)) * n, i, j, k, cond, nx, ny, nz)
        vf = fixed_boundaries(vf + (vn - wp.dot(vf, n)) * n, i, j, k, cond_free, nx, ny, nz)
    else:  # separating from a cohesive contact: the impulse (N s) that would stop it, up to the cohesion's
        impulse = wp.min(mb * mf / (mb + mf) * w, cond_free.field_cohesion * wp.length(gf) * gs.dt)
        vb = fixed_boundaries(vb + (impulse / mb) * n, i, j, k, cond, nx, ny, nz)
        vf = fixed_boundaries(vf - (impulse / mf) * n, i, j, k, cond_free, nx, ny, nz)
    body[i, j, k] = wp.vec4(vb[0], vb[1], vb[2], mb)
    free[i, j, k] = wp.vec4(vf[0], vf[1], vf[2], mf)
