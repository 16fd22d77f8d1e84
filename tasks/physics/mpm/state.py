"""The solver's state on the device: the background grid (its geometry around the particles and tracers, the two
P2G/grid buffers, the Dirichlet arrays' placeholders), the particle arrays (allocated only for the models present,
bundled in the kernels' :class:`~tasks.physics.mpm.kernels.structs.Particles`), a thin wall's normal-fibre launch,
and the small per-substep buffers (error flags, stencil box, frame sums).  SI units.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np
import warp as wp

from .diagnostics import SimulationError, energy_state_changed, reset_flags
from .kernels.structs import N_FLAGS, Colliders, DirichletGrid, GridInfo, Particles
from .kernels.walls import k_wall_fibres
from .materials import PLASTIC_MODELS
from .model import FIXED_COROTATED, update_fields, upload_materials
from .thin_walls import (
    check_membranes,
    contact_reach,
    convert_membrane_normals,
    membrane_fibres_checked,
    wall_offsets,
)

if TYPE_CHECKING:
    from .solver import MPMSolver


def place_grid(solver: MPMSolver, x: np.ndarray, vol: np.ndarray, tr: Optional[np.ndarray]) -> None:
    """The background grid of the particles ``x`` (N, 3) m of volumes ``vol`` (N,) m^3 and tracers ``tr`` (T, 3) m:
    its spacing (``mpm.dx``, or the largest extent / ``cells_across``), the floor's height, the domain box (the
    bounding box plus ``margin_cells``, down to the floor, or ``domain_lo``/``domain_hi``) with its padding layer,
    and the kernels' :class:`GridInfo`.  A particle starting in the padding is a :class:`SimulationError`."""
    cfg = solver.cfg
    pts = x if tr is None or len(tr) == 0 else np.concatenate([x, tr], axis=0)
    bb_lo, bb_hi = pts.min(axis=0).astype(np.float64), pts.max(axis=0).astype(np.float64)
    extent = float(np.max(bb_hi - bb_lo))
    if cfg.dx is not None:
        dx = float(cfg.dx)
    else:
        dx = max(extent, 1e-6) / cfg.cells_across
    solver.floor_height: Optional[float] = None
    if cfg.floor:
        # default: the lowest particle (not tracer) rests on the floor: its centre (grid contact) or, with surface
        # contact, its surface (centre minus half its spacing, see Collider)
        low = x[:, 2] - (0.5 * np.cbrt(vol) if cfg.contact == "surface" else 0.0)
        solver.floor_height = float(low.min() if cfg.floor_height is None else cfg.floor_height)
    if cfg.domain_lo is not None:
        box_lo = np.asarray(cfg.domain_lo, np.float64)
        box_hi = np.asarray(cfg.domain_hi, np.float64)
    else:
        box_lo = bb_lo - cfg.margin_cells * dx
        box_hi = bb_hi + cfg.margin_cells * dx
        if solver.floor_height is not None:
            box_lo[2] = min(solver.floor_height, bb_lo[2])
    pad = cfg.padding
    dims = np.ceil((box_hi - box_lo) / dx - 1e-9).astype(int) + 2 * pad + 1
    lo = box_lo - pad * dx
    solver.dx = dx
    solver.lo = lo
    solver.dims = tuple(int(d) for d in dims)
    solver.gi = GridInfo()
    solver.gi.lo = wp.vec3(*lo.astype(np.float32))
    solver.gi.dx = float(dx)
    solver.gi.inv_dx = float(1.0 / dx)
    solver.gi.safe_lo = wp.vec3(1.0, 1.0, 1.0)
    solver.gi.safe_hi = wp.vec3(*(np.asarray(solver.dims, np.float32) - 2.0))
    g0 = (x.astype(np.float64) - lo) / dx
    outside = np.any((g0 < pad - 0.5) | (g0 > np.asarray(solver.dims) - pad - 0.5), axis=1)
    if np.any(outside):
        raise SimulationError(
            f"{int(outside.sum())} particles start inside the padding layer / outside the domain box "
            f"[{box_lo.round(4).tolist()}, {box_hi.round(4).tolist()}]: enlarge domain_lo/domain_hi"
        )
    solver.floor_g = 0.0 if solver.floor_height is None else float((solver.floor_height - lo[2]) / dx)


