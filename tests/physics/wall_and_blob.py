"""A two-field MPM scene shared by the multi-field and rollout-recorder tests: a stiff, mass-scaled wall on the
floor and a fluid blob with physical inertia beside it (real Warp solver on the CPU)."""
from __future__ import annotations

import numpy as np

from tasks.physics.mpm import MPMSolver
from tasks.physics.mpm.materials import Material
from tests.physics.particles import lattice

DX = 0.005  # m
FRAME_DT = 1.0 / 60.0  # s
WALL = Material(name="wall", model="fixed_corotated", youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0)
BLOB = Material(name="blob", model="fluid", youngs_modulus=2e4, poisson_ratio=0.3, density=1000.0, viscosity=0.01,
                mass_scaled=False)


def wall_and_blob(blob_lo, blob_hi, multi_field=True, gravity=(0.0, 0.0, -9.81), floor=True, velocity=(0, 0, 0)):
    """A stiff wall (2 x 8 x 6 cm, mass-scaled under selective scaling: heavy) standing on the floor at x in
    [0, 0.02] m, and a fluid blob with physical inertia (field 1) in the box [blob_lo, blob_hi] with ``velocity``."""
    Xw = lattice([0.0, 0.0, 0.0], [0.02, 0.08, 0.06], DX / 2)
    Xb = lattice(blob_lo, blob_hi, DX / 2)
    ids = np.repeat([0, 1], [len(Xw), len(Xb)])
    v = np.zeros((len(ids), 3), np.float32)
    v[ids == 1] = velocity
    cfg = dict(device="cpu", dx=DX, mass_scaling="selective", target_substeps_per_frame=10, floor=floor,
               floor_height=0.0, floor_sticky=True, gravity=list(gravity), multi_field=multi_field,
               domain_lo=[-0.04, -0.02, -0.02], domain_hi=[0.1, 0.1, 0.12])
    return MPMSolver(np.concatenate([Xw, Xb]), (DX / 2) ** 3, [WALL, BLOB], material_ids=ids, velocities=v,
                     config=cfg), ids
