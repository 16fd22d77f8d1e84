"""MLS-MPM driver: :class:`MPMSolver` owns the Warp arrays and runs frames of CFL-adaptive substeps.

Per substep (paper sec. "Squeezing-Driven Deformation"): P2G -> grid update (gravity, walls, floor, Dirichlet
nodes with reaction forces, external finger forces) -> G2P with F_E <- (I + dt grad v) F_E and the material's
return mapping.  See :mod:`tasks.physics.mpm.kernels` for the kernels and :mod:`tasks.physics.mpm.constitutive` for the models.

Boundary conditions (generic; the finger field is connected by the caller)
    * :class:`DirichletPoints`: constrained points (positions, target velocities, finger ids, optional slip
      normals).  Every substep they are projected onto the nodes their quadratic B-spline stencils touch; a
      node's prescribed velocity is the weight-averaged target of the points touching it, per constrained
      direction (sticky points: all three; slip points: their normal; constraints with different normals on one
      node each keep their own component, see :func:`tasks.physics.mpm.kernels.grid.dirichlet_velocity`).  Before the
      overwrite the solver accumulates the reaction  F_k = sum_{i in nodes of k} m_i (v_bc - v*_i) / dt
      (a node shared by several fingers is split in proportion to their weights).  F_k is the force the
      constraint applies to the material (N); the finger feels -F_k.
    * :class:`DirichletNodes`: explicit node indices with prescribed velocities.
    * :class:`ForcePatch` ("force mode"): a total force vector per finger, distributed over the massive nodes
      that finger's points touch in proportion to the B-spline weight, so the total force per finger is exactly
      the given vector, independent of the particle count.
    * :class:`Collider` (surface contact): rigid planes, spheres and capsules with signed distances, acting on the
      particles whose surface touches them (:func:`tasks.physics.mpm.kernels.contact.contact_velocity`); their impulses
      join the per-finger reactions.  ``mpm.contact = surface`` makes the floor such a plane (``grid``: for the
      released field only).
    * floor plane and domain walls (config).
Tracers (surface 3D Gaussians) are embedded in the material: each is bound at rest to its nearest particles
(:func:`tasks.physics.mpm.tracers.bind_tracers`) and placed from their positions and deformation gradients when read
(``tracer_positions``, ``tracer_state``), so it cannot drift off the material; deform covariances with
:func:`deform_covariances` (F Sigma F^T) and rotate with :func:`polar_rotation`.
"""
from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np
import warp as wp

from conf.mpm_schema import MPMConfig, mpm_config_from

from .boundary import (
    alloc_finger_arrays,
    on_table_plane,
    project_points,
    set_colliders,
    set_pins,
    surface_points,
    table_plane_fields,
    upload_colliders,
    upload_dirichlet,
    upload_forces,
)
from .diagnostics import (
    EnergyBudget,
    FrameStats,
    SimulationError,
    check_energy,
    check_flags,
    check_state,
    energy_baseline,
    energy_state_changed,
    frame_stats,
)
from .initial_state import initial_velocity_gradient
from .inputs import BoundarySpec, Collider, DirichletNodes, ForcePatch, ParticlePins
from .kernels.contact import k_collider_advance, k_pin_advance
from .kernels.structs import MaterialTable
from .kernels.transfer import k_g2p, k_p2g
from .kernels.walls import k_plane_stress_F
from .launch import (
    launch_fused,
    launch_grid,
    read_box,
    record_bc,
    recorded,
    replay,
    reset_bbox,
    set_debug_mode,
    step_params,
    substep_params,
    thread_count,
    young_objects_collected,
)
from .mass_scaling import (
    QuasiStaticLoad,
    close_quasi_static_contact,
    lowest_period,
    mass_scale_for,
    quasi_static_materials,
    resolve_auto_mass_scale,
    resume_load,
    set_damping,
)
from .materials import (
    COL_DENSITY,
    COL_PHYSICAL_DENSITY,
    N_COLS,
    Material,
)
from .model import (
    present_materials,
    released_field_materials,
    resolve_device,
    upload_materials,
)
from .state import (
    allocate_buffers,
    allocate_grid,
    allocate_particles,
    assign_materials,
    grid_nbytes,
    place_grid,
    seat_floor,
    state_nbytes,
)
from .thin_walls import (
    check_membranes,
    membrane_normals_checked,
)
from .tracers import TRACER_ANCHORS, bind_tracers, place_tracers, rebind_tracers_to_preload

wp.config.quiet = True


# grid cells the body must have moved before a preload pass may end at its crest (:meth:`MPMSolver.preload_gravity`)
PRELOAD_CREST_CELLS = 0.5


@dataclass
class GravityPreload:
    """What :meth:`MPMSolver.preload_gravity` did (SI).  ``moved``: m, the largest solid-particle displacement of
    each pass, at its end (its crest: the equilibrium it settles to, or where it came to rest); its first is the
    ``sag`` (how far the body moves under its weight from the shape it was given), its last the ``residual`` (what
    the prestress leaves unbalanced); ``frames``: damped frames over all passes; ``converged``: the last pass ended
    at its crest or at rest within its frames."""

    moved: tuple[float, ...]
    frames: int
    converged: bool

    @property
    def passes(self) -> int:
        return len(self.moved)

    @property
    def sag(self) -> float:
        return self.moved[0]

    @property
    def residual(self) -> float:
        return self.moved[-1]

    def as_dict(self) -> dict:
        return {"passes": self.passes, "frames": self.frames, "sag": self.sag, "residual": self.residual,
                "converged": self.converged, "moved": list(self.moved)}