def allocate_particles(solver: MPMSolver, x: np.ndarray, v: np.ndarray, vol: np.ndarray, mid: np.ndarray,
                       normals: Optional[np.ndarray], membrane_fibres: Optional[np.ndarray],
                       codes_present: set[int]) -> None:
    """The particle arrays (positions m, velocities m/s, F_E, APIC C, volumes m^3, material ids; rotation and
    plastic state only when a model present needs them, membrane normals only for a thin wall), the contact radii
    and wall offsets, and the thin walls' normal-fibre launch (``mpm.wall_fibres``)."""
    cfg, d, n = solver.cfg, solver.device, len(x)
    solver.x = wp.array(x, dtype=wp.vec3, device=d)
    solver.x_carry = wp.zeros(n, dtype=wp.vec3, device=d)  # the advection's round-off (kernels.round_off)
    solver.v = wp.array(v, dtype=wp.vec3, device=d)
    solver.C = wp.zeros(n, dtype=wp.mat33, device=d)
    solver.F = wp.array(np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), dtype=wp.mat33, device=d)
    solver.F_carry = wp.zeros(n, dtype=wp.mat33, device=d)  # F_E's update's round-off (kernels.round_off)
    solver.has_corotated = FIXED_COROTATED in codes_present
    solver.has_plastic = any(m.code in PLASTIC_MODELS for m in solver.materials)  # also one assigned mid-run
    qn = n if solver.has_corotated or solver.has_plastic else 1  # rotation / eigenbasis warm starts
    solver.q = wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (qn, 1)), dtype=wp.quat, device=d)
    solver.alpha = wp.zeros(n if solver.has_plastic else 1, dtype=float, device=d)
    solver.vol = wp.array(vol, dtype=float, device=d)
    solver.mat_id = wp.array(mid, dtype=wp.int32, device=d)
    solver.n_membrane = int(np.count_nonzero(solver._membrane_rows))
    solver.normal = wp.array(normals if solver.n_membrane else np.zeros((1, 3), np.float32), dtype=wp.vec3, device=d)
    solver.particles = Particles()
    fibres = membrane_fibres_checked(membrane_fibres, solver._membrane_rows, x)
    solver.reach = wp.array(contact_reach(vol, fibres), dtype=float, device=d)
    shared = fibres is not None and cfg.wall_stencil == "shared"
    solver.wall_offset = wp.array(wall_offsets(x, normals, fibres) if shared else np.zeros(1, np.float32),
                                  dtype=float, device=d)
    for name in ("x", "v", "C", "F", "q", "alpha", "vol", "mat_id", "normal", "reach", "x_carry", "F_carry",
                 "wall_offset"):
        setattr(solver.particles, name, getattr(solver, name))
    seat_floor(solver)
    fibres = fibres if cfg.wall_fibres else None
    solver.n_fibres = 0 if fibres is None else len(fibres.rest)
    solver._fibre_arrays = [] if fibres is None else [  # first, second, rest (a middle layer moves with the grid)
        wp.array(f, device=d) for f in (fibres.first, fibres.second, fibres.rest)]
    solver._fibres = None if fibres is None else wp.launch(
        k_wall_fibres, dim=solver.n_fibres, device=d, record_cmd=True,
        inputs=[solver.x, solver.vol, solver.mat_id, *solver._fibre_arrays])


def seat_floor(solver: MPMSolver) -> None:
    """Under ``mpm.contact = surface`` with the floor's height left to the solver: the table where the lowest
    particle's contact surface is (its centre minus its contact reach, :meth:`MPMSolver.contact_radii`: half its
    spacing, a thin wall's face), so the body rests on it.  :func:`place_grid` sized the domain with half the
    spacing; a thin wall's face lies within that (the rubber ball's 0.6 mm against 1.0-1.5 mm: it hung 0.86 mm above
    the table and dropped onto it in the gravity preload, which then left it there)."""
    cfg = solver.cfg
    if solver.floor_height is None or cfg.floor_height is not None or cfg.contact != "surface":
        return
    z = solver.x.numpy()[:, 2].astype(np.float64) - solver.reach.numpy().astype(np.float64)
    solver.floor_height = float(z.min())
    solver.floor_g = float((solver.floor_height - solver.lo[2]) / solver.dx)


def allocate_grid(solver: MPMSolver) -> None:
    """The two grid buffers (the fused G2P/P2G reads one and fills the other), the released field's placeholders
    and the Dirichlet arrays' placeholders (allocated when a constraint first appears)."""
    d = solver.device
    solver.grid_a = wp.zeros(solver.dims, dtype=wp.vec4, device=d)
    solver.grid_b = wp.zeros(solver.dims, dtype=wp.vec4, device=d)
    solver._bc_alloc = False
    dummy3 = wp.zeros((1, 1, 1), dtype=wp.vec4, device=d)
    # the released field's grid buffer paired with each body buffer (a one-node placeholder while unused)
    solver._field2 = {id(solver.grid_a): dummy3, id(solver.grid_b): dummy3}
    solver.two_fields = False
    solver.field_cohesion = 0.0
    update_fields(solver)
    solver.bc_grid = DirichletGrid()
    solver.bc_grid.target = solver.bc_grid.reaction = dummy3
    solver.bc_grid.proj = wp.zeros((1, 1, 1), dtype=wp.mat33, device=d)


