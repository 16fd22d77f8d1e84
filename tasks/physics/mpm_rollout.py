"""Squeezing-driven deformation: the MPM rollout of one object under its squeeze (paper sec. 3.2, eqs. 4-5).

Per output frame the displacement field of eq. 3 is imposed as Dirichlet boundary conditions: every surface
point constrained at the end of the frame is driven towards its target ``x0 + dx(x0)`` (the tracked surface points
are the 3D Gaussians, tracers embedded in the body).  By default (``mpm.fingers = particles``, :func:`particle_pins`)
the particles each point is embedded in are driven by the displacement it still needs, and the constraint reaches the
grid through the P2G momentum (:class:`ParticlePins`; a wall thinner than the spacing is pinned at its particles'
centres); with ``mpm.fingers = dirichlet`` the velocity ``(target - current) / frame_dt`` overwrites the grid nodes
of the point's B-spline stencil instead (:func:`dirichlet_points`), whose ~1.5-cell halo holds the material around
the patch.  The contact is unilateral: a point is driven only
while the finger pushes or holds it: (target - current) . d_k >= -dx/4 while the target advances or holds (d_k the
inward patch normal; the tolerance stops contact chatter) and >= 0 while it retreats, so material that lies
deeper than a retreating finger is left free, so on release the object rebounds or keeps its dent as its
material dictates.  The ``force`` boundary mode (the
no_dirichlet ablation) pushes with a total per-finger force ``force_per_coefficient * c_k,t`` along the
inward patch normal instead, less each finger's share of the fingers' net force and moment
(``simulation.force_balance``: the hand's grip is a closed force loop; :func:`balanced_push`).

Collider fingers (``mpm.fingers = collider``, meant with ``mpm.contact = surface``): instead of the Dirichlet points,
each active finger is a rigid sphere ``Collider`` of the fingertip pad radius (``conf.hand.FINGERTIP_PAD_RADIUS``)
whose lowest point is the patch centre moved inwards by the eq. 3 amplitude eta c_k,t (read back from the field,
:func:`fingertip_travel`), moved there from its previous place within each frame (:func:`finger_colliders`).  It
acts on the particles whose surface it touches, pushes and never pulls (unilateral by construction, no tolerance),
and its impulses are the finger's reaction.  Measured (README, ``python -m flows.finger_study``): the reaction
converges (Hertz within 3-15 % at 1.5 cells per contact radius), but the squeeze no longer holds the material
where eq. 3 puts it: under the default mass scaling a pushed clay keeps flowing past the finger and the one-layer
rubber ball's shell buckles in, so Table 2 gets worse; not the default.

Particle fingers, the default, against grid-node Dirichlet points (README, known limits, ``python -m
flows.finger_study``): on the default grid the pins hold the constrained points 1.03-3.7x closer to their targets
and act on the material only, so the dent spreads past the patch rims as a real one does; the halo had moved the rims
with the patch and held the body around it, which Table 2's BDC-S and mIoU rewarded (0.052 and 0.018 more).

Gravity preload (``simulation.gravity_preload_frames``, :meth:`MPMSolver.preload_gravity`): before the first frame
the body settles under its weight and is put back where it was given with the stress that carried it, so the given
(captured) shape is its equilibrium on the table and the run starts at rest, not sagging from its first frame.

Squeezing threshold (sec. 3.2): the squeeze strain of finger k is the indentation under the fingertip divided
by the object's half extent along the squeeze direction, ``eps_k = mean(u . d_k) / h(d_k)``, the mean taken over
the contact core of finger k's patch (the surface points of its region with patch weight phi >= exp(-1/2), i.e.
within one patch sigma of the centre; the mean over the whole 2.5-sigma support, whose rim barely moves,
reads ~3x lower), u = x - x0 the surface displacement (the object's base is held by the table,
``mpm.floor_sticky``, so u carries no rigid translation) and ``h(d) = sum_i |d_i| half_i``.  When ``max_k eps_k``
first reaches the material oracle's threshold, the shell ruptures within ``release_radius`` of that finger's
contact (those shell particles become ``ruptured_softening`` times softer, and an elastic skin's torn flakes crumple
and tear apart plastically beyond the strain they tore at (:func:`_torn_skin`); no finger constrains the surface
within ``release_radius + 1.5 dx`` any more, so the opening is free) and the interior there is released opposite
to the squeeze direction (along the outward patch normal) at the Bernoulli speed sqrt(2 p_k / rho) (capped,
:func:`bernoulli_speed`), p_k the finger's contact pressure = |reaction| / patch area, rho the interior's density,
from its rest volume (its pressure is that speed), while the torn skin over it peels back along the surface, away
from the opening (:func:`peel_velocities`), so it opens locally and stays on the object.  Packed stuffing (a ``foam``
interior) leaves at its packed volume (``simulation.stuffing_packing``) through a seam that opens at once into a hole
(:func:`seam_opening`), so it expands out of the tear as one cohesive bulge.  A scene with releasable
material gets at least ``simulation.release_margin_cells`` free cells around it.

Interior and core: the oracle's ``core`` (fruit flesh, plush stuffing) fills the cavity and is part of the body:
it is always simulated and holds the shell up.  The releasable ``interior`` (juice, loose stuffing) is made of
the core particles within ``release_radius`` of the rupture, which switch to the interior material (labels in
``particle_material``: 0 shell, 1 interior, 2 ruptured shell, 3 core).  Without a core (a sealed can of cola)
the interior fills the cavity from the start.  Objects without interior material, or whose control signals never
reach the threshold (predicted from the prescribed field before simulating), allocate no interior at all: no
interior material, no ``released`` array.  A fluid interior has no tension (``tasks.physics.mpm.constitutive``), so the
released liquid separates from what stays instead of pulling back on it.

Resistive force feedback (sec. 3.2, ``simulation.feedback_rule``): the paper's ``f_k = clip(tau_y * A_k, 0,
feedback_max_force)`` with tau_y the shell's yield stress and A_k the contact patch area (for materials without a
yield stress, elastic rubber, the simulated contact force |reaction_k| instead, clipped the same way), or the
simulated |reaction_k| clipped (``reaction``; ``auto`` picks it with collider fingers, whose reactions converge).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Mapping, Optional

import numpy as np
from scipy.spatial import cKDTree

from conf.hand import FINGERTIP_PAD_RADIUS, N_FINGERS
from conf.mpm_schema import MPMConfig, mpm_config_from
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.physics.attachment import detached_summary
from tasks.physics.free_flight import (
    flight_summary,
    held_by_boundary,
    prune_held,
    rollout_flights,
    shares_node,
    stencil_bases,
    touches_table,
)
from tasks.physics.labels import CORE, INTERIOR, N_LABELS, RUPTURED, SHELL
from tasks.physics.mpm.materials import MEMBRANE_MODELS, Material, material_from_dict
from tasks.physics.mpm.solver import (
    Collider,
    DirichletPoints,
    ForcePatch,
    GravityPreload,
    MPMSolver,
    ParticlePins,
    QuasiStaticLoad,
    contact_reach,
    deform_covariances,
    material_mass_scales,
    membrane_fibres_checked,
    polar_rotation,
    rotate_quaternions,
)
from tasks.physics.oracle.convert import materials_from_dict, mpm_material_kwargs
from tasks.physics.oracle.schema import ObjectMaterials
from tasks.physics.regions import finger_regions, region_weights, squeeze_strain

# The sub-frame flight recorder (FlightRecord): the released material reaches the table within 2-4 frames of the
# release in the default scenes, too few frame samples for a fitted acceleration; it samples the loose particles'
# positions every FLIGHT_SAMPLE_SUBSTEPS substeps (~20 samples per frame at 100 substeps) for FLIGHT_FRAMES frames
# (1/3 s at 30 fps: a fall of 0.5 m) after the release.
FLIGHT_FRAMES = 10
FLIGHT_SAMPLE_SUBSTEPS = 5
STATS_KEYS = ("substeps", "dt_min", "courant", "max_speed", "j_min", "j_max", "kinetic_energy", "internal_energy",
              "plastic_dissipation", "ke_ie_ratio", "ke_ie_contact", "energy_growth")  # per-frame step_frame statistics
STATS_UNITS = {"dt_min": "s", "courant": "1", "max_speed": "m/s", "j_min": "1", "j_max": "1", "kinetic_energy": "J",
               "internal_energy": "J", "plastic_dissipation": "J", "ke_ie_ratio": "1", "substeps": "1",
               "ke_ie_contact": "1", "energy_growth": "1"}


def cauchy_free_measures(F: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J = det F and the von Mises stress 3 mu eps_eq of the Hencky strain (Pa) per particle.

    eps_eq = sqrt(2/3) |dev log V|, V the left stretch of F (the elastic part for plastic models), so
    sigma_vm = 2 mu sqrt(3/2) |dev eps| = 3 mu eps_eq (StVK-Hencky, exact for that model).
    """
    J = np.linalg.det(F)
    # log of the singular values from the eigenvalues of F^T F (half the cost of the SVD, the same to ~1e-15)
    logs = 0.5 * np.log(np.clip(np.linalg.eigvalsh(np.swapaxes(F, -1, -2) @ F), 1e-12, None))
    dev = logs - logs.mean(axis=1, keepdims=True)
    eps_eq = math.sqrt(2.0 / 3.0) * np.linalg.norm(dev, axis=1)
    return J, 3.0 * mu * eps_eq


def _covariances(scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(np.concatenate([quats[:, 1:], quats[:, :1]], axis=1)).as_matrix()
    return np.einsum("nij,nj,nkj->nik", R, scales.astype(np.float64) ** 2, R)


def _sym6(cov: np.ndarray) -> np.ndarray:
    """(N,3,3) symmetric -> (N,6) as xx, xy, xz, yy, yz, zz."""
    return np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], axis=1)


@dataclass
class SqueezeRegions:
    """Where each finger squeezes (sec. 3.2 squeezing threshold), from the eq. 3 field and the contact patches.

    ``region`` (frame, finger, point) bool: finger k's surface points (remembered after release);
    ``direction`` (frame, finger, xyz) 1: inward squeeze direction d_k; ``phi`` (frame, finger, point) 1: patch
    weights of the region; ``half`` (xyz,) m: the object's half extents; ``predicted`` (frame, finger) 1: the
    squeeze strain the prescribed field alone would give (decides whether the interior is needed)."""

    region: np.ndarray
    direction: np.ndarray
    phi: np.ndarray
    half: np.ndarray
    predicted: np.ndarray


@dataclass
class Scene:
    """Stage 1 of the rollout: the MPM scene of one object, ready to step.

    ``materials`` are the solver's materials (index ``slot[label]``), ``labels`` (particle,) the initial particle
    labels (SHELL, INTERIOR, RUPTURED, CORE), ``dx`` m the grid spacing, ``frame_dt`` s the output frame
    interval, ``surface0`` (point, xyz) m the rest positions of the tracked surface points (the 3D Gaussians)."""

    oracle: ObjectMaterials
    solver: MPMSolver
    materials: list[Material]
    slot: np.ndarray
    labels: np.ndarray
    with_interior: bool
    dx: float
    config: MPMConfig
    frame_dt: float
    surface0: np.ndarray
    regions: SqueezeRegions
    notes: list[str]
    thin_wall: bool = False  # the shell is a wall thinner than the spacing (object model; sampling.thin_wall_layers)
    preload: Optional[GravityPreload] = None  # the gravity preload's figures (simulation.gravity_preload_frames)
    j_given: Optional[np.ndarray] = None  # (particle,) det F of the given shape after the preload (None: 1)


