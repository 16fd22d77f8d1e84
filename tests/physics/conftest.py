"""Fixtures shared by the physics tests."""
from __future__ import annotations

import numpy as np
import pytest

from tasks.physics.mpm import DirichletPoints, ForcePatch, Material
from tests.physics.mpm_setup import JELLY, cube, solver_for


@pytest.fixture(scope="session")
def warm_mpm_kernels():
    """Compile (or load from Warp's kernel cache) the solver's kernels for every material model, Dirichlet points,
    force patches and tracers once per test process, before the first MPM test's clock starts."""
    X, vol = cube(0.02)
    mats = [JELLY,
            Material(name="rubber", model="neo_hookean", youngs_modulus=5e4, poisson_ratio=0.4, density=1000.0),
            Material(name="clay", model="von_mises", youngs_modulus=5e4, poisson_ratio=0.3, density=1000.0,
                     yield_stress=1e3),
            Material(name="stuffing", model="foam", youngs_modulus=5e4, poisson_ratio=0.2, density=300.0,
                     yield_stress=1e3, viscosity=1.0),
            Material(name="juice", model="fluid", youngs_modulus=5e4, poisson_ratio=0.3, density=1000.0,
                     bulk_modulus=5e4, viscosity=1e-3)]
    ids = np.arange(len(X)) % len(mats)
    s = solver_for(X, vol, mats, material_ids=ids, tracers=X[:10])
    pts = X[X[:, 2] > X[:, 2].max() - 1e-9][:20]
    s.step_frame(1e-3, dirichlet=DirichletPoints(pts, np.zeros((len(pts), 3)), np.zeros(len(pts), int)),
                 forces=ForcePatch(pts, np.zeros(len(pts), int), np.zeros((1, 3))))
