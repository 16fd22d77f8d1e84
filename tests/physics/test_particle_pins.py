"""Particle pins (:class:`tasks.physics.mpm.ParticlePins`, ``mpm.fingers = particles``): Dirichlet conditions on
the particles' surface points instead of the grid nodes of their stencils.  Known answers:

  * uniaxial compression of a cube between two pinned slip layers (frictionless plates): F = E A eps within 5 % at
    nu = 0.3, 0.45, 0.49 with 8 cells across (grid-node plates: +30 % and more), the two plates' reactions equal
    and opposite, and the layer next to a plate strains like the middle (no held layer);
  * a pinned layer dragged sideways (no slip) carries the block along its path: its surface points (or, with
    arms 0, the pinned centres a wall thinner than the spacing gets) end on their targets within a few per cent of
    the travel;
  * with nothing else acting, the pins' reactions integrated over the frames are the block's momentum change;
  * the eq. 3 field on a rollout (the default ``mpm.fingers=particles``) pins the particles the constrained points
    are embedded in, and they follow the field (``tests/physics/test_mpm_rollout.py``, the default fingers' test);
  * bad input: one line naming ``ParticlePins``; a pinned particle crushed by its push: the volume guard's line
    names its finger and the fix.
"""
from __future__ import annotations

import numpy as np
import pytest

from tasks.physics.mpm import Material, MPMSolver, ParticlePins, SimulationError
from tasks.verification.contact import block_particles, uniaxial_case


@pytest.mark.parametrize("nu", [0.3, 0.45, 0.49])
def test_uniaxial_compression_between_pinned_layers_matches_E_A_eps(nu):
    """1 % travel of the top layer's surface points on a 40 mm cube, 8 cells across: within 5 % of E A eps
    (measured -4.3 / -1.1 / +0.4 %, and -2.0 / -0.2 / +0.7 % with 16 cells), the bottom pins' reaction the same
    within 0.5 %, and the second particle layer from each plate strains like the middle third within 10 % (a
    grid-node plate holds that layer at zero axial strain)."""
    r = uniaxial_case("pins", nu, cells_across=8)
    print(f"nu={nu}: force error {100 * r['error']:+.2f} %, floor {100 * r['error_floor']:+.2f} %")
    assert abs(r["error"]) < 0.05, r["error"]
    assert abs(r["error_floor"] - r["error"]) < 0.005
    s = r["solver"]
    z0 = s.positions()[:, 2]
    ezz = 1.0 - s.deformation_gradients()[:, 2, 2]
    order = np.argsort(z0)
    layers = np.array_split(order, 16)  # 16 particle layers (the cube's 2 x 8 particles high)
    per_layer = np.array([ezz[ix].mean() for ix in layers])
    middle = per_layer[5:11].mean()
    assert np.all(np.abs(per_layer[[1, -2]] / middle - 1.0) < 0.1), per_layer / middle


