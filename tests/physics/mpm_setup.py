"""The small MLS-MPM set-ups shared by the solver's tests (tests/physics/test_mpm_*.py): a cube of particles,
a solver on the CPU and the soft jelly."""
from __future__ import annotations

from tasks.physics.mpm import Material, MPMSolver
from tests.physics.particles import lattice

DX = 0.005  # m


def cube(side, h=DX / 2, z0=0.0):
    X = lattice([0, 0, z0], [side, side, z0 + side], h)
    return X, h ** 3


def solver_for(X, vol, mats, **cfg):
    kw = dict(device="cpu", dx=DX)
    kw.update(cfg)
    mat_ids = kw.pop("material_ids", None)
    vel = kw.pop("velocities", None)
    tracers = kw.pop("tracers", None)
    return MPMSolver(X, vol, mats, material_ids=mat_ids, velocities=vel, config=kw, tracers=tracers)


JELLY = Material(name="jelly", model="fixed_corotated", youngs_modulus=5e4, poisson_ratio=0.3, density=1000.0)