@dataclass
class FrameRecord:
    """Stage 2 of the rollout: what the frame loop recorded, per output frame (axes as in the artifact).

    ``labels`` are the particle labels after the run (a release changes them), ``released`` (particle,) bool
    the particles released at the threshold crossing (None without interior), ``event`` the crossing."""

    particle_positions: np.ndarray  # (frame, particle, xyz) m
    particle_J: np.ndarray  # (frame, particle) 1
    particle_von_mises: np.ndarray  # (frame, particle) Pa
    plastic_strain: Optional[np.ndarray]  # (frame, particle) 1, only with a plastic material
    gaussian_positions: np.ndarray  # (frame, point, xyz) m
    gaussian_covariances: np.ndarray  # (frame, point, sym6) m^2
    gaussian_rotations: np.ndarray  # (frame, point, quat) 1
    reaction: np.ndarray  # (frame, finger, xyz) N
    applied: np.ndarray  # (frame, finger, xyz) N
    strain: np.ndarray  # (frame, finger) 1
    tracking: np.ndarray  # (frame,) m
    stats: dict[str, np.ndarray]  # STATS_KEYS -> (frame,)
    labels: np.ndarray
    released: Optional[np.ndarray]
    event: dict[str, Any]
    flight: Optional[FlightRecord] = None
    openings: Optional[tuple[np.ndarray, np.ndarray]] = None  # torn surface points (point,), their finger (point,)
    beneath: Optional[np.ndarray] = None  # (particle,) int32: the finger pushing it through its opening, -1 none


@dataclass
class FlightRecord:
    """The sub-frame flight recorder of the released material (module constants FLIGHT_*), from the release to
    FLIGHT_FRAMES frames after it: at every sample the time ``times`` (s), the positions ``x`` (loose, xyz) m of
    the loose particles (labels INTERIOR and RUPTURED after the release: the released interior and the torn skin it
    may carry off) and which of them are ``held`` (loose,) bool: their B-spline stencil shares a grid node with the
    body (every other particle), a boundary point of the frame (Dirichlet or force point) or a wall or floor node,
    or, where the table acts as a plane collider (the released field), their surface touches it
    (:mod:`tasks.physics.free_flight`; collider fingers are not counted).  ``mass``/``physical_mass`` (loose,) kg
    the inertial and physical masses after the release, ``radius`` (loose,) m half their undeformed spacing."""

    loose: np.ndarray  # (particle,) bool: the particles sampled
    mass: np.ndarray
    physical_mass: np.ndarray
    radius: np.ndarray
    times: list[float]
    x: list[np.ndarray]
    held: list[np.ndarray]

    @classmethod
    def start(cls, solver: MPMSolver, labels: np.ndarray) -> "FlightRecord":
        """An empty record of the loose particles of ``labels`` (particle,), the labels after the release."""
        loose = (labels == INTERIOR) | (labels == RUPTURED)
        return cls(loose, solver.masses()[loose], solver.physical_masses()[loose],
                   solver.contact_radii()[loose], [], [], [])

    def sample(self, solver: MPMSolver, t: float, points: Optional[np.ndarray] = None) -> None:
        """Record the ``solver``'s particles at time ``t`` (s); ``points`` (n, xyz) m the boundary points acting
        then."""
        x = solver.positions()
        bases = stencil_bases(x[self.loose], solver.lo, solver.dx)
        holders = x[~self.loose] if points is None else np.concatenate([x[~self.loose], points])
        plane = solver.on_table_plane()[self.loose]
        floor = np.where(plane, -np.inf, solver.floor_g if solver.floor_height is not None else -np.inf)
        held = shares_node(bases, stencil_bases(holders, solver.lo, solver.dx))
        held |= held_by_boundary(bases, np.asarray(solver.dims), int(solver.cfg.padding), floor)
        if plane.any():
            held[plane] |= touches_table(x[self.loose][plane, 2], self.radius[plane], solver.floor_height)
        self.times.append(float(t))
        self.x.append(x[self.loose].astype(np.float32))
        self.held.append(held)

    def as_arrays(self, solver: MPMSolver) -> dict[str, np.ndarray]:
        """The record as the artifact's ``released_flight_*`` arrays (:func:`tasks.physics.free_flight.
        prune_held`: the loose particles held at every sample, e.g. a can's cola that stays in, are left out)."""
        x, held = np.array(self.x, np.float32), np.array(self.held, bool)
        kept, held = prune_held(x, held, solver.lo, solver.dx)
        return {"released_flight_time": np.array(self.times), "released_flight_positions": x[:, kept],
                "released_flight_held": held,
                "released_flight_particle": np.flatnonzero(self.loose)[kept].astype(np.int32),
                "released_flight_mass": self.mass[kept].astype(np.float64),
                "released_flight_physical_mass": self.physical_mass[kept].astype(np.float64)}


def boundary_points(bc: Optional[DirichletPoints], push: Optional[list[ForcePatch]], t: float) -> Optional[np.ndarray]:
    """(n, xyz) m: where the frame's Dirichlet points (advected with their velocities) or force points (at the
    frame start) are ``t`` s after the frame start (None: neither)."""
    if bc is not None:
        return np.asarray(bc.positions) + (t * np.asarray(bc.velocities) if bc.advect else 0.0)
    return None if not push else np.concatenate([np.asarray(p.positions).reshape(-1, 3) for p in push])


def mpm_rollout(obj: Mapping[str, np.ndarray], obj_attrs: Mapping[str, Any], field: Mapping[str, np.ndarray],
                forces: np.ndarray, patches: Mapping[str, np.ndarray], times: np.ndarray,
                materials: Mapping[str, Any], mpm: Mapping[str, Any], sim: Mapping[str, Any],
                boundary: str) -> tuple[dict[str, Array], dict[str, Any]]:
    """Simulate one object through its squeeze session (sec. 3.2); returns the rollout arrays and attributes.

    ``times`` (frame,) s; ``forces`` (frame, finger) the force coefficients c_k,t of eq. 1; ``field`` the eq. 3
    Dirichlet field, ``patches`` the eq. 2 contact patches, ``materials`` the oracle's attributes."""
    if boundary not in ("dirichlet", "force"):
        raise ValueError(f"variant.boundary must be dirichlet or force, got {boundary!r}")
    scene = build_scene(obj, obj_attrs, field, patches, times, materials, mpm, sim, forces, boundary)
    frames = run_frames(scene, obj, field, forces, patches, times, sim, boundary)
    return collect_outputs(scene, frames, times, patches, sim, boundary)


# ----------------------------------------------------------------------------------------------- 1. the scene
def squeeze_regions(obj_attrs: Mapping[str, Any], field: Mapping[str, np.ndarray], patches: Mapping[str, np.ndarray],
                    n_frames: int) -> SqueezeRegions:
    """The fingers' squeeze regions and the strain the prescribed field predicts over ``n_frames`` frames
    (``eps_k`` of the module doc with u the eq. 3 displacement of the constrained points): (frame, finger)."""
    half = 0.5 * (np.asarray(obj_attrs["bbox_max"]) - np.asarray(obj_attrs["bbox_min"]))
    disp, finger_of = field["displacement"], field["finger"]
    region, direction = finger_regions(finger_of, patches["patch_normals"])
    phi = region_weights(finger_of, field["weight"])
    constrained_now = finger_of >= 0
    predicted = np.stack([squeeze_strain(np.where(constrained_now[f][:, None], disp[f], 0.0), region[f],
                                         direction[f], half, phi[f]) for f in range(n_frames)])
    return SqueezeRegions(region=region, direction=direction, phi=phi, half=half, predicted=predicted)


def interior_plan(mats: ObjectMaterials, has_cavity: bool, predicted: np.ndarray) -> tuple[bool, bool, list[str]]:
    """Which interior particles the scene needs: (with_core, with_interior, notes).

    The core (pulp, stuffing) is body and always simulated when the object has one and a cavity; the releasable
    interior only when the material has a squeeze threshold that the ``predicted`` strain (frame, finger)
    reaches."""
    notes: list[str] = []
    threshold = mats.squeeze_threshold
    with_core = mats.core is not None and has_cavity  # the pulp / stuffing is body: always simulated
    with_interior = mats.interior is not None and has_cavity
    core_note = f"; the {mats.core.name} core is simulated as part of the body" if with_core else ""
    if mats.interior is None or not has_cavity:
        notes.append("interior and release skipped: the object has no interior material")
    elif threshold is None:
        with_interior = False
        notes.append("interior and release skipped: the material never ruptures (no squeeze threshold)" + core_note)
    elif predicted.max() < threshold:
        with_interior = False
        notes.append(f"interior and release skipped: the controls never reach the squeeze threshold "
                     f"(predicted peak strain {predicted.max():.3f} < {threshold:.3f})" + core_note)
    return with_core, with_interior, notes


def scene_particles(obj: Mapping[str, np.ndarray], mats: ObjectMaterials, with_core: bool, with_interior: bool,
                    sim: Mapping[str, Any]) -> tuple[dict[int, Material], np.ndarray, np.ndarray, np.ndarray]:
    """Solver materials by label and the particles: (materials by label, x0 (particle, xyz) m float32,
    volumes (particle,) m^3 float32, labels (particle,) int32 of SHELL, INTERIOR, RUPTURED, CORE)."""
    shell = material_from_dict(mpm_material_kwargs(mats.shell, "shell"))
    by_label: dict[int, Material] = {SHELL: shell}
    positions = [obj["particle_positions"]]
    volumes = [obj["particle_volumes"]]
    ids = [np.full(len(obj["particle_positions"]), SHELL, np.int32)]
    if with_core:
        by_label[CORE] = _cohesionless_core(material_from_dict(mpm_material_kwargs(mats.core, "core")))
        positions.append(obj["interior_positions"])
        volumes.append(obj["interior_volumes"])
        ids.append(np.full(len(obj["interior_positions"]), CORE, np.int32))
    if with_interior:
        by_label[INTERIOR] = _released_material(mats.interior, sim)
        if not with_core:  # no solid core: the interior fills the cavity from the start (cola in a can)
            positions.append(obj["interior_positions"])
            volumes.append(obj["interior_volumes"])
            ids.append(np.full(len(obj["interior_positions"]), INTERIOR, np.int32))
        soft = float(sim["ruptured_softening"])
        by_label[RUPTURED] = replace(shell, name="ruptured_shell", youngs_modulus=shell.youngs_modulus * soft,
                                     yield_stress=shell.yield_stress * soft)
    initial = {by_label[lab].model for lab in set(np.concatenate(ids).tolist())}
    if with_interior and shell.model == "fixed_corotated" and initial != {"fixed_corotated"}:
        by_label[RUPTURED] = _torn_skin(by_label[RUPTURED], float(mats.squeeze_threshold))
    x0 = np.concatenate(positions).astype(np.float32)
    vol = np.concatenate(volumes).astype(np.float32)
    return by_label, x0, vol, np.concatenate(ids)


