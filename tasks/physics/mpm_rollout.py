"""Squeezing-driven deformation: the MPM rollout of one object under its squeeze (paper sec. 3.2, eqs. 4-5).

Per output frame the displacement field of eq. 3 is imposed as Dirichlet boundary conditions: every surface
point constrained at the end of the frame is driven towards its target ``x0 + dx(x0)`` with the velocity
``(target - current) / frame_dt``, projected onto the grid nodes of its B-spline stencil (the tracked surface
points are the 3D Gaussians, advected as massless tracers).  The contact is unilateral: a point is driven only
while the finger pushes or holds it: (target - current) . d_k >= -dx/4 while the target advances or holds (d_k the
inward patch normal; the tolerance stops contact chatter) and >= 0 while it retreats, so material that lies
deeper than a retreating finger is left free, so on release the object rebounds or keeps its dent as its
material dictates.  The ``force`` boundary mode (the
no_dirichlet ablation) pushes with a total per-finger force ``force_per_coefficient * c_k,t`` along the
inward patch normal instead.

Squeezing threshold (sec. 3.2): the squeeze strain of finger k is the indentation under the fingertip divided
by the object's half extent along the squeeze direction, ``eps_k = mean(u . d_k) / h(d_k)``, the mean taken over
the contact core of finger k's patch (the surface points of its region with patch weight phi >= exp(-1/2), i.e.
within one patch sigma of the centre; the mean over the whole 2.5-sigma support, whose rim barely moves,
reads ~3x lower), u = x - x0 the surface displacement (the object's base is held by the table,
``mpm.floor_sticky``, so u carries no rigid translation) and ``h(d) = sum_i |d_i| half_i``.  When ``max_k eps_k``
first reaches the material oracle's threshold, the shell ruptures within ``release_radius`` of that finger's
contact (those shell particles become ``ruptured_softening`` times softer; no finger constrains the surface
within ``release_radius + 1.5 dx`` any more, so the opening is free) and the interior there is released opposite
to the squeeze direction with speed ``release_speed_per_pascal * p_k`` (capped), p_k the finger's contact
pressure = |reaction| / patch area.

Interior and core: the oracle's ``core`` (fruit flesh, plush stuffing) fills the cavity and is part of the body:
it is always simulated and holds the shell up.  The releasable ``interior`` (juice, loose stuffing) is made of
the core particles within ``release_radius`` of the rupture, which switch to the interior material (labels in
``particle_material``: 0 shell, 1 interior, 2 ruptured shell, 3 core).  Without a core (a sealed can of cola)
the interior fills the cavity from the start.  Objects without interior material, or whose control signals never
reach the threshold (predicted from the prescribed field before simulating), allocate no interior at all: no
interior material, no ``released`` array.  A fluid interior has no tension (``tasks.physics.mpm.constitutive``), so the
released liquid separates from what stays instead of pulling back on it.

Resistive force feedback (sec. 3.2): ``f_k = clip(tau_y * A_k, 0, feedback_max_force)`` with tau_y the
shell's yield stress and A_k the contact patch area; for materials without a yield stress (elastic rubber)
the simulated contact force |reaction_k| is used instead, clipped the same way.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Mapping

import numpy as np

from conf.mpm_schema import mpm_config_from
from conf.hand import N_FINGERS
from tasks.core.artifacts import Array
from tasks.physics.material_oracle import materials_from_dict, mpm_material_kwargs
from tasks.physics.mpm.materials import Material, material_from_dict
from tasks.physics.free_flight import free_flying, released_flight
from tasks.physics.mpm.solver import (DirichletPoints, ForcePatch, MPMSolver, deform_covariances,
                              material_mass_scales, polar_rotation, rotate_quaternions)
from tasks.core.step import artifact_step, report_progress
from tasks.physics.labels import CORE, INTERIOR, N_LABELS, RUPTURED, SHELL
from tasks.physics.regions import finger_regions, region_weights, squeeze_strain

def cauchy_free_measures(F: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """J = det F and the von Mises stress 3 mu eps_eq of the Hencky strain (Pa) per particle.

    eps_eq = sqrt(2/3) |dev log V|, V the left stretch of F (the elastic part for plastic models), so
    sigma_vm = 2 mu sqrt(3/2) |dev eps| = 3 mu eps_eq (StVK-Hencky, exact for that model).
    """
    J = np.linalg.det(F)
    s = np.linalg.svd(F, compute_uv=False)
    logs = np.log(np.clip(s, 1e-6, None))
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


def mpm_rollout(obj: Mapping[str, np.ndarray], obj_attrs: Mapping[str, Any], field: Mapping[str, np.ndarray],
                forces: np.ndarray, patches: Mapping[str, np.ndarray], times: np.ndarray,
                materials: Mapping[str, Any], mpm: Mapping[str, Any], sim: Mapping[str, Any],
                boundary: str) -> tuple[dict[str, Array], dict[str, Any]]:
    """Simulate one object through its squeeze session; returns the rollout arrays and attributes."""
    if boundary not in ("dirichlet", "force"):
        raise ValueError(f"variant.boundary must be dirichlet or force, got {boundary!r}")
    mats = materials_from_dict(materials)
    shell = material_from_dict(mpm_material_kwargs(mats.shell, "shell"))
    T = len(times)
    frame_dt = float(times[1] - times[0]) if T > 1 else 1.0 / 30.0
    half = 0.5 * (np.asarray(obj_attrs["bbox_max"]) - np.asarray(obj_attrs["bbox_min"]))
    disp, finger_of = field["displacement"], field["finger"]
    notes: list[str] = []

    # ---- what this scene needs: interior particles only if they can be released
    threshold = mats.squeeze_threshold
    region, direction = finger_regions(finger_of, patches["patch_normals"])
    phi = region_weights(finger_of, field["weight"])
    constrained_now = finger_of >= 0
    predicted = np.stack([squeeze_strain(np.where(constrained_now[f][:, None], disp[f], 0.0), region[f],
                                         direction[f], half, phi[f]) for f in range(T)])
    has_cavity = len(obj["interior_positions"]) > 0
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

    # materials by label (SHELL, INTERIOR, RUPTURED, CORE); the solver indexes the list of those present
    by_label: dict[int, Material] = {SHELL: shell}
    positions = [obj["particle_positions"]]
    volumes = [obj["particle_volumes"]]
    ids = [np.full(len(obj["particle_positions"]), SHELL, np.int32)]
    if with_core:
        by_label[CORE] = material_from_dict(mpm_material_kwargs(mats.core, "core"))
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
        # torn skin carried off by the released interior: neo-Hookean's ln J barrier keeps the soft flakes from
        # inverting where the spray piles up (fixed-corotated's (J - 1)^2 term barely resists J -> 0)
        by_label[RUPTURED] = replace(by_label[RUPTURED], model="neo_hookean")
    labels = sorted(by_label)
    mat_list: list[Material] = [by_label[lab] for lab in labels]
    slot = np.full(N_LABELS, -1, np.int32)
    slot[labels] = np.arange(len(labels))
    x0 = np.concatenate(positions).astype(np.float32)
    vol = np.concatenate(volumes).astype(np.float32)
    mid = np.concatenate(ids)  # labels; the solver's material ids are slot[mid]

    # ---- grid and time scaling
    cfg = mpm_config_from(dict(mpm))
    spacing = float(obj_attrs["particle_spacing"])
    dx = cfg.dx or spacing * cfg.particles_per_cell ** (1.0 / 3.0)
    cfg = replace(cfg, dx=dx)  # the solver applies mpm.mass_scaling (per material; weights stay physical)
    if with_interior:  # released material keeps its physical inertia under selective mass scaling
        mat_list[slot[INTERIOR]] = replace(mat_list[slot[INTERIOR]], mass_scaled=False)
    if with_interior and mat_list[slot[INTERIOR]].model == "fluid":
        # weakly compressible: sound speed = the fastest speed the released fluid reaches / fluid_mach, that speed
        # being the larger of fluid_reference_speed and a release at max_release_speed followed by a fall from the
        # object's top to the table, instead of water's 1450 m/s.  K = s_f rho c^2 with s_f the mass scale the solver
        # gives the fluid (1 under selective scaling), so the sound speed is c whatever the scaling.
        present = [mat_list[i] for i in np.unique(slot[mid])]
        scale_fluid = float(material_mass_scales(mat_list, present, dx, frame_dt, cfg)[slot[INTERIOR]])
        height = float(obj_attrs["bbox_max"][2] - obj_attrs["bbox_min"][2])
        v = max(float(sim["fluid_reference_speed"]),
                math.sqrt(float(sim["max_release_speed"]) ** 2 + 2.0 * abs(float(cfg.gravity[2])) * height))
        c_fluid = v / float(sim["fluid_mach"])
        k_fluid = scale_fluid * mat_list[slot[INTERIOR]].density * c_fluid ** 2 / cfg.stiffness_scaling
        notes.append(f"interior fluid bulk modulus {k_fluid:.3g} Pa (sound speed {c_fluid:.3g} m/s at mass scale "
                     f"x{scale_fluid:.3g}: Mach {sim['fluid_mach']:g} at {v:.3g} m/s) instead of "
                     f"{mats.interior.bulk_modulus:.3g} Pa")
        mat_list[slot[INTERIOR]] = replace(mat_list[slot[INTERIOR]], bulk_modulus=k_fluid)
    solver = MPMSolver(x0, vol, mat_list, material_ids=slot[mid], config=cfg, tracers=obj["surface_points"],
                       label=str(obj_attrs.get("name", "")))
    contact_tolerance = 0.25 * dx  # m: a point this much deeper than its finger is still in contact

    # ---- outputs (only what the scene needs)
    P, S = len(x0), len(obj["surface_points"])
    plastic = any(m.is_plastic for m in mat_list)
    out_x = np.zeros((T, P, 3), np.float32)
    out_J = np.ones((T, P), np.float32)
    out_vm = np.zeros((T, P), np.float32)
    out_ep = np.zeros((T, P), np.float32) if plastic else None
    g_pos = np.zeros((T, S, 3), np.float32)
    g_cov = np.zeros((T, S, 6), np.float32)
    g_rot = np.zeros((T, S, 4), np.float32)
    reaction = np.zeros((T, N_FINGERS, 3), np.float32)
    applied = np.zeros((T, N_FINGERS, 3), np.float32)
    strain = np.zeros((T, N_FINGERS), np.float32)
    tracking = np.zeros(T, np.float32)
    stats_keys = ("substeps", "dt_min", "courant", "max_speed", "j_min", "j_max", "kinetic_energy",
                  "internal_energy", "ke_ie_ratio")
    stats = {k: np.zeros(T, np.float64) for k in stats_keys}
    mu_phys = np.array([m.mu for m in mat_list])[slot[mid]]
    cov0 = _covariances(obj["gaussian_scales"], obj["gaussian_rotations"])
    q0 = obj["gaussian_rotations"].astype(np.float64)
    released = np.zeros(P, bool) if with_interior else None
    torn = np.zeros(len(obj["surface_points"]), bool)  # surface points whose skin ruptured: no longer constrained
    event: dict[str, Any] = {"crossed": False, "threshold": threshold}
    surface0 = obj["surface_points"].astype(np.float64)

    def record(f: int) -> None:
        F = solver.deformation_gradients().astype(np.float64)
        out_x[f] = solver.positions()
        out_J[f], out_vm[f] = cauchy_free_measures(F, mu_phys)
        if out_ep is not None:
            out_ep[f] = solver.plastic_strain()
        tx, tF = solver.tracer_positions(), solver.tracer_F().astype(np.float64)
        g_pos[f] = tx
        g_cov[f] = _sym6(deform_covariances(tF, cov0))
        g_rot[f] = rotate_quaternions(polar_rotation(tF), q0)
        moved = tx - surface0
        # torn skin (around an opening) is no longer under a finger: the released interior may carry it off
        strain[f] = squeeze_strain(moved, region[f] & ~torn, direction[f], half, phi[f])

    record(0)
    for f in range(1, T):
        bc, push = None, None
        if boundary == "dirichlet":
            idx = np.flatnonzero(field["constrained"][f] & ~torn)
            if len(idx):
                current = solver.tracer_positions()[idx].astype(np.float64)
                target_x = surface0[idx] + disp[f, idx]
                # unilateral contact: a finger pushes or holds, it never pulls material outwards
                inward = direction[f, finger_of[f, idx]]
                gap = np.einsum("ij,ij->i", target_x - current, inward)
                retreating = np.einsum("ij,ij->i", disp[f, idx] - disp[f - 1, idx], inward) < 0.0
                push_or_hold = gap >= np.where(retreating, 0.0, -contact_tolerance)
                idx, current, target_x = idx[push_or_hold], current[push_or_hold], target_x[push_or_hold]
            if len(idx):
                bc = DirichletPoints(positions=current, velocities=(target_x - current) / frame_dt,
                                     finger_ids=finger_of[f, idx].astype(np.int32))
        else:  # a finger that punctured the skin no longer presses on the torn part (as in dirichlet mode)
            idx = np.flatnonzero(field["constrained"][f] & ~torn)
            if len(idx):
                total = np.zeros((N_FINGERS, 3))
                for k in range(N_FINGERS):
                    if patches["patch_active"][f, k] and (finger_of[f, idx] == k).any():
                        total[k] = float(sim["force_per_coefficient"]) * forces[f, k] * -patches["patch_normals"][f, k]
                push = ForcePatch(positions=solver.tracer_positions()[idx], finger_ids=finger_of[f, idx].astype(np.int32),
                                  forces=total)
        st = solver.step_frame(frame_dt, dirichlet=bc, forces=push)  # KE/IE per frame: summarised in the attrs
        if f == 1:
            notes.append("stable substep per material (s): " + ", ".join(
                f"{k} {v:.3g} ({math.ceil(frame_dt / v)} substeps per frame)"
                for k, v in solver.stable_dt_per_material().items()))
        for k in stats_keys:
            stats[k][f] = float(getattr(st, k))
        reaction[f] = np.asarray(st.reaction)[:N_FINGERS]
        applied[f] = np.asarray(st.applied_force)[:N_FINGERS]
        record(f)
        report_progress(f, T - 1)
        if bc is not None:  # RMS distance of the imposed points from their targets at the end of the frame
            tracking[f] = np.sqrt(np.mean(np.sum((g_pos[f][idx] - target_x) ** 2, axis=1)))
        if with_interior and not event["crossed"] and threshold is not None and strain[f].max() >= threshold:
            tx = solver.tracer_positions()
            centers = np.array([tx[region[f, k]].mean(axis=0) if region[f, k].any() else patches["patch_centers"][f, k]
                                for k in range(N_FINGERS)])
            event = _release(solver, f, times[f], strain[f], threshold, patches, centers, reaction[f], applied[f],
                             boundary, mid, slot, released, sim)
            # the finger punctured the skin: it no longer presses on its patch, and no finger constrains the
            # surface within release_radius + 1.5 dx of the opening (a constrained point's B-spline stencil reaches
            # 1.5 dx deep: it would hold the released interior in place under the opening)
            opening = float(sim["release_radius"]) + 1.5 * dx
            for k in event["fingers"]:
                torn |= region[f, k] | (np.linalg.norm(tx - centers[k], axis=1) <= opening)
            mid = event.pop("labels")
            mu_phys = np.array([m.mu for m in mat_list])[slot[mid]]

    # ---- resistive force feedback (per finger, N)
    area = patches["patch_areas"] * patches["patch_active"]
    contact = np.linalg.norm(reaction if boundary == "dirichlet" else applied, axis=-1)
    tau_y = mats.shell.yield_stress
    raw_feedback = tau_y * area if tau_y else contact
    feedback = np.clip(raw_feedback, 0.0, float(sim["feedback_max_force"])).astype(np.float32)

    arrays: dict[str, Array] = {
        "time": Array(times.astype(np.float64), ("frame",), "s"),
        "particle_positions": Array(out_x, ("frame", "particle", "xyz"), "m"),
        "particle_material": Array(mid.astype(np.int8), ("particle",), "1",
                                   "0 shell, 1 interior (released juice / cola / stuffing), 2 ruptured shell, "
                                   "3 core (pulp / stuffing: part of the body)"),
        "particle_J": Array(out_J, ("frame", "particle"), "1", "det F (volume ratio)"),
        "particle_von_mises": Array(out_vm, ("frame", "particle"), "Pa", "3 mu eps_eq of the elastic Hencky strain"),
        "gaussian_positions": Array(g_pos, ("frame", "point", "xyz"), "m"),
        "gaussian_covariances": Array(g_cov, ("frame", "point", "sym6"), "m^2", "F Sigma F^T: xx xy xz yy yz zz"),
        "gaussian_rotations": Array(g_rot, ("frame", "point", "quat"), "1", "polar(F) q0, w first"),
        "reaction_force": Array(reaction, ("frame", "finger", "xyz"), "N",
                                "sum m (v_bc - v*) / dt over the finger's constrained nodes, frame mean"),
        "applied_force": Array(applied, ("frame", "finger", "xyz"), "N", "force mode push, frame mean"),
        "feedback_force": Array(feedback, ("frame", "finger"), "N", "resistive force for the glove"),
        "squeeze_strain": Array(strain, ("frame", "finger"), "1"),
        "dirichlet_tracking_error": Array(tracking, ("frame",), "m",
                                          "RMS |x - (x0 + dx)| over the points imposed in that frame"),
        "predicted_squeeze_strain": Array(predicted.astype(np.float32), ("frame", "finger"), "1"),
    }
    units = {"dt_min": "s", "courant": "1", "max_speed": "m/s", "j_min": "1", "j_max": "1", "kinetic_energy": "J",
             "internal_energy": "J", "ke_ie_ratio": "1", "substeps": "1"}
    for k in stats_keys:
        arrays[k] = Array(stats[k], ("frame",), units[k])
    if out_ep is not None:
        arrays["plastic_strain"] = Array(out_ep, ("frame", "particle"), "1", "equivalent plastic strain")
    if released is not None:
        arrays["released"] = Array(released, ("particle",), "1", "released at the threshold crossing")
        free = free_flying(out_x, mid == INTERIOR, obj_attrs["bbox_min"], obj_attrs["bbox_max"],
                           float(solver.floor_height if solver.floor_height is not None else -np.inf), 2.0 * dx)
        height, free_fall = released_flight(out_x, free, frame_dt)
        arrays["released_height"] = Array(height.astype(np.float32), ("frame",), "m",
                                          "mean z of the released particles flying free (NaN: none)")
    attrs = {
        "boundary": boundary, "materials": [m.name for m in mat_list], "n_particles": int(P),
        "n_interior": int((mid == INTERIOR).sum()),
        "with_interior": bool(with_interior), "dx": float(dx), "mass_scale": solver.mass_scale,
        "gravity_effective": solver.gravity, "device": solver.device, "substeps_total": int(stats["substeps"].sum()),
        "threshold_event": event, "notes": notes,
        "material_mass_scales": {m.name: float(k) for m, k in zip(mat_list, solver.material_mass_scale)},
        "released_free_fall_acceleration": free_fall if released is not None else None,
        "feedback_rule": "tau_y * area" if tau_y else "|contact force| (no yield stress)",
        "bytes_per_particle": float(solver.bytes_per_particle()),
        "quasi_static": _quasi_static_summary(stats["ke_ie_ratio"], reaction if boundary == "dirichlet" else applied,
                                              solver.mass_scale, float(cfg.quasi_static_ke_ie_max)),
    }
    return arrays, attrs


def _quasi_static_summary(ke_ie: np.ndarray, contact: np.ndarray, mass_scale: float, limit: float) -> dict:
    """How well the mass-scaled run stayed quasi-static while the fingers were in contact (KE/IE per frame)."""
    in_contact = np.linalg.norm(contact, axis=-1).max(axis=1) > 0
    ratio = ke_ie[in_contact] if in_contact.any() else np.zeros(1)
    return {"mass_scale": mass_scale, "limit": limit, "max_ke_ie_in_contact": float(ratio.max()),
            "median_ke_ie_in_contact": float(np.median(ratio)),
            "frames_over_limit": int((ratio > limit).sum()), "frames_in_contact": int(in_contact.sum())}


def _released_material(interior: Any, sim: Mapping[str, Any]) -> Material:
    """The solver material of what is released past the threshold (label INTERIOR).

    A fluid (juice, cola, the table's loose stuffing) gets the Tait exponent ``simulation.fluid_tait_exponent``
    (its bulk modulus is set with the mass scale).  A solid interior (an LLM's answer may give one) is
    ``ruptured_softening`` times softer than stated: torn loose, it no longer carries load."""
    m = material_from_dict(mpm_material_kwargs(interior, "interior"))
    if m.model == "fluid":
        return replace(m, fluid_gamma=float(sim["fluid_tait_exponent"]))
    soft = float(sim["ruptured_softening"])
    return replace(m, name="released_interior", youngs_modulus=m.youngs_modulus * soft,
                   yield_stress=m.yield_stress * soft)


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
    speeds = []
    for k in fingers:
        c = centers[k]
        n_out = patches["patch_normals"][f, k]
        area = max(float(patches["patch_areas"][f, k]), 1e-8)
        force = np.linalg.norm(reaction[k] if boundary == "dirichlet" else applied[k])
        speed = float(min(float(sim["release_speed_per_pascal"]) * force / area, float(sim["max_release_speed"]),
                          float(sim["release_mach_max"]) * c_released))
        near = np.linalg.norm(x - c, axis=1) <= radius
        torn = near & (mid == SHELL)
        ids[torn] = RUPTURED
        out = near & ((mid == INTERIOR) | (mid == CORE)) & ~released
        ids[out] = INTERIOR
        # opposite to the squeeze direction (-n_out); the torn shell over the opening is pushed out with it (a
        # thick peel or a fabric heavier than the stuffing behind it would otherwise stop the interior)
        v[out | torn] = n_out * speed
        released |= out
        speeds.append(speed)
    solver.set_material_ids(slot[ids])
    solver.set_velocities(v.astype(np.float32))
    return {"crossed": True, "frame": int(f), "time": float(t), "fingers": fingers,
            "strain": float(strain.max()), "threshold": threshold, "released_particles": int(released.sum()),
            "release_speeds": speeds, "release_sound_speed": float(c_released), "labels": ids}


ROLLOUT_OUTPUTS = ("time", "particle_positions", "particle_material", "particle_J", "particle_von_mises",
                   "gaussian_positions", "gaussian_covariances", "gaussian_rotations", "reaction_force",
                   "applied_force", "feedback_force", "squeeze_strain", "dirichlet_tracking_error",
                   "predicted_squeeze_strain", "substeps", "dt_min", "courant", "max_speed", "j_min", "j_max",
                   "kinetic_energy", "internal_energy", "ke_ie_ratio", "plastic_strain?", "released?",
                   "released_height?")


@artifact_step("mpm_rollout",
               inputs=("object_model", "signal_smoothing", "force_coefficients", "contact_patches", "dirichlet_field",
                       "material_oracle"),
               reads=("mpm", "simulation", "variant.boundary"),
               outputs=ROLLOUT_OUTPUTS)
def mpm_rollout_step(inputs, params):
    """The squeeze simulated with MLS-MPM (eqs. 4-5) under the eq. 3 field (``variant.boundary=dirichlet``) or the
    per-finger force (``force``, the no_dirichlet ablation), with the oracle's materials."""
    obj = inputs["object_model"]
    return mpm_rollout(obj.arrays, {**obj.attrs, "name": obj.ref.scope}, inputs["dirichlet_field"].arrays,
                       inputs["force_coefficients"]["force_coefficients"], inputs["contact_patches"].arrays,
                       inputs["signal_smoothing"]["time"], inputs["material_oracle"].attrs["materials"],
                       params["mpm"], params["simulation"], params["variant.boundary"])
