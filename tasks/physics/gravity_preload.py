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

from tasks.core.step import artifact_step
from tasks.physics.preload_state import PRELOAD_OUTPUTS, gravity_preload, preload_arrays


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
    return preload_arrays(state)