def load_rise_time(forces: np.ndarray, frame_dt: float) -> Optional[float]:
    """How fast the fingers load the object, s: the time the total force coefficient C_t = sum_k c_k,t of eq. 1
    (``forces`` (frame, finger)) would take to reach its peak at its steepest rise, max C / max dC/dt (a linear ramp
    gives its duration; a finger barely touching does not count, as it would alone).  The displacement field of
    eq. 3 follows the same coefficients.  None: no finger pushes."""
    total = np.asarray(forces, np.float64).sum(axis=1)
    rate = float(np.diff(total).max(initial=0.0)) / frame_dt  # 1/s
    return float(total.max()) / rate if rate > 0 else None


def build_scene(obj: Mapping[str, np.ndarray], obj_attrs: Mapping[str, Any], field: Mapping[str, np.ndarray],
                patches: Mapping[str, np.ndarray], times: np.ndarray, materials: Mapping[str, Any],
                mpm: Mapping[str, Any], sim: Mapping[str, Any], forces: np.ndarray, boundary: str) -> Scene:
    """Stage 1: the MPM scene of one object (materials by label, particles, grid, time scaling, solver).  Under a
    force-driven ``boundary`` (``force``) the force coefficients ``forces`` (frame, finger) set the load's time
    scale for the quasi-static bound of the mass scale (``mpm.quasi_static_margin``)."""
    # 1. what the scene needs: interior particles only if they can be released
    mats = materials_from_dict(materials)
    T = len(times)
    frame_dt = float(times[1] - times[0]) if T > 1 else 1.0 / 30.0
    regions = squeeze_regions(obj_attrs, field, patches, T)
    with_core, with_interior, notes = interior_plan(mats, len(obj["interior_positions"]) > 0, regions.predicted)

    # 2. materials by label (SHELL, INTERIOR, RUPTURED, CORE); the solver indexes the list of those present
    by_label, x0, vol, mid = scene_particles(obj, mats, with_core, with_interior, sim)
    labels = sorted(by_label)
    mat_list: list[Material] = [by_label[lab] for lab in labels]
    slot = np.full(N_LABELS, -1, np.int32)
    slot[labels] = np.arange(len(labels))  # the solver's material ids are slot[mid]

    # 3. grid and time scaling
    cfg = mpm_config_from(dict(mpm))
    spacing = float(obj_attrs["particle_spacing"])
    dx = cfg.dx or spacing * cfg.particles_per_cell ** (1.0 / 3.0)
    cfg = replace(cfg, dx=dx)  # the solver applies mpm.mass_scaling (per material; weights stay physical)
    # a hollow object's wall thinner than the grid spacing is a shell the grid cannot resolve through its thickness:
    # held in plane stress (mpm.thin_walls; elastic and von Mises models) up to mpm.membrane_max_thickness of a cell.
    # Its in-plane wave speed, not the 3D one, sets its stable step, hence the mass scale
    thin_wall = bool(obj_attrs.get("thin_wall", False))
    thickness = float(obj_attrs.get("wall_thickness", 0.0) or 0.0)
    normals = fibres = None
    membrane = 0.0 < thickness < dx and cfg.thin_walls == "membrane" and by_label[SHELL].model in MEMBRANE_MODELS
    # ...a thicker wall in Gauss layers carries 3D stress (one layer on the mid-surface has no bending as a solid
    # either, and locks: it stays a membrane)
    thick = thickness >= cfg.membrane_max_thickness * dx and len(obj["wall_fibres"]) > 0
    if membrane and thick:
        notes.append(f"the {by_label[SHELL].name} wall ({1e3 * thickness:.3g} mm) is {thickness / dx:.2f} of the "
                     f"{1e3 * dx:.3g} mm grid's cell, at least mpm.membrane_max_thickness "
                     f"({cfg.membrane_max_thickness:g}): held as a 3D solid in its Gauss layers")
    elif membrane:
        normals = np.zeros_like(x0)
        normals[mid == SHELL] = obj["particle_normals"]  # the shell's particles come first (scene_particles)
        if len(obj["wall_fibres"]):  # the Gauss layers' fibres (the shell's particles come first)
            fibres = np.asarray(obj["wall_fibres"], np.int64)
        for lab in (SHELL, RUPTURED):  # the torn skin is the shell's particles; as foam it stays 3D
            if lab in by_label and by_label[lab].model in MEMBRANE_MODELS:
                mat_list[slot[lab]] = replace(mat_list[slot[lab]], membrane=True)
        shell = mat_list[slot[SHELL]]
        notes.append(f"the {shell.name} wall ({1e3 * thickness:.3g} mm) is thinner than the {1e3 * dx:.3g} mm grid: "
                     f"held in plane stress (mpm.thin_walls=membrane), in-plane wave speed "
                     f"{shell.p_wave_speed():.3g} m/s instead of {replace(shell, membrane=False).p_wave_speed():.3g}")
    if with_interior:  # room for the spray to fly before a domain wall stops it (simulation.release_margin_cells)
        cfg = replace(cfg, margin_cells=max(cfg.margin_cells, int(sim["release_margin_cells"])))
    # the quasi-static bound of the mass scale (mpm.quasi_static_margin) for a force-driven squeeze only: a force
    # leaves the body free to lean and rock on the table in its slowest mode (under the former unbalanced push,
    # simulation.force_balance=none, the ball and duck: 85-99 % of their kinetic energy), while Dirichlet fingers
    # hold the points they press, so that mode does not exist and the deformation under the fingers is local and
    # faster (measured KE/IE of the default Dirichlet squeezes <= 0.034 at the unbounded scale)
    rise = load_rise_time(forces, frame_dt) if boundary == "force" else None
    load = None if rise is None else QuasiStaticLoad(rise_time=rise, height=float(obj_attrs["bbox_max"][2]
                                                                                 - obj_attrs["bbox_min"][2]))
    if with_interior:  # released material keeps its physical inertia under selective mass scaling
        mat_list[slot[INTERIOR]] = replace(mat_list[slot[INTERIOR]], mass_scaled=False)
    if with_interior and mat_list[slot[INTERIOR]].model == "fluid":
        # weakly compressible: sound speed = the fastest speed the released fluid reaches / fluid_mach, that speed
        # being the larger of fluid_reference_speed and a release at max_release_speed followed by a fall from the
        # object's top to the table, instead of water's 1450 m/s.  K = s_f rho c^2 with s_f the mass scale the solver
        # gives the fluid (1 under selective scaling), so the sound speed is c whatever the scaling.
        # Under global (one-factor) scaling the former model is kept: c = 10 fluid_reference_speed, capped at the
        # solids' scaled P-wave speed (juice made from burst pulp appears mid-run and must not need a smaller step).
        present = [mat_list[i] for i in np.unique(slot[mid])]
        scale_fluid = float(material_mass_scales(mat_list, present, dx, frame_dt, cfg, load)[slot[INTERIOR]])
        if cfg.mass_scaling == "selective":
            height = float(obj_attrs["bbox_max"][2] - obj_attrs["bbox_min"][2])
            v = max(float(sim["fluid_reference_speed"]),
                    math.sqrt(float(sim["max_release_speed"]) ** 2 + 2.0 * abs(float(cfg.gravity[2])) * height))
            c_fluid = v / float(sim["fluid_mach"])
        else:
            v = float(sim["fluid_reference_speed"])
            c_solid = max(m.p_wave_speed(cfg.stiffness_scaling, scale_fluid) for m in present if m.model != "fluid")
            c_fluid = min(10.0 * v, c_solid)
        k_fluid = scale_fluid * mat_list[slot[INTERIOR]].density * c_fluid ** 2 / cfg.stiffness_scaling
        notes.append(f"interior fluid bulk modulus {k_fluid:.3g} Pa (sound speed {c_fluid:.3g} m/s at mass scale "
                     f"x{scale_fluid:.3g}: Mach {v / c_fluid:.2g} at {v:.3g} m/s) instead of "
                     f"{mats.interior.bulk_modulus:.3g} Pa")
        mat_list[slot[INTERIOR]] = replace(mat_list[slot[INTERIOR]], bulk_modulus=k_fluid)

    # 4. the solver, with the surface points (3D Gaussians) as tracers embedded in the shell: the skin they draw, not
    #    the interior or the core, which a rupture releases (a Gaussian bound to pulp that burst into juice was
    #    dragged off the tomato with it, between its skin and juice anchors: 77 of 3000 ended > 2 cells off the fruit)
    solver = MPMSolver(x0, vol, mat_list, material_ids=slot[mid], config=cfg, tracers=obj["surface_points"],
                       tracer_anchors=mid == SHELL, label=str(obj_attrs.get("name", "")), load=load,
                       membrane_normals=normals, membrane_fibres=fibres)
    if fibres is None and len(obj["wall_fibres"]):  # Gauss layers held as a 3D solid touch colliders at their faces
        layers = membrane_fibres_checked(np.asarray(obj["wall_fibres"], np.int64), np.ones(len(x0), bool), x0)
        solver.set_contact_radii(contact_reach(solver.volumes(), layers))
    if thin_wall and cfg.fingers == "particles":
        notes.append("particle fingers pin the wall's particles at their centres: a wall thinner than the "
                     f"{1e3 * spacing:.3g} mm spacing (ParticlePins arms 0)")
    # 5. the given shape is the body's equilibrium on the table under its weight (simulation.gravity_preload_frames)
    pre = j_given = None
    if int(sim["gravity_preload_frames"]) > 0:
        pre = solver.preload_gravity(frame_dt, int(sim["gravity_preload_frames"]), int(sim["gravity_preload_passes"]),
                                     tolerance=float(sim["gravity_preload_tolerance"]))
        notes.append(f"gravity preload: unsupported, the body would settle by up to {1e3 * pre.sag:.3g} mm under its "
                     f"weight; held in its given shape by that stress ({pre.passes} pass(es), {pre.frames} damped "
                     f"frames, {1e3 * pre.residual:.2g} mm left{'' if pre.converged else ', not at rest'}; per pass "
                     + ", ".join(f"{1e3 * m:.3g}" for m in pre.moved) + " mm)")
        j_given = np.linalg.det(solver.deformation_gradients(plane_stress=True).astype(np.float64))
    return Scene(oracle=mats, solver=solver, materials=mat_list, slot=slot, labels=mid, with_interior=with_interior,
                 dx=dx, config=cfg, frame_dt=frame_dt, surface0=obj["surface_points"].astype(np.float64),
                 regions=regions, notes=notes, thin_wall=thin_wall, preload=pre, j_given=j_given)


