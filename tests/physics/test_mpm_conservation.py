"""The MLS-MPM stencil and conservation (real Warp kernels on the CPU): the quadratic B-spline stencil's partition of
unity and linear reproduction; mass conserved exactly, momentum in free flight, rest states on and off the floor, and
motion below float32 resolution per substep that still adds up.
"""
from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from tasks.physics.mpm import (
    Material,
)
from tasks.physics.mpm.boundary import bspline_stencil
from tasks.physics.mpm.kernels.stencil import stencil_at, stencil_weight
from tests.physics.mpm_setup import DX, JELLY, cube, solver_for

pytestmark = pytest.mark.usefixtures("warm_mpm_kernels")


# ============================================================================================ stencil
@wp.kernel
def _k_stencils(g: wp.array(dtype=wp.vec3), base: wp.array(dtype=wp.vec3i), w_axis: wp.array3d(dtype=float),
                w_node: wp.array2d(dtype=float)):
    p = wp.tid()
    s = stencil_at(g[p])
    base[p] = s.base
    for i in range(3):
        w_axis[p, 0, i] = s.wx[i]
        w_axis[p, 1, i] = s.wy[i]
        w_axis[p, 2, i] = s.wz[i]
        for j in range(3):
            for k in range(3):
                w_node[p, 9 * i + 3 * j + k] = stencil_weight(s, i, j, k)


