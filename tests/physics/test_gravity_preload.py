"""Gravity preload (:meth:`MPMSolver.preload_gravity`): the given shape becomes the body's equilibrium under its weight.

Known answers: a laterally free elastic column on a frictionless floor settles, unsupported, by the uniaxial closed
form (top drop rho g H^2 / (2 E), nu = 0); preloaded, it stays where it was given (its motion a small fraction of
that sag) with the weight carried by its stress (the uniaxial rho g (H - z) at mid-height), and its tracers sit on
their given positions with an identity deformation.
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from tasks.physics.mpm import Material, MPMSolver
from tests.physics.particles import lattice

DX = 0.01  # m
H, W = 0.08, 0.04  # m, column height and width (8 cells tall)
E, RHO = 2.0e4, 1000.0  # Pa, kg/m^3: the top sags rho g H^2 / (2 E) = 1.57 mm unsupported
COLUMN = Material(name="column", model="fixed_corotated", youngs_modulus=E, poisson_ratio=0.0, density=RHO)
FRAME = 1.0 / 30.0  # s


def column(tracers: np.ndarray | None = None, material: Material = COLUMN) -> MPMSolver:
    X = lattice([0.0, 0.0, 0.0], [W, W, H], DX / 2)
    return MPMSolver(X, (DX / 2) ** 3, [material], tracers=tracers,
                     config={"device": "cpu", "dx": DX, "floor_sticky": False, "mass_scaling": "off"})


def top_drop(s: MPMSolver, z0: np.ndarray) -> float:
    """m, how far the column's top layer of particles is below where it was given."""
    top = z0 >= z0.max() - 1e-6
    return float(z0[top].mean() - s.positions()[top, 2].mean())


@pytest.mark.parametrize("youngs", [E, E / 5], ids=["stiff: sags 0.16 cells, passes run to rest",
                                                   "soft: sags 0.79 cells, its first pass ends at its crest"])
def test_an_unsupported_column_sags_by_the_closed_form_and_a_preloaded_one_stays_where_it_was_given(youngs):
    closed = RHO * 9.81 * H ** 2 / (2.0 * youngs)  # m, top drop of a laterally free column under its weight, nu = 0
    material = Material(name="column", model="fixed_corotated", youngs_modulus=youngs, poisson_ratio=0.0,
                        density=RHO)
    s = column(material=material)
    z0 = s.positions()[:, 2].astype(np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        free = []
        for _ in range(12):  # T = 4 H / sqrt(E / rho) = 0.072 s (soft: 0.16 s): five (two) periods, averaged
            s.step_frame(FRAME)
            free.append(top_drop(s, z0))
    assert np.mean(free[2:]) == pytest.approx(closed, rel=0.15), np.mean(free[2:]) / closed

    s = column(material=material)
    pre = s.preload_gravity(FRAME, max_frames=60, passes=3)
    # the damped settle found the same sag (a pass that ends at its crest reads it there, at the equilibrium; one run
    # to rest reads it at the turning point of its overshoot)
    assert pre.sag == pytest.approx(closed, rel=0.25 if youngs == E else 0.1), pre.sag / closed
    assert pre.residual < 0.2 * pre.sag and pre.converged
    np.testing.assert_allclose(s.positions()[:, 2], z0, atol=1e-7)  # back where it was given, at rest
    assert np.abs(s.velocities()).max() == 0.0 and s.time == 0.0 and s.frame == 0
    drops = []
    for _ in range(12):
        s.step_frame(FRAME)
        drops.append(abs(top_drop(s, z0)))
    assert max(drops) < 0.2 * closed, max(drops) / closed  # it no longer sags: the stress holds the weight
    # the stress that holds it: uniaxial sigma_zz = -rho g (H - z) (the mid-height layer, within 25 %)
    F = s.deformation_gradients()
    mid = np.abs(s.positions()[:, 2] - H / 2) < DX / 2
    strain = F[mid, 2, 2].mean() - 1.0
    assert youngs * strain == pytest.approx(-RHO * 9.81 * H / 2, rel=0.25)


def test_tracers_stay_on_their_given_positions_through_a_preload_and_deform_from_it():
    X = lattice([0.0, 0.0, 0.0], [W, W, H], DX / 2)
    tracers = X[X[:, 2] > H - DX / 2][:10] + np.array([0.0, 0.0, DX / 4])  # on the top face
    s = column(tracers)
    s.preload_gravity(FRAME, max_frames=60, passes=2)
    x, F = s.tracer_state()
    np.testing.assert_allclose(x, tracers, atol=1e-6)
    np.testing.assert_allclose(F, np.broadcast_to(np.eye(3), F.shape), atol=1e-5)
    assert np.abs(s.deformation_gradients()[:, 2, 2] - 1.0).max() > 1e-3  # the particles keep their prestrain


def test_preload_arguments_are_checked():
    s = column()
    for kw in ({"max_frames": 0}, {"max_frames": 5, "passes": 0}, {"max_frames": 5, "damping": 1.0},
               {"max_frames": 5, "tolerance": 0.0}):
        with pytest.raises(ValueError, match="preload_gravity"):
            s.preload_gravity(FRAME, **kw)
