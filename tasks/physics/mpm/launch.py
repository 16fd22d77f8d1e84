"""Launching the kernels of a substep: the per-launch structs, the recorded launches replayed every substep (a
``wp.launch`` costs ~0.1-0.3 ms of Python), the grid update over the active node box, the fused G2P/P2G split
over CPU threads (``mpm.threads``: chunks with their own grids, summed in chunk order), and the garbage
collector kept to the objects a frame makes.
"""
from __future__ import annotations

import gc
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from .diagnostics import reset_flags
from .kernels import boundary as boundary_kernels
from .kernels import contact as contact_kernels
from .kernels import grid as grid_kernels
from .kernels import tracers as tracer_kernels
from .kernels import transfer as transfer_kernels
from .kernels import walls as wall_kernels
from .kernels.boundary import (
    k_bc_clear_advance,
    k_bc_reaction,
    k_bc_scatter,
    k_force_apply,
    k_force_weights,
    k_force_work,
)
from .kernels.grid import k_field_contact, k_grid_accumulate, k_grid_update
from .kernels.structs import N_FLAGS, Colliders, GridConditions, GridStep, StepParams
from .kernels.transfer import fused_kernel as fused_kernel_for
from .materials import MODEL_CODES

if TYPE_CHECKING:
    from .solver import MPMSolver


def set_debug_mode() -> None:
    """Compile every kernel module of the engine in Warp's debug mode (``mpm.debug``: bounds checks)."""
    for module in (boundary_kernels, contact_kernels, grid_kernels, tracer_kernels, transfer_kernels, wall_kernels):
        wp.set_module_options({"mode": "debug"}, module)


# mpm.threads: the hand-over (pool, 4 chunk launches, 3 grid sums) costs ~170 us of CPU per substep (measured on 64
# particles under load) and a thread saves ~80 ns per particle of its share: break-even ~2000 particles, 2x margin
MIN_PARTICLES_PER_THREAD = 4096
CHUNKS_PER_THREAD = 2  # mpm.threads > 1: particle chunks per thread (each has its own P2G grid)


@contextmanager
def young_objects_collected():
    """Inside, Python's cyclic garbage collector scans only the objects made inside (``gc.freeze`` /
    ``gc.unfreeze``): every substep's launches allocate a few Python objects, and the full collection they
    trigger every few hundred substeps scans every object of the process (a pipeline worker holds ~0.5 M).
    Measured on a 4913-particle cube in a process of 140 k objects: one full collection per 600 substeps, 134-212
    ms each under load (~0.2-0.35 ms per 1.2 ms substep); none inside.  Left alone when the caller already froze
    objects or disabled the collector."""
    if gc.get_freeze_count() or not gc.isenabled():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def step_params(solver: MPMSolver, dt_g2p: float, dt_p2g: float, restart: bool = False) -> StepParams:
    sp = StepParams()
    sp.dt_g2p = float(dt_g2p)
    sp.dt_p2g = float(dt_p2g)
    sp.substep = int(solver.substep)
    sp.j_min = float(solver.cfg.j_min)
    sp.j_max = float(solver.cfg.j_max)
    sp.polar_iters = int(solver.cfg.polar_restart_iterations if restart else solver.cfg.polar_iterations)
    sp.polar_tol = float(solver.cfg.polar_tol)
    sp.polar_newton = int(restart or solver.cfg.polar_method == "newton")
    sp.weight_g = wp.vec3(*solver.cfg.gravity)
    sp.weight_in_p2g = int(solver._weight_in_p2g)
    sp.wall_k = float(solver.cfg.wall_normal_stiffness)
    return sp


def grid_conditions(solver: MPMSolver, released: bool = False) -> GridConditions:
    """Gravity (m/s^2: g / s under a uniform mass scale s, else zero: the P2G adds the weight), domain walls
    and floor of the grid update of the body's field, or with ``released`` of the released field (no floor:
    the table acts on its particles as a plane collider, :meth:`table_plane_fields`; and the cohesion of its
    contact with the body, :attr:`field_cohesion`)."""
    cfg = solver.cfg
    gc = GridConditions()
    gc.gravity = wp.vec3(*solver._grid_gravity)
    gc.pad = int(cfg.padding)
    gc.wall_sticky = int(cfg.wall_sticky)
    # surface contact, or the released field: the table is a plane collider
    gc.floor_on = int(solver.floor_height is not None and cfg.contact == "grid" and not released)
    gc.floor_g = float(solver.floor_g)
    gc.floor_mu = float(cfg.floor_friction)
    gc.floor_sticky = int(cfg.floor_sticky)
    gc.field_cohesion = solver.field_cohesion if released else 0.0
    return gc