def _free_block(h: float = 0.0025, dx: float = 0.005) -> MPMSolver:
    X = block_particles(0.01, 0.02, h)
    mat = Material(name="block", model="fixed_corotated", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    return MPMSolver(X, h ** 3, mat, config=dict(device="cpu", dx=dx, gravity=[0.0, 0.0, 0.0], floor=False,
                                                 margin_cells=6, energy_guard_tolerance=0.0))


@pytest.mark.parametrize("arm", [1.0, 0.0])
def test_a_pinned_layer_drags_the_block_along_its_path_and_its_reactions_are_the_momentum_change(arm):
    """The top layer's surface points (arm 1; arm 0: its centres) dragged 1 mm along x over each of 6 frames (no
    slip, nothing else acting): at every frame's end they are on their targets within 5 % of a frame's travel, the
    block follows (its centre of mass moves along x), and the pins' reactions x frame_dt sum to the block's momentum
    change within 1e-3 of the impulse."""
    s = _free_block()
    x0 = s.positions()
    top = np.flatnonzero(x0[:, 2] > x0[:, 2].max() - 1e-6)
    up = np.tile([0.0, 0.0, 1.0], (len(top), 1))
    arms = np.full(len(top), arm)
    frame_dt, step = 0.004, np.array([0.001, 0.0, 0.0])
    impulse, m = np.zeros(3), s.masses()
    p0 = (m[:, None] * s.velocities()).sum(axis=0)
    if arm == 0.0:
        np.testing.assert_allclose(s.surface_points(top, up, arms), x0[top])
    for _ in range(6):
        target = s.surface_points(top, up, arms) + step
        st = s.step_frame(frame_dt, pins=ParticlePins(top, target, up, np.zeros(len(top), int), arms=arms))
        impulse += np.asarray(st.reaction)[0] * frame_dt
        miss = np.linalg.norm(s.surface_points(top, up, arms) - target, axis=1)
        assert miss.max() < 0.05 * np.linalg.norm(step), miss.max()
    assert (s.positions() - x0)[:, 0].mean() > 0.3 * 6 * step[0]  # the block came along
    momentum = (m[:, None] * s.velocities()).sum(axis=0) - p0
    assert np.linalg.norm(impulse) > 1e-6
    np.testing.assert_allclose(momentum, impulse, atol=1e-3 * np.linalg.norm(impulse))


def test_bad_pins_are_one_line_errors():
    s = _free_block()
    n = 3
    with pytest.raises(ValueError, match="ParticlePins: 3 indices but 2 targets"):
        s.step_frame(0.004, pins=ParticlePins(np.arange(n), np.zeros((2, 3)), np.ones((n, 3))))
    with pytest.raises(ValueError, match="ParticlePins: indices must be distinct particles"):
        s.step_frame(0.004, pins=ParticlePins(np.array([0, 0, 1]), np.zeros((n, 3)), np.ones((n, 3))))
    with pytest.raises(ValueError, match=r"arms must lie in \[0, 1\]"):
        s.step_frame(0.004, pins=ParticlePins(np.arange(n), np.zeros((n, 3)), np.ones((n, 3)), arms=np.full(n, 2.0)))
    with pytest.raises(ValueError, match="3 indices but 3 targets, 3 normals, 3 finger ids, 2 arms and 3 free flags"):
        s.step_frame(0.004, pins=ParticlePins(np.arange(n), np.zeros((n, 3)), np.ones((n, 3)), np.zeros(n, int),
                                              arms=np.ones(2)))
    with pytest.raises(ValueError, match="3 finger ids, 3 arms and 1 free flags"):
        s.step_frame(0.004, pins=ParticlePins(np.arange(n), np.zeros((n, 3)), np.ones((n, 3)), np.zeros(n, int),
                                              free=np.ones(1, bool)))
    with pytest.raises(ValueError, match="NaN/inf targets or zero normals"):
        s.step_frame(0.004, pins=ParticlePins(np.arange(n), np.zeros((n, 3)), np.zeros((n, 3))))


def test_a_crushed_pinned_particle_is_named_in_the_error():
    """Top and bottom layers pinned, the top driven down 4 mm a frame into the block until it is crushed: the
    volume guard stops the run with one line that names the pinned particle's finger and the grid-node fingers
    as the fix, before any state goes non-finite."""
    s = _free_block()
    x0 = s.positions()
    top = np.flatnonzero(x0[:, 2] > x0[:, 2].max() - 1e-6)
    bottom = np.flatnonzero(x0[:, 2] < x0[:, 2].min() + 1e-6)
    pinned = np.concatenate([top, bottom])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(top), 1)), np.tile([0.0, 0.0, -1.0], (len(bottom), 1))])
    fingers = np.concatenate([np.full(len(top), 3), np.full(len(bottom), 1)])
    with pytest.raises(SimulationError, match=r"extreme volume change .* Likely cause: it is pinned \(ParticlePins, "
                                              r"finger id (1|3)\).*mpm.fingers=dirichlet"):
        for _ in range(20):
            target = s.surface_points(pinned, normals)
            target[: len(top), 2] -= 0.004
            s.step_frame(0.004, pins=ParticlePins(pinned, target, normals, fingers))
    assert np.isfinite(s.positions()).all()
