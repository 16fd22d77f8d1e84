"""The body's gravity preload as a rollout input (:mod:`tasks.physics.gravity_preload`, the step): computed on the
rollout's scene without its boundary load (:func:`gravity_preload`) and stored as an artifact's arrays and attributes
(:func:`preload_arrays`, read back by :func:`preload_from_artifact`).  The state itself:
:mod:`tasks.physics.mpm.preload`.
"""
from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np

from conf.hand import N_FINGERS
from tasks.core.artifacts import Array
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


def preload_arrays(state: Optional[PreloadedState]) -> tuple[dict[str, Array], dict[str, Any]]:
    """The artifact of a preloaded state (None: the scene has no preload: no weight or
    ``simulation.gravity_preload_frames`` = 0)."""
    if state is None:
        return {}, {"preloaded": False}
    arrays = {out: Array(state.arrays[name], _DIMS[name], _UNITS.get(name, "1"),
                         "particle state after the gravity preload (rows: the solver's; one placeholder row when the "
                         "scene's models need none)") for name, out in PARTICLE_STATE.items()}
    if "tracer_offsets" in state.arrays:
        arrays["tracer_offsets"] = Array(state.arrays["tracer_offsets"], ("tracer", "anchor", "xyz"), "m",
                                         "rest offsets of each surface point from its anchor particles, F0^-1 r")
        arrays["tracer_F0_inv"] = Array(state.arrays["tracer_F0_inv"], ("tracer", "i", "j"), "1",
                                        "inverse of each surface point's preloaded deformation gradient")
    attrs = {"preloaded": True, "preload_key": state.key, "gravity_preload": state.figures.as_dict(),
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
