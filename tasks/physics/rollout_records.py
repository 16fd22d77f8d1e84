"""What the rollout records (paper sec. 3.2): per-frame particle and Gaussian states, the fingers' forces and squeeze
strains, the solver's statistics, the released material's sub-frame flight, and the rollout artifact with the
resistive force feedback and the quasi-static summary."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Optional

import numpy as np

from conf.hand import N_FINGERS
from conf.mpm_schema import MPMConfig
from tasks.core.artifacts import Array
from tasks.physics.attachment import detached_summary
from tasks.physics.free_flight import (
    blob_held,
    flight_summary,
    held_by_boundary,
    prune_held,
    rollout_flights,
    shares_node,
    stencil_bases,
    touches_table,
)
from tasks.physics.labels import CORE, INTERIOR, RUPTURED, SHELL
from tasks.physics.mpm import MPMSolver, deform_covariances, polar_rotation, rotate_quaternions
from tasks.physics.oracle.schema import ObjectMaterials
from tasks.physics.regions import squeeze_strain
from tasks.physics.rollout_scene import Scene

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


def rest_covariances(scales: np.ndarray, quats: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    R = Rotation.from_quat(np.concatenate([quats[:, 1:], quats[:, :1]], axis=1)).as_matrix()
    return np.einsum("nij,nj,nkj->nik", R, scales.astype(np.float64) ** 2, R)


def _sym6(cov: np.ndarray) -> np.ndarray:
    """(N,3,3) symmetric -> (N,6) as xx, xy, xz, yy, yz, zz."""
    return np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], axis=1)


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
    stopped_after: Optional[int] = None  # the last frame run when the caller stopped the run early (run_frames)


@dataclass
class FlightRecord:
    """The sub-frame flight recorder of the released material (module constants FLIGHT_*), from the release to
    FLIGHT_FRAMES frames after it: at every sample the time ``times`` (s), the positions ``x`` (loose, xyz) m of
    the loose particles (labels INTERIOR and RUPTURED after the release: the released interior and the torn skin it
    may carry off) and which of them are ``held`` (loose,) bool: their blob (:func:`tasks.physics.free_flight.
    blob_held`) holds a particle whose B-spline stencil shares a grid node with the body (every other particle), a
    boundary point of the frame (Dirichlet or force point) or a wall or floor node, or, where the table acts as a
    plane collider (the released field), whose surface touches it (:mod:`tasks.physics.free_flight`; collider
    fingers are not counted): a sample that is not held is one of a free blob, falling at g; ``attached`` (loose,)
    bool: the particle's own stencil is held so (its blob aside).  ``mass``/``physical_mass`` (loose,) kg
    the inertial and physical masses after the release, ``radius`` (loose,) m half their undeformed spacing."""

    loose: np.ndarray  # (particle,) bool: the particles sampled
    mass: np.ndarray
    physical_mass: np.ndarray
    radius: np.ndarray
    times: list[float]
    x: list[np.ndarray]
    held: list[np.ndarray]
    attached: list[np.ndarray]

    @classmethod
    def start(cls, solver: MPMSolver, labels: np.ndarray) -> "FlightRecord":
        """An empty record of the loose particles of ``labels`` (particle,), the labels after the release."""
        loose = (labels == INTERIOR) | (labels == RUPTURED)
        return cls(loose, solver.masses()[loose], solver.physical_masses()[loose],
                   solver.contact_radii()[loose], [], [], [], [])

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
        self.attached.append(held)
        self.held.append(blob_held(bases, held))  # linked to held material through released material: held too
        self.times.append(float(t))
        self.x.append(x[self.loose].astype(np.float32))

    def as_arrays(self, solver: MPMSolver) -> dict[str, np.ndarray]:
        """The record as the artifact's ``released_flight_*`` arrays (:func:`tasks.physics.free_flight.
        prune_held`: the loose particles attached at every sample, e.g. a can's cola that stays in, are left out; a
        jet held through its blob at every sample is kept, its flight drawn though never free)."""
        x, held = np.array(self.x, np.float32), np.array(self.held, bool)
        kept, held = prune_held(x, held, solver.lo, solver.dx, attached=np.array(self.attached, bool))
        return {"released_flight_time": np.array(self.times), "released_flight_positions": x[:, kept],
                "released_flight_held": held,
                "released_flight_particle": np.flatnonzero(self.loose)[kept].astype(np.int32),
                "released_flight_mass": self.mass[kept].astype(np.float64),
                "released_flight_physical_mass": self.physical_mass[kept].astype(np.float64)}


def allocate_record(scene: Scene, T: int, S: int) -> FrameRecord:
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
        "quasi_static": {**quasi_static_summary(solver.quasi_static_contacts, rec.stats["ke_ie_contact"], contact,
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
    "released_flight_held": (("sample", "loose"), "1", "its blob (loose particles linked by shared grid nodes) has a "
                             "particle whose stencil shares a grid node with the body, a boundary point, a wall or "
                             "the table: not held = in a free blob, falling at g"),
    "released_flight_particle": (("loose",), "1", "index on the particle axis"),
    "released_flight_mass": (("loose",), "kg", "inertial (mass-scaled)"),
    "released_flight_physical_mass": (("loose",), "kg", "")}
# the rollout artifact's arrays (mpm_rollout_step and the force-matched variant's step; ``?``: optional)
ROLLOUT_OUTPUTS = ("time", "particle_positions", "particle_material", "particle_J", "particle_von_mises",
                   "gaussian_positions", "gaussian_covariances", "gaussian_rotations", "reaction_force",
                   "applied_force", "feedback_force", "squeeze_strain", "dirichlet_tracking_error",
                   "predicted_squeeze_strain", "substeps", "dt_min", "courant", "max_speed", "j_min", "j_max",
                   "kinetic_energy", "internal_energy", "plastic_dissipation", "ke_ie_ratio", "ke_ie_contact",
                   "energy_growth",
                   "plastic_strain?", "released?",
                   *(f"{k}?" for k in FLIGHT_ARRAYS))


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


def quasi_static_summary(contacts: list[dict], ke_ie_contact: np.ndarray, contact: np.ndarray, mass_scale: float,
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
