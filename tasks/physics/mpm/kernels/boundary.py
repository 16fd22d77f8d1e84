"""Boundary points: Dirichlet point sets projected onto their stencil nodes (targets, reactions, advance) and
force patches (a finger's total force spread over the massive nodes its points touch, and its work).
"""
from __future__ import annotations

import warp as wp

from .stencil import base_index, clamped_grid_coord, point_stencil, stencil_at, stencil_weight
from .structs import KERNEL_OPTIONS, DirichletGrid, DirichletPointSet, GridInfo, GridStep

wp.set_module_options(KERNEL_OPTIONS)


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
                    flags: wp.array(dtype=wp.int32), gs: GridStep):
    """Total mass-weighted B-spline weight sum(w m_i) of each finger's points (force-mode normaliser)."""
    p = wp.tid()
    if pfinger[p] < 0:  # a tracer not in the patch
        return
    s = point_stencil(px[p], gi, flags, gs.substep, p)
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
    if kf < 0:  # a tracer not in the patch
        return wp.vec3(0.0)
    W = finger_w[kf]
    if W <= 0.0:
        return wp.vec3(0.0)
    return finger_force[kf] * (dt / W)


@wp.kernel
def k_force_apply(gi: GridInfo, px: wp.array(dtype=wp.vec3), pfinger: wp.array(dtype=wp.int32),
                  finger_force: wp.array(dtype=wp.vec3), finger_w: wp.array(dtype=float), gs: GridStep,
                  grid: wp.array3d(dtype=wp.vec4), finger_impulse: wp.array(dtype=wp.vec3)):
    """Add dt F_k w m_i / W_k momentum (dt = ``gs.dt``) to the stencil nodes (W_k = sum w m): the total impulse per
    finger is exactly F_k dt, whatever the number of points or particles, and every node under the patch gets the same
    acceleration (a light fringe node is not flung away, as it would be with a weight-only split).  Its work is
    counted by :func:`k_force_work` once every point has pushed."""
    p = wp.tid()
    kf = int(pfinger[p])
    Fk = patch_impulse_per_weight(finger_force, finger_w, kf, gs.dt)
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
                 finger_force: wp.array(dtype=wp.vec3), finger_w: wp.array(dtype=float), gs: GridStep,
                 grid: wp.array3d(dtype=wp.vec4), work: wp.array(dtype=wp.float64)):
    """The work of the pushes of :func:`k_force_apply`, impulse . node velocity after all of them (J, added to
    ``work[0]``): the discrete work of symplectic Euler, F . displacement, as for the Dirichlet nodes.  Read after
    every point has pushed: a node under many points is accelerated by their sum.  (Counting each point's impulse
    against the node velocity before the later points' pushes missed O(dt F^2 / W) per substep, the more the less
    mass scaling: the force-driven tomato at mass scale 26 was credited 0.0256 J for 0.0346 J of work by frame 34,
    and stopped on the energy guard.)"""
    p = wp.tid()
    kf = int(pfinger[p])
    Fk = patch_impulse_per_weight(finger_force, finger_w, kf, gs.dt)
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