# ============================================================================================ helpers


def _num(x: float) -> str:
    """3 significant digits, keeping a decimal point (1 -> '1.0', 1.4 -> '1.4')."""
    s = f"{x:.3g}"
    return s if ("." in s or "e" in s or "inf" in s or "nan" in s) else s + ".0"


# ============================================================================================ solver
class MPMSolver:
    """MLS-MPM solver (Warp, CPU or CUDA).

    Args:
        positions: (N, 3) particle positions, m.
        volumes: (N,) or scalar initial particle volumes, m^3 (mass = volume x material density, constant).
        materials: one :class:`Material` or a list; ``material_ids`` (N,) index into it (default all 0).
        velocities: (N, 3) initial velocities, m/s (default 0); the particles' APIC affine velocities C start from
            their gradient (:func:`tasks.physics.mpm.initial_state.initial_velocity_gradient`).
        config: :class:`conf.mpm_schema.MPMConfig`, a mapping or an OmegaConf node (default settings if None).
        tracers: (T, 3) tracer positions (surface Gaussians), embedded in the particles nearest to them at rest
            (:func:`tasks.physics.mpm.tracers.bind_tracers`).
        tracer_anchors: (N,) bool, the particles tracers may be bound to (default all): a surface Gaussian belongs
            to the skin, not to the interior that a rupture releases.
        device: overrides ``config.device``.
        n_fingers: size of the per-finger reaction/force arrays (grows automatically with the finger ids seen).
        label: name of the simulated object, quoted by the energy guard's message.
        load: the time scale of the boundary load (:class:`QuasiStaticLoad`): with ``config.quasi_static_margin`` > 0
            it bounds the mass scale of ``global`` / ``selective`` scaling (:func:`mass_scale_for`).
        membrane_normals: (N, 3) rest unit normals of the particles of a wall thinner than the grid spacing (a
            shell the grid cannot resolve through its thickness), zero rows for the others: an elastic
            (fixed-corotated, neo-Hookean) membrane particle has no normal stress on its wall (plane stress,
            :func:`tasks.physics.mpm.constitutive.membrane_F`), so its wall thins as it stretches instead of
            locking its volume.  A von Mises membrane particle returns in plane stress
            (:func:`tasks.physics.mpm.constitutive.membrane_plastic_return`) and its row becomes the wall's current
            normal, carried by the flow every substep (plastic flow moves F_E's reference, so the rest normal no
            longer tells where the wall lies in it); :meth:`set_material_ids` converts a row between the two when a
            particle changes between an elastic and a von Mises material.  Whether a particle is a membrane is its
            row (non-zero), whatever its material's ``membrane`` flag.  Foam and fluid models ignore it.
        membrane_fibres: (P, 2) or (P, 3) particle indices, the Gauss layers of a thin wall at each point of it
            (membrane particles; outer, inner and, in three layers, middle; ``config.wall_fibres``): after every
            substep's advection each fibre's outer and inner particles are put back at their rest distance about
            their centre of mass (:func:`tasks.physics.mpm.kernels.walls.k_wall_fibres`, Kirchhoff-Love's inextensible
            normal fibre), which nothing else holds on a grid coarser than the wall.  A middle particle moves with the
            grid: put back on its fibre's mid-point every substep, clamped strips 0.86 of a cell thick read 1.14x
            Euler-Bernoulli at dx 3.5 mm and 0.95x at dx 8 mm, free 1.03x and 1.09x, what the B-splines' clamp, a
            node plane behind the strip's root, makes of the closed form (1.04x and 1.08x).  A fibre whose outer and
            inner particles come to differ in material is left alone.

    Mass (time) scaling, its quasi-static check and the quasi-static damping (``config.mass_scaling``,
    ``quasi_static_ke_ie_max``, ``quasi_static_damping``): :mod:`tasks.physics.mpm.mass_scaling`.  The energy guard
    (``config.energy_guard_tolerance``) and the other guards: :mod:`tasks.physics.mpm.diagnostics`.
    """

    def __init__(
        self,
        positions: np.ndarray,
        volumes: Union[np.ndarray, float],
        materials: Union[Material, Sequence[Material]],
        material_ids: Optional[np.ndarray] = None,
        velocities: Optional[np.ndarray] = None,
        config: Any = None,
        tracers: Optional[np.ndarray] = None,
        tracer_anchors: Optional[np.ndarray] = None,
        device: Optional[str] = None,
        n_fingers: int = 5,
        label: str = "",
        load: Optional[QuasiStaticLoad] = None,
        membrane_normals: Optional[np.ndarray] = None,
        membrane_fibres: Optional[np.ndarray] = None,
    ) -> None:
        self.cfg: MPMConfig = mpm_config_from(config)
        self.label = str(label)
        self.load = load
        self.device = resolve_device(device or self.cfg.device)
        if self.cfg.debug:
            set_debug_mode()
        self.materials: list[Material] = [materials] if isinstance(materials, Material) else list(materials)
        x = np.ascontiguousarray(np.asarray(positions, dtype=np.float32).reshape(-1, 3))
        n = x.shape[0]
        if n == 0:
            raise ValueError("MPMSolver needs at least one particle")
        if not np.all(np.isfinite(x)):
            raise SimulationError("initial particle positions contain NaN/inf")
        self.n_particles = n
        vol = np.broadcast_to(np.asarray(volumes, dtype=np.float32), (n,)).copy()
        if not np.all(vol > 0):
            raise ValueError("particle volumes must be > 0")
        mid = np.zeros(n, np.int32) if material_ids is None else np.asarray(material_ids, np.int32).reshape(n)
        if mid.min() < 0 or mid.max() >= len(self.materials):
            raise ValueError(f"material_ids must be in [0, {len(self.materials)})")
        v = np.zeros_like(x) if velocities is None else np.asarray(velocities, np.float32).reshape(n, 3)
        if not np.all(np.isfinite(v)):  # stability suite guard: bad input is refused, not reported as a blow-up
            raise SimulationError(f"initial particle velocities contain NaN/inf ({int((~np.isfinite(v)).any(1).sum())} "
                                  "particles): the caller's input is corrupt")
        normals = membrane_normals_checked(membrane_normals, n)
        self._membrane_rows = np.zeros(n, bool) if normals is None else normals.any(axis=1)
        check_membranes(self, mid)
        self._mid_host = mid
        self._warned_quasi_static = False
        self._loaded_frames = 0  # consecutive frames in which the boundary loaded the material (quasi-static check)
        self._contact: Optional[dict] = None  # the open contact of the quasi-static check: its frames, sums of KE, IE (J)
        self.quasi_static_contacts: list[dict] = []  # judged contacts: first and last checked frame, KE/IE (mass_scaling)
        self._damping = np.zeros(len(self.materials))  # local damping coefficient per material (quasi-static damping)
        self._preload_damping = 0.0  # local damping of every material while the body settles (preload_gravity)
        self._tracer_F0_inv: Optional[np.ndarray] = None  # (T, 3, 3) the tracers' F after a preload, inverted
        present = sorted(set(int(i) for i in np.unique(mid)))
        self._present = present
        codes_present = {self.materials[i].code for i in present}
        self.n_fingers = int(n_fingers)

        # ---------------- grid geometry
        cfg = self.cfg
        tr = None if tracers is None else np.asarray(tracers, np.float32).reshape(-1, 3)
        place_grid(self, x, vol, tr)

        # ---------------- scaling and material table
        self.stiffness_scale = float(cfg.stiffness_scaling)
        # global / selective: fixed by the first step_frame's duration
        self._mass_scale_pending = cfg.mass_scaling in ("global", "selective")
        self.mass_scale = 1.0 if self._mass_scale_pending else mass_scale_for(present_materials(self), self.dx, None, cfg)
        self.material_mass_scale = np.full(len(self.materials), self.mass_scale)
        d = self.device
        self.mat_model = wp.zeros(len(self.materials), dtype=wp.int32, device=d)
        self.mat_par = wp.zeros((len(self.materials), N_COLS), dtype=float, device=d)
        self.mat_table = MaterialTable()
        self.mat_table.model = self.mat_model
        self.mat_table.par = self.mat_par
        self.mat_field = wp.zeros(len(self.materials), dtype=wp.int32, device=d)
        self.mat_table.field = self.mat_field
        upload_materials(self)

        # ---------------- particle state and grid buffers
        allocate_particles(self, x, v, vol, mid, normals, membrane_fibres, codes_present)
        if velocities is not None:  # APIC's C from the initial field's gradient (C = 0 lost a spin's local rotation)
            self.C.assign(initial_velocity_gradient(x, v, vol, mid).astype(np.float32))
        allocate_grid(self)

        # ---------------- tracers
        self.n_tracers = 0 if tr is None else len(tr)
        self.tx = wp.array(tr if self.n_tracers else np.zeros((1, 3), np.float32), dtype=wp.vec3, device=d)
        self.tF = wp.array(np.tile(np.eye(3, dtype=np.float32), (max(self.n_tracers, 1), 1, 1)), dtype=wp.mat33,
                           device=d)
        bind_tracers(self, x, vol, tr, tracer_anchors)

        # ---------------- small buffers, colliders, pins, fingers and threads
        allocate_buffers(self, codes_present)
        set_colliders(self, [])
        set_pins(self, None)
        alloc_finger_arrays(self, self.n_fingers)
        # CPU threads of the fused G2P/P2G (mpm.threads): the particles are cut into CHUNKS_PER_THREAD x threads
        # chunks; chunk c > 0 scatters into its own P2G grid, error flags, stencil box and collider impulses
        # (``_shares``), summed in chunk order after every launch, whichever thread ran it
        self.threads = thread_count(self)
        self._shares: list[dict] = []
        self._pool: Optional[ThreadPoolExecutor] = None
        self._energy_ref: Optional[EnergyBudget] = None  # energy guard reference (see _check_energy)
        self._energy_initial = True  # the reference is the initial state (F = I, C = 0: no internal energy)
        self._loading_force = 0.0  # N, the largest load seen (weight or boundary force): the guard's floor

        self.time = 0.0
        self.frame = 0
        self.substep = 0
        self._vmax = float(np.max(np.linalg.norm(v, axis=1))) if n else 0.0
        self._times: list[tuple[int, float]] = []
        self.last_stats: Optional[FrameStats] = None


    def lowest_period(self) -> float:
        """Estimated period (s) of the slowest mode of the body as scaled (:func:`lowest_period` of the measured
        materials present, each with its own mass scale, the height from ``load``); inf without a load."""
        if self.load is None:
            return math.inf
        measured = quasi_static_materials(self)
        return max((lowest_period([self.materials[i]], self.load.height, self.stiffness_scale,
                                  float(self.material_mass_scale[i])) for i in self._present if measured[i]),
                   default=math.inf)


    def released_field_materials(self) -> np.ndarray:
        """See :func:`tasks.physics.mpm.model.released_field_materials`."""
        return released_field_materials(self)


    def stable_dt_per_material(self) -> dict[str, float]:
        """The stable substep (s) each material of the table needs alone, present or not yet (a ruptured skin, a
        released interior): C dx / c_p with its own (un)scaled P-wave speed, and for a viscous fluid also
        rho dx^2 / (6 mu) (explicit viscosity).  The solver steps with the smallest over the materials present."""
        out = {}
        for m, scale in zip(self.materials, self.material_mass_scale.tolist()):
            dt = self.cfg.courant * self.dx / m.p_wave_speed(self.stiffness_scale, scale)
            if m.model == "fluid" and m.viscosity > 0:
                dt = min(dt, m.density * scale * self.dx ** 2 / (6.0 * m.viscosity))
            out[m.name] = dt
        return out


    # ------------------------------------------------------------------ public geometry helpers
    def node_position(self, idx: np.ndarray) -> np.ndarray:
        """World positions (m) of integer grid indices (M, 3)."""
        return self.lo + np.asarray(idx, np.float64) * self.dx

    def project_points(self, positions: np.ndarray, velocities: np.ndarray, finger_ids: Optional[np.ndarray] = None,
                       min_weight: float = 0.0) -> DirichletNodes:
        """See :func:`tasks.physics.mpm.boundary.project_points`."""
        return project_points(self, positions, velocities, finger_ids, min_weight)


    # ------------------------------------------------------------------ time step
    def courant_number(self, dt: float) -> float:
        return dt * self.c_max / self.dx

    def _stable_dt(self, vmax: float) -> float:
        cfg = self.cfg
        dt = cfg.courant * self.dx / self.c_max
        if vmax > 0:
            dt = min(dt, cfg.max_speed_cfl * self.dx / vmax)
        return min(dt, self.dt_visc)

    def _next_dt(self, remaining: float, vmax: float) -> float:
        cfg = self.cfg
        if cfg.dt is not None:
            dt = float(cfg.dt)
            cn = self.courant_number(dt)
            if cn > cfg.courant_limit:
                raise SimulationError(
                    f"Courant number {_num(cn)} > limit {_num(cfg.courant_limit)}: lower dt or E "
                    f"(forced dt={dt:.3g} s, c_p={self.c_max:.4g} m/s, dx={self.dx:.4g} m; "
                    f"at substep {self.substep}, t={self.time:.6g} s)"
                )
            adv = vmax * dt / self.dx
            if adv > cfg.courant_limit:
                raise SimulationError(
                    f"advective Courant number {_num(adv)} > limit {_num(cfg.courant_limit)}: lower dt "
                    f"(max speed {vmax:.4g} m/s at substep {self.substep}, t={self.time:.6g} s)"
                )
        else:
            dt = self._stable_dt(vmax)
        if dt >= remaining * (1.0 - 1e-6):
            return remaining
        n_left = math.ceil(remaining / dt - 1e-6)
        return remaining / n_left


    def surface_points(self, indices: np.ndarray, normals: np.ndarray, arms: Optional[np.ndarray] = None
                       ) -> np.ndarray:
        """See :func:`tasks.physics.mpm.boundary.surface_points`."""
        return surface_points(self, indices, normals, arms)

    def tracer_anchor_particles(self) -> np.ndarray:
        """(T, TRACER_ANCHORS) the particles each tracer is embedded in, nearest first."""
        return self._anchor[0].numpy().copy() if self._anchor is not None else np.zeros((0, TRACER_ANCHORS), np.int32)

    def table_plane_fields(self) -> Optional[int]:
        """See :func:`tasks.physics.mpm.boundary.table_plane_fields`."""
        return table_plane_fields(self)

    def on_table_plane(self) -> np.ndarray:
        """See :func:`tasks.physics.mpm.boundary.on_table_plane`."""
        return on_table_plane(self)


    def step_frame(self, frame_dt: float, dirichlet: BoundarySpec = None,
                   forces: Optional[Union[ForcePatch, Sequence[ForcePatch]]] = None,
                   quasi_static: bool = True,
                   colliders: Optional[Union[Collider, Sequence[Collider]]] = None,
                   probe: Optional[Callable[[float], None]] = None, probe_every: int = 1,
                   pins: Optional[ParticlePins] = None) -> FrameStats:
        """Advance by ``frame_dt`` seconds with CFL-adaptive substeps; returns the frame statistics.

        ``dirichlet``: DirichletPoints / DirichletNodes (or a list), constant targets over the frame (points are
        advected with their target velocity every substep), or a callable ``(t, dt) -> spec`` evaluated at every
        substep (t = time since the frame start; dt = the substep's size, None at the frame's first call, which
        only sizes the first substep).  ``forces``: ForcePatch (force mode, or a list, or such a callable),
        constant over the frame.  ``quasi_static``: whether the motion of this frame is meant to be quasi-static
        (False: dynamic by design, e.g. after a rupture; the quasi-static check skips it).  ``colliders``: rigid
        :class:`Collider` s (surface contact) at their positions at the frame start, moved with their velocities
        every substep; their reactions join ``FrameStats.reaction`` under their finger ids.  ``probe``: called
        with the time since the frame start (s) after every ``probe_every``-th substep's particle update inside the
        frame (the particles, e.g. :meth:`positions`, are then at that time; the frame's end is not probed).
        ``pins``: :class:`ParticlePins`, particles whose surface points reach their targets at the frame's end; their
        reactions join ``FrameStats.reaction`` under their finger ids.  Raises :class:`SimulationError` when a guard
        trips.
        """
        if not frame_dt > 0:
            raise ValueError("frame_dt must be > 0")
        with young_objects_collected():
            return self._advance_frame(frame_dt, dirichlet, forces, quasi_static, colliders, probe, probe_every, pins)

    def _advance_frame(self, frame_dt: float, dirichlet: BoundarySpec,
                       forces: Optional[Union[ForcePatch, Sequence[ForcePatch]]], quasi_static: bool,
                       colliders: Optional[Union[Collider, Sequence[Collider]]],
                       probe: Optional[Callable[[float], None]], probe_every: int,
                       pins: Optional[ParticlePins]) -> FrameStats:
        """The body of :meth:`step_frame`."""
        wall0 = time.perf_counter()
        resolve_auto_mass_scale(self, frame_dt)
        set_damping(self, quasi_static)
        cfg = self.cfg
        d = self.device
        bc_fn = dirichlet if callable(dirichlet) else None
        f_fn = forces if callable(forces) else None
        bcs = upload_dirichlet(self, dirichlet(0.0, None) if bc_fn else dirichlet)
        fps = upload_forces(self, forces(0.0, None) if f_fn else forces)
        n_col = upload_colliders(self, colliders)
        n_pin = set_pins(self, pins, frame_dt)
        # m/s: a moving collider or pin bounds the step like a Dirichlet target's speed
        col_speed = max(self._collider_speed, self._pin_speed)
        record_bc(self, bcs, fps)
        col_advance = wp.launch(k_collider_advance, dim=n_col, device=d, record_cmd=True,
                                inputs=[self.col, recorded(self)["gs"]]) if n_col else None
        pin_advance = wp.launch(k_pin_advance, dim=n_pin, device=d, record_cmd=True,
                                inputs=[self.col, recorded(self)["gs"]]) if n_pin else None
        self.finger_react.zero_()
        self.finger_applied.zero_()
        self.boundary_work.zero_()
        for sh in self._shares:
            sh["react"].zero_()
            sh["work"].zero_()
        energy_baseline(self)
        has_bc = int(len(bcs) > 0)
        bc_speed = max([b["speed"] for b in bcs], default=0.0)
        check_every = 1 if cfg.debug else cfg.check_every
        n = self.n_particles

        t = 0.0
        nsub = 0
        dts: list[float] = []
        self._frame_dts = dts  # the substeps taken so far (the guard messages quote their Courant number)
        self._times = [(self.substep, self.time)]
        dt = self._next_dt(frame_dt, max(self._vmax, bc_speed, col_speed))
        cur, other = self.grid_b, self.grid_a
        # P2G of the frame's first substep (stress from the stored state)
        reset_bbox(self)
        wp.launch(k_p2g, dim=n, device=d, inputs=[
            self.gi, step_params(self, 0.0, dt, restart=True), self.particles, self.mat_table, cur,
            self._field2[id(cur)], self.flags, self.bbox, self.col])
        box_cur = read_box(self)
        box_prev = self._last_box if self._last_box is not None else box_cur
        while True:
            if nsub > 0 and bc_fn is not None:  # time-varying constraints: re-evaluated every substep
                bcs = upload_dirichlet(self, bc_fn(t, dt))
                has_bc = int(len(bcs) > 0)
                bc_speed = max([b["speed"] for b in bcs], default=0.0)
            if nsub > 0 and f_fn is not None:
                fps = upload_forces(self, f_fn(t, dt))
            if nsub > 0 and (bc_fn is not None or f_fn is not None):  # new points, or re-allocated finger arrays
                record_bc(self, bcs, fps)
            gs = substep_params(self, dt, has_bc)
            if any(fp["follow"] for fp in fps):
                place_tracers(self)  # the points of a patch given by tracers follow the material
            for fp in fps:
                fp["w"].zero_()
                replay(fp["cmds"][id(cur)][0], gs)  # k_force_weights
                replay(fp["cmds"][id(cur)][1], gs)  # k_force_apply
            for fp in fps:  # the work, once every patch has pushed
                replay(fp["cmds"][id(cur)][2], gs)  # k_force_work
            for bc in bcs:
                replay(bc["cmds"][0], gs)  # k_bc_scatter
            vmax = launch_grid(self, cur, np.minimum(box_cur[0], box_prev[0]), np.maximum(box_cur[1], box_prev[1]), gs)
            for bc in bcs:
                replay(bc["cmds"][1], gs)  # k_bc_reaction
                replay(bc["cmds"][2], gs)  # k_bc_clear_advance
            t += dt
            nsub += 1
            dts.append(dt)
            remaining = frame_dt - t
            if remaining <= 1e-6 * frame_dt:
                self.sums.zero_()
                self.mat_energy.zero_()
                wp.copy(self.ext, self.ext_init)
                wp.launch(k_g2p, dim=n, device=d, inputs=[
                    self.gi, step_params(self, dt, 0.0, restart=True), self.particles, self.mat_table, cur,
                    self._field2[id(cur)], self.flags, self.sums, self.ext, wp.vec3(*self.cfg.gravity), self.mat_energy])
                if self._fibres is not None:
                    self._fibres.launch()
                self.substep += 1
                self._times.append((self.substep, self.time + t))
                self._last_box = box_cur
                break
            if not math.isfinite(vmax):
                self._vmax = vmax
                check_flags(self, force_nonfinite=True)
            dt_next = self._next_dt(remaining, max(vmax, bc_speed, col_speed))
            if col_advance is not None:  # the next P2G sees the colliders where they are at its time
                replay(col_advance, gs)
            if pin_advance is not None:  # and the pins' targets
                replay(pin_advance, gs)
            reset_bbox(self)
            launch_fused(self, cur, dt, dt_next)
            if self._fibres is not None:  # the next G2P advects the restored layers (their P2G is a substep behind)
                self._fibres.launch()
            box_prev, box_cur = box_cur, read_box(self)
            cur, other = other, cur
            dt = dt_next
            self.substep += 1
            self._times.append((self.substep, self.time + t))
            self._vmax = vmax
            if probe is not None and nsub % probe_every == 0:
                probe(t)
            if nsub % check_every == 0:
                check_flags(self)
            if nsub >= cfg.max_substeps_per_frame:
                raise SimulationError(
                    f"frame {self.frame} needs more than {cfg.max_substeps_per_frame} substeps "
                    f"(dt={dt:.3g} s, max speed {vmax:.4g} m/s at substep {self.substep}, "
                    f"t={self.time + t:.6g} s): the time step collapsed; likely cause: runaway velocities "
                    f"(unstable material or boundary velocities too large)")
        for sh in self._shares:  # the chunks' collider impulses (N s; fingers added this frame: none yet) and work (J)
            react, own = self.finger_react.numpy(), sh["react"].numpy()
            k = min(len(react), len(own))
            react[:k] += own[:k]
            self.boundary_work.numpy()[:] += sh["work"].numpy()
        # grid_a: last grid state (velocities + masses of the last P2G); grid_b: zeroed, the next frame's P2G target
        self.grid_a, self.grid_b = cur, other
        self.time += frame_dt
        self.frame += 1
        self._vmax = vmax
        stats = frame_stats(self, nsub, dts, frame_dt, wall0, quasi_static)
        check_flags(self)
        check_state(self, stats)
        check_energy(self, stats)
        self.last_stats = stats
        return stats


    def preload_gravity(self, frame_dt: float, max_frames: int, passes: int = 3, damping: float = 0.8,
                        tolerance: float = 0.01, pins: Optional[ParticlePins] = None) -> GravityPreload:
        """Gravity preload (geostatic prestress): make the body's given shape (a captured object standing on the
        table) its equilibrium under its weight, so that the run starts at rest instead of sagging and swaying
        from the first frame (the plush toy, given gravity at t = 0: its top swung 4 cm forward before the
        fingers arrived).  Each pass (at most ``passes``):

        1. settles the body by dynamic relaxation (Cundall's local damping ``damping`` on every material, as FLAC's
           static solutions and LS-DYNA's dynamic-relaxation preload do; gravity, floor and walls only) until its
           crest, or until the fastest solid particle moves at most ``tolerance`` grid cells per ``frame_dt`` s
           after its motion peaked, or for ``max_frames`` frames (``pins``' particles are held: not counted in
           either measure).  The crest: the solids' kinetic energy peaked in
           the last frame while the body had moved at least ``PRELOAD_CREST_CELLS`` grid cells (less is a local
           motion, e.g. a skin dropping onto its stuffing in the first frames).  Under local damping a settling
           mode accelerates with (1 - damping) of its net force and brakes with (1 + damping) of it, so its speed
           peaks where that force vanishes: at the equilibrium, which the pass takes, its state put back to the
           vertex of the parabola through the last three frames' energies (first order: dF/dt = C F, dx/dt = v).
           Until 2026-12-06 every pass ran on to rest: past its equilibrium to the turning point of its overshoot
           and back (the plush toy: 40 + 38 + 2 frames, now 29 + 6 + 3; docs/limits/gravity-preload.md);
        2. puts the particles back where they were given, at rest (v = 0, C = 0), keeping their deformation
           gradients: the stress that carried the weight in the settled shape now holds the given shape, whose
           stress-free shape is the given one less the sag (first order in the sag).  The next pass settles what
           that change of geometry left.  A body that leans under its weight (a soft toy rocking on its base) is
           over-held by the full settled strain, since its upright given shape has less overturning moment than
           the settled one, and its passes converge slowly (the plush toy's 36.6, 22, 16.5, 11 mm); from the
           second pass on each pass keeps omega times its strain, omega by Aitken's rule (Irons and Tuck 1969, as
           partitioned fluid-structure codes relax their coupling iterations), exact for a linear response (the
           plush toy, its passes run to rest: 36.6, 22, 0.2 mm; ended at their crests: 25.0, 0.47, 0.03 mm).  A
           fluid (the can's cola) has no shape to hold: it stays where it settled,
           at rest, with the pressure it settled to.

        The tracers (surface Gaussians) are re-bound to stay on their given positions, and :meth:`tracer_state`
        reports their deformation from the preloaded state.  Time and frame count restart at 0.  The body settles at
        the mass scale it has without a boundary ``load`` (the equilibrium under its weight does not depend on the
        inertia, which dynamic relaxation only uses to get there): every variant of a body, however its push bounds
        its scale afterwards (a force-driven push's quasi-static bound, resolved at the next frame), starts from the
        same preloaded state, so one preload serves them all (:mod:`tasks.physics.mpm.preload`).  ``pins``: held
        in every frame of it (the table's hold, :mod:`tasks.physics.table_hold`).  Raises :class:`SimulationError`
        like :meth:`step_frame`."""
        if not (max_frames >= 1 and passes >= 1 and 0.0 < damping < 1.0 and tolerance > 0.0):
            raise ValueError(f"preload_gravity: need max_frames >= 1, passes >= 1, damping in (0, 1) and tolerance "
                             f"> 0, got {max_frames}, {passes}, {damping}, {tolerance}")
        x0 = self.positions()
        fluid = np.array([m.model == "fluid" for m in self.materials])[self._mid_host]  # no shape to hold: it settles
        # whose motion tells rest and crest: the solids less the pinned particles (the table's hold), whose stored
        # velocity is the pin's correction of the last substep (the grid's pull on them over dt: 0.5 m/s on a held
        # plush toy standing still, which then never came to rest), not a motion: the pins say where they are
        moving = ~fluid
        if pins is not None:
            moving[np.asarray(pins.indices)] = False
        zero_v, zero_c = np.zeros((self.n_particles, 3)), np.zeros((self.n_particles, 3, 3))
        frames, moved, rest = 0, [], False
        start, last, omega = self.F.numpy().astype(np.float64), None, 1.0
        self._preload_damping = damping
        load, self.load = self.load, None  # the load-free mass scale (resolved by the first frame below)
        mass = None
        try:
            for _ in range(passes):
                peak = -math.inf  # the pass starts at rest: it is over at its crest or once its motion has died down
                energy: list[float] = []  # the solids' kinetic energy at each frame's end (J)
                crest = False
                for _ in range(max_frames):
                    self.step_frame(frame_dt, quasi_static=False, pins=pins)
                    frames += 1
                    if mass is None:  # the mass scale is resolved by the first frame
                        mass = self.masses()[moving].astype(np.float64)
                    v = self.velocities()[moving]
                    speed = float(np.linalg.norm(v, axis=1).max(initial=0.0))
                    energy.append(0.5 * float(mass @ (v.astype(np.float64) ** 2).sum(axis=1)))
                    rest = speed * frame_dt <= tolerance * self.dx and speed < peak
                    crest = len(energy) >= 3 and energy[-2] >= max(energy) and energy[-1] < energy[-2]
                    if crest:  # a crest counts once the body has moved PRELOAD_CREST_CELLS (not a skin's local bump)
                        shift = np.linalg.norm(self.positions()[~fluid] - x0[~fluid], axis=1).max(initial=0.0)
                        crest = bool(shift >= PRELOAD_CREST_CELLS * self.dx)
                    if rest or crest:
                        break
                    peak = max(peak, speed)
                x = self.positions()
                settled = self.F.numpy().astype(np.float64)
                if crest and not rest:  # back to the crest, the vertex of the parabola through the last three
                    e0, e1, e2 = energy[-3:]  # energies (0.5-1.5 frames ago), to first order: dF/dt = C F, dx/dt = v
                    back = frame_dt * (1.0 - 0.5 * (e0 - e2) / (e0 - 2.0 * e1 + e2))
                    settled = settled - back * np.einsum("pij,pjk->pik", self.C.numpy().astype(np.float64), settled)
                    x = x - back * self.velocities()
                moved.append(float(np.linalg.norm(x - x0, axis=1)[~fluid].max(initial=0.0)))
                update = np.where(fluid[:, None, None], 0.0, settled - start)  # the solids' settled strain
                if last is not None:  # Aitken relaxation of the passes (Irons and Tuck 1969)
                    change = update - last
                    size = float(np.vdot(change, change))
                    if size > 0.0:
                        omega = float(np.clip(-omega * np.vdot(last, change) / size, 0.1, 2.0))
                last, start = update, np.where(fluid[:, None, None], settled, start + omega * update)
                self.set_deformation_gradients(start)
                self.set_positions(np.where(fluid[:, None], x, x0))
                self.set_velocities(zero_v)
                self.set_affine_velocities(zero_c)
                if (rest or crest) and moved[-1] <= tolerance * self.dx:
                    break
        finally:
            self._preload_damping = 0.0
            resume_load(self, load)
        rebind_tracers_to_preload(self)
        self.time, self.frame, self.substep = 0.0, 0, 0
        return GravityPreload(moved=tuple(moved), frames=frames, converged=rest or crest)


    def close_quasi_static_contact(self) -> bool:
        """See :func:`tasks.physics.mpm.mass_scaling.close_quasi_static_contact`."""
        return close_quasi_static_contact(self)


    # ------------------------------------------------------------------ accessors
    def positions(self) -> np.ndarray:
        return self.x.numpy().copy()

    def velocities(self) -> np.ndarray:
        return self.v.numpy().copy()

    def deformation_gradients(self, plane_stress: bool = False) -> np.ndarray:
        """Elastic deformation gradients F_E (N, 3, 3) (fluid: J^(1/3) I), as stored; with ``plane_stress`` a thin
        wall's elastic particles as their plane-stress projection, the material's state (the stored F_E keeps the
        grid's normal stretch, which ``mpm.wall_normal_stiffness`` resists: under a finger's nodes its J left 1 as
        far as a locked solid wall's, 0.26)."""
        if not plane_stress or self.n_membrane == 0:
            return self.F.numpy().copy()
        out = wp.zeros(self.n_particles, dtype=wp.mat33, device=self.device)
        wp.launch(k_plane_stress_F, dim=self.n_particles, device=self.device,
                  inputs=[self.particles, self.mat_table, out])
        return out.numpy()

    def plastic_strain(self) -> np.ndarray:
        """Equivalent plastic strain alpha (N,) (zeros when no plastic material is present)."""
        if not self.has_plastic:
            return np.zeros(self.n_particles, np.float32)
        return self.alpha.numpy().copy()

    def set_plastic_strain(self, alpha: np.ndarray) -> None:
        """Set the equivalent plastic strain alpha (N,) (e.g. 0 for material released as a fresh mass); a solver
        without plastic materials holds none and accepts only zeros."""
        alpha = np.asarray(alpha, np.float32).reshape(self.n_particles)
        if not (np.isfinite(alpha).all() and alpha.min(initial=0.0) >= 0.0):
            raise ValueError("set_plastic_strain: alpha must be finite and >= 0 (an equivalent plastic strain)")
        if not self.has_plastic:
            if alpha.any():
                raise ValueError("set_plastic_strain: no plastic material in this solver, so no plastic strain")
            return
        self.alpha.assign(alpha)

    def volumes(self) -> np.ndarray:
        return self.vol.numpy().copy()

    def contact_radii(self) -> np.ndarray:
        """(particle,) m: the radius with which surface contact reaches a collider
        (:func:`tasks.physics.mpm.kernels.contact.contact_velocity`, before its F^T n stretch; :func:`contact_reach`)."""
        return self.reach.numpy().astype(np.float64)

    def set_contact_radii(self, reach: np.ndarray) -> None:
        """Set each particle's contact radius (m; :meth:`contact_radii`), e.g. a wall sampled in Gauss layers but held
        as a 3D solid, whose layers touch at the wall's faces (:func:`contact_reach` with its fibres)."""
        r = np.asarray(reach, np.float64)
        if r.shape != (self.n_particles,) or not (np.all(np.isfinite(r)) and np.all(r >= 0)):
            raise ValueError(f"set_contact_radii: need {self.n_particles} finite radii >= 0 (m), one per particle; "
                             f"got shape {r.shape}")
        self.reach.assign(r.astype(np.float32))
        seat_floor(self)  # the table under the new contact surface (mpm.contact = surface)

    def masses(self) -> np.ndarray:
        """Particle masses (kg), including the material's current mass scale (the inertia)."""
        par = self.mat_par.numpy()
        return self.vol.numpy() * par[self._mid_host, COL_DENSITY]

    def physical_masses(self) -> np.ndarray:
        """Physical particle masses (kg), without mass scaling (the weight is m_phys g)."""
        par = self.mat_par.numpy()
        return self.vol.numpy() * par[self._mid_host, COL_PHYSICAL_DENSITY]

    def material_ids(self) -> np.ndarray:
        return self._mid_host.copy()


    def tracer_positions(self) -> np.ndarray:
        """(T, 3) m, the tracers placed from their anchors' current state."""
        place_tracers(self)
        return self.tx.numpy()[: self.n_tracers].copy()

    def tracer_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The tracers placed once from their anchors' current state: positions (T, 3) m and deformation
        gradients (T, 3, 3), each the weighted mean of its anchors' F (after :meth:`preload_gravity`, relative to
        the preloaded state: I at its end)."""
        place_tracers(self)
        tF = self.tF.numpy()[: self.n_tracers].copy()
        if self._tracer_F0_inv is not None:
            tF = np.einsum("tij,tjk->tik", tF.astype(np.float64), self._tracer_F0_inv).astype(np.float32)
        return self.tx.numpy()[: self.n_tracers].copy(), tF

    def grid_mass(self) -> float:
        """Total mass (kg) on the grid from the last P2G (float64 sum of the nodal masses of both velocity
        fields)."""
        grids = [self.grid_a] + ([self._field2[id(self.grid_a)]] if self.two_fields else [])
        return float(sum(g.numpy()[..., 3].astype(np.float64).sum() for g in grids))

    def set_velocities(self, v: np.ndarray) -> None:
        energy_state_changed(self)
        self.v.assign(np.asarray(v, np.float32).reshape(-1, 3))
        self._vmax = max(self._vmax, float(np.max(np.linalg.norm(v, axis=1))))

    def set_positions(self, x: np.ndarray) -> None:
        energy_state_changed(self)
        self.x.assign(np.asarray(x, np.float32).reshape(-1, 3))
        self.x_carry.zero_()  # a round-off belongs to the positions it was lost from

    def set_material_ids(self, ids: np.ndarray) -> None:
        """See :func:`tasks.physics.mpm.state.assign_materials`."""
        return assign_materials(self, ids)


    def affine_velocities(self) -> np.ndarray:
        """APIC affine velocity matrices C (N, 3, 3), 1/s (the particle's velocity gradient, stored at frame ends)."""
        return self.C.numpy().copy()

    def set_affine_velocities(self, C: np.ndarray) -> None:
        """Set the APIC affine velocity matrices C (N, 3, 3), 1/s, e.g. with :meth:`set_velocities` for an initial
        rigid spin v = w x (x - c): C = [w]x (the skew matrix of w), so the first P2G carries the spin's full
        angular momentum and kinetic energy (Jiang et al. 2015, APIC) instead of losing the part within each
        particle's stencil.  The velocity field is unchanged, so the energy guard's reference stays."""
        C = np.asarray(C, np.float32).reshape(self.n_particles, 3, 3)
        if not np.isfinite(C).all():
            raise ValueError("set_affine_velocities: C contains NaN/inf; pass finite velocity gradients (1/s)")
        self.C.assign(C)

    def set_deformation_gradients(self, F: np.ndarray) -> None:
        self._energy_initial = False
        self._energy_ref = EnergyBudget.rebase(self._energy_ref)
        self.F.assign(np.asarray(F, np.float32).reshape(-1, 3, 3))
        self.F_carry.zero_()

    def state_nbytes(self) -> dict[str, int]:
        """See :func:`tasks.physics.mpm.state.state_nbytes`."""
        return state_nbytes(self)

    def bytes_per_particle(self) -> float:
        return sum(self.state_nbytes().values()) / self.n_particles

    def grid_nbytes(self) -> int:
        """See :func:`tasks.physics.mpm.state.grid_nbytes`."""
        return grid_nbytes(self)