# ----------------------------------------------------------------------------------------------- 2. the frames
def _allocate_record(scene: Scene, T: int, S: int) -> FrameRecord:
    """Zeroed outputs for T frames, S surface points and the scene's particles (only what the scene needs)."""
    P = len(scene.labels)
    plastic = any(m.is_plastic for m in scene.materials)
    return FrameRecord(
        particle_positions=np.zeros((T, P, 3), np.float32), particle_J=np.ones((T, P), np.float32),
        particle_von_mises=np.zeros((T, P), np.float32),
        plastic_strain=np.zeros((T, P), np.float32) if plastic else None,
        gaussian_positions=np.zeros((T, S, 3), np.float32), gaussian_covariances=np.zeros((T, S, 6), np.float32),
        gaussian_rotations=np.zeros((T, S, 4), np.float32), reaction=np.zeros((T, N_FINGERS, 3), np.float32),
        applied=np.zeros((T, N_FINGERS, 3), np.float32), strain=np.zeros((T, N_FINGERS), np.float32),
        tracking=np.zeros(T, np.float32), stats={k: np.full(T, math.nan if k == "ke_ie_contact" else 0.0) for k in STATS_KEYS},
        labels=scene.labels, released=np.zeros(P, bool) if scene.with_interior else None,
        event={"crossed": False, "threshold": scene.oracle.squeeze_threshold})


def record_frame(rec: FrameRecord, f: int, scene: Scene, mu_phys: np.ndarray, cov0: np.ndarray, q0: np.ndarray,
                 torn: np.ndarray) -> None:
    """Store frame f of the solver's state in ``rec``: particles (x, J, von Mises with the per-particle shear
    moduli ``mu_phys`` Pa, plastic strain), the Gaussians (positions, covariances F cov0 F^T, rotations
    polar(F) q0) and the squeeze strain of each finger (torn skin no longer counts)."""
    solver, reg = scene.solver, scene.regions
    F = solver.deformation_gradients(plane_stress=True).astype(np.float64)  # a thin wall's: its material state
    rec.particle_positions[f] = solver.positions()
    rec.particle_J[f], rec.particle_von_mises[f] = cauchy_free_measures(F, mu_phys)
    if scene.j_given is not None:  # volume ratio to the given shape, which the preload holds under its weight
        rec.particle_J[f] /= scene.j_given
    if rec.plastic_strain is not None:
        rec.plastic_strain[f] = solver.plastic_strain()
    tx, tF = solver.tracer_state()
    tF = tF.astype(np.float64)
    rec.gaussian_positions[f] = tx
    rec.gaussian_covariances[f] = _sym6(deform_covariances(tF, cov0))
    rec.gaussian_rotations[f] = rotate_quaternions(polar_rotation(tF), q0)
    moved = tx - scene.surface0
    # torn skin (around an opening) is no longer under a finger: the released interior may carry it off
    rec.strain[f] = squeeze_strain(moved, reg.region[f] & ~torn, reg.direction[f], reg.half, reg.phi[f])


def dirichlet_points(scene: Scene, field: Mapping[str, np.ndarray], f: int, torn: np.ndarray,
                     contact_tolerance: float) -> tuple[Optional[DirichletPoints], np.ndarray, np.ndarray]:
    """The Dirichlet conditions of frame f (module doc): the constrained, untorn points a finger pushes or holds,
    driven to their eq. 3 targets within one frame.  Returns (conditions or None, point indices, targets (m))."""
    disp, finger_of = field["displacement"], field["finger"]
    idx = np.flatnonzero(field["constrained"][f] & ~torn)
    target_x = np.zeros((0, 3))
    if len(idx):
        current = scene.solver.tracer_positions()[idx].astype(np.float64)
        target_x = scene.surface0[idx] + disp[f, idx]
        # unilateral contact: a finger pushes or holds, it never pulls material outwards
        inward = scene.regions.direction[f, finger_of[f, idx]]
        gap = np.einsum("ij,ij->i", target_x - current, inward)
        retreating = np.einsum("ij,ij->i", disp[f, idx] - disp[f - 1, idx], inward) < 0.0
        push_or_hold = gap >= np.where(retreating, 0.0, -contact_tolerance)
        idx, current, target_x = idx[push_or_hold], current[push_or_hold], target_x[push_or_hold]
    if not len(idx):
        return None, idx, target_x
    bc = DirichletPoints(positions=current, velocities=(target_x - current) / scene.frame_dt,
                         finger_ids=finger_of[f, idx].astype(np.int32))
    return bc, idx, target_x


def particle_pins(scene: Scene, bc: Optional[DirichletPoints], idx: np.ndarray, target_x: np.ndarray, f: int,
                  field: Mapping[str, np.ndarray]) -> Optional[ParticlePins]:
    """``mpm.fingers = particles``: the Dirichlet conditions of frame f (:func:`dirichlet_points`: surface points
    ``idx``, targets ``target_x``) on the particles instead of the grid nodes.  Every particle a constrained point
    is embedded in (its anchors) has its surface point, along the finger's outward patch normal, driven by the
    mean displacement its points still need (target - where they are), so the points move by that much; the push
    acts on those particles only, at their surface (no node is held, so no layer next to the finger is held rigid)
    or, on a wall thinner than the spacing (``scene.thin_wall``: ``sampling.thin_wall_layers`` particle layers
    within it), at their centres (:class:`ParticlePins` ``arms``), and its impulses are the finger's reaction."""
    if bc is None:
        return None
    anchors = scene.solver.tracer_anchor_particles()[idx]  # (point, anchor)
    point = np.repeat(np.arange(len(idx)), anchors.shape[1])
    particles, which = np.unique(anchors.reshape(-1), return_inverse=True)
    count = np.bincount(which, minlength=len(particles)).astype(np.float64)[:, None]
    finger = field["finger"][f, idx]
    outward = -scene.regions.direction[f, finger]
    need = (target_x - bc.positions)[point]
    move = np.stack([np.bincount(which, need[:, c], len(particles)) for c in range(3)], 1)
    normal = np.stack([np.bincount(which, outward[point, c], len(particles)) for c in range(3)], 1)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    first = np.full(len(particles), -1, np.int64)
    first[which[::-1]] = point[::-1]  # each particle's first point gives its finger
    arms = np.full(len(particles), 0.0 if scene.thin_wall else 1.0)
    start = scene.solver.surface_points(particles, normal, arms)
    return ParticlePins(particles, start + move / count, normal, finger[first].astype(np.int32), arms=arms)


def fingertip_travel(field: Mapping[str, np.ndarray], patches: Mapping[str, np.ndarray], f: int) -> np.ndarray:
    """The eq. 3 amplitude eta c_k,t (m) of every finger at frame f, read from the field: the least-squares A_k of
    u_i . d_k = A_k phi_k(x_i) over finger k's constrained points (u the displacement, phi_k = the stored weight,
    d_k the inward patch normal); exact where finger k's patch alone reaches (phi_k = 1 at the patch centre).
    (finger,); 0 for a finger without constrained points."""
    finger_of = field["finger"][f]
    w = field["weight"][f].astype(np.float64)
    inward = -patches["patch_normals"][f].astype(np.float64)
    along = np.einsum("ij,ij->i", field["displacement"][f].astype(np.float64), inward[np.maximum(finger_of, 0)])
    mine = finger_of[None, :] == np.arange(N_FINGERS)[:, None]
    den = (mine * w * w).sum(axis=1)
    return np.where(den > 0, (mine * w * along).sum(axis=1) / np.maximum(den, 1e-30), 0.0)


def fingertip_centres(field: Mapping[str, np.ndarray], patches: Mapping[str, np.ndarray], f: int,
                      radius: float) -> np.ndarray:
    """Centre (m) of each finger's fingertip sphere (``radius`` m) at frame f (finger, xyz): its lowest point is
    the patch centre moved inwards by the eq. 3 amplitude (:func:`fingertip_travel`), so at zero force it touches
    the rest surface and at frame f it reaches the target the field prescribes at the patch centre."""
    outward = patches["patch_normals"][f].astype(np.float64)
    travel = fingertip_travel(field, patches, f)
    return patches["patch_centers"][f].astype(np.float64) + (radius - travel)[:, None] * outward


def finger_colliders(solver: MPMSolver, surface0: np.ndarray, field: Mapping[str, np.ndarray],
                     patches: Mapping[str, np.ndarray], f: int, torn: np.ndarray, frame_dt: float,
                     friction: float = 0.0) -> list[Collider]:
    """The fingers of frame f under ``mpm.fingers = collider`` (module doc): a rigid sphere of the fingertip pad
    radius per active finger, from its place at frame f - 1 to its place at frame f (:func:`fingertip_centres`) in
    the frame's time, i.e. velocity = displacement / frame_dt (m/s).  A finger that was not active at frame f - 1
    starts where it just touches the material (:func:`_touching`), not at the rest surface: particle surfaces stick
    out of it by up to the sampling jitter, and a sphere placed over them would kick them out within one substep.
    The contact is unilateral by construction (a collider pushes, never pulls), frictionless or with Coulomb
    ``friction`` (``mpm.finger_friction``).  A finger whose patch centre lies on torn skin (``torn`` (point,) bool
    over the rest surface points ``surface0`` (point, xyz) m: the one nearest to the centre ruptured) no longer
    presses: the opening is free."""
    radius, active = FINGERTIP_PAD_RADIUS, patches["patch_active"]
    end = fingertip_centres(field, patches, f, radius)
    start = fingertip_centres(field, patches, f - 1, radius)
    centres = patches["patch_centers"][f].astype(np.float64)
    nearest = np.argmin(((surface0[None, :, :] - centres[:, None, :]) ** 2).sum(axis=-1), axis=1)
    on = [k for k in range(N_FINGERS) if active[f, k] and not torn[nearest[k]]]
    arriving = [k for k in on if not active[f - 1, k]]
    if arriving:
        x, half = solver.positions().astype(np.float64), solver.contact_radii()
        for k in arriving:
            start[k] = _touching(x, half, centres[k] + radius * patches["patch_normals"][f, k],
                                 patches["patch_normals"][f, k], radius)
    return [Collider("sphere", start[k], radius=radius, velocity=(end[k] - start[k]) / frame_dt,
                     friction=float(friction), finger_id=k) for k in on]


def _touching(x: np.ndarray, half: np.ndarray, centre: np.ndarray, outward: np.ndarray, radius: float) -> np.ndarray:
    """The sphere (``radius`` m) at ``centre`` (m) moved out along ``outward`` until no particle surface (centre
    ``x`` (particle, xyz) m + ``half`` its half spacing, m) lies inside it (a few fixed-point steps)."""
    for _ in range(4):
        depth = float(np.max(radius + half - np.linalg.norm(x - centre, axis=1), initial=0.0))
        if depth <= 1e-6 * radius:
            break
        centre = centre + depth * np.asarray(outward, np.float64)
    return centre


