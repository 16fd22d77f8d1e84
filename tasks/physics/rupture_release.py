"""Rupture and release at the squeezing threshold (paper sec. 3.2; :mod:`tasks.physics.mpm_rollout`'s module doc):
the materials of what is released and of the torn skin, the release speed (Bernoulli), the torn skin's peel-back and
a seam's opening, and the release itself on the solver's state."""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any, Mapping

import numpy as np

from conf.hand import N_FINGERS
from tasks.physics.labels import CORE, INTERIOR, RUPTURED, SHELL
from tasks.physics.mpm import MPMSolver
from tasks.physics.mpm.materials import Material, material_from_dict
from tasks.physics.oracle.convert import mpm_material_kwargs


def released_material(interior: Any, sim: Mapping[str, Any]) -> Material:
    """The solver material of what is released past the threshold (label INTERIOR).

    A fluid (juice, cola) gets the Tait exponent ``simulation.fluid_tait_exponent`` (its bulk modulus is set with
    the mass scale).  A ``foam`` (the table's loose fibrefill stuffing: a cohesive, crushable fibre mass) is used as
    stated, the torn-out fibre mass itself, with a crush cap that admits the packed state it is released at
    (``simulation.stuffing_packing``, :func:`rupture_and_release`): compression up to it is elastic, beyond it permanent; its
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


def cohesionless_core(core: Material) -> Material:
    """A ``foam`` core (fibrefill stuffing, a fibre mass without tensile strength) pulled apart separates into
    tufts instead of stretching elastically: volumetric expansion beyond its crush strain is permanent (elastic
    J <= exp(crush_strain)), the tension counterpart of the crush cap.  Without it the stuffing next to an opening,
    dragged by the loose stuffing flowing out, was stretched elastically to det F_E = 20 (the upper guard) in the
    force-driven plush toy.  Other core models are returned unchanged."""
    return replace(core, dilation_strain=core.crush_strain) if core.model == "foam" else core


def torn_skin_material(soft: Material, tear_strain: float) -> Material:
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


def rupture_and_release(solver: MPMSolver, f: int, t: float, strain: np.ndarray, threshold: float,
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
