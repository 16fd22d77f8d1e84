"""Boundary conditions: the frame's inputs (:mod:`tasks.physics.mpm.inputs`) checked and uploaded into the kernels'
structs (Dirichlet point sets, force patches, colliders with the table as a plane, particle pins), the per-finger
reaction arrays, and the numpy projection of constrained points onto their B-spline stencil nodes.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Optional, Sequence, Union

import numpy as np
import warp as wp

from .inputs import BoundarySpec, Collider, DirichletNodes, DirichletPoints, ForcePatch, ParticlePins
from .kernels.structs import DirichletPointSet

if TYPE_CHECKING:
    from .solver import MPMSolver


def bspline_stencil(g: np.ndarray, base: Optional[np.ndarray] = None):
    """numpy twin of the kernel stencil: base (P,3) int, weights (P,3,3) per axis; with ``base`` given, the
    B-spline's polynomial pieces on the nodes from it (the kernels' ``stencil_on``)."""
    base = np.floor(g - 0.5).astype(np.int64) if base is None else np.asarray(base, np.int64)
    f = g - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)  # (P,3 axes,3)
    return base, w


def alloc_finger_arrays(solver: MPMSolver, k: int) -> None:
    d = solver.device
    solver.n_fingers = k
    solver.finger_react = wp.zeros(k, dtype=wp.vec3, device=d)
    solver.finger_applied = wp.zeros(k, dtype=wp.vec3, device=d)
    solver.col.impulse = solver.finger_react  # the colliders' impulses are the fingers' reactions
    solver._col_version += 1


def ensure_bc_arrays(solver: MPMSolver) -> None:
    if not solver._bc_alloc:
        d = solver.device
        solver.bc_grid.target = wp.zeros(solver.dims, dtype=wp.vec4, device=d)
        solver.bc_grid.proj = wp.zeros(solver.dims, dtype=wp.mat33, device=d)
        solver.bc_grid.reaction = wp.zeros(solver.dims, dtype=wp.vec4, device=d)
        solver._bc_alloc = True
        solver._cmds = None  # recorded grid launches reference the boundary arrays


def project_points(solver: MPMSolver, positions: np.ndarray, velocities: np.ndarray, finger_ids: Optional[np.ndarray] = None,
                   min_weight: float = 0.0) -> DirichletNodes:
    """Project constrained points onto the grid nodes within their B-spline support (numpy).

    Returns the touched nodes with the weight-averaged target velocity and the finger with the largest weight
    share; the solver does the same projection on the device every substep for :class:`DirichletPoints`.
    """
    P = np.asarray(positions, np.float64).reshape(-1, 3)
    V = np.asarray(velocities, np.float64).reshape(-1, 3)
    fid = np.zeros(len(P), np.int64) if finger_ids is None else np.asarray(finger_ids, np.int64)
    g = (P - solver.lo) / solver.dx
    base, w = bspline_stencil(g)
    off = np.stack(np.meshgrid(range(3), range(3), range(3), indexing="ij"), -1).reshape(-1, 3)
    ww = w[:, 0, off[:, 0]] * w[:, 1, off[:, 1]] * w[:, 2, off[:, 2]]  # (P, 27)
    nodes = (base[:, None, :] + off[None]).reshape(-1, 3)
    ww = ww.reshape(-1)
    keep = ww > min_weight
    nodes, ww = nodes[keep], ww[keep]
    vv = np.repeat(V, 27, axis=0)[keep]
    ff = np.repeat(fid, 27)[keep]
    uniq, inv = np.unique(nodes, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    W = np.bincount(inv, weights=ww)
    vel = np.stack([np.bincount(inv, weights=ww * vv[:, c]) for c in range(3)], 1) / W[:, None]
    nf = int(ff.max()) + 1 if len(ff) else 1
    share = np.zeros((len(uniq), nf))
    np.add.at(share, (inv, ff), ww)
    return DirichletNodes(indices=uniq.astype(np.int32), velocities=vel.astype(np.float32),
                          finger_ids=share.argmax(axis=1).astype(np.int32))


def upload_dirichlet(solver: MPMSolver, spec: BoundarySpec) -> list[dict]:
    if spec is None:
        return []
    items = [spec] if isinstance(spec, (DirichletPoints, DirichletNodes)) else list(spec)
    out = []
    for it in items:
        if isinstance(it, DirichletNodes):
            idx = np.asarray(it.indices, np.float64).reshape(-1, 3)
            # the outermost node layer belongs to the domain walls and has no full stencil: skipped
            keep = np.all((idx >= 1) & (idx <= np.asarray(solver.dims) - 2), axis=1)
            it = DirichletNodes(idx[keep], np.broadcast_to(np.asarray(it.velocities, np.float32).reshape(-1, 3),
                                                           (len(idx), 3))[keep],
                                None if it.finger_ids is None else np.asarray(it.finger_ids).reshape(-1)[keep],
                                None if it.normals is None else np.broadcast_to(
                                    np.asarray(it.normals, np.float32).reshape(-1, 3), (len(idx), 3))[keep])
            idx = idx[keep]
            # the point sits on its node, moved 1e-3 dx towards the grid centre: in float32 a node of layer 1
            # would otherwise round to grid coordinate 0.99999976, outside the band [1, dims - 2] every point
            # must lie in (the stencil, base floor(g - 0.5), is the same either way)
            centre = 0.5 * (np.asarray(solver.dims, np.float64) - 1.0)
            pos = solver.lo + (idx + 1e-3 * np.sign(centre - idx)) * solver.dx
            # a point on a node has weight 0.75^3 = 0.42 there and <= 0.75^2 0.125 = 0.07 on the other stencil
            # nodes: min_weight 0.2 keeps exactly that node
            it = DirichletPoints(pos, it.velocities, it.finger_ids, it.normals, min_weight=0.2, advect=False)
        pos = np.asarray(it.positions, np.float32).reshape(-1, 3)
        m = len(pos)
        if m == 0:
            continue
        vel = np.broadcast_to(np.asarray(it.velocities, np.float32).reshape(-1, 3), (m, 3))
        fid = np.zeros(m, np.int32) if it.finger_ids is None else np.asarray(it.finger_ids, np.int32).reshape(m)
        nrm = np.zeros((m, 3), np.float32) if it.normals is None else np.broadcast_to(
            np.asarray(it.normals, np.float32).reshape(-1, 3), (m, 3))
        if nrm.any():
            ln = np.linalg.norm(nrm, axis=1, keepdims=True)
            nrm = np.where(ln > 0, nrm / np.maximum(ln, 1e-30), 0.0).astype(np.float32)
        if fid.min() < 0:
            raise ValueError("finger ids must be >= 0")
        bad = ~(np.isfinite(pos).all(1) & np.isfinite(vel).all(1) & np.isfinite(nrm).all(1))
        if bad.any():  # stability suite guard: a NaN target is an input error, not a numerical blow-up
            raise ValueError(
                f"Dirichlet boundary input contains NaN/inf positions, velocities or normals: {int(bad.sum())} of "
                f"{m} points (fingers {sorted(set(fid[bad].tolist()))}) at frame {solver.frame}, t={solver.time:.6g} s; "
                "the finger field / targets passed to step_frame are corrupt")
        grow_fingers(solver, int(fid.max()) + 1)
        d = solver.device
        pts = DirichletPointSet()
        pts.x = wp.array(np.ascontiguousarray(pos), dtype=wp.vec3, device=d)
        pts.v = wp.array(np.ascontiguousarray(vel), dtype=wp.vec3, device=d)
        pts.n = wp.array(np.ascontiguousarray(nrm), dtype=wp.vec3, device=d)
        pts.finger = wp.array(fid, dtype=wp.int32, device=d)
        pts.min_w = float(it.min_weight)
        pts.advect = int(bool(it.advect))
        out.append(dict(pts=pts, count=m, speed=float(np.linalg.norm(vel, axis=1).max())))
    if out:
        ensure_bc_arrays(solver)
    return out


def upload_forces(solver: MPMSolver, spec: Optional[Union[ForcePatch, Sequence[ForcePatch]]]) -> list[dict]:
    if spec is None:
        return []
    items = [spec] if isinstance(spec, ForcePatch) else list(spec)
    out = []
    for it in items:
        pos = np.asarray(it.positions, np.float32).reshape(-1, 3)
        fid = np.asarray(it.finger_ids, np.int32).reshape(-1)
        forces = np.asarray(it.forces, np.float32).reshape(-1, 3)
        if len(pos) == 0:
            continue
        if fid.max() >= len(forces) or fid.min() < 0:
            raise ValueError("ForcePatch.finger_ids must index ForcePatch.forces")
        if not (np.isfinite(pos).all() and np.isfinite(forces).all()):  # stability suite guard (input error)
            raise ValueError(f"ForcePatch input contains NaN/inf positions or forces at frame {solver.frame}, "
                             f"t={solver.time:.6g} s; the finger forces passed to step_frame are corrupt")
        grow_fingers(solver, len(forces))
        d = solver.device
        ff = np.zeros((solver.n_fingers, 3), np.float32)
        ff[: len(forces)] = forces
        x, follow = wp.array(pos, dtype=wp.vec3, device=d), it.tracers is not None
        if follow and it.particles is not None:
            raise ValueError("ForcePatch: give tracers or particles, not both")
        if follow:  # every tracer is a point; those not in the patch have finger -1 (no push)
            x, fid = solver.tx, points_on(it.tracers, fid, solver.n_tracers, len(solver.tx), "tracers")
        elif it.particles is not None:  # every particle is a point, at its own position
            x, fid = solver.x, points_on(it.particles, fid, solver.n_particles, solver.n_particles, "particles")
        out.append(dict(x=x, f=wp.array(fid, dtype=wp.int32, device=d), F=wp.array(ff, dtype=wp.vec3, device=d),
                        w=wp.zeros(len(ff), dtype=float, device=d), count=len(fid), follow=follow))
    return out


def points_on(index: np.ndarray, fid: np.ndarray, n: int, size: int, name: str) -> np.ndarray:
    """The finger id per entry of a solver array of ``size`` entries (-1: not pushed) for a patch whose points
    are its entries ``index`` (< n, one per point of finger ``fid``)."""
    index = np.asarray(index, np.int64).reshape(-1)
    if len(index) != len(fid) or index.min() < 0 or index.max() >= n:
        raise ValueError(f"ForcePatch.{name} must give one index (< {n}) per point")
    full = np.full(size, -1, np.int32)
    full[index] = fid
    return full


def set_colliders(solver: MPMSolver, rows: list[tuple[int, np.ndarray, np.ndarray, float, np.ndarray, float, int, int]]) -> None:
    """Upload collider rows (kind code, a, b, radius, velocity, friction, finger id, field) into ``solver.col``."""
    d, n = solver.device, len(rows)
    cols = list(zip(*rows)) if n else [[0], [np.zeros(3)], [np.zeros(3)], [0.0], [np.zeros(3)], [0.0], [-1], [-1]]
    solver.col.count = n
    solver.col.kind = wp.array(np.asarray(cols[0], np.int32), dtype=wp.int32, device=d)
    for name, vals in (("a", cols[1]), ("b", cols[2]), ("vel", cols[4])):
        setattr(solver.col, name, wp.array(np.asarray(vals, np.float32).reshape(-1, 3), dtype=wp.vec3, device=d))
    solver.col.radius = wp.array(np.asarray(cols[3], np.float32), dtype=float, device=d)
    solver.col.mu = wp.array(np.asarray(cols[5], np.float32), dtype=float, device=d)
    solver.col.finger = wp.array(np.asarray(cols[6], np.int32), dtype=wp.int32, device=d)
    solver.col.field = wp.array(np.asarray(cols[7], np.int32), dtype=wp.int32, device=d)
    solver.col.fields = int(np.bitwise_or.reduce([3 if f < 0 else 1 << f for f in cols[7]])) if n else 0
    solver.col.work = solver.boundary_work
    solver._col_version += 1


def set_pins(solver: MPMSolver, pins: Optional[ParticlePins], frame_dt: float = 0.0) -> int:
    """Upload the frame's :class:`ParticlePins` into ``solver.col`` (none: ``pins = 0``); returns their number.
    Each pin's path starts at its particle's surface point now and ends at its target at the frame's end,
    ``frame_dt`` (s) later."""
    d, col = solver.device, solver.col
    n = 0 if pins is None else len(np.asarray(pins.indices).reshape(-1))
    solver._pin_speed = 0.0
    if n == 0:
        if col.pins or col.pin_slot is None:
            col.pins, col.pin_slip = 0, 0
            col.pin_slot = wp.full(1, -1, dtype=wp.int32, device=d)
            for name in ("pin_y", "pin_v", "pin_n"):
                setattr(col, name, wp.zeros(1, dtype=wp.vec3, device=d))
            col.pin_arm = wp.zeros(1, dtype=float, device=d)
            col.pin_finger = wp.full(1, -1, dtype=wp.int32, device=d)
            col.pin_free = wp.zeros(1, dtype=wp.int32, device=d)
            solver._col_version += 1
        return 0
    idx = np.asarray(pins.indices, np.int64).reshape(-1)
    target = np.asarray(pins.targets, np.float64).reshape(-1, 3)
    normal = np.asarray(pins.normals, np.float64).reshape(-1, 3)
    fid = (np.full(n, -1, np.int32) if pins.finger_ids is None
           else np.asarray(pins.finger_ids, np.int32).reshape(-1))
    arm = np.ones(n) if pins.arms is None else np.asarray(pins.arms, np.float64).reshape(-1)
    free = np.zeros(n, np.int32) if pins.free is None else np.asarray(pins.free, bool).reshape(-1).astype(np.int32)
    if not (len(target) == len(normal) == len(fid) == len(arm) == len(free) == n):
        raise ValueError(f"ParticlePins: {n} indices but {len(target)} targets, {len(normal)} normals, "
                         f"{len(fid)} finger ids, {len(arm)} arms and {len(free)} free flags")
    if not ((arm >= 0) & (arm <= 1)).all():
        raise ValueError("ParticlePins: arms must lie in [0, 1] (0: the particle's centre, 1: its surface)")
    if idx.min() < 0 or idx.max() >= solver.n_particles or len(np.unique(idx)) != n:
        raise ValueError(f"ParticlePins: indices must be distinct particles in [0, {solver.n_particles})")
    length = np.linalg.norm(normal, axis=1)
    if not (np.isfinite(target).all() and np.isfinite(normal).all() and (length > 0).all()):
        raise ValueError(f"ParticlePins at frame {solver.frame}: NaN/inf targets or zero normals")
    normal = normal / length[:, None]
    start = surface_points(solver, idx, normal, arm)
    velocity = (target - start) / frame_dt
    slot = np.full(solver.n_particles, -1, np.int32)
    slot[idx] = np.arange(n, dtype=np.int32)
    col.pins, col.pin_slip = n, int(bool(pins.slip))
    col.pin_slot = wp.array(slot, dtype=wp.int32, device=d)
    col.pin_y = wp.array(start.astype(np.float32), dtype=wp.vec3, device=d)
    col.pin_v = wp.array(velocity.astype(np.float32), dtype=wp.vec3, device=d)
    col.pin_n = wp.array(normal.astype(np.float32), dtype=wp.vec3, device=d)
    col.pin_arm = wp.array(arm.astype(np.float32), dtype=float, device=d)
    col.pin_finger = wp.array(fid, dtype=wp.int32, device=d)
    col.pin_free = wp.array(free, dtype=wp.int32, device=d)
    grow_fingers(solver, int(fid.max()) + 1)
    solver._pin_speed = float(np.linalg.norm(velocity, axis=1).max())
    solver._col_version += 1
    return n


def pin_finger_of(solver: MPMSolver, particle: int) -> Optional[int]:
    """The finger id of ``particle``'s pin in the frame's uploaded :class:`ParticlePins` (None: not pinned)."""
    if not solver.col.pins:
        return None
    slot = int(solver.col.pin_slot.numpy()[particle])
    return None if slot < 0 else int(solver.col.pin_finger.numpy()[slot])


def upload_colliders(solver: MPMSolver, spec: Optional[Union[Collider, Sequence[Collider]]]) -> int:
    """The frame's colliders plus the table as a plane collider (:meth:`MPMSolver.table_plane_fields`: for every particle
    under ``mpm.contact = surface``, for the released field under ``grid`` contact; friction ``floor_friction``,
    no slip if ``floor_sticky``); returns their number."""
    items = [] if spec is None else ([spec] if isinstance(spec, Collider) else list(spec))
    table = table_plane_fields(solver)
    if table is not None:
        mu = -1.0 if solver.cfg.floor_sticky else float(solver.cfg.floor_friction)
        items = [Collider("plane", (0.0, 0.0, solver.floor_height), (0.0, 0.0, 1.0), friction=mu,
                          field=table)] + items
    rows = []
    for i, c in enumerate(items):
        a, b, vel = (np.asarray(v, np.float64).reshape(3) for v in (c.a, c.b, c.velocity))
        if c.kind not in Collider.KINDS:
            raise ValueError(f"collider {i}: kind '{c.kind}' is not one of {', '.join(Collider.KINDS)}")
        if not (np.isfinite(a).all() and np.isfinite(b).all() and np.isfinite(vel).all()
                and math.isfinite(c.radius) and math.isfinite(c.friction)):
            raise ValueError(f"collider {i} ({c.kind}) has NaN/inf position, velocity, radius or friction at "
                             f"frame {solver.frame}; the colliders passed to step_frame are corrupt")
        if c.kind == "plane":
            if not np.linalg.norm(b) > 0:
                raise ValueError(f"collider {i} (plane): normal b must be non-zero")
            b = b / np.linalg.norm(b)
        elif not c.radius > 0:
            raise ValueError(f"collider {i} ({c.kind}): radius must be > 0 m (got {c.radius})")
        if c.field > 1:
            raise ValueError(f"collider {i} ({c.kind}): field {c.field} is not a velocity field; use 0 (the body), "
                             f"1 (the released field) or -1 (every particle)")
        rows.append((Collider.KINDS.index(c.kind), a, b, float(c.radius), vel, float(c.friction),
                     int(c.finger_id), int(c.field)))
    grow_fingers(solver, max([r[6] + 1 for r in rows], default=0))
    solver._collider_speed = max([float(np.linalg.norm(r[4])) for r in rows], default=0.0)
    if rows or solver.col.count:
        set_colliders(solver, rows)
    return len(rows)


def grow_fingers(solver: MPMSolver, k: int) -> None:
    if k > solver.n_fingers:
        alloc_finger_arrays(solver, k)


def surface_points(solver: MPMSolver, indices: np.ndarray, normals: np.ndarray, arms: Optional[np.ndarray] = None
                   ) -> np.ndarray:
    """(P, 3) m: the surface points of particles ``indices`` along the unit ``normals`` (P, 3), centre + r n
    with r = arm radius |F^T n| (radius half the particle's undeformed spacing; ``arms`` (P,) default 1, 0 the
    centre: :class:`ParticlePins`), as the contact and pin kernels measure them."""
    idx = np.asarray(indices, np.int64).reshape(-1)
    F = solver.deformation_gradients()[idx].astype(np.float64)
    radius = 0.5 * np.cbrt(solver.volumes()[idx].astype(np.float64))
    if arms is not None:
        radius = radius * np.asarray(arms, np.float64).reshape(-1)
    reach = radius * np.linalg.norm(np.einsum("pji,pj->pi", F, normals), axis=1)
    return solver.positions()[idx].astype(np.float64) + reach[:, None] * normals


def table_plane_fields(solver: MPMSolver) -> Optional[int]:
    """Which particles the table (floor) acts on as a plane collider, where their surface touches it: every
    particle under ``mpm.contact = surface`` (-1), the released field's (1) under ``grid`` contact with two
    velocity fields (the body's field keeps the floor as a grid condition, :func:`tasks.physics.mpm.kernels.grid.
    fixed_boundaries`), or none (None: no table, or one field under ``grid`` contact)."""
    if solver.floor_height is None:
        return None
    if solver.cfg.contact == "surface":
        return -1
    return 1 if solver.two_fields else None


def on_table_plane(solver: MPMSolver) -> np.ndarray:
    """(particle,) bool: the particles the table acts on as a plane collider (:meth:`table_plane_fields`)."""
    which = table_plane_fields(solver)
    if which is None:
        return np.zeros(solver.n_particles, bool)
    if which < 0:
        return np.ones(solver.n_particles, bool)
    return solver.mat_field.numpy()[solver.material_ids()] == which
