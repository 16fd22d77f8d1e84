"""The gravity preload's result as data (:meth:`~tasks.physics.mpm.solver.MPMSolver.preload_gravity`): the solver state
it leaves, taken from one solver (:func:`preloaded_state`) and put into another built from the same inputs
(:func:`restore_preloaded`), which then steps exactly as the first would have (the same float32 bits).  So the
preload of a body is computed once and shared by its variants and by the force-matched calibration's runs
(:mod:`tasks.physics.gravity_preload`).  SI units.

The state: the particles' positions (m), velocities (m/s, zero), APIC C (1/s, zero), elastic deformation gradients,
their round-off carries, rotation warm starts, plastic strain and thin-wall normals; the tracers' rest offsets (m)
and inverse preloaded F; the last substep's speed (m/s, which sizes the next frame's first substep), the last P2G's
node box (which the next frame's first grid update spans), the energy guard's scale (J) and loading force (N), and the
preload's figures.  The mass scale is not in it: the preload runs at the body's load-free scale, which the solver
resolves from its own inputs.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from .diagnostics import EnergyBudget
from .mass_scaling import resolve_auto_mass_scale, resume_load, set_damping
from .tracers import place_tracers

if TYPE_CHECKING:
    from .solver import GravityPreload, MPMSolver

# the solver's particle arrays a preload changes (attribute: the name it is stored under; each restored with ``assign``)
PARTICLE_STATE = {"x": "particle_positions", "v": "particle_velocities", "C": "affine_velocities",
                  "F": "deformation_gradients", "x_carry": "position_round_off", "F_carry": "deformation_round_off",
                  "q": "rotation_warm_starts", "alpha": "plastic_strain", "normal": "membrane_normals"}


@dataclass
class PreloadedState:
    """What :func:`preloaded_state` takes from a preloaded solver: ``arrays`` (the solver's :data:`PARTICLE_STATE`
    arrays by attribute name, ``tracer_offsets`` (T, anchors, 3) m, ``tracer_F0_inv`` (T, 3, 3)), ``vmax`` m/s,
    ``box`` the last P2G's node box (lo, hi), ``energy_scale`` J, ``loading_force`` N, ``damping`` the preload's
    local damping, ``frame_dt`` s, ``mass_scale`` the (load-free) scale it ran at, the preload's ``figures`` and the
    ``key`` of the inputs it was computed from (:func:`tasks.physics.rollout_scene.preload_key`)."""

    arrays: dict[str, np.ndarray]
    vmax: float
    box: tuple[list[int], list[int]]
    energy_scale: float
    loading_force: float
    damping: float
    frame_dt: float
    mass_scale: float
    figures: GravityPreload
    key: str


def preloaded_state(solver: MPMSolver, figures: GravityPreload, frame_dt: float, damping: float,
                    key: str) -> PreloadedState:
    """The state ``solver`` is in right after :meth:`~MPMSolver.preload_gravity` (``figures`` its result, run with
    ``frame_dt`` s frames and local damping ``damping``; ``key`` that of its inputs)."""
    arrays = {name: getattr(solver, name).numpy().copy() for name in PARTICLE_STATE}
    if solver.n_tracers:
        arrays["tracer_offsets"] = solver._anchor[2].numpy().copy()
        arrays["tracer_F0_inv"] = np.asarray(solver._tracer_F0_inv, np.float64).copy()
    box = solver._last_box
    return PreloadedState(arrays=arrays, vmax=float(solver._vmax),
                          box=([int(b) for b in box[0]], [int(b) for b in box[1]]),
                          energy_scale=float(solver._energy_ref.scale) if solver._energy_ref is not None else 0.0,
                          loading_force=float(solver._loading_force), damping=float(damping),
                          frame_dt=float(frame_dt), mass_scale=float(solver.mass_scale), figures=figures, key=key)


def restore_preloaded(solver: MPMSolver, state: PreloadedState) -> GravityPreload:
    """Put ``solver`` (fresh, built from the inputs of the solver ``state`` was taken from) into the preloaded state,
    as :meth:`~MPMSolver.preload_gravity` would have left it; returns the preload's figures.  Raises ``ValueError``
    naming the array when the state does not fit the solver (another body or grid)."""
    if solver.frame != 0 or solver.substep != 0:
        raise ValueError(f"restore_preloaded: the solver has already stepped ({solver.frame} frames); a preloaded "
                         "state goes into a fresh solver")
    for name in PARTICLE_STATE:
        target, value = getattr(solver, name), state.arrays[name]
        if tuple(value.shape[:1]) != tuple(target.shape):
            raise ValueError(f"restore_preloaded: {name} has {value.shape[0]} rows, the solver {target.shape[0]}: "
                             "the preload is of another body (rebuild it from this scene's inputs)")
        target.assign(value)
    if solver.n_tracers:
        anchor, weight, offsets = solver._anchor
        solver._anchor = (anchor, weight, wp.array(state.arrays["tracer_offsets"], dtype=wp.vec3,
                                                   device=solver.device))
        place_tracers(solver)
        solver._tracer_F0_inv = state.arrays["tracer_F0_inv"].copy()
    # the mass scale and material table as the preload's frames left them: resolved without the load, damped
    load, solver.load = solver.load, None
    resolve_auto_mass_scale(solver, state.frame_dt)
    solver._preload_damping = state.damping
    set_damping(solver, quasi_static=False)
    solver._preload_damping = 0.0
    resume_load(solver, load)  # as preload_gravity leaves it
    solver._vmax = state.vmax
    solver._last_box = (np.array(state.box[0]), np.array(state.box[1]))
    solver._energy_initial = False
    solver._energy_ref = EnergyBudget(frame=None, energy=np.zeros(0), potential=0.0, scale=state.energy_scale)
    solver._loading_force = state.loading_force
    return state.figures