def kernel_models(solver: MPMSolver) -> frozenset:
    """The material models (codes) the solver's fused kernel is generated for (:func:`fused_kernel_for`): fixed-corotated
    alone while every particle present is, else every model of its material table (a particle may change to any of
    them, e.g. a ruptured skin to foam, without a new kernel)."""
    if solver.all_corotated:
        return frozenset({MODEL_CODES["fixed_corotated"]})
    return frozenset(m.code for m in solver.materials)


def recorded(solver: MPMSolver) -> dict:
    """Recorded launches of the per-substep kernels (fused G2P/P2G, grid update, field contact; one set per grid-buffer
    parity): replaying them avoids re-packing the arguments per launch (a ``wp.launch`` costs ~0.1-0.3 ms of
    Python, which dominates small scenes).  A replay updates only the per-launch struct of each kernel: ``sp``
    (:class:`StepParams`) and ``gs`` (:class:`GridStep`).  The boundary points' launches are recorded per
    frame (:func:`record_bc`)."""
    if solver._cmds is not None:
        return solver._cmds
    d = solver.device
    cmds: dict = {"sp": step_params(solver, 0.0, 0.0), "gs": GridStep()}
    fused_kernel = fused_kernel_for(kernel_models(solver), solver.two_fields)
    conditions = grid_conditions(solver)
    conditions_free = grid_conditions(solver, released=True)
    cmds["gs2"] = GridStep()  # the released field's grid update: no Dirichlet nodes
    shares = thread_shares(solver)
    # one StepParams per chunk: a recorded launch holds its struct argument by reference
    cmds["sp_threads"] = [cmds["sp"]] + [step_params(solver, 0.0, 0.0) for _ in shares]
    for sp, (first, _) in zip(cmds["sp_threads"], solver._ranges):
        sp.first = first
    for cur, other in ((solver.grid_a, solver.grid_b), (solver.grid_b, solver.grid_a)):
        cur2, other2 = solver._field2[id(cur)], solver._field2[id(other)]
        fused = [wp.launch(fused_kernel, dim=solver.n_particles if not shares else solver._ranges[0][1], device=d,
                           record_cmd=True, inputs=[solver.gi, cmds["sp"], solver.particles, solver.mat_table, cur,
                                                    other, cur2, other2, solver.flags, solver.bbox, solver.col])]
        accumulate = []
        for sh, sp, (_, count) in zip(shares, cmds["sp_threads"][1:], solver._ranges[1:]):
            fused.append(wp.launch(fused_kernel, dim=count, device=d, record_cmd=True, inputs=[
                solver.gi, sp, solver.particles, solver.mat_table, cur, sh["grid"], cur2, sh["grid2"],
                sh["flags"], sh["bbox"], sh["col"]]))
            accumulate.append([wp.launch(k_grid_accumulate, dim=(1, 1, 1), device=d, record_cmd=True,
                                         inputs=[wp.vec3i(0, 0, 0), out, part])
                               for out, part in ((other, sh["grid"]), (other2, sh["grid2"]))[:1 + solver.two_fields]])
        grid = wp.launch(k_grid_update, dim=(1, 1, 1), device=d, record_cmd=True, inputs=[
            cmds["gs"], conditions, cur, other, solver.bc_grid, solver.gstats, solver.boundary_work])
        fields = None
        if solver.two_fields:
            fields = (wp.launch(k_grid_update, dim=(1, 1, 1), device=d, record_cmd=True, inputs=[
                cmds["gs2"], conditions_free, cur2, other2, solver.bc_grid, solver.gstats, solver.boundary_work]),
                      wp.launch(k_field_contact, dim=(1, 1, 1), device=d, record_cmd=True, inputs=[
                    cmds["gs"], conditions, conditions_free, cur, cur2]))
        cmds[id(cur)] = (fused, grid, fields, accumulate)
    cmds["col_version"] = {id(solver.grid_a): solver._col_version, id(solver.grid_b): solver._col_version}
    solver._cmds = cmds
    return cmds


