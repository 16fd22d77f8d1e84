"""Boundary conditions of the MLS-MPM solver (real Warp kernels on the CPU): Dirichlet points and nodes, per-finger
reactions, force patches, time-varying targets and tracers, and the defects once found in them (two slip constraints
on one node, Dirichlet nodes on the first node layer, the APIC affine setter, force patches on moving material).
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from tasks.physics.mpm import (
    DirichletNodes,
    DirichletPoints,
    ForcePatch,
    Material,
    deform_covariances,
    polar_rotation,
)
from tests.physics.mpm_setup import DX, JELLY, cube, solver_for
from tests.physics.particles import lattice

pytestmark = pytest.mark.usefixtures("warm_mpm_kernels")


# ============================================================================================ boundary conditions
def _press(mat, press_depth=0.006, speed=0.1, release_time=0.15, radius=0.01, side=0.04):
    X, vol = cube(side)
    s = solver_for(X, vol, mat, floor_friction=0.5, tracers=None)
    ctr = np.array([side / 2, side / 2, side])
    pg = lattice([ctr[0] - radius, ctr[1] - radius, side], [ctr[0] + radius, ctr[1] + radius, side], DX / 2)
    pts = pg[np.linalg.norm(pg[:, :2] - ctr[:2], axis=1) <= radius]
    pts[:, 2] = side
    top = X[:, 2] > side - DX / 2
    rad = np.linalg.norm(X[:, :2] - ctr[:2], axis=1)
    probe = (rad < 0.6 * radius) & top  # top layer under the pad
    ring = (rad > 1.9 * radius) & top  # top-layer corners, far from the pad

    def dent(x):  # shape measure, independent of rigid motion of the cube (it may hop after release)
        return x[ring, 2].mean() - x[probe, 2].mean()

    fdt = 0.01
    t_press = press_depth / speed
    n_press = int(round(t_press / fdt))
    vel = np.tile([0.0, 0.0, -speed], (len(pts), 1))
    for _ in range(n_press):
        s.step_frame(fdt, dirichlet=DirichletPoints(pts, vel, np.zeros(len(pts), int)))
        pts[:, 2] -= speed * fdt
    x = s.positions()
    dent_pressed = dent(x)
    follow_err = np.abs((x[probe, 2] - X[probe, 2]) + speed * n_press * fdt).max()
    dents = []
    n_rel = int(round(release_time / fdt))
    for f in range(n_rel):
        s.step_frame(fdt)
        if f >= n_rel // 2:
            dents.append(dent(s.positions()))
    return dent_pressed, float(np.mean(dents)), follow_err, s


def test_dirichlet_points_follow_targets_and_elastic_recovers():
    dent_pressed, dent_after, follow_err, _ = _press(JELLY)
    print("elastic dent pressed/after (m):", dent_pressed, dent_after)
    assert dent_pressed > 0.002
    assert follow_err < 0.25 * DX, follow_err  # material under the pad follows the prescribed motion
    assert abs(dent_after) < 0.25 * dent_pressed, (dent_pressed, dent_after)  # elastic: shape recovers


def test_von_mises_object_keeps_its_dent():
    clay = Material(name="clay", model="von_mises", youngs_modulus=5e4, poisson_ratio=0.3, density=1000.0,
                    yield_stress=1.5e3)
    dent_pressed, dent_after, _, s = _press(clay)
    print("plastic dent pressed/after (m):", dent_pressed, dent_after)
    assert dent_pressed > 0.002
    assert dent_after > 0.5 * dent_pressed, (dent_pressed, dent_after)
    assert s.plastic_strain().max() > 0.01


def test_per_finger_reaction_matches_compression_force_and_fingers_are_separate():
    """Two fingers press opposite faces of a free cube with the same speed: equal and opposite reactions whose
    magnitude matches E A eps of the squeezed cube (nu = 0, frictionless pads)."""
    E = 1e5
    mat = Material(name="block", model="fixed_corotated", youngs_modulus=E, poisson_ratio=0.0, density=1000.0)
    side = 0.04
    X = lattice([0, 0, 0], [side, side, side], DX / 2)
    s = solver_for(X, (DX / 2) ** 3, mat, gravity=[0, 0, 0], floor=False, margin_cells=3)
    pg = lattice([-DX, -DX, 0], [side + DX, side + DX, 0], DX / 2)[:, :2]
    left = np.c_[np.zeros(len(pg)), pg]
    right = np.c_[np.full(len(pg), side), pg]
    nx = np.tile([1.0, 0.0, 0.0], (len(pg), 1))
    c = mat.bar_wave_speed()
    T = 20 * side / c
    V = 0.01 * side / T / 2  # each pad moves half of a 1 % total strain
    n = 20
    for f in range(n):
        vx = V * min(1.0, (f + 0.5) / (0.2 * n)) / (1 - 0.1)
        bcs = [DirichletPoints(left, np.tile([vx, 0, 0], (len(pg), 1)), np.full(len(pg), 2), normals=nx),
               DirichletPoints(right, np.tile([-vx, 0, 0], (len(pg), 1)), np.full(len(pg), 4), normals=nx)]
        st = s.step_frame(T / n, dirichlet=bcs)
        left[:, 0] += vx * T / n
        right[:, 0] -= vx * T / n
    F = s.deformation_gradients()
    mid = np.abs(X[:, 0] - side / 2) < side / 6
    eps = -(F[mid, 0, 0].mean() - 1.0)
    expected = E * side * side * eps
    assert st.reaction.shape[0] >= 5
    f2, f4 = st.reaction[2, 0], st.reaction[4, 0]
    assert f2 > 0 > f4  # finger 2 pushes +x, finger 4 pushes -x
    assert abs(f2 - expected) / expected < 0.10 and abs(-f4 - expected) / expected < 0.10, (f2, f4, expected)
    assert np.abs(st.reaction[[0, 1, 3]]).max() == 0.0


def test_force_mode_total_impulse_independent_of_particle_count():
    side = 0.03
    F = np.array([[0.0, 0.0, -0.02], [0.01, 0.0, 0.0]])  # N, two fingers
    res = []
    for h in (DX / 2, DX / (2 * 2 ** (1 / 3))):  # 8 and 16 particles per cell
        X = lattice([0, 0, 0], [side, side, side], h)
        s = solver_for(X, h ** 3, JELLY, gravity=[0, 0, 0], floor=False, margin_cells=6)
        top = X[X[:, 2] > side - h]
        side_pts = X[X[:, 0] < h]
        pts = np.r_[top, side_pts]
        fid = np.r_[np.zeros(len(top), int), np.ones(len(side_pts), int)]
        T = 0.0
        for _ in range(3):
            st = s.step_frame(1 / 200, forces=ForcePatch(pts, fid, F))
            T += 1 / 200
            np.testing.assert_allclose(st.applied_force[:2], F, rtol=1e-4, atol=1e-9)  # exact total per finger
        m = s.masses().astype(np.float64)
        P = (m[:, None] * s.velocities().astype(np.float64)).sum(0)
        res.append(P)
        np.testing.assert_allclose(P, F.sum(0) * T, rtol=0.02, atol=1e-3 * np.abs(F).max() * T)
    assert np.abs(res[0] - res[1]).max() < 0.05 * np.abs(res[0]).max()


def test_dirichlet_nodes_and_projection_helper():
    X, vol = cube(0.02)
    s = solver_for(X, vol, JELLY, gravity=[0, 0, 0])
    pts = X[X[:, 2] > X[:, 2].max() - 1e-9]
    nodes = s.project_points(pts, np.tile([0, 0, -0.05], (len(pts), 1)), np.zeros(len(pts), int))
    assert len(nodes.indices) > len(pts) // 4
    np.testing.assert_allclose(nodes.velocities, np.tile([0, 0, -0.05], (len(nodes.indices), 1)), atol=1e-6)
    # node positions are within the B-spline support (1.5 dx) of some constrained point
    npos = s.node_position(nodes.indices)
    d = np.abs(npos[:, None, :] - pts[None]).max(-1).min(1)
    assert d.max() <= 1.5 * DX + 1e-9
    # explicit nodes (re-projected each frame as the surface moves)
    for f in range(4):
        st = s.step_frame(1 / 60, dirichlet=DirichletNodes(nodes.indices, nodes.velocities, nodes.finger_ids))
        top = s.positions()[X[:, 2] > X[:, 2].max() - 1e-9]
        nodes = s.project_points(top, np.tile([0, 0, -0.05], (len(top), 1)), np.zeros(len(top), int))
    assert np.abs(top[:, 2] - pts[:, 2] + 4 * 0.05 / 60).max() < 0.25 * DX  # 3.3 mm prescribed
    assert st.reaction[0, 2] < 0  # pulls the top layer down against the cube's elasticity
    # node mask form: hold the bottom node layer of the cube still (finger 3)
    mask = np.zeros(s.dims, bool)
    k0 = int(round((X[:, 2].min() - s.lo[2]) / DX))
    mask[:, :, k0] = True
    s.step_frame(1 / 60, dirichlet=DirichletNodes.from_mask(mask, [0.0, 0.0, 0.0], finger_id=3))


def test_time_varying_dirichlet_callable_per_substep():
    """A callable boundary spec is re-evaluated every substep: here a pad oscillating in z (v = A w cos(w t))."""
    X, vol = cube(0.02)
    s = solver_for(X, vol, JELLY, gravity=[0, 0, 0])
    top0 = X[X[:, 2] > X[:, 2].max() - 1e-9]
    A, w, T = 0.002, 2 * np.pi * 10.0, 0.05
    calls = []

    def spec(t, dt):
        tg = s.time + t
        calls.append(t)
        z = top0[:, 2] + A * np.sin(w * tg)
        v = np.zeros_like(top0)
        v[:, 2] = A * w * np.cos(w * tg)
        return DirichletPoints(np.c_[top0[:, :2], z], v, advect=False, min_weight=0.05)

    for _ in range(5):
        st = s.step_frame(T / 5, dirichlet=spec)
    assert len(calls) >= 5 * st.substeps
    top = s.positions()[X[:, 2] > X[:, 2].max() - 1e-9]
    assert np.abs(top[:, 2] - (top0[:, 2] + A * np.sin(w * s.time))).max() < 0.25 * DX


def test_tracers_follow_material_and_gaussian_helpers():
    side = 0.03
    X, vol = cube(side)
    rng = np.random.default_rng(1)
    tr = X[rng.choice(len(X), 50, replace=False)] + 0.2 * DX * rng.standard_normal((50, 3))
    c = X.mean(0)
    w = 3.0
    V = np.cross([0.0, 0.0, w], X - c)  # rigid rotation about z
    s = solver_for(X, vol, JELLY, velocities=V, gravity=[0, 0, 0], floor=False, tracers=tr, margin_cells=6)
    t_end = 0.1
    for _ in range(5):
        s.step_frame(t_end / 5)
    ang = w * t_end
    Rz = np.array([[math.cos(ang), -math.sin(ang), 0], [math.sin(ang), math.cos(ang), 0], [0, 0, 1]])
    expected = (tr - c) @ Rz.T + c
    assert np.abs(s.tracer_positions() - expected).max() < 0.25 * DX
    R = polar_rotation(s.tracer_state()[1])
    assert np.abs(R - Rz).max() < 0.03
    # helpers: covariance F S F^T and a proper rotation
    Fm = np.array([[[1.2, 0.1, 0.0], [0.0, 0.9, 0.0], [0.0, 0.0, -1.0]]])
    S = np.diag([1.0, 2.0, 3.0])[None]
    np.testing.assert_allclose(deform_covariances(Fm, S)[0], Fm[0] @ S[0] @ Fm[0].T)
    Rp = polar_rotation(Fm)
    assert np.linalg.det(Rp[0]) == pytest.approx(1.0)
    np.testing.assert_allclose(Rp[0] @ Rp[0].T, np.eye(3), atol=1e-12)


# ============================================================================================ boundary defects
def test_two_slip_constraints_on_one_node_keep_each_normal_component():
    """A wall (normal x, target 0) and a plate (normal z, target -0.05 m/s) on the same massive node: the node keeps
    each normal's own component, (0, v_y, -0.05), not the average along the mean normal (-0.0125, 0, -0.0125); the
    free tangential component v_y = 0.02 m/s of the material is untouched."""
    X, vol = cube(0.02)
    s = solver_for(X, vol, JELLY, velocities=np.tile([0.03, 0.02, 0.01], (len(X), 1)), gravity=[0, 0, 0],
                   floor=False)
    node = np.round((X.mean(axis=0) - s.lo) / DX).astype(np.int32)[None]
    wall = DirichletNodes(node, np.zeros((1, 3)), normals=np.array([[1.0, 0, 0]]))
    plate = DirichletNodes(node, np.array([[0, 0, -0.05]]), normals=np.array([[0, 0, 1.0]]))
    s.step_frame(1e-4, dirichlet=[wall, plate])  # one substep (1e-4 s < the stable step)
    v = s.grid_a.numpy()[tuple(node[0])][:3]
    np.testing.assert_allclose(v, [0.0, 0.02, -0.05], atol=1e-6)
    # one slip normal alone: only its component is prescribed, the tangential velocity stays the material's
    s = solver_for(X, vol, JELLY, velocities=np.tile([0.03, 0.02, 0.01], (len(X), 1)), gravity=[0, 0, 0],
                   floor=False)
    s.step_frame(1e-4, dirichlet=plate)
    np.testing.assert_allclose(s.grid_a.numpy()[tuple(node[0])][:3], [0.03, 0.02, -0.05], atol=1e-6)


def test_dirichlet_nodes_on_node_layer_1_are_usable():
    """Node layer 1 (the first layer the solver accepts; layer 0 is skipped) lies at grid coordinate 1, which float32
    rounds to 0.99999976 < 1 for this grid origin: it used to crash the run ("boundary point left the grid").  Now a
    cube touching the domain's low-x face is driven by those nodes (sticky, 0.02 m/s along y): they carry mass, keep
    their prescribed velocity, and report a finite reaction along +y."""
    X, vol = cube(0.02)
    X = X - [0.02, 0.0, 0.0]  # touching the domain's low-x face x = -0.02
    s = solver_for(X, vol, JELLY, padding=2, domain_lo=[-0.02, -0.01, -0.01], domain_hi=[0.02, 0.03, 0.03],
                   gravity=[0, 0, 0], floor=False, velocities=np.tile([-0.05, 0, 0], (len(X), 1)))
    g32 = (np.float32(s.lo[0] + DX) - np.float32(s.lo[0])) * np.float32(1 / DX)  # the kernel's float32 coordinate
    assert g32 == np.float32(0.99999976)
    j, k = np.meshgrid(np.arange(s.dims[1]), np.arange(s.dims[2]), indexing="ij")
    layer1 = np.stack([np.ones(j.size, int), j.ravel(), k.ravel()], axis=1)
    st = s.step_frame(1 / 60, dirichlet=DirichletNodes(layer1, np.tile([0.0, 0.02, 0.0], (len(layer1), 1))))
    g = s.grid_a.numpy()[1]
    massive = g[..., 3] > 0
    assert massive.sum() > 10
    np.testing.assert_allclose(g[massive][:, :3], np.tile([0.0, 0.02, 0.0], (int(massive.sum()), 1)), atol=1e-7)
    assert np.isfinite(st.reaction).all() and st.reaction[0, 1] > 0  # the nodes drag the material along +y


@pytest.mark.parametrize("follow", ["tracers", "particles"])
def test_force_patch_follows_moving_material(follow):
    """A free block gliding 2.5 block sides in the frame, pushed along its motion through its top layer, as tracers
    (the skin's points) or as the particles themselves (the stuffing beneath a torn finger): the push follows it
    (closed form P = M v0 + F T; every particle near v0 + F T / M).  (The same points fixed in space: the block
    slid out from under them at t = 55 ms, the force went to the fringe mass left under them and the step
    collapsed, dt 1.5e-9 s at 1.7e6 m/s.)"""
    side, h, v0, fdt = 0.02, DX / 2, 0.5, 1 / 10  # m, m, m/s, s: 5 cm in the frame = 10 cells
    X = lattice([0, 0, 0], [side, side, side], h)
    top = np.flatnonzero(X[:, 2] > side - h)
    s = solver_for(X, h ** 3, JELLY, velocities=np.tile([v0, 0.0, 0.0], (len(X), 1)), gravity=[0, 0, 0],
                   floor=False, tracers=X[top], margin_cells=40)
    m = s.masses().astype(np.float64)
    F = np.array([[0.2 * m.sum(), 0.0, 0.0]])  # N: 0.2 m/s^2
    points = {"tracers": np.arange(len(top))} if follow == "tracers" else {"particles": top}
    with pytest.raises(ValueError, match="tracers or particles, not both"):
        s.step_frame(fdt, forces=ForcePatch(X[top], np.zeros(len(top), int), F, tracers=points.get("tracers", top),
                                            particles=top))
    with pytest.raises(ValueError, match="one index"):
        s.step_frame(fdt, forces=ForcePatch(X[top], np.zeros(len(top), int), F, particles=top + len(X)))
    st = s.step_frame(fdt, forces=ForcePatch(X[top], np.zeros(len(top), int), F, **points))
    v = s.velocities().astype(np.float64)
    np.testing.assert_allclose(st.applied_force[0], F[0], rtol=1e-4)
    np.testing.assert_allclose((m[:, None] * v).sum(0), m.sum() * np.array([v0, 0, 0]) + F[0] * fdt, rtol=1e-3,
                               atol=1e-6 * m.sum() * v0)
    assert np.abs(v[:, 0] - (v0 + 0.2 * fdt)).max() < 0.05  # the soft block rings: +-0.02 m/s