def test_bspline_stencil_partition_of_unity_and_linear_reproduction():
    """The kernels' quadratic B-spline stencil: base = floor(g - 1/2), per-axis weights >= 0 summing to 1 and
    reproducing linear functions (sum_i w_i (base + i) = g); hand values 1/8, 3/4, 1/8 on a node (f = 1) and
    1/2, 1/2, 0 halfway between nodes (f = 1/2); node weight = product of the axis weights; equal to the numpy
    twin used by ``project_points``."""
    rng = np.random.default_rng(3)
    g = np.r_[[[2.0, 2.5, 3.25], [5.49, 5.5, 5.51]], rng.uniform(1.0, 30.0, (200, 3))].astype(np.float32)
    P = len(g)
    base = wp.zeros(P, dtype=wp.vec3i, device="cpu")
    w_axis = wp.zeros((P, 3, 3), dtype=float, device="cpu")
    w_node = wp.zeros((P, 27), dtype=float, device="cpu")
    wp.launch(_k_stencils, dim=P, device="cpu", inputs=[wp.array(g, dtype=wp.vec3, device="cpu"), base, w_axis,
                                                          w_node])
    b, w, wn = base.numpy(), w_axis.numpy(), w_node.numpy()
    np.testing.assert_array_equal(b, np.floor(g - np.float32(0.5)))
    assert (w >= 0).all()
    np.testing.assert_allclose(w.sum(-1), 1.0, atol=1e-6)
    np.testing.assert_allclose((w * (b[..., None] + np.arange(3))).sum(-1), g, atol=2e-5)
    np.testing.assert_allclose(w[0, 0], [0.125, 0.75, 0.125], atol=1e-7)  # g = 2: on node 2 (f = 1)
    np.testing.assert_allclose(w[0, 1], [0.5, 0.5, 0.0], atol=1e-7)  # g = 2.5: halfway between nodes 2 and 3
    expected_node = (w[:, 0, :, None, None] * w[:, 1, None, :, None] * w[:, 2, None, None, :]).reshape(P, 27)
    np.testing.assert_allclose(wn, expected_node, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(wn.sum(1), 1.0, atol=1e-6)
    b_np, w_np = bspline_stencil(g.astype(np.float64))
    np.testing.assert_array_equal(b, b_np)
    np.testing.assert_allclose(w, w_np, atol=1e-6)


# ============================================================================================ conservation
def test_mass_conserved_exactly_with_mixed_materials():
    X, vol = cube(0.03)
    mats = [JELLY,
            Material(name="juice", model="fluid", density=1050.0, bulk_modulus=5e4, viscosity=1e-3),
            Material(name="clay", model="von_mises", youngs_modulus=5e4, density=1800.0, yield_stress=2e3)]
    c = X.mean(0)
    r = np.abs(X - c).max(1)
    ids = np.where(r > 0.011, 0, np.where(X[:, 2] > c[2], 1, 2))  # shell, juice and clay interior
    s = solver_for(X, vol, mats, material_ids=ids)
    m0 = s.masses().copy()
    expected = vol * np.array([m.density for m in mats])[ids]
    np.testing.assert_allclose(m0, expected, rtol=1e-6)
    for _ in range(3):
        s.step_frame(1 / 120)
        np.testing.assert_array_equal(s.masses(), m0)  # particle masses never change
        assert s.grid_mass() == pytest.approx(m0.astype(np.float64).sum(), rel=1e-5)  # grid mass = particle mass
        assert s.last_stats.mass == pytest.approx(m0.astype(np.float64).sum(), rel=1e-6)


def test_momentum_conserved_in_free_flight():
    X, vol = cube(0.03)
    rng = np.random.default_rng(0)
    c = X.mean(0)
    V = np.array([0.2, -0.1, 0.3]) + np.cross([0.0, 0.0, 4.0], X - c) + 0.02 * rng.standard_normal(X.shape)
    s = solver_for(X, vol, JELLY, velocities=V, gravity=[0, 0, 0], floor=False, margin_cells=12)
    m = s.masses().astype(np.float64)
    p0 = (m[:, None] * V).sum(0)
    for _ in range(4):
        st = s.step_frame(1 / 240)
    p1 = (m[:, None] * s.velocities().astype(np.float64)).sum(0)
    scale = m.sum() * np.abs(V).max()
    assert np.abs(p1 - p0).max() < 1e-5 * scale, (p0, p1)
    assert np.abs(st.momentum - p0).max() < 1e-5 * scale
    x = s.positions()
    com_expected = c + p0 / m.sum() * s.time
    assert np.abs((m[:, None] * x).sum(0) / m.sum() - com_expected).max() < 1e-6


def test_cube_at_rest_without_gravity_stays_exactly():
    X, vol = cube(0.02)
    s = solver_for(X, vol, JELLY, gravity=[0, 0, 0])
    x0 = s.positions()
    for _ in range(3):
        st = s.step_frame(1 / 60)
    assert np.array_equal(s.positions(), x0)
    assert np.all(s.velocities() == 0.0)
    assert st.j_min == 1.0 and st.j_max == 1.0 and st.kinetic_energy == 0.0


def test_motion_below_float32_resolution_per_substep_still_adds_up():
    """A position near 0.1 m resolves 7.5e-9 m and an F_E entry near 1 resolves 1.2e-7, so a substep that moves a
    particle by less than half of that (here 2.5e-9 m: 1e-5 m/s on 0.25 ms steps) or strains it by less than 6e-8
    (here 2.5e-8: 1e-4 /s) changed nothing at all: a slowly drifting body stood still and a slowly stretching one
    kept F_E = I.  With the round-off carried into the next substep (``round_off``) they follow their closed forms
    over 1 s (4,000 substeps): the drift moves the block v t = 1e-5 m (within 2 %), and a free stretch (E = 1 uPa,
    no force worth the name: every particle keeps its velocity, v = e (x - c)) gives F_xx = 1 + e t = 1.0001
    (within 1 %; without the carries 0 and 0)."""
    soft = Material(name="soft", model="fixed_corotated", youngs_modulus=1e-6, poisson_ratio=0.3, density=1000.0)
    X, vol = cube(0.02, z0=0.1)
    drift = solver_for(X, vol, soft, velocities=np.tile([0.0, 0.0, 1e-5], (len(X), 1)), gravity=[0, 0, 0],
                       floor=False, dt=2.5e-4)
    c = X.mean(0)
    rate = 1e-4
    V = np.zeros_like(X)
    V[:, 0] = rate * (X[:, 0] - c[0])
    stretch = solver_for(X, vol, soft, velocities=V, gravity=[0, 0, 0], floor=False, dt=2.5e-4)
    stretch.set_affine_velocities(np.tile(np.diag([rate, 0.0, 0.0]), (len(X), 1, 1)))
    z0 = drift.positions()[:, 2].astype(np.float64)
    for _ in range(50):
        drift.step_frame(0.02)
        stretch.step_frame(0.02)
    moved = drift.positions()[:, 2].astype(np.float64) - z0
    assert abs(moved.mean() / 1e-5 - 1.0) < 0.02, moved.mean()
    Fxx = stretch.deformation_gradients()[:, 0, 0].astype(np.float64)
    assert np.abs((Fxx - 1.0) / (rate * 1.0) - 1.0).max() < 0.01, (Fxx.min() - 1, Fxx.max() - 1)


def test_resting_cube_on_floor_under_gravity():
    side = 0.04
    X, vol = cube(side)
    s = solver_for(X, vol, JELLY)
    x0 = s.positions()
    stats = [s.step_frame(1 / 60) for _ in range(12)]  # 0.2 s
    x = s.positions()
    disp = np.linalg.norm(x - x0, axis=1)
    # static sag of the top: rho g L^2 / (2 E) = 0.16 mm; the dynamic settling overshoots at most ~2x
    sag_static = 1000.0 * 9.81 * side ** 2 / (2 * JELLY.youngs_modulus)
    assert disp.max() < 0.25 * DX, disp.max()
    top = x0[:, 2] > side - DX / 2
    assert 0.0 < x0[top, 2].mean() - x[top, 2].mean() < 4 * sag_static + 0.05 * DX
    assert all(0.98 < st.j_min and st.j_max < 1.01 for st in stats)
    assert stats[-1].max_speed < 0.05
    assert stats[-1].substeps > 1 and stats[-1].courant <= 0.3 + 1e-6