def thread_count(solver: MPMSolver) -> int:
    """Threads of the fused kernel: ``mpm.threads`` on the CPU (1 on CUDA), at most one per
    ``MIN_PARTICLES_PER_THREAD`` particles (below, a thread's hand-over costs more than its share saves)."""
    if not solver._cpu:
        return 1
    return max(1, min(int(solver.cfg.threads), solver.n_particles // MIN_PARTICLES_PER_THREAD))


def thread_shares(solver: MPMSolver) -> list[dict]:
    """The buffers of chunks 1.. of the fused kernel (allocated once, the released field's grid when it first
    appears) and the chunks' particle ranges ``_ranges`` [(first, count)] (contiguous, equal).  More chunks than
    threads: a thread that another process slows down leaves its next chunk to the others (each substep waits
    for the last chunk), while every chunk keeps its own buffers, so the sums do not depend on which thread ran
    which chunk (the run is reproducible)."""
    t = solver.threads * CHUNKS_PER_THREAD if solver.threads > 1 else 1
    bounds = np.linspace(0, solver.n_particles, t + 1).round().astype(int)
    solver._ranges = [(int(a), int(b - a)) for a, b in zip(bounds[:-1], bounds[1:])]
    d = solver.device
    while len(solver._shares) < t - 1:
        sh = dict(grid=wp.zeros(solver.dims, dtype=wp.vec4, device=d), grid2=wp.zeros((1, 1, 1), dtype=wp.vec4,
                                                                                     device=d),
                  flags=wp.zeros(N_FLAGS, dtype=wp.int32, device=d), bbox=wp.clone(solver.bbox_init),
                  react=wp.zeros(solver.n_fingers, dtype=wp.vec3, device=d),
                  work=wp.zeros(1, dtype=wp.float64, device=d), col=Colliders())
        reset_flags(solver, sh["flags"])
        sh["bbox_np"] = sh["bbox"].numpy()
        solver._shares.append(sh)
    for sh in solver._shares:
        if solver.two_fields and sh["grid2"].shape != solver.grid_a.shape:
            sh["grid2"] = wp.zeros(solver.dims, dtype=wp.vec4, device=d)
        share_colliders(solver, sh)
    if t > 1 and solver._pool is None:
        solver._pool = ThreadPoolExecutor(max_workers=solver.threads - 1, thread_name_prefix="mpm")
    return solver._shares


def share_colliders(solver: MPMSolver, sh: dict) -> None:
    """A thread's view of the colliders: the same ones, with its own impulse (N s per finger) and work (J)
    accumulators (summed into the fingers' reactions and the boundary work at the frame's end)."""
    if sh["react"].shape[0] != solver.n_fingers:
        sh["react"] = wp.zeros(solver.n_fingers, dtype=wp.vec3, device=solver.device)
    for name in ("count", "fields", "kind", "a", "b", "radius", "vel", "mu", "finger", "field", "pins",
                 "pin_slip", "pin_slot", "pin_y", "pin_v", "pin_n", "pin_arm", "pin_finger"):
        setattr(sh["col"], name, getattr(solver.col, name))
    sh["col"].impulse = sh["react"]
    sh["col"].work = sh["work"]


def gather_shares(solver: MPMSolver, accumulate: list) -> None:
    """After the threads' fused launches: add each thread's P2G grid into the shared one over the node box its
    particles touched (:func:`tasks.physics.mpm.kernels.grid.k_grid_accumulate`) and merge its stencil box."""
    box = solver._bbox_np
    for sh, launches in zip(solver._shares, accumulate):
        b = sh["bbox_np"]
        if b[0] > b[3]:  # no particle
            continue
        lo, hi = clamp_box(solver, b)
        dims = tuple(int(a) for a in hi - lo + 1)
        for launch in launches:
            launch.set_param_at_index(0, wp.vec3i(int(lo[0]), int(lo[1]), int(lo[2])))
            launch.set_dim(dims)
            launch.launch()
        box[:3] = np.minimum(box[:3], b[:3])
        box[3:] = np.maximum(box[3:], b[3:])


def reset_bbox(solver: MPMSolver) -> None:
    if solver._cpu:
        for b in [solver._bbox_np] + [sh["bbox_np"] for sh in solver._shares]:
            b[:3] = 2**30
            b[3:] = -(2**30)
    else:
        wp.copy(solver.bbox, solver.bbox_init)


def record_bc(solver: MPMSolver, bcs: list[dict], fps: list[dict]) -> None:
    """Record the launches of each boundary point set (projection, reaction, clear + advance) into its dict under
    ``cmds``, and those of each force patch (weights, push, work; one set per grid-buffer parity, keyed by the
    buffer's id), after the frame's uploads (which may re-allocate the finger and boundary arrays)."""
    gs = recorded(solver)["gs"]
    for bc in bcs:
        common = dict(dim=bc["count"], device=solver.device, record_cmd=True)
        bc["cmds"] = (
            wp.launch(k_bc_scatter, **common, inputs=[solver.gi, bc["pts"], solver.bc_grid, solver.flags, gs]),
            wp.launch(k_bc_reaction, **common, inputs=[solver.gi, bc["pts"], gs, solver.bc_grid, solver.finger_react]),
            wp.launch(k_bc_clear_advance, **common, inputs=[solver.gi, bc["pts"], gs, solver.bc_grid]))
    for fp in fps:
        common = dict(dim=fp["count"], device=solver.device, record_cmd=True)
        fp["cmds"] = {id(g): (
            wp.launch(k_force_weights, **common, inputs=[solver.gi, fp["x"], fp["f"], g, fp["w"], solver.flags, gs]),
            wp.launch(k_force_apply, **common, inputs=[
                solver.gi, fp["x"], fp["f"], fp["F"], fp["w"], gs, g, solver.finger_applied]),
            wp.launch(k_force_work, **common, inputs=[
                solver.gi, fp["x"], fp["f"], fp["F"], fp["w"], gs, g, solver.boundary_work]))
            for g in (solver.grid_a, solver.grid_b)}


def substep_params(solver: MPMSolver, dt: float, has_bc: int) -> GridStep:
    """The per-launch struct ``gs`` of this substep (dt in s, Dirichlet nodes on or off, substep counter)."""
    gs = recorded(solver)["gs"]
    gs.dt = float(dt)
    gs.has_bc = int(has_bc)
    gs.substep = int(solver.substep)
    return gs


def replay(cmd, gs: GridStep) -> None:
    """Launch a recorded command with this substep's ``gs``."""
    cmd.set_param_by_name("gs", gs)
    cmd.launch()


def launch_grid(solver: MPMSolver, cur, box_lo: np.ndarray, box_hi: np.ndarray, gs: GridStep) -> float:
    """Grid update over the node box [box_lo, box_hi] with the substep's ``gs`` (with two velocity fields: both
    fields' updates, then their contact, :func:`tasks.physics.mpm.kernels.grid.k_field_contact`); returns the max
    grid speed (m/s)."""
    cmds = recorded(solver)
    grid, fields = cmds[id(cur)][1], cmds[id(cur)][2]
    if solver._cpu:
        solver._gstats_np[0] = 0.0
    else:
        solver.gstats.zero_()
    gs.origin = wp.vec3i(int(box_lo[0]), int(box_lo[1]), int(box_lo[2]))
    dims = tuple(int(a) for a in box_hi - box_lo + 1)
    grid.set_dim(dims)
    replay(grid, gs)
    if fields is not None:
        gs2 = cmds["gs2"]
        gs2.origin, gs2.dt, gs2.has_bc, gs2.substep = gs.origin, gs.dt, 0, gs.substep
        for launch, params in zip(fields, (gs2, gs)):
            launch.set_dim(dims)
            replay(launch, params)
    return float(solver._gstats_np[0]) if solver._cpu else float(solver.gstats.numpy()[0])


def launch_fused(solver: MPMSolver, cur, dt: float, dt_next: float) -> None:
    cmds = recorded(solver)
    fused = cmds[id(cur)][0]
    new_col = cmds["col_version"][id(cur)] != solver._col_version
    if new_col:
        for sh in solver._shares:
            share_colliders(solver, sh)
        cmds["col_version"][id(cur)] = solver._col_version
    for c, (launch, sp) in enumerate(zip(fused, cmds["sp_threads"])):
        sp.dt_g2p = float(dt)
        sp.dt_p2g = float(dt_next)
        sp.substep = int(solver.substep)
        launch.set_param_by_name("sp", sp)
        if new_col:
            launch.set_param_by_name("col", solver.col if c == 0 else solver._shares[c - 1]["col"])
    if len(fused) == 1:
        fused[0].launch()
        return
    # Warp releases the GIL while a CPU kernel runs: every thread takes the next chunk until none is left
    chunks = iter(fused)

    def work() -> None:
        for launch in chunks:  # a shared iterator: each chunk is taken once (the GIL guards next())
            launch.launch()

    pending = [solver._pool.submit(work) for _ in range(solver.threads - 1)]
    work()
    for job in pending:
        job.result()
    gather_shares(solver, cmds[id(cur)][3])


def read_box(solver: MPMSolver) -> tuple[np.ndarray, np.ndarray]:
    """Node box [lo, hi] (inclusive) touched by the last P2G (stencil bases + 2), clamped to the grid."""
    return clamp_box(solver, solver._bbox_np if solver._cpu else solver.bbox.numpy())


def clamp_box(solver: MPMSolver, bbox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Node box [lo, hi] (inclusive) of the stencil bases [bbox[:3], bbox[3:]] (+ 2), clamped to the grid."""
    b = bbox.tolist()
    dims = solver.dims
    lo = [min(max(b[i], 0), dims[i] - 1) for i in range(3)]
    hi = [max(min(b[3 + i] + 2, dims[i] - 1), lo[i]) for i in range(3)]
    return np.array(lo), np.array(hi)