def allocate_buffers(solver: MPMSolver, codes_present: set[int]) -> None:
    """The small per-substep buffers: error flags, grid speed, stencil box (host views on the CPU), frame sums,
    per-material energies, boundary work, and the (empty) colliders."""
    d = solver.device
    solver.flags = wp.zeros(N_FLAGS, dtype=wp.int32, device=d)
    reset_flags(solver)
    solver.gstats = wp.zeros(1, dtype=float, device=d)
    big = 2**30
    solver.bbox_init = wp.array(np.array([big, big, big, -big, -big, -big], np.int32), dtype=wp.int32, device=d)
    solver.bbox = wp.zeros(6, dtype=wp.int32, device=d)
    solver._last_box: Optional[tuple[np.ndarray, np.ndarray]] = None
    solver.all_corotated = codes_present == {FIXED_COROTATED}
    # CPU: host views of the small per-substep buffers (zero-copy); CUDA: device ops + copies
    solver._cpu = wp.get_device(d).is_cpu
    solver._gstats_np = solver.gstats.numpy() if solver._cpu else None
    solver._bbox_np = solver.bbox.numpy() if solver._cpu else None
    solver._cmds: Optional[dict] = None
    solver.sums = wp.zeros(6, dtype=wp.float64, device=d)
    solver.ext = wp.zeros(3, dtype=float, device=d)
    solver.ext_init = wp.array(np.array([np.inf, -np.inf, 0.0], np.float32), dtype=float, device=d)
    solver.mat_energy = wp.zeros((len(solver.materials), 3), dtype=wp.float64, device=d)
    solver.boundary_work = wp.zeros(1, dtype=wp.float64, device=d)  # J, this frame (energy guard)
    solver.col = Colliders()  # surface-contact colliders (count 0: none), see _upload_colliders
    solver._col_version = 0  # bumped when solver.col changes (the recorded launches re-read it)


def assign_materials(solver: MPMSolver, ids: np.ndarray) -> None:
    """Re-assign particle materials (e.g. a ruptured shell).  The new materials must use models whose state
    is already allocated and the same (physical) density: the physical mass, hence the weight, is conserved
    exactly; under selective mass scaling the inertia follows the new material's scale (burst pulp that
    becomes released juice gets its physical mass back).  The set of materials present, the stable time step
    (their wave speeds, fluid viscosity) and the fixed-corotated fast path are updated; the scale s stays as
    it was."""
    energy_state_changed(solver)
    ids = np.asarray(ids, np.int32).reshape(solver.n_particles)
    if ids.min() < 0 or ids.max() >= len(solver.materials):
        raise ValueError(f"material ids must be in [0, {len(solver.materials)})")
    changed = ids != solver._mid_host
    for a, b in {(int(i), int(j)) for i, j in zip(solver._mid_host[changed], ids[changed])}:
        ma, mb = solver.materials[a], solver.materials[b]
        if ma.density != mb.density:
            raise ValueError(f"material {mb.name} has another density than {ma.name}: mass would change")
        if (mb.code == FIXED_COROTATED and not solver.has_corotated) or (mb.is_plastic and not solver.has_plastic):
            raise ValueError(f"material {mb.name} needs solver state that was not allocated")
    check_membranes(solver, ids)
    convert_membrane_normals(solver, ids)
    solver._mid_host = ids.copy()
    solver.mat_id.assign(ids)
    solver._present = sorted(set(int(i) for i in np.unique(ids)))
    solver.all_corotated = {solver.materials[i].code for i in solver._present} == {FIXED_COROTATED}
    upload_materials(solver)
    update_fields(solver)


def state_nbytes(solver: MPMSolver) -> dict[str, int]:
    """Bytes of the per-particle state arrays (allocated only for the models present)."""
    arrs = dict(x=solver.x, x_carry=solver.x_carry, v=solver.v, C=solver.C, F=solver.F, F_carry=solver.F_carry, q=solver.q,
                alpha=solver.alpha, vol=solver.vol, mat_id=solver.mat_id, normal=solver.normal,
                wall_offset=solver.wall_offset)
    return {k: int(a.size * wp.types.type_size_in_bytes(a.dtype)) for k, a in arrs.items()}


def grid_nbytes(solver: MPMSolver) -> int:
    """Bytes of the grid arrays: two vec4 buffers (four once a second velocity field was used), plus the
    Dirichlet target, reaction (vec4) and projector (mat33) arrays once a constraint was used, plus one vec4
    P2G buffer per field for every particle chunk after the first (``mpm.threads`` > 1)."""
    nodes = int(np.prod(solver.dims))
    fields = 2 if solver._field2[id(solver.grid_a)].shape == solver.grid_a.shape else 1
    chunks = sum(16 * nodes * (1 + (sh["grid2"].shape == solver.grid_a.shape)) for sh in solver._shares)
    return nodes * (2 * 16 * fields + ((16 + 16 + 36) if solver._bc_alloc else 0)) + chunks
