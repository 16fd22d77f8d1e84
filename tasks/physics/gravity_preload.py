"""The gravity preload step: the body's given shape made its equilibrium under its weight once per object, before any
rollout (paper sec. 3.2's simulation starts from the captured object at rest on the table;
``simulation.gravity_preload_frames``, :meth:`tasks.physics.mpm.solver.MPMSolver.preload_gravity`).

It reads exactly what the preload reads: the object's particles and surface points, its materials, the grid and solver
settings (``mpm``; the thread count left out of its key) and the preload's (``simulation``), the output frame interval
and which interior particles the scene simulates (from the eq. 3 field's predicted strain and the contact patches);
not the variant, the fingers' forces or the force constant.  Every rollout of the object (both variants of Table 2,
each run of the force-matched calibration) puts this state into its solver (:mod:`tasks.physics.mpm.preload`)
instead of settling the body again: the plush toy's preload is 80 damped frames, most of its rollout's first
seconds.  A rollout whose scene does not match the state's key (:func:`tasks.physics.rollout_scene.preload_key`)
computes its own, with a note.
"""
from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

from conf.hand import N_FINGERS
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step
from tasks.physics.mpm.preload import PARTICLE_STATE, PreloadedState, preloaded_state
from tasks.physics.mpm.solver import GravityPreload
from tasks.physics.rollout_scene import PRELOAD_DAMPING, build_scene

_DIMS = {"x": ("particle", "xyz"), "v": ("particle", "xyz"), "C": ("particle", "i", "j"), "F": ("particle", "i", "j"),
         "x_carry": ("particle", "xyz"), "F_carry": ("particle", "i", "j"), "q": ("particle", "xyzw"),
         "alpha": ("particle",), "normal": ("particle", "xyz")}
_UNITS = {"x": "m", "v": "m/s", "C": "1/s", "x_carry": "m"}
# PARTICLE_STATE's names, then the tracers' (all absent when the scene has no preload)
PRELOAD_OUTPUTS = ("particle_positions?", "particle_velocities?", "affine_velocities?", "deformation_gradients?",
                   "position_round_off?", "deformation_round_off?", "rotation_warm_starts?", "plastic_strain?",
                   "membrane_normals?", "tracer_offsets?", "tracer_F0_inv?")


def preload_arrays(state: Optional[PreloadedState], key: str) -> tuple[dict[str, Array], dict[str, Any]]:
    """The artifact of a preloaded state (None: the scene has no preload: no weight or
    ``simulation.gravity_preload_frames`` = 0)."""
    if state is None:
        return {}, {"preloaded": False, "preload_key": key}
    arrays = {out: Array(state.arrays[name], _DIMS[name], _UNITS.get(name, "1"),
                         "particle state after the gravity preload (rows: the solver's; one placeholder row when the "
                         "scene's models need none)") for name, out in PARTICLE_STATE.items()}
    if "tracer_offsets" in state.arrays:
        arrays["tracer_offsets"] = Array(state.arrays["tracer_offsets"], ("tracer", "anchor", "xyz"), "m",
                                         "rest offsets of each surface point from its anchor particles, F0^-1 r")
        arrays["tracer_F0_inv"] = Array(state.arrays["tracer_F0_inv"], ("tracer", "i", "j"), "1",
                                        "inverse of each surface point's preloaded deformation gradient")
    attrs = {"preloaded": True, "preload_key": key, "gravity_preload": state.figures.as_dict(),
             "max_speed": state.vmax, "node_box": [state.box[0], state.box[1]], "energy_scale": state.energy_scale,
             "loading_force": state.loading_force, "damping": state.damping, "frame_dt": state.frame_dt,
             "mass_scale": state.mass_scale}
    return arrays, attrs


def preload_from_artifact(arrays: Mapping[str, np.ndarray], attrs: Mapping[str, Any]) -> Optional[PreloadedState]:
    """The preloaded state in a ``gravity_preload`` artifact (None when the scene has no preload)."""
    if not attrs["preloaded"]:
        return None
    state = {name: np.asarray(arrays[out]) for name, out in PARTICLE_STATE.items()}
    state.update({k: np.asarray(arrays[k]) for k in ("tracer_offsets", "tracer_F0_inv") if k in arrays})
    figures = attrs["gravity_preload"]
    return PreloadedState(arrays=state, vmax=float(attrs["max_speed"]),
                          box=(list(attrs["node_box"][0]), list(attrs["node_box"][1])),
                          energy_scale=float(attrs["energy_scale"]), loading_force=float(attrs["loading_force"]),
                          damping=float(attrs["damping"]), frame_dt=float(attrs["frame_dt"]),
                          mass_scale=float(attrs["mass_scale"]),
                          figures=GravityPreload(moved=tuple(float(m) for m in figures["moved"]),
                                                 frames=int(figures["frames"]), converged=bool(figures["converged"])),
                          key=str(attrs["preload_key"]))


def gravity_preload(obj: Mapping[str, np.ndarray], obj_attrs: Mapping[str, Any], field: Mapping[str, np.ndarray],
                    patches: Mapping[str, np.ndarray], times: np.ndarray, materials: Mapping[str, Any],
                    mpm: Mapping[str, Any], sim: Mapping[str, Any]) -> Optional[PreloadedState]:
    """The body's preloaded state (the arguments of :func:`tasks.physics.mpm_rollout.mpm_rollout`; None without a
    preload): the rollout's scene built without a boundary load and preloaded."""
    scene = build_scene(obj, obj_attrs, field, patches, times, materials, mpm, sim,
                        np.zeros((len(times), N_FINGERS)), "dirichlet")
    if scene.preload is None:
        return None
    return preloaded_state(scene.solver, scene.preload, scene.frame_dt, PRELOAD_DAMPING, scene.preload_key)


@artifact_step("gravity_preload",
               inputs=("object_model", "mpm_particles", "signal_smoothing", "contact_patches", "dirichlet_field",
                       "material_oracle"),
               reads=("mpm", "simulation"),
               unkeyed=("mpm.threads",),  # as the rollout's: the same kernel split into threads
               outputs=PRELOAD_OUTPUTS)
def gravity_preload_step(inputs, params):
    """The object's gravity preload, once for all its rollouts: its particles' state after settling under its weight
    and being put back in their given shape with the stress that carried it."""
    obj, particles = inputs["object_model"], inputs["mpm_particles"]
    state = gravity_preload({**obj.arrays, **particles.arrays}, {**obj.attrs, **particles.attrs, "name": obj.ref.scope},
                            inputs["dirichlet_field"].arrays, inputs["contact_patches"].arrays,
                            inputs["signal_smoothing"]["time"], inputs["material_oracle"].attrs["materials"],
                            params["mpm"], params["simulation"])
    return preload_arrays(state, "" if state is None else state.key)
