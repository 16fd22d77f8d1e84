"""The MPM particles step: the object's volume particles for the grid the rollout will use (paper sec. "Physics
Simulation"; :mod:`tasks.physics.particle_fill`).

A physics step, not part of the object model: a wall thinner than the grid spacing dx (``mpm.dx``, or
``sampling.particle_spacing x cbrt(mpm.particles_per_cell)``: :func:`tasks.physics.wall_resolution.grid_spacing`) is
sampled in Gauss layers on its mid-surface, a thicker one on the grid, so the particles read the grid while the
control chain (object model to Dirichlet field) does not.
"""
from __future__ import annotations

from tasks.core.step import artifact_step
from tasks.physics.particle_fill import PARTICLE_OUTPUTS, build_mpm_particles
from tasks.physics.wall_resolution import grid_spacing


@artifact_step("mpm_particles",
               reads=("object.name", "object.geometry", "object.filled", "object.interior", "sampling", "mpm.dx",
                      "mpm.particles_per_cell"),
               files=("object.geometry.path",),
               outputs=PARTICLE_OUTPUTS)
def mpm_particles_step(inputs, params):
    """The MPM particles of one object: its wall or body and its cavity (no inputs; a ply/mesh file is read from
    ``object.geometry.path``, whose content digest is in the key), with the wall judged against the grid spacing."""
    obj = {key: params[f"object.{key}"] for key in ("name", "geometry", "filled", "interior")}
    mpm = {"dx": params["mpm.dx"], "particles_per_cell": params["mpm.particles_per_cell"]}
    return build_mpm_particles(obj, params["sampling"], grid_spacing(mpm, float(params["sampling"]["particle_spacing"])))