def force_patch(scene: Scene, field: Mapping[str, np.ndarray], forces: np.ndarray,
                patches: Mapping[str, np.ndarray], f: int, torn: np.ndarray, sim: Mapping[str, Any],
                openings: Optional[tuple[np.ndarray, np.ndarray]] = None,
                beneath: Optional[np.ndarray] = None) -> Optional[list[ForcePatch]]:
    """The force-mode push of frame f (the no_dirichlet ablation): a total force ``force_per_coefficient *
    c_k,t`` N per active finger along its inward patch normal, spread over its constrained, untorn points.

    1. The skin: the points are the surface tracers, re-placed every substep (``ForcePatch.tracers``): the push
    follows the skin.  (Fixed for a frame, they were left behind by a torn arm moving at 3 m/s, 10 cm per frame, and
    the finger's whole force went to the fringe mass still under them, 2.3 N on 4e-5 kg: the divergence, dt 1e-9 s,
    of the plush toy pushed with balanced fingers after its rupture.)  A finger that punctured the skin no longer
    presses on its torn points: their share of its force (torn / constrained points of its patch) goes 2. to the
    stuffing or pulp beneath its opening (``simulation.torn_finger_push=beneath``), as far as the grip needs it
    (:func:`grip_closing_share`): the core particles (CORE) chosen at the rupture within two grid cells of the
    finger's torn points and of the interior released under it (``beneath`` (particle,) the finger pushing each,
    -1 none; :func:`stuffing_beneath`), of which those still within ``release_radius`` + two cells of the torn
    points where they are now (``openings``: the torn surface points and their fingers) are pushed, on their own
    positions (``ForcePatch.particles``).  The finger presses on through the hole onto what lies under it; what it
    pushed deep leaves its reach (the whole set pushed with the whole share carried particles out of the plush
    toy's far side, 8 cm from its centre at 1.9 m/s, J guard at frame 63 of seed 0).  Without such particles
    (``torn_finger_push=none``, or a hollow can whose cola is a fluid) that share is dropped: the released material
    offers no support.  (Concentrating the whole force on the few skin points left beside an opening crushed the
    loose stuffing there to det F = 3e-4; spread over the torn skin too, it followed the flaps as they folded away
    and flung 7.4 % of the plush toy's torn skin off the toy.)  3. The fingers' forces are then
    balanced (``simulation.force_balance``, :func:`balanced_push`; each finger's moment arm from the centre of its
    points, skin and beneath weighted by their shares), before and after a rupture: the hand still closes its grip
    on a torn toy.  Whether the push is a grasp (two fingers against each other) or a poke is read from the
    fingers' intended push, torn patches included: a finger that punctured the skin still closes the grip.
    (Unbalanced after its rupture, the force-driven plush toy's index pushed 5.8 N against the pinky's 1.7 N and
    toppled it; balanced, both push 1.8 N.  With the torn thumb's share dropped, its four fingers left side by
    side cannot close the grip within their friction cones and shoved it over in two of three sampling seeds.)"""
    finger_of = field["finger"][f]
    constrained = field["constrained"][f]
    idx = np.flatnonzero(constrained & ~torn)
    surface = scene.solver.tracer_positions()
    deep, x = np.zeros(0, np.int64), None
    if beneath is not None and openings is not None and len(openings[0]):
        x = scene.solver.positions()
        reach = float(sim["release_radius"]) + 2.0 * scene.dx
        deep = np.flatnonzero(stuffing_beneath(x, beneath >= 0, surface[openings[0]], openings[1], reach) >= 0)
    # 1.-2. each finger's intended force and the shares with a point of application (skin, beneath)
    intended, on_skin, below = np.zeros((N_FINGERS, 3)), np.zeros(N_FINGERS), np.zeros(N_FINGERS)
    for k in range(N_FINGERS):
        patch = int((constrained & (finger_of == k)).sum())
        if patches["patch_active"][f, k] and patch:
            intended[k] = float(sim["force_per_coefficient"]) * forces[f, k] * -patches["patch_normals"][f, k]
            on_skin[k] = int((finger_of[idx] == k).sum()) / patch
            below[k] = (1.0 - on_skin[k]) * bool((beneath[deep] == k).any()) if len(deep) else 0.0
    grasp = bool((intended @ intended.T < 0.0).any())
    below *= grip_closing_share(intended * on_skin[:, None], intended * below[:, None])
    applied = on_skin + below
    if not (applied > 0).any():
        return None
    skin_x, skin_k = surface[idx], finger_of[idx].astype(np.int32)
    deep_x, deep_k = (x[deep], beneath[deep].astype(np.int32)) if len(deep) else (None, None)
    centres = np.zeros((N_FINGERS, 3))
    for k in np.flatnonzero(applied > 0):
        if on_skin[k]:
            centres[k] += on_skin[k] * skin_x[skin_k == k].mean(axis=0)
        if below[k]:
            centres[k] += below[k] * deep_x[deep_k == k].mean(axis=0)
        centres[k] /= applied[k]
    # 3. the balance of the whole push, then each finger's force split between its skin and what lies beneath
    push = balanced_push(intended * applied[:, None], str(sim["force_balance"]), float(sim["force_balance_friction"]),
                         centres, grasp=grasp)
    part = np.divide(1.0, applied, out=np.zeros(N_FINGERS), where=applied > 0)[:, None] * push
    out = []
    if len(idx):
        out.append(ForcePatch(positions=skin_x, finger_ids=skin_k, tracers=idx, forces=on_skin[:, None] * part))
    if below.any():
        out.append(ForcePatch(positions=deep_x, finger_ids=deep_k, particles=deep, forces=below[:, None] * part))
    return out


def grip_closing_share(skin: np.ndarray, beneath: np.ndarray) -> float:
    """The share s in [0, 1] of the push through the openings ``beneath`` (finger, xyz) N that leaves the fingers'
    push ``skin + s beneath`` (N) the least net force, s = clip(-N_skin . N_b / |N_b|^2, 0, 1) (N the sums over
    the fingers): the stuffing under an opening carries what closes the grip, no more.  It is crushable (the plush
    toy's yields at 1 kPa: 0.4 N under a 4 cm^2 fingertip) and offers a finger pressing into it only the reaction
    the hand's closed force loop asks of it.  (Pushed with their whole force, the three fingers through their
    openings of seed 0 of the force-driven plush toy tore its head off, J guard at frame 54.)"""
    net = np.asarray(beneath).sum(axis=0)
    size = float(net @ net)
    return float(np.clip(-np.asarray(skin).sum(axis=0) @ net / size, 0.0, 1.0)) if size > 0 else 0.0


def _beneath_openings(x: np.ndarray, labels: np.ndarray, released: np.ndarray, surface: np.ndarray,
                      openings: tuple[np.ndarray, np.ndarray], centers: np.ndarray, fingers: list[int],
                      radius: float, depth: float) -> np.ndarray:
    """:func:`stuffing_beneath` at the rupture: each finger's opening is its torn surface points (``openings``:
    indices into ``surface`` (point, xyz) m, where the skin was as it tore, and their fingers) and, for the fingers
    that punctured it (``fingers``, patch centres ``centers`` m), the interior released within ``radius`` m of its
    centre (particles ``x`` m, ``released`` bool)."""
    points, owner = [surface[openings[0]]], [openings[1]]
    for k in fingers:
        out = released & (np.linalg.norm(x - centers[k], axis=1) <= radius)
        points.append(x[out])
        owner.append(np.full(int(out.sum()), k))
    return stuffing_beneath(x, labels == CORE, np.concatenate(points), np.concatenate(owner).astype(np.int32),
                            depth)


def stuffing_beneath(x: np.ndarray, candidates: np.ndarray, opening: np.ndarray, fingers: np.ndarray,
                     depth: float) -> np.ndarray:
    """(particle,) int32: the finger (0..4) that presses through its opening on each particle, -1 none: the
    ``candidates`` (particle,) bool - at the rupture the core (label CORE: the stuffing or pulp that stays part of
    the body), later the core chosen then - within ``depth`` m of the finger's ``opening`` points (n, xyz) m
    (``fingers`` (n,) the finger of each); the nearest finger where two reach.  ``x`` (particle, xyz) m.  The
    released interior itself is not pushed: it leaves through the opening (the stuffing's bulge, the juice)."""
    out = np.full(len(x), -1, np.int32)
    core = np.flatnonzero(candidates)
    if not len(core) or not len(opening):
        return out
    dist, nearest = cKDTree(np.asarray(opening, np.float64)).query(x[core], distance_upper_bound=depth)
    hit = np.isfinite(dist)
    out[core[hit]] = np.asarray(fingers)[nearest[hit]]
    return out


def balanced_push(total: np.ndarray, balance: str, friction: float,
                  centres: Optional[np.ndarray] = None, grasp: Optional[bool] = None) -> np.ndarray:
    """The fingers' push (finger, xyz) N with its net force - and under ``wrench`` then its net moment - removed as
    far as the grip can (``simulation.force_balance``, ``simulation.force_balance_friction`` = mu).

    A hand squeezing an object is a closed force loop: what its fingers put on the object sums to zero, force and
    moment.  1. The force (``fingers`` and ``wrench``): the net force F_net = sum_k F_k is taken off the fingers in
    proportion to their force magnitudes, F_k' = F_k - a (|F_k| / W) F_net with W = sum_j |F_j|; at a = 1 the change
    of least sum_k |F_k' - F_k|^2 / |F_k| (each finger keeps its share of the squeeze) with sum_k F_k' = 0.  Along
    its own direction d_k = F_k / |F_k| a finger still pushes, F_k' . d_k = |F_k| (1 - a d_k . F_net / W) >= 0
    (|F_net| <= W), never pulls; the rest of its change, a |F_k| |F_net,perp k| / W, is tangential: the grip's
    friction, which cannot exceed mu times the finger's push.  So a is the largest value <= 1 at which every
    finger's tangential / normal force stays <= mu, a = min(1, min_k mu W / (|F_net,perp k| + mu d_k . F_net)), and
    what remains of the net force (1 - a) F_net is the table's.  2. The moment (``wrench``), about the fingers'
    points of application ``centres`` (finger, xyz) m (:func:`couple_change`): the least change of the same
    weights that cancels the net moment of step 1's forces without touching their net force, scaled by the largest
    b <= 1 that keeps every finger inside its friction cone about d_k (:func:`inside_friction_cones`); (1 - b) of
    that moment is the table's.  In two steps so that the moment never takes friction from the force balance.  Why
    the moment: the force-driven plush toy, its force points following the skin, swayed on the table under the
    moment its force-balanced fingers left (0.028 N m two frames before the rupture; KE/IE 0.123, 85 % of its KE in
    the sway).  The default grasps' force step needs <= 0.74 (a = 1 before any rupture).  A push without two fingers
    against each other (F_j . F_k < 0: one finger, or fingers side by side, the clay's poke) is left as given, for
    the table to carry as under Dirichlet fingers (balanced, a poke would vanish); ``grasp`` (default: that test on
    ``total``) overrides the test, e.g. for a grasp whose opposing finger tore through the skin (the fingers left
    side by side then balance to what they push against each other).  ``none``: the push as given (its net force,
    up to ~50 % of the fingers' sum along the eq. 3 directions, is carried by nothing but the table)."""
    if balance == "none":
        return total
    if balance not in ("wrench", "fingers"):
        raise ValueError(f"simulation.force_balance must be wrench, fingers or none, got {balance!r}")
    if balance == "wrench" and centres is None:
        raise ValueError("balanced_push: simulation.force_balance=wrench needs the fingers' centres")
    if not ((total @ total.T < 0.0).any() if grasp is None else grasp):  # a poke: no two fingers against each other
        return total
    # 1. the net force
    size = np.linalg.norm(total, axis=1)
    net, on = total.sum(axis=0), size > 0
    d = total[on] / size[on, None]
    along = d @ net
    across = np.linalg.norm(net - along[:, None] * d, axis=1)
    limit = across + friction * along  # > 0 where removing the net force uses up that finger's friction
    share = min([1.0, *(friction * size.sum() / limit[limit > 0])])
    balanced = total - share * (size / size.sum())[:, None] * net
    if balance == "fingers":
        return balanced
    # 2. the net moment, within the friction cones
    change = couple_change(balanced, centres, size)
    low, high = 0.0, 1.0
    if not inside_friction_cones(balanced + change, total, friction):
        for _ in range(40):  # the cones are convex and step 1 is inside them: the admissible b form [0, b_max]
            middle = 0.5 * (low + high)
            low, high = (middle, high) if inside_friction_cones(balanced + middle * change, total, friction) \
                else (low, middle)
        high = low
    return balanced + high * change


