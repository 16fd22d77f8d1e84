"""The rollout's scene (paper sec. 3.2): the fingers' squeeze regions, which interior particles the scene needs,
the materials by label, the grid, the time and mass scaling, the solver and its gravity preload
(:mod:`tasks.physics.mpm_rollout`'s module doc)."""
from __future__ import annotations

import hashlib
import math
from dataclasses import asdict, dataclass, replace
from typing import Any, Mapping, Optional

import numpy as np

from conf.mpm_schema import MPMConfig, mpm_config_from
from tasks.core.artifacts import digest_of
from tasks.physics.labels import CORE, INTERIOR, N_LABELS, RUPTURED, SHELL
from tasks.physics.mpm import MPMSolver, ParticlePins, material_mass_scales
from tasks.physics.mpm.mass_scaling import QuasiStaticLoad
from tasks.physics.mpm.materials import MEMBRANE_MODELS, Material, material_from_dict
from tasks.physics.mpm.preload import PreloadedState, restore_preloaded
from tasks.physics.mpm.solver import GravityPreload
from tasks.physics.mpm.thin_walls import contact_reach, membrane_fibres_checked
from tasks.physics.oracle.convert import materials_from_dict, mpm_material_kwargs
from tasks.physics.oracle.schema import ObjectMaterials
from tasks.physics.regions import finger_regions, region_weights, squeeze_strain
from tasks.physics.rupture_release import cohesionless_core, released_material, torn_skin_material
from tasks.physics.table_hold import table_hold
from tasks.physics.wall_resolution import grid_spacing


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
    preload_key: str = ""  # digest of what the preload reads (preload_key), which a preloaded state must match
    hold: Optional[ParticlePins] = None  # the table's hold on the body, preload and rollout (mpm.table_hold)


# Cundall's local damping of the gravity preload (MPMSolver.preload_gravity)
PRELOAD_DAMPING = 0.8


