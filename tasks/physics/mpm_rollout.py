"""Squeezing-driven deformation: the MPM rollout of one object under its squeeze (paper sec. 3.2, eqs. 4-5).

The step and its frame loop (:func:`run_frames`); the scene set-up is :mod:`tasks.physics.rollout_scene`, the fingers
:mod:`tasks.physics.rollout_fingers`, the rupture and release :mod:`tasks.physics.rupture_release`, the records and the
artifact :mod:`tasks.physics.rollout_records`.

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
whose lowest point is the patch centre moved inwards by the eq. 3 amplitude eta c_k,t (the field's ``amplitude``,
:func:`~tasks.physics.rollout_fingers.fingertip_travel`), moved there from its previous place within each frame (:func:`finger_colliders`).  It
acts on the particles whose surface it touches, pushes and never pulls (unilateral by construction, no tolerance),
and its impulses are the finger's reaction.  Measured (README, ``python -m flows.finger_study``): the reaction
converges (Hertz within 3-15 % at 1.5 cells per contact radius), but the squeeze no longer holds the material
where eq. 3 puts it: under the default mass scaling a pushed clay keeps flowing past the finger and the one-layer
rubber ball's shell buckles in, so Table 2 gets worse; not the default.

Particle fingers, the default, against grid-node Dirichlet points (docs/limits/fingers-and-contact.md, ``python -m
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
and tear apart plastically beyond the strain they tore at (:func:`torn_skin_material`); no finger constrains the surface
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
from typing import Any, Callable, Mapping, Optional

import numpy as np

from conf.hand import N_FINGERS
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.physics.mpm.preload import PreloadedState
from tasks.physics.preload_state import preload_from_artifact
from tasks.physics.rollout_fingers import (
    beneath_openings,
    boundary_points,
    dirichlet_points,
    finger_colliders,
    force_patch,
    particle_pins,
)
from tasks.physics.rollout_records import (
    FLIGHT_FRAMES,
    FLIGHT_SAMPLE_SUBSTEPS,
    ROLLOUT_OUTPUTS,
    STATS_KEYS,
    FlightRecord,
    FrameRecord,
    allocate_record,
    collect_outputs,
    record_frame,
    rest_covariances,
)
from tasks.physics.rollout_scene import Scene, build_scene
from tasks.physics.rupture_release import rupture_and_release
from tasks.physics.table_hold import held_pins, join_pins


def mpm_rollout(obj: Mapping[str, np.ndarray], obj_attrs: Mapping[str, Any], field: Mapping[str, np.ndarray],
                forces: np.ndarray, patches: Mapping[str, np.ndarray], times: np.ndarray,
                materials: Mapping[str, Any], mpm: Mapping[str, Any], sim: Mapping[str, Any],
                boundary: str, preloaded: Optional[PreloadedState] = None) -> tuple[dict[str, Array], dict[str, Any]]:
    """Simulate one object through its squeeze session (sec. 3.2); returns the rollout arrays and attributes.

    ``obj`` the object's surface Gaussians and MPM particles (the ``object_model`` and ``mpm_particles`` arrays),
    ``obj_attrs`` their attributes and ``name``; ``times`` (frame,) s; ``forces`` (frame, finger) the force
    coefficients c_k,t of eq. 1; ``field`` the eq. 3 Dirichlet field, ``patches`` the eq. 2 contact patches,
    ``materials`` the oracle's attributes; ``preloaded`` the body's gravity preload computed before
    (:mod:`tasks.physics.gravity_preload`; None: computed here)."""
    if boundary not in ("dirichlet", "force"):
        raise ValueError(f"variant.boundary must be dirichlet or force, got {boundary!r}")
    scene = build_scene(obj, obj_attrs, field, patches, times, materials, mpm, sim, forces, boundary, preloaded)
    frames = run_frames(scene, obj, field, forces, patches, times, sim, boundary)
    return collect_outputs(scene, frames, times, patches, sim, boundary)


def run_frames(scene: Scene, obj: Mapping[str, np.ndarray], field: Mapping[str, np.ndarray], forces: np.ndarray,
               patches: Mapping[str, np.ndarray], times: np.ndarray, sim: Mapping[str, Any],
               boundary: str, keep_going: Optional[Callable[[int, np.ndarray], bool]] = None) -> FrameRecord:
    """Stage 2: the frame loop.  Per frame: the boundary condition (Dirichlet points or force patches), one
    solver frame, the record, and the threshold release the first time a finger's strain reaches the threshold.
    ``keep_going(f, strain)`` (optional; ``strain`` the (frame, finger) squeeze strains recorded so far) is asked
    after each frame but the last: False stops the run there (``stopped_after = f``; the later frames stay unset),
    as the force-matched calibration (:mod:`tasks.physics.force_match`) stops a run it will not use."""
    solver, reg, slot = scene.solver, scene.regions, scene.slot
    T, threshold = len(times), scene.oracle.squeeze_threshold
    rec = allocate_record(scene, T, len(obj["surface_points"]))
    mid = scene.labels
    mu_phys = np.array([m.mu for m in scene.materials])[slot[mid]]
    cov0 = rest_covariances(obj["gaussian_scales"], obj["gaussian_rotations"])
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
        pins = join_pins(pins, held_pins(scene.hold, solver))  # the table's hold (mpm.table_hold), under the fingers'
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
            rec.event = rupture_and_release(solver, f, times[f], rec.strain[f], threshold, patches, centers, rec.reaction[f],
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
                rec.beneath = beneath_openings(solver.positions(), mid, rec.released, tx, rec.openings, centers,
                                                rec.event["fingers"], float(sim["release_radius"]), 2.0 * scene.dx)
                rec.event["pushed_beneath"] = int((rec.beneath >= 0).sum())
            rec.flight = FlightRecord.start(solver, mid)
            rec.flight.sample(solver, float(times[f]), boundary_points(bc, push, scene.frame_dt))
        # 5. the caller's stop
        if keep_going is not None and f < T - 1 and not keep_going(f, rec.strain):
            rec.stopped_after = f
            break
    solver.close_quasi_static_contact()  # the run ends: a contact still loaded is judged too
    rec.labels = mid
    return rec


@artifact_step("mpm_rollout",
               inputs=("object_model", "mpm_particles", "signal_smoothing", "force_coefficients", "contact_patches",
                       "dirichlet_field", "material_oracle", "gravity_preload"),
               reads=("mpm", "simulation", "variant.boundary"),
               # the thread count splits the same particle kernel (results agree to float32 round-off): flows.squeeze
               # / flows.export (2 threads) reuse flows.evaluate's rollouts (1 thread per worker) and vice versa
               unkeyed=("mpm.threads",),
               outputs=ROLLOUT_OUTPUTS)
def mpm_rollout_step(inputs, params):
    """The squeeze simulated with MLS-MPM (eqs. 4-5) under the eq. 3 field (``variant.boundary=dirichlet``: particle
    pins, grid-node Dirichlet points with ``mpm.fingers=dirichlet`` or fingertip colliders with
    ``mpm.fingers=collider``) or the per-finger force (``force``, the no_dirichlet ablation), with the oracle's
    materials, from the body's gravity preload (the ``gravity_preload`` step's, shared by the variants)."""
    obj, particles, pre = inputs["object_model"], inputs["mpm_particles"], inputs["gravity_preload"]
    return mpm_rollout({**obj.arrays, **particles.arrays}, {**obj.attrs, **particles.attrs, "name": obj.ref.scope},
                       inputs["dirichlet_field"].arrays,
                       inputs["force_coefficients"]["force_coefficients"], inputs["contact_patches"].arrays,
                       inputs["signal_smoothing"]["time"], inputs["material_oracle"].attrs["materials"],
                       params["mpm"], params["simulation"], params["variant.boundary"],
                       preload_from_artifact(pre.arrays, pre.attrs))