def couple_change(push: np.ndarray, centres: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """The change (finger, xyz) N of least sum_k |dF_k|^2 / w_k (``weight`` (finger,) w_k >= 0: |F_k| of the given
    push) that cancels the net moment of ``push`` (finger, xyz) N acting at ``centres`` (finger, xyz) m and adds no
    net force: dF_k = w_k m x r_k with r_k = centre_k - c (c the w-weighted mean centre, so sum_k dF_k = m x sum_k
    w_k r_k = 0) and m = -J^+ M, M = sum_k r_k x push_k, J = sum_k w_k (|r_k|^2 I - r_k r_k^T) (its Lagrange
    condition; J is the fingers' "inertia" about c, and its pseudo-inverse leaves the moment about the line of
    collinear fingers, which forces through those points cannot make, to the table)."""
    weight = np.asarray(weight, np.float64)
    if not weight.sum() > 0:
        return np.zeros_like(push)
    lever = centres - (weight / weight.sum()) @ centres
    moment = np.cross(lever, push).sum(axis=0)
    inertia = np.einsum("k,kij->ij", weight, (lever * lever).sum(axis=1)[:, None, None] * np.eye(3)
                        - lever[:, :, None] * lever[:, None, :])
    m = -np.linalg.pinv(inertia, rcond=1e-9, hermitian=True) @ moment
    return weight[:, None] * np.cross(m, lever)


def inside_friction_cones(push: np.ndarray, given: np.ndarray, friction: float) -> bool:
    """Whether every finger's ``push`` (finger, xyz) N lies in its friction cone about the direction of its
    ``given`` push (tangential <= ``friction`` x normal, normal >= 0; fingers with no given push are skipped)."""
    size = np.linalg.norm(given, axis=1)
    d = given[size > 0] / size[size > 0, None]
    normal = np.einsum("ij,ij->i", push[size > 0], d)
    tangential = np.linalg.norm(push[size > 0] - normal[:, None] * d, axis=1)
    return bool(np.all(tangential <= friction * normal * (1.0 + 1e-12) + 1e-15))


def run_frames(scene: Scene, obj: Mapping[str, np.ndarray], field: Mapping[str, np.ndarray], forces: np.ndarray,
               patches: Mapping[str, np.ndarray], times: np.ndarray, sim: Mapping[str, Any],
               boundary: str) -> FrameRecord:
    """Stage 2: the frame loop.  Per frame: the boundary condition (Dirichlet points or force patches), one
    solver frame, the record, and the threshold release the first time a finger's strain reaches the threshold."""
    solver, reg, slot = scene.solver, scene.regions, scene.slot
    T, threshold = len(times), scene.oracle.squeeze_threshold
    rec = _allocate_record(scene, T, len(obj["surface_points"]))
    mid = scene.labels
    mu_phys = np.array([m.mu for m in scene.materials])[slot[mid]]
    cov0 = _covariances(obj["gaussian_scales"], obj["gaussian_rotations"])
    q0 = obj["gaussian_rotations"].astype(np.float64)
    torn = np.zeros(len(obj["surface_points"]), bool)  # surface points whose skin ruptured: no longer constrained
    contact_tolerance = 0.25 * scene.dx  # m: a point this much deeper than its finger is still in contact

    record_frame(rec, 0, scene, mu_phys, cov0, q0, torn)
    for f in range(1, T):
        # 1. boundary condition of the frame
        bc, push, tips, pins, idx = None, None, None, None, np.zeros(0, np.int64)
        if boundary == "dirichlet":  # (the Dirichlet points also give the tracking error of the collider fingers)
            bc, idx, target_x = dirichlet_points(scene, field, f, torn, contact_tolerance)
            if scene.config.fingers == "particles":
                bc, pins = None, particle_pins(scene, bc, idx, target_x, f, field)
            elif scene.config.fingers == "collider":
                bc, tips = None, finger_colliders(solver, scene.surface0, field, patches, f, torn, scene.frame_dt,
                                                  scene.config.finger_friction)
        else:
            push = force_patch(scene, field, forces, patches, f, torn, sim, rec.openings, rec.beneath)
        # 2. one output frame of the solver (KE/IE per frame: summarised in the attrs)
        # (after the rupture the motion is dynamic by design: no quasi-static check)
        flying = rec.flight is not None and f <= rec.event["frame"] + FLIGHT_FRAMES
        start = float(times[f - 1])
        st = solver.step_frame(scene.frame_dt, dirichlet=bc, forces=push, quasi_static=not rec.event["crossed"],
                               colliders=tips, pins=pins, probe_every=FLIGHT_SAMPLE_SUBSTEPS,
                               probe=(lambda t: rec.flight.sample(solver, start + t, boundary_points(bc, push, t)))
                               if flying else None)
        if flying:
            rec.flight.sample(solver, float(times[f]), boundary_points(bc, push, scene.frame_dt))
        if f == 1:
            scene.notes.append("stable substep per material (s): " + ", ".join(
                f"{k} {v:.3g} ({math.ceil(scene.frame_dt / v)} substeps per frame)"
                for k, v in solver.stable_dt_per_material().items()))
        for k in STATS_KEYS:
            rec.stats[k][f] = float(getattr(st, k))
        rec.reaction[f] = np.asarray(st.reaction)[:N_FINGERS]
        rec.applied[f] = np.asarray(st.applied_force)[:N_FINGERS]
        # 3. record
        record_frame(rec, f, scene, mu_phys, cov0, q0, torn)
        report_progress(f, T - 1)
        if len(idx):  # RMS distance of the points the field imposes from their targets at the end of the frame
            rec.tracking[f] = np.sqrt(np.mean(np.sum((rec.gaussian_positions[f][idx] - target_x) ** 2, axis=1)))
        # 4. the threshold release (once)
        if (scene.with_interior and not rec.event["crossed"] and threshold is not None
                and rec.strain[f].max() >= threshold):
            tx = rec.gaussian_positions[f]  # placed by record_frame at the end of this frame
            centers = np.array([tx[reg.region[f, k]].mean(axis=0) if reg.region[f, k].any()
                                else patches["patch_centers"][f, k] for k in range(N_FINGERS)])
            rec.event = _release(solver, f, times[f], rec.strain[f], threshold, patches, centers, rec.reaction[f],
                                 rec.applied[f], boundary, mid, slot, rec.released, sim)
            # the finger punctured the skin: it no longer presses on its patch, and no finger constrains the
            # surface within release_radius + 1.5 dx of the opening (a constrained point's B-spline stencil reaches
            # 1.5 dx deep: it would hold the released interior in place under the opening)
            opening = float(sim["release_radius"]) + 1.5 * scene.dx
            for k in rec.event["fingers"]:
                torn |= reg.region[f, k] | (np.linalg.norm(tx - centers[k], axis=1) <= opening)
            mid = rec.event.pop("labels")
            mu_phys = np.array([m.mu for m in scene.materials])[slot[mid]]
            if boundary == "force" and sim["torn_finger_push"] == "beneath":  # each finger's torn points
                opened = np.flatnonzero(torn & field["constrained"][f])
                rec.openings = (opened, field["finger"][f][opened].astype(np.int32))
                rec.beneath = _beneath_openings(solver.positions(), mid, rec.released, tx, rec.openings, centers,
                                                rec.event["fingers"], float(sim["release_radius"]), 2.0 * scene.dx)
                rec.event["pushed_beneath"] = int((rec.beneath >= 0).sum())
            rec.flight = FlightRecord.start(solver, mid)
            rec.flight.sample(solver, float(times[f]), boundary_points(bc, push, scene.frame_dt))
    solver.close_quasi_static_contact()  # the run ends: a contact still loaded is judged too
    rec.labels = mid
    return rec


# ----------------------------------------------------------------------------------------------- 3. the outputs
def resistive_feedback(oracle: ObjectMaterials, contact: np.ndarray, patches: Mapping[str, np.ndarray],
                       max_force: float, rule: str = "yield_area") -> tuple[np.ndarray, str]:
    """Resistive force feedback (sec. 3.2) per frame and finger, N, clipped to [0, ``max_force``]: under ``rule``
    ``yield_area`` (the paper's) tau_y A_k with tau_y the shell's yield stress (Pa) and A_k the active patch area
    (m^2), or the contact force |``contact``| (frame, finger, xyz) N for a shell without a yield stress; under
    ``reaction`` that contact force.  Returns (feedback (frame, finger), the rule applied)."""
    area = patches["patch_areas"] * patches["patch_active"]
    tau_y = oracle.shell.yield_stress if rule == "yield_area" else 0.0
    raw_feedback = tau_y * area if tau_y else np.linalg.norm(contact, axis=-1)
    feedback = np.clip(raw_feedback, 0.0, max_force).astype(np.float32)
    if tau_y:
        return feedback, "tau_y * area"
    return feedback, "|contact force|" + (" (no yield stress)" if rule == "yield_area" else "")


def feedback_rule(sim: Mapping[str, Any], fingers: str) -> str:
    """``simulation.feedback_rule`` resolved: ``auto`` is ``reaction`` with collider fingers (their reactions are
    the fingertip impulses at the surface) and the paper's ``yield_area`` with Dirichlet fingers (particle pins or grid
    nodes), whose reactions are not converged."""
    rule = str(sim.get("feedback_rule", "auto"))
    if rule == "auto":
        return "reaction" if fingers == "collider" else "yield_area"
    return rule


def collect_outputs(scene: Scene, rec: FrameRecord, times: np.ndarray, patches: Mapping[str, np.ndarray],
                    sim: Mapping[str, Any], boundary: str) -> tuple[dict[str, Array], dict[str, Any]]:
    """Stage 3: the rollout artifact: the recorded arrays with axes and units, the resistive feedback and the
    attributes (materials, scaling, threshold event, notes, quasi-static summary)."""
    solver, mid = scene.solver, rec.labels
    contact = rec.reaction if boundary == "dirichlet" else rec.applied
    free_fall = None
    fingers = scene.config.fingers if boundary == "dirichlet" else "force"
    feedback, rule = resistive_feedback(scene.oracle, contact, patches, float(sim["feedback_max_force"]),
                                        feedback_rule(sim, fingers))
    arrays: dict[str, Array] = {
        "time": Array(times.astype(np.float64), ("frame",), "s"),
        "particle_positions": Array(rec.particle_positions, ("frame", "particle", "xyz"), "m"),
        "particle_material": Array(mid.astype(np.int8), ("particle",), "1",
                                   "0 shell, 1 interior (released juice / cola / stuffing), 2 ruptured shell, "
                                   "3 core (pulp / stuffing: part of the body)"),
        "particle_J": Array(rec.particle_J, ("frame", "particle"), "1",
                            "det F / det F_given: volume ratio to the given shape (F_given: after the gravity preload)"),
        "particle_von_mises": Array(rec.particle_von_mises, ("frame", "particle"), "Pa",
                                    "3 mu eps_eq of the elastic Hencky strain"),
        "gaussian_positions": Array(rec.gaussian_positions, ("frame", "point", "xyz"), "m"),
        "gaussian_covariances": Array(rec.gaussian_covariances, ("frame", "point", "sym6"), "m^2",
                                      "F Sigma F^T: xx xy xz yy yz zz"),
        "gaussian_rotations": Array(rec.gaussian_rotations, ("frame", "point", "quat"), "1", "polar(F) q0, w first"),
        "reaction_force": Array(rec.reaction, ("frame", "finger", "xyz"), "N",
                                "frame mean of the fingertip collider's impulses m dv / dt on the particles it touched"
                                if fingers == "collider" else
                                "sum m (v_bc - v*) / dt over the finger's constrained nodes, frame mean"),
        "applied_force": Array(rec.applied, ("frame", "finger", "xyz"), "N", "force mode push, frame mean"),
        "feedback_force": Array(feedback, ("frame", "finger"), "N", "resistive force for the glove"),
        "squeeze_strain": Array(rec.strain, ("frame", "finger"), "1"),
        "dirichlet_tracking_error": Array(rec.tracking, ("frame",), "m",
                                          "RMS |x - (x0 + dx)| over the points imposed in that frame"),
        "predicted_squeeze_strain": Array(scene.regions.predicted.astype(np.float32), ("frame", "finger"), "1"),
    }
    for k in STATS_KEYS:
        arrays[k] = Array(rec.stats[k], ("frame",), STATS_UNITS[k])
    if rec.plastic_strain is not None:
        arrays["plastic_strain"] = Array(rec.plastic_strain, ("frame", "particle"), "1", "equivalent plastic strain")
    if rec.released is not None:
        arrays["released"] = Array(rec.released, ("particle",), "1", "released at the threshold crossing")
        if rec.flight is not None and rec.flight.times:
            flight = rec.flight.as_arrays(solver)
            arrays.update(_flight_arrays(flight))
            free_fall = _flight_summary(flight, solver)
    attrs = {
        "boundary": boundary, "materials": [m.name for m in scene.materials], "n_particles": int(len(mid)),
        "n_interior": int((mid == INTERIOR).sum()),
        "with_interior": bool(scene.with_interior), "dx": float(scene.dx), "mass_scale": solver.mass_scale,
        "membrane_max_thickness": float(scene.config.membrane_max_thickness),
        "gravity_preload": None if scene.preload is None else scene.preload.as_dict(),
        "gravity_effective": solver.gravity, "device": solver.device,
        "substeps_total": int(rec.stats["substeps"].sum()),
        "threshold_event": rec.event, "notes": scene.notes,
        "material_mass_scales": {m.name: float(k) for m, k in zip(scene.materials, solver.material_mass_scale)},
        "released_free_fall": free_fall,
        "feedback_rule": rule, "fingers": fingers,
        "bytes_per_particle": float(solver.bytes_per_particle()),
        "quasi_static": {**_quasi_static_summary(solver.quasi_static_contacts, rec.stats["ke_ie_contact"], contact,
                                                 solver.mass_scale, float(scene.config.quasi_static_ke_ie_max)),
                         **_quasi_static_bound(solver, scene.config)},
        "energy_guard": {"tolerance": float(scene.config.energy_guard_tolerance),
                         "max_energy_growth": float(rec.stats["energy_growth"].max())},
        "skin_attachment": detached_summary(rec.particle_positions[-1], mid, (SHELL, RUPTURED, CORE),
                                            _held_labels(scene), scene.dx),
    }
    return arrays, attrs


def _held_labels(scene: Scene) -> dict[str, int]:
    """The particles that must stay on the object (name -> label; ``skin_attachment``): the shell and its torn skin,
    and the released interior where its contact holds it to the body (``Material.cohesion``: torn-out stuffing),
    not juice or cola, which are meant to leave."""
    held = {"shell": SHELL, "ruptured": RUPTURED}
    if scene.with_interior and scene.materials[int(scene.slot[INTERIOR])].cohesion > 0:
        held["stuffing"] = INTERIOR
    return held


FLIGHT_ARRAYS = {  # name: (axes, unit, description) of the flight recorder's arrays in the rollout artifact
    "released_flight_time": (("sample",), "s", f"flight recorder: every {FLIGHT_SAMPLE_SUBSTEPS} substeps for "
                             f"{FLIGHT_FRAMES} frames after the release"),
    "released_flight_positions": (("sample", "loose", "xyz"), "m", "the loose particles (released interior and torn "
                                  "skin) not held at every sample"),
    "released_flight_held": (("sample", "loose"), "1", "stencil shares a grid node with the body, a boundary point, "
                             "a wall, the table or a held loose particle"),
    "released_flight_particle": (("loose",), "1", "index on the particle axis"),
    "released_flight_mass": (("loose",), "kg", "inertial (mass-scaled)"),
    "released_flight_physical_mass": (("loose",), "kg", "")}


def _flight_arrays(flight: dict[str, np.ndarray]) -> dict[str, Array]:
    """The flight recorder's arrays (:meth:`FlightRecord.as_arrays`) in the artifact: enough to recompute the
    flights offline (:func:`tasks.physics.free_flight.rollout_flights` with the ``released_free_fall`` attrs)."""
    return {k: Array(flight[k], *FLIGHT_ARRAYS[k]) for k in FLIGHT_ARRAYS}


def _flight_summary(flight: dict[str, np.ndarray], solver: MPMSolver) -> dict[str, Any]:
    """The released material's measured free fall (:func:`tasks.physics.free_flight.flight_summary` of its free
    blobs' flights), with the grid the flights are recomputed on (``grid_origin`` m, ``dx`` m, ``gravity`` m/s^2)
    and the table's height ``floor_height`` (m, world z; None without a floor) that the flight figure measures from."""
    grid = {"grid_origin": np.asarray(solver.lo, np.float64).tolist(), "dx": float(solver.dx),
            "gravity": float(solver.cfg.gravity[2])}
    return {**flight_summary(rollout_flights(flight, grid)), **grid, "floor_height": solver.floor_height}


def _quasi_static_summary(contacts: list[dict], ke_ie_contact: np.ndarray, contact: np.ndarray, mass_scale: float,
                          limit: float) -> dict:
    """How well the mass-scaled run stayed quasi-static: the solver's judged ``contacts`` (``first_frame``,
    ``last_frame``, ``ke_ie`` = sum KE / sum (IE + plastic work) of the mass-scaled material over the contact's
    checked frames, see :class:`MPMSolver`), the largest of them and how many exceed ``limit``; ``ke_ie_contact``
    (frame,) finite in the checked frames; ``contact`` (frame, finger, xyz) N the boundary's force.  The max is
    None (JSON for NaN) when no contact was judged."""
    in_contact = np.linalg.norm(contact, axis=-1).max(axis=1) > 0
    ratios = [float(c["ke_ie"]) for c in contacts]
    finite = lambda r: r if math.isfinite(r) else None  # noqa: E731  (JSON: inf, KE without IE, as None)
    return {"mass_scale": mass_scale, "limit": limit,
            "contacts": [{**c, "ke_ie": finite(r)} for c, r in zip(contacts, ratios)],
            "max_ke_ie_in_contact": finite(max(ratios)) if ratios else None,
            "contacts_over_limit": sum(r > limit for r in ratios), "contacts_checked": len(ratios),
            "frames_checked": int(np.isfinite(ke_ie_contact).sum()), "frames_in_contact": int(in_contact.sum())}


def _quasi_static_bound(solver: MPMSolver, cfg: MPMConfig) -> dict:
    """The quasi-static bound of the mass scale as applied (``mpm.quasi_static_margin``): the margin k, the load's
    rise time t_load (s, None: no finger pushes) and the scaled body's estimated slowest period T1 (s)."""
    period = solver.lowest_period()
    return {"margin": float(cfg.quasi_static_margin),
            "load_rise_time": None if solver.load is None else solver.load.rise_time,
            "lowest_period": period if math.isfinite(period) else None}


def _released_material(interior: Any, sim: Mapping[str, Any]) -> Material:
    """The solver material of what is released past the threshold (label INTERIOR).

    A fluid (juice, cola) gets the Tait exponent ``simulation.fluid_tait_exponent`` (its bulk modulus is set with
    the mass scale).  A ``foam`` (the table's loose fibrefill stuffing: a cohesive, crushable fibre mass) is used as
    stated, the torn-out fibre mass itself, with a crush cap that admits the packed state it is released at
    (``simulation.stuffing_packing``, :func:`_release`): compression up to it is elastic, beyond it permanent; its
    contact with the toy holds its yield stress x ``simulation.stuffing_cohesion`` in tension (``Material.cohesion``:
    its fibres stay entangled with the stuffing it tore from).  Any
    other solid interior (an LLM's answer may give one) is ``ruptured_softening`` times softer than stated: torn
    loose, it no longer carries load."""
    m = material_from_dict(mpm_material_kwargs(interior, "interior"))
    if m.model == "fluid":
        return replace(m, fluid_gamma=float(sim["fluid_tait_exponent"]))
    if m.model == "foam":
        return replace(m, crush_strain=max(m.crush_strain, -math.log(float(sim["stuffing_packing"]))),
                       cohesion=m.yield_stress * float(sim["stuffing_cohesion"]), mass_scaled=False)
    soft = float(sim["ruptured_softening"])
    return replace(m, name="released_interior", youngs_modulus=m.youngs_modulus * soft,
                   yield_stress=m.yield_stress * soft)


def _cohesionless_core(core: Material) -> Material:
    """A ``foam`` core (fibrefill stuffing, a fibre mass without tensile strength) pulled apart separates into
    tufts instead of stretching elastically: volumetric expansion beyond its crush strain is permanent (elastic
    J <= exp(crush_strain)), the tension counterpart of the crush cap.  Without it the stuffing next to an opening,
    dragged by the loose stuffing flowing out, was stretched elastically to det F_E = 20 (the upper guard) in the
    force-driven plush toy.  Other core models are returned unchanged."""
    return replace(core, dilation_strain=core.crush_strain) if core.model == "foam" else core


def _torn_skin(soft: Material, tear_strain: float) -> Material:
    """The torn skin of an elastic shell (label RUPTURED): the ``foam`` model (StVK-Hencky, von Mises yield and
    the volumetric crush cap) with the softened shell's E and nu, yielding at the strain it tore at.

    Torn skin is pressed by the released interior against what stops it (the flesh behind a finger; before the
    skin peeled back (:func:`peel_velocities`), the table and the domain walls the spray carried flakes to).  There
    a thin flake folds and crumples instead of being compressed elastically: an elastic model (even neo-Hookean's ln J barrier) let det F_E of the soft flakes fall below
    ``mpm.j_min`` between the spray and a wall (flattened to singular values ~(5, 0.4, 0.03)).  Here compaction beyond
    the crush strain stays as permanent plastic volume change (elastic J >= exp(-crush_strain)) and shear beyond
    the yield strain as plastic flow.  Where the spray spreads, a lone flake embedded in it follows the juice's
    diverging velocity (an elastic flake was stretched to det F_E = 20, the upper guard, with singular values
    ~(3, 2.8, 2.4)): it tears apart instead, so dilation beyond the dilation strain is permanent too.  All three
    are the squeeze threshold ``tear_strain`` (1): the skin already failed at that strain, so the flake's elastic
    range is no larger; yield stress = E_torn x tear_strain (Pa)."""
    return replace(soft, model="foam", yield_stress=soft.youngs_modulus * tear_strain, hardening=0.0,
                   viscosity=0.0, crush_strain=tear_strain, dilation_strain=tear_strain)


def peel_velocities(x: np.ndarray, centre: np.ndarray, normal: np.ndarray, speed: float,
                    radius: float) -> np.ndarray:
    """(particle, xyz) m/s: the torn skin ``x`` (particle, xyz) m of an opening at ``centre`` (m) with outward
    ``normal`` peeling back: each particle moves along the surface, away from the opening's axis, at ``speed`` (m/s,
    the interior's release speed) x its distance from the axis / ``radius`` (m, the torn patch's radius), the
    velocity of a uniformly widening hole, with no component along ``normal``.

    A skin tears and its flaps fold back onto the fruit (or a seam's edges part) instead of leaving with what it
    held in: the flaps slide into the intact, mass-scaled shell at the rim, which stops them, while the released
    interior pushes out through the hole.  Launching the torn skin outward with the interior (the former rule) tore
    the tomato's skin at the centre of its opening off as a flake that the juice carried 3.8 cm away (20 % of its
    torn skin > 3 cells off the fruit; peeled back, 0 %; default release_radius 2.5 cells).  Limit: the grid averages a
    velocity that diverges within a cell, so the middle of a wider torn patch stays a free disk that the interior
    pushes off (a pocket of juice under a torn 1 mm skin, dx 5 mm: no torn particle > 3 cells off at a 3.5-cell
    patch radius, 37 % at 4 cells, as many as launched)."""
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    r = np.asarray(x, np.float64) - np.asarray(centre, np.float64)
    along = r - np.outer(r @ n, n)
    return speed / radius * along


def seam_opening(x: np.ndarray, centre: np.ndarray, normal: np.ndarray, radius: float, hole: float) -> np.ndarray:
    """(particle, xyz) m: the torn fabric ``x`` (particle, xyz) m of an opening at ``centre`` (m) with outward
    ``normal``, moved along the surface to open a hole of radius ``hole`` (m) in the torn patch of radius ``radius``
    (m): a particle at distance r from the opening's axis moves away from it to hole + r (radius - hole) / radius,
    with no component along ``normal``, so the torn fabric is folded into the ring between the hole and the intact
    fabric (the patch's rim, r = radius, stays).

    A seam or fabric tear over packed stuffing opens as the stuffing pushes the lips apart and the stretched fabric
    springs back.  The fabric retracts at its bar wave speed sqrt(E / rho) (the table's plush: 32 m/s, 1 cm in 0.3 ms,
    about one substep), so the opening is applied at once.  In the grid a torn patch only parts where its pieces end
    farther apart than a B-spline stencil (~1.5 cells): the peel-back of :func:`peel_velocities` leaves the middle of
    a 2.5-cell patch in place, a lid the stuffing cannot pass (the plush toy's stuffing moved 4 mm out and stopped
    under it)."""
    if not 0.0 <= hole < radius:
        raise ValueError(f"seam_opening: the hole radius must be in [0, radius = {radius} m), got {hole} m")
    n = np.asarray(normal, np.float64) / np.linalg.norm(normal)
    r = np.asarray(x, np.float64) - np.asarray(centre, np.float64)
    along = r - np.outer(r @ n, n)
    dist = np.linalg.norm(along, axis=1)
    scale = (hole + dist * (radius - hole) / radius) / np.maximum(dist, 1e-12)
    return np.asarray(x, np.float64) + along * (scale - 1.0)[:, None]


def bernoulli_speed(pressure: float, density: float) -> float:
    """The speed (m/s) at which a liquid at gauge ``pressure`` (Pa) leaves through an opening into still air,
    sqrt(2 p / rho) (Bernoulli along a streamline from the pressed interior, at rest, to the jet at ambient
    pressure); ``density`` kg/m^3.  0 for p <= 0 (nothing is pressed out)."""
    if not density > 0:
        raise ValueError(f"bernoulli_speed: density must be > 0 kg/m^3, got {density}")
    return math.sqrt(2.0 * max(float(pressure), 0.0) / float(density))


def _release(solver: MPMSolver, f: int, t: float, strain: np.ndarray, threshold: float,
             patches: Mapping[str, np.ndarray], centers: np.ndarray, reaction: np.ndarray, applied: np.ndarray,
             boundary: str, mid: np.ndarray, slot: np.ndarray, released: np.ndarray,
             sim: Mapping[str, Any]) -> dict[str, Any]:
    """Rupture the shell and release interior particles at the finger(s) past the threshold.

    ``centers`` (finger, xyz) m: where each finger's contact is now (the deformed patch), not at rest.  ``mid``
    holds the particle labels, ``slot`` maps a label to the solver's material index.  Within ``release_radius``
    of a finger past the threshold the shell ruptures and the interior is released: the interior particles
    there, or, for an object with a solid core (pulp, stuffing), the core particles there, which become the
    interior material (the pulp's cells burst into juice, the stuffing tears loose).  The returned event holds
    the new labels under ``labels``."""
    x = solver.positions().astype(np.float64)
    v = solver.velocities().astype(np.float64)
    ids = mid.copy()
    radius = float(sim["release_radius"])
    fingers = [k for k in range(N_FINGERS) if strain[k] >= threshold and patches["patch_active"][f, k]]
    fingers = fingers or [int(np.argmax(strain))]
    interior = solver.materials[int(slot[INTERIOR])]
    c_released = interior.p_wave_speed(solver.stiffness_scale, float(solver.material_mass_scale[int(slot[INTERIOR])]))
    stuffing = interior.model == "foam"  # packed stuffing: released compressed, through a seam that opens
    speeds, pressures = [], []
    for k in fingers:
        c = centers[k]
        n_out = patches["patch_normals"][f, k]
        area = max(float(patches["patch_areas"][f, k]), 1e-8)
        pressure = float(np.linalg.norm(reaction[k] if boundary == "dirichlet" else applied[k])) / area  # Pa
        speed = float(min(bernoulli_speed(pressure, interior.density), float(sim["max_release_speed"]),
                          float(sim["release_mach_max"]) * c_released))
        near = np.linalg.norm(x - c, axis=1) <= radius
        torn = near & (mid == SHELL)
        ids[torn] = RUPTURED
        out = near & ((mid == INTERIOR) | (mid == CORE)) & ~released
        ids[out] = INTERIOR
        # the interior leaves opposite to the squeeze direction (-n_out); the torn skin over it peels back
        v[out] = n_out * speed
        v[torn] = peel_velocities(x[torn], c, n_out, speed, radius)
        if stuffing:
            x[torn] = seam_opening(x[torn], c, n_out, radius, float(sim["seam_opening"]) * radius)
        released |= out
        speeds.append(speed)
        pressures.append(pressure)
    solver.set_material_ids(slot[ids])
    solver.set_velocities(v.astype(np.float32))
    if stuffing:
        solver.set_positions(x.astype(np.float32))
    # a liquid's pressure is spent on the release speed (Bernoulli): what leaves starts at its rest volume and moves
    # as one (F = I, C = 0); the squeezed pulp's compression left in it would burst it in every direction.  Stuffing
    # is a solid fibre mass packed into the toy: it leaves at its packed volume J = simulation.stuffing_packing
    # (F = J^(1/3) I) and expands out of the opening, cohesive (the foam carries tension), as a bulge
    packing = float(sim["stuffing_packing"]) if stuffing else 1.0
    F, C = solver.deformation_gradients(), solver.affine_velocities()
    F[released], C[released] = np.cbrt(packing) * np.eye(3, dtype=F.dtype), 0.0
    solver.set_deformation_gradients(F)
    solver.set_affine_velocities(C)
    # what leaves starts as a fresh mass: F above is its whole state, so the plastic strain the core accumulated
    # under the fingers (the plush toy's stuffing: median 0.45, up to 1.2) is not carried into it (it would raise
    # the yield of a hardening interior and read as the released stuffing's plastic strain)
    alpha = solver.plastic_strain()
    alpha[released] = 0.0
    solver.set_plastic_strain(alpha)
    return {"crossed": True, "frame": int(f), "time": float(t), "fingers": fingers,
            "strain": float(strain.max()), "threshold": threshold, "released_particles": int(released.sum()),
            "release_speeds": speeds, "release_pressures": pressures,
            "release_density": float(interior.density), "release_sound_speed": float(c_released), "labels": ids}


ROLLOUT_OUTPUTS = ("time", "particle_positions", "particle_material", "particle_J", "particle_von_mises",
                   "gaussian_positions", "gaussian_covariances", "gaussian_rotations", "reaction_force",
                   "applied_force", "feedback_force", "squeeze_strain", "dirichlet_tracking_error",
                   "predicted_squeeze_strain", "substeps", "dt_min", "courant", "max_speed", "j_min", "j_max",
                   "kinetic_energy", "internal_energy", "plastic_dissipation", "ke_ie_ratio", "ke_ie_contact",
                   "energy_growth",
                   "plastic_strain?", "released?",
                   *(f"{k}?" for k in FLIGHT_ARRAYS))


@artifact_step("mpm_rollout",
               inputs=("object_model", "signal_smoothing", "force_coefficients", "contact_patches", "dirichlet_field",
                       "material_oracle"),
               reads=("mpm", "simulation", "variant.boundary"),
               # the thread count splits the same particle kernel (results agree to float32 round-off): flows.squeeze
               # / flows.export (2 threads) reuse flows.evaluate's rollouts (1 thread per worker) and vice versa
               unkeyed=("mpm.threads",),
               outputs=ROLLOUT_OUTPUTS)
def mpm_rollout_step(inputs, params):
    """The squeeze simulated with MLS-MPM (eqs. 4-5) under the eq. 3 field (``variant.boundary=dirichlet``: particle
    pins, grid-node Dirichlet points with ``mpm.fingers=dirichlet`` or fingertip colliders with
    ``mpm.fingers=collider``) or the per-finger force (``force``, the no_dirichlet ablation), with the oracle's
    materials."""
    obj = inputs["object_model"]
    return mpm_rollout(obj.arrays, {**obj.attrs, "name": obj.ref.scope}, inputs["dirichlet_field"].arrays,
                       inputs["force_coefficients"]["force_coefficients"], inputs["contact_patches"].arrays,
                       inputs["signal_smoothing"]["time"], inputs["material_oracle"].attrs["materials"],
                       params["mpm"], params["simulation"], params["variant.boundary"])