def preload_key(solver_inputs: Mapping[str, Any], sim: Mapping[str, Any], frame_dt: float) -> str:
    """Digest of exactly what the gravity preload reads: the solver's inputs (particles, volumes, materials, their
    ids, the grid and solver settings but ``mpm.threads``, tracers, thin walls, contact radii; not
    its boundary ``load``, which the preload does without), the frame interval (s) and the preload's settings.  The
    fingers, the variant and the signals are not in it: every variant of a body shares its preload."""
    def part(v: Any) -> Any:
        if isinstance(v, np.ndarray):
            return [str(v.dtype), list(v.shape), hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest()]
        return v
    return digest_of({**{k: part(v) for k, v in solver_inputs.items()}, "frame_dt": float(frame_dt),
                      "damping": PRELOAD_DAMPING,
                      **{k: sim[k] for k in ("gravity_preload_frames", "gravity_preload_passes",
                                             "gravity_preload_tolerance")}})


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
        by_label[CORE] = cohesionless_core(material_from_dict(mpm_material_kwargs(mats.core, "core")))
        positions.append(obj["interior_positions"])
        volumes.append(obj["interior_volumes"])
        ids.append(np.full(len(obj["interior_positions"]), CORE, np.int32))
    if with_interior:
        by_label[INTERIOR] = released_material(mats.interior, sim)
        if not with_core:  # no solid core: the interior fills the cavity from the start (cola in a can)
            positions.append(obj["interior_positions"])
            volumes.append(obj["interior_volumes"])
            ids.append(np.full(len(obj["interior_positions"]), INTERIOR, np.int32))
        soft = float(sim["ruptured_softening"])
        by_label[RUPTURED] = replace(shell, name="ruptured_shell", youngs_modulus=shell.youngs_modulus * soft,
                                     yield_stress=shell.yield_stress * soft)
    initial = {by_label[lab].model for lab in set(np.concatenate(ids).tolist())}
    if with_interior and shell.model == "fixed_corotated" and initial != {"fixed_corotated"}:
        by_label[RUPTURED] = torn_skin_material(by_label[RUPTURED], float(mats.squeeze_threshold))
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
                mpm: Mapping[str, Any], sim: Mapping[str, Any], forces: np.ndarray, boundary: str,
                preloaded: Optional[PreloadedState] = None) -> Scene:
    """Stage 1: the MPM scene of one object (materials by label, particles, grid, time scaling, solver).  Under a
    force-driven ``boundary`` (``force``) the force coefficients ``forces`` (frame, finger) set the load's time
    scale for the quasi-static bound of the mass scale (``mpm.quasi_static_margin``).  ``preloaded``: the body's
    gravity preload computed before (:mod:`tasks.physics.gravity_preload`), put into the solver instead of computing
    it again when its key is this scene's (:func:`preload_key`; else it is computed, with a note)."""
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
    dx = grid_spacing(cfg, spacing)
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
    solver_inputs = dict(positions=x0, volumes=vol, material_ids=slot[mid], tracers=obj["surface_points"],
                         tracer_anchors=mid == SHELL, membrane_normals=normals, membrane_fibres=fibres)
    solver = MPMSolver(materials=mat_list, config=cfg, label=str(obj_attrs.get("name", "")), load=load,
                       **solver_inputs)
    if fibres is None and len(obj["wall_fibres"]):  # Gauss layers held as a 3D solid touch colliders at their faces
        layers = membrane_fibres_checked(np.asarray(obj["wall_fibres"], np.int64), np.ones(len(x0), bool), x0)
        solver.set_contact_radii(contact_reach(solver.volumes(), layers))
    key = preload_key({**solver_inputs, "materials": [asdict(m) for m in mat_list],
                       "config": asdict(replace(cfg, threads=1)), "contact_radii": solver.contact_radii()},
                      sim, frame_dt)
    if boundary == "dirichlet" and cfg.fingers == "dirichlet":  # grid-node constraints: what they hold (issue 50)
        notes.append(f"grid-node fingers (mpm.fingers=dirichlet): every constrained point sets the velocity of the "
                     f"grid nodes of its B-spline stencil, so the material within ~1.5 cells ({1.5e3 * dx:.3g} mm) of "
                     "a patch moves with it rigidly (a cube between grid-node plates reads +31 to +57 % of E A eps; "
                     "docs/limits/fingers-and-contact.md)")
    if cfg.floor and cfg.contact == "grid":
        notes.append(f"grid-node table (mpm.contact=grid): the floor holds the material within ~1.5 cells "
                     f"({1.5e3 * dx:.3g} mm) of it (a sphere pressed on it reads 2-6x Hertz's force at 1-4 mm; "
                     "docs/limits/table-contact.md)")
    if thin_wall and cfg.fingers == "particles":
        notes.append("particle fingers pin the wall's particles at their centres: a wall thinner than the "
                     f"{1e3 * spacing:.3g} mm spacing (ParticlePins arms 0)")
    # 5. the table's hold on the body as it rests in its given shape (mpm.table_hold), from the preload on
    hold = table_hold(solver, cfg.table_hold if cfg.floor else "none")
    if cfg.table_hold != "none" and not cfg.floor:
        notes.append(f"no table (mpm.floor=false): the table's hold (mpm.table_hold={cfg.table_hold}) is left out")
    elif cfg.table_hold != "none":
        notes.append(f"table hold (mpm.table_hold={cfg.table_hold}): "
                     f"{0 if hold is None else len(hold.indices)} particles within one spacing of the table held "
                     "where they rest (no slip, no lift), in the gravity preload and the rollout")
    # 6. the given shape is the body's equilibrium on the table under its weight (simulation.gravity_preload_frames)
    pre = j_given = None
    if preloaded is not None and preloaded.key != key:
        notes.append("gravity preload: the preloaded state given is of other inputs (another body, grid, material "
                     "table or preload setting): computed again")
        preloaded = None
    if int(sim["gravity_preload_frames"]) > 0 and any(cfg.gravity):  # no weight (a study's mpm.gravity=0): no preload
        if preloaded is not None:  # this body's preload, computed once for all its variants
            pre = restore_preloaded(solver, preloaded)
        else:
            pre = solver.preload_gravity(frame_dt, int(sim["gravity_preload_frames"]),
                                         int(sim["gravity_preload_passes"]), damping=PRELOAD_DAMPING,
                                         tolerance=float(sim["gravity_preload_tolerance"]), pins=hold)
        notes.append(f"gravity preload: unsupported, the body would settle by up to {1e3 * pre.sag:.3g} mm under its "
                     f"weight; held in its given shape by that stress ({pre.passes} pass(es), {pre.frames} damped "
                     f"frames, {1e3 * pre.residual:.2g} mm left{'' if pre.converged else ', not at rest'}; per pass "
                     + ", ".join(f"{1e3 * m:.3g}" for m in pre.moved) + " mm)")
        j_given = np.linalg.det(solver.deformation_gradients(plane_stress=True).astype(np.float64))
    return Scene(oracle=mats, solver=solver, materials=mat_list, slot=slot, labels=mid, with_interior=with_interior,
                 dx=dx, config=cfg, frame_dt=frame_dt, surface0=obj["surface_points"].astype(np.float64),
                 regions=regions, notes=notes, thin_wall=thin_wall, preload=pre, j_given=j_given, preload_key=key,
                 hold=hold)
