"""Known-answer tests of SC-CAE (eq. 2, tasks/control/contact_patches.py) and the displacement field (eq. 3,
tasks/control/dirichlet_field.py) on analytic shapes: a Fibonacci sphere, a cylinder and hand-built patches."""
from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from conf.hand import FINGERS
from conf.schema import ContactConfig, DisplacementConfig
from tasks.control.contact_patches import DEFAULT_PAD_RADIUS, contact_patches
from tasks.control.dirichlet_field import constrained_points, dirichlet_field, patch_weight
from tasks.core.artifacts import Array

R_SPHERE = 0.03  # m
S_POINTS = 3000
F = len(FINGERS)


# ----------------------------------------------------------------------------------------------- shapes
def fibonacci_sphere(n: int = S_POINTS, radius: float = R_SPHERE, center=(0.0, 0.0, 0.0)):
    """Sphere samples: points, outward normals, curvature (1/R, 1/R), orthonormal tangents, area 4 pi R^2 / n."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    theta = np.pi * (1.0 + 5.0 ** 0.5) * i
    normals = np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    return dict(
        surface_points=np.asarray(center) + radius * normals,
        surface_normals=normals,
        surface_curvature=np.full((n, 2), 1.0 / radius),
        surface_principal_dirs=np.stack([t1, t2], axis=1),
        surface_area=np.full(n, 4.0 * np.pi * radius ** 2 / n),
    )


def cylinder(radius: float = 0.02, height: float = 0.1, n_theta: int = 63, n_z: int = 50):
    """Side surface of a z-axis cylinder: k1 = 1/R around (circumferential direction), k2 = 0 along z."""
    th, z = np.meshgrid(np.arange(n_theta) * 2 * np.pi / n_theta, (np.arange(n_z) + 0.5) / n_z * height - height / 2)
    th, z = th.ravel(), z.ravel()
    normals = np.stack([np.cos(th), np.sin(th), np.zeros_like(th)], axis=1)
    circ = np.stack([-np.sin(th), np.cos(th), np.zeros_like(th)], axis=1)
    axial = np.tile([0.0, 0.0, 1.0], (th.size, 1))
    k = np.zeros((th.size, 2))
    k[:, 0] = 1.0 / radius
    return dict(
        surface_points=np.stack([radius * np.cos(th), radius * np.sin(th), z], axis=1),
        surface_normals=normals,
        surface_curvature=k,
        surface_principal_dirs=np.stack([circ, axial], axis=1),
        surface_area=np.full(th.size, 2 * np.pi * radius * height / th.size),
    )


def spacing_of(surface) -> float:
    return float(np.sqrt(np.median(surface["surface_area"])))


def controls(T: int, directions, standoff: float = 0.015, radius: float = R_SPHERE, forces=None):
    """Fingertips outside the sphere on rays through its centre: P = (R + standoff) d, a = -d."""
    d = np.asarray(directions, float).reshape(-1, 3)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    P = np.zeros((T, F, 3))
    a = np.zeros((T, F, 3))
    P[:] = (radius + standoff) * d[None, :F] if d.shape[0] >= F else (radius + standoff) * d[0]
    a[:] = -d[None, :F] if d.shape[0] >= F else -d[0]
    c = np.zeros((T, F)) if forces is None else np.asarray(forces, float).reshape(T, F)
    return P, a, c


def run(surface, P, a, c, cfg=None, **kw):
    return {k: v.data for k, v in contact_patches(**surface, fingertip_positions=P, squeeze_directions=a,
                                                  force_coefficients=c, cfg=cfg or ContactConfig(), **kw).items()}


def directional_radius(axes, radii, direction):
    """1-sigma radius of a patch ellipse towards ``direction`` (projected into the patch plane)."""
    e1, e2 = direction @ axes[0], direction @ axes[1]
    t = np.hypot(e1, e2)
    return 1.0 / np.sqrt((e1 / t / radii[0]) ** 2 + (e2 / t / radii[1]) ** 2)


def point_ray_distance(x, p, a):
    v = x - p
    return np.linalg.norm(v - max(v @ a, 0.0) * a)


# ----------------------------------------------------------------------------------------------- eq. 2
@pytest.fixture(scope="module")
def sphere():
    return fibonacci_sphere()


def test_outputs_are_labelled_arrays(sphere):
    P, a, c = controls(3, [1, 0, 0], forces=np.full((3, F), 0.5))
    out = contact_patches(**sphere, fingertip_positions=P, squeeze_directions=a, force_coefficients=c,
                          cfg=ContactConfig())
    expect = {
        "patch_centers": (("frame", "finger", "xyz"), "m", (3, F, 3)),
        "patch_normals": (("frame", "finger", "xyz"), "1", (3, F, 3)),
        "patch_axes": (("frame", "finger", "principal", "xyz"), "1", (3, F, 2, 3)),
        "patch_radii": (("frame", "finger", "principal"), "m", (3, F, 2)),
        "patch_areas": (("frame", "finger"), "m^2", (3, F)),
        "patch_active": (("frame", "finger"), "1", (3, F)),
        "patch_cost": (("frame", "finger"), "1", (3, F)),
    }
    assert set(out) == set(expect)
    for name, (dims, units, shape) in expect.items():
        assert isinstance(out[name], Array)
        assert tuple(out[name].dims) == dims and out[name].units == units and out[name].data.shape == shape
        assert np.all(np.isfinite(out[name].data))
    assert out["patch_active"].data.dtype == bool


@pytest.mark.parametrize("direction", [[1, 2, 3], [0, 0, 1], [-1, 0.3, -0.2], [0.2, -1, 0]])
def test_ray_through_centre_hits_the_surface_head_on(sphere, direction):
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    P, a, c = controls(1, d)
    c[0, 1] = 1.0  # the index finger pushes, the others rest
    out = run(sphere, P, a, c)
    x, n = out["patch_centers"][0, 1], out["patch_normals"][0, 1]
    assert out["patch_active"][0, 1] and not out["patch_active"][0, [0, 2, 3, 4]].any()
    assert point_ray_distance(x, P[0, 1], a[0, 1]) <= spacing_of(sphere)
    assert np.linalg.norm(x - R_SPHERE * d) <= spacing_of(sphere)
    assert abs(np.linalg.norm(x) - R_SPHERE) < 1e-3 * R_SPHERE  # on the surface (quadric refinement)
    assert n @ a[0, 1] < -0.95  # outward normal anti-parallel to the squeeze direction
    axes = out["patch_axes"][0, 1]
    np.testing.assert_allclose(axes @ axes.T, np.eye(2), atol=1e-9)
    np.testing.assert_allclose(axes @ n, 0.0, atol=1e-9)
    # alone on a sphere the patch has the force prior: sigma1 = sigma2 = sigma_max at c = 1 (umbilic point)
    np.testing.assert_allclose(out["patch_radii"][0, 1], ContactConfig().sigma_max, rtol=1e-9)
    np.testing.assert_allclose(out["patch_areas"][0, 1], np.pi * ContactConfig().sigma_max ** 2, rtol=1e-9)


def test_penetrating_fingertip_still_takes_the_near_surface(sphere):
    d = np.array([0.0, 1.0, 0.0])
    P, a, c = controls(1, d, standoff=-0.004)  # fingertip 4 mm inside the object, ray exits at the back
    c[0, 0] = 0.8
    out = run(sphere, P, a, c)
    x = out["patch_centers"][0, 0]
    assert np.linalg.norm(x - R_SPHERE * d) <= spacing_of(sphere)
    assert out["patch_active"][0, 0]


def test_two_fingers_on_the_same_spot_do_not_overlap(sphere):
    d = np.array([0.3, -0.5, 0.8])
    P, a, c = controls(1, d)
    c[0, 1] = c[0, 2] = 1.0  # index and middle aimed at the same point with equal force
    out = run(sphere, P, a, c)
    assert out["patch_active"][0, 1] and out["patch_active"][0, 2]
    x1, x2 = out["patch_centers"][0, 1], out["patch_centers"][0, 2]
    dist = np.linalg.norm(x2 - x1)
    rho1 = directional_radius(out["patch_axes"][0, 1], out["patch_radii"][0, 1], x2 - x1)
    rho2 = directional_radius(out["patch_axes"][0, 2], out["patch_radii"][0, 2], x1 - x2)
    # criterion: centre distance >= 0.9 x the sum of the 1-sigma radii along the line of centres
    assert dist >= 0.9 * (rho1 + rho2), (dist, rho1, rho2)
    assert dist > 2 * spacing_of(sphere)  # they really moved apart, not just shrank to nothing
    assert np.all(out["patch_radii"][0, [1, 2]] >= 0.25 * ContactConfig().sigma_max - 1e-12)
    # overlap made the objective worse than a lone finger's
    lone = run(sphere, P, a, np.where(np.arange(F) == 1, 1.0, 0.0)[None])
    assert out["patch_cost"][0, 1] + out["patch_cost"][0, 2] > 2 * lone["patch_cost"][0, 1]


def test_opposite_fingers_do_not_interact(sphere):
    d = np.array([1.0, 0.2, 0.1])
    P, a, c = controls(1, np.stack([d, -d, d * [0, 1, 1] + [0, 0, 1], d, d]))
    c[0, :2] = 1.0  # thumb and index pinch the sphere from opposite sides
    out = run(sphere, P, a, c)
    np.testing.assert_allclose(out["patch_radii"][0, :2], ContactConfig().sigma_max, rtol=1e-9)
    assert out["patch_normals"][0, 0] @ out["patch_normals"][0, 1] < -0.95


def test_higher_force_gives_larger_patch(sphere):
    forces = np.array([0.05, 0.2, 0.4, 0.6, 0.8, 1.0, 1.3])
    T = forces.size
    P, a, c = controls(T, [0.0, 1.0, 1.0])
    c[:, 2] = forces
    out = run(sphere, P, a, c)
    area = out["patch_areas"][:, 2]
    assert out["patch_active"][:, 2].all()
    assert np.all(np.diff(area[:-1]) > 0)  # strictly increasing up to c = 1
    assert area[-1] == pytest.approx(area[-2])  # the prior saturates at sigma_max for c >= 1
    cfg = ContactConfig()
    r0 = cfg.sigma_min + (cfg.sigma_max - cfg.sigma_min) * np.clip(forces, 0, 1)
    np.testing.assert_allclose(area, np.pi * r0 ** 2, rtol=1e-9)  # sphere: isotropic prior, pi r0^2


def test_zero_force_is_inactive_and_does_not_displace(sphere):
    P, a, c = controls(4, [0, 0, 1])
    c[2, 3] = ContactConfig().activation / 2  # below the activation threshold
    out = run(sphere, P, a, c)
    assert not out["patch_active"].any()
    assert np.all(out["patch_areas"] == 0) and np.all(out["patch_radii"] == 0)
    field = dirichlet_field(sphere["surface_points"], out["patch_centers"], out["patch_normals"],
                            out["patch_axes"], out["patch_radii"], out["patch_active"], c, DisplacementConfig())
    assert np.all(field["displacement"].data == 0)
    assert not field["constrained"].data.any()
    assert np.all(field["finger"].data == -1)


def test_out_of_reach_finger_is_inactive(sphere):
    P, a, c = controls(1, [1, 0, 0])
    P[0, 4] = [0.0, 0.2, 0.0]  # pinky far to the side, pointing past the object
    a[0, 4] = [1.0, 0.0, 0.0]
    c[0, 4] = 1.0
    c[0, 0] = 1.0
    out = run(sphere, P, a, c)
    assert out["patch_active"][0, 0] and not out["patch_active"][0, 4]


def test_penetrating_fingertip_does_not_reach_through_the_object():
    """Two spheres 40 mm apart; the index tip is 4 mm inside the upper one pointing down.  The ray leaves the
    upper sphere and hits the lower one head-on (ray distance 0), but that surface is occluded: the patch must
    stay on the upper sphere where the finger is (behind the tip, 4 mm from it)."""
    upper = fibonacci_sphere()
    lower = fibonacci_sphere(center=(0.0, 0.0, -0.1))
    both = {k: np.concatenate([upper[k], lower[k]]) for k in upper}
    P, a, c = controls(1, [0.0, 0.0, 1.0], standoff=-0.004)
    c[0, 1] = 0.8
    out = run(both, P, a, c)
    assert np.linalg.norm(out["patch_centers"][0, 1] - [0.0, 0.0, R_SPHERE]) <= spacing_of(upper)
    assert out["patch_active"][0, 1]


def test_finger_facing_only_the_back_of_the_surface_is_inactive(sphere):
    # tip 4 mm inside the bottom of the sphere, pointing down and out: the only surface ahead faces away
    P, a, c = controls(1, [0.0, 0.0, 1.0], standoff=-0.004)
    P[0, 2] = [0.0, 0.0, -(R_SPHERE - 0.004)]
    a[0, 2] = [0.0, 0.0, -1.0]
    c[0, 2] = 1.0
    out = run(sphere, P, a, c)
    assert not out["patch_active"][0, 2]
    assert out["patch_normals"][0, 2] @ a[0, 2] < 0  # never placed on a back face
    assert out["patch_areas"][0, 2] == 0


def test_cylinder_patch_is_long_along_the_axis():
    cyl = cylinder(radius=0.02)
    d = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    P, a, c = controls(1, d, radius=0.02)
    c[0, 0] = 0.7
    out = run(cyl, P, a, c)
    axes, radii = out["patch_axes"][0, 0], out["patch_radii"][0, 0]
    long = int(np.argmax(radii))
    assert long == 1 and abs(axes[long] @ [0.0, 0.0, 1.0]) > 0.99  # long axis = cylinder axis
    # known answer of the Hertz-like prior: sigma2/sigma1 = sqrt((1/R + 1/pad) / (1/pad)), sigma1 sigma2 = r0^2
    cfg = ContactConfig()
    r0 = cfg.sigma_min + (cfg.sigma_max - cfg.sigma_min) * 0.7
    aspect = np.sqrt((1 / 0.02 + 1 / DEFAULT_PAD_RADIUS) / (1 / DEFAULT_PAD_RADIUS))
    assert radii[1] / radii[0] == pytest.approx(aspect, rel=1e-9)
    assert radii[0] * radii[1] == pytest.approx(r0 ** 2, rel=1e-9)
    assert np.linalg.norm(out["patch_centers"][0, 0] - 0.02 * d) <= spacing_of(cyl)


def test_temporal_consistency_for_static_input(sphere):
    d = np.array([[0, 0, 1.0], [1.0, 0, 0.3], [1.0, 0.3, 0.3], [1.0, 0.6, 0.3], [1.0, 0.9, 0.3]])
    P, a, c = controls(6, d)
    c[:] = [0.9, 1.0, 1.0, 0.8, 0.6]
    out = run(sphere, P, a, c)
    # frame 0 is a cold start (contested surface goes to the first finger in force order); the warm-started
    # frames continue from it and settle within two frames into a fixed point that is then held exactly
    np.testing.assert_array_equal(out["patch_active"], out["patch_active"][:1].repeat(6, axis=0))
    for name in ("patch_centers", "patch_radii", "patch_axes", "patch_cost"):
        np.testing.assert_allclose(out[name][2:], out[name][2:3].repeat(4, axis=0), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(out["patch_centers"], out["patch_centers"][-1:].repeat(6, axis=0),
                               atol=2 * spacing_of(sphere))
    # and the warm start never makes the frame's objective worse than the cold start
    assert out["patch_cost"][-1].sum() <= out["patch_cost"][0].sum() + 1e-12


def test_invalid_inputs_raise(sphere):
    P, a, c = controls(2, [1, 0, 0])
    c[1, 1] = np.nan
    with pytest.raises(ValueError, match="force_coefficients"):
        run(sphere, P, a, c)
    with pytest.raises(ValueError, match="surface_normals"):
        run({**sphere, "surface_normals": sphere["surface_normals"][:10]}, P, a, np.zeros((2, F)))


# ----------------------------------------------------------------------------------------------- eq. 3
def flat_patch(T=1, force=0.8):
    """One hand-built patch per frame on the plane z = 0: centre 0, normal +z, radii (10 mm, 20 mm)."""
    C = np.zeros((T, F, 3))
    Nn = np.zeros((T, F, 3))
    Nn[..., 2] = 1.0
    U = np.zeros((T, F, 2, 3))
    U[..., 0, 0] = 1.0
    U[..., 1, 1] = 1.0
    R = np.zeros((T, F, 2))
    act = np.zeros((T, F), bool)
    c = np.zeros((T, F))
    R[:, 1] = [0.01, 0.02]
    act[:, 1] = True
    c[:, 1] = force
    return C, Nn, U, R, act, c


def test_displacement_known_answers():
    cfg = DisplacementConfig()
    C, Nn, U, R, act, c = flat_patch()
    pts = np.array([
        [0.0, 0.0, 0.0],  # centre: phi = 1
        [0.005, 0.0, 0.0],  # half sigma1 along axis 0
        [0.0, 0.03, 0.0],  # 1.5 sigma2 along axis 1
        [0.004, 0.01, 0.002],  # mixed, with a normal offset (sigma_n = min sigma = 10 mm)
        [0.03, 0.0, 0.0],  # 3 sigma1: beyond the 2.5 sigma support
        [0.0, 0.0, -0.03],  # far side of a thick body: 3 sigma_n below
    ])
    field = dirichlet_field(pts, C, Nn, U, R, act, c, cfg)
    disp, weight = field["displacement"].data, field["weight"].data
    assert disp.dtype == np.float32 and weight.dtype == np.float32
    q = np.array([0.0, 0.25, 2.25, 0.16 + 0.25 + 0.04, 9.0, 9.0])
    phi = np.where(q <= cfg.support ** 2, np.exp(-0.5 * q), 0.0)
    np.testing.assert_allclose(weight[0], phi, rtol=1e-6)
    inward = np.array([0.0, 0.0, -1.0])
    np.testing.assert_array_equal(disp[0, 0], (cfg.eta * 0.8 * inward).astype(np.float32))  # exactly eta c (-n)
    expect = cfg.eta * 0.8 * phi[:, None] * inward
    expect[phi < cfg.min_weight] = 0.0
    np.testing.assert_allclose(disp[0], expect, rtol=1e-6, atol=1e-12)
    np.testing.assert_array_equal(field["finger"].data[0], np.where(phi >= cfg.min_weight, 1, -1))
    np.testing.assert_allclose(patch_weight(pts, C[0, 1], Nn[0, 1], U[0, 1], R[0, 1], cfg.support), phi, rtol=1e-12)


def test_displacement_at_estimated_patch_centre(sphere):
    P, a, c = controls(1, [0.0, -1.0, 0.5])
    c[0, 0] = 1.2
    out = run(sphere, P, a, c)
    pts = np.concatenate([sphere["surface_points"], out["patch_centers"][0, :1]])
    cfg = DisplacementConfig()
    field = dirichlet_field(pts, out["patch_centers"], out["patch_normals"], out["patch_axes"], out["patch_radii"],
                            out["patch_active"], c, cfg)
    np.testing.assert_allclose(field["displacement"].data[0, -1], cfg.eta * 1.2 * -out["patch_normals"][0, 0],
                               rtol=1e-6)
    assert field["weight"].data[0, -1] == pytest.approx(1.0)
    # every displaced sample moves inwards, the most at the patch
    disp = field["displacement"].data[0, :-1]
    moved = np.linalg.norm(disp, axis=1) > 0
    assert moved.sum() > 10
    assert np.all(np.sum(disp[moved] * sphere["surface_normals"][moved], axis=1) < 0)


def test_superposition_of_two_fingers():
    cfg = dataclasses.replace(DisplacementConfig(), min_weight=0.0)  # keep every point: compare the raw eq. 3
    C, Nn, U, R, act, c = flat_patch()
    C[0, 3] = [0.012, 0.004, 0.0]
    Nn[0, 3] = [0.0, 0.6, 0.8]
    U[0, 3] = [[1.0, 0.0, 0.0], [0.0, 0.8, -0.6]]
    R[0, 3] = [0.015, 0.008]
    c[0, 3] = 1.1
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.03, 0.03, (500, 3)) * [1, 1, 0.2]
    both = act.copy()
    both[0, 3] = True
    only1 = both.copy()
    only1[0, 3] = False
    only3 = both.copy()
    only3[0, 1] = False
    f_both = dirichlet_field(pts, C, Nn, U, R, both, c, cfg)["displacement"].data
    f_1 = dirichlet_field(pts, C, Nn, U, R, only1, c, cfg)["displacement"].data
    f_3 = dirichlet_field(pts, C, Nn, U, R, only3, c, cfg)["displacement"].data
    assert np.abs(f_1).max() > 0 and np.abs(f_3).max() > 0
    np.testing.assert_allclose(f_both, f_1 + f_3, rtol=1e-6, atol=1e-9)


def test_constrained_mask_and_points():
    cfg = DisplacementConfig()
    C, Nn, U, R, act, c = flat_patch(T=2)
    c[1, 1] = 0.3
    g = np.linspace(-0.05, 0.05, 41)
    pts = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), axis=-1).reshape(-1, 3)
    field = dirichlet_field(pts, C, Nn, U, R, act, c, cfg)
    weight, mask = field["weight"].data, field["constrained"].data
    np.testing.assert_array_equal(mask, weight >= np.float32(cfg.min_weight))
    assert mask.any() and not mask.all()
    assert np.all(field["displacement"].data[~mask] == 0)
    assert np.all(field["finger"].data[~mask] == -1) and np.all(field["finger"].data[mask] == 1)
    assert field["finger"].data.dtype == np.int8
    for frame in (0, 1):
        idx, targets = constrained_points(field, frame)
        np.testing.assert_array_equal(idx, np.flatnonzero(mask[frame]))
        np.testing.assert_allclose(targets, pts[idx] + field["displacement"].data[frame, idx], atol=1e-9)
        # also from a loaded artifact's plain arrays, with the rest positions given explicitly
        plain = {k: v.data for k, v in field.items()}
        idx2, targets2 = constrained_points(plain, frame, surface_points=pts)
        np.testing.assert_array_equal(idx2, idx)
        np.testing.assert_allclose(targets2, targets, atol=1e-9)
    # frame 1 pushes less hard: same region, smaller displacement
    assert np.abs(field["displacement"].data[1]).max() < np.abs(field["displacement"].data[0]).max()
    dims = {k: tuple(v.dims) for k, v in field.items()}
    assert dims["displacement"] == ("frame", "point", "xyz") and dims["weight"] == ("frame", "point")


def test_far_face_of_thin_wall_is_not_pushed_when_normals_given():
    C, Nn, U, R, act, c = flat_patch()
    g = np.linspace(-0.02, 0.02, 11)
    top = np.stack(np.meshgrid(g, g, [0.0], indexing="ij"), axis=-1).reshape(-1, 3)
    bottom = top - [0.0, 0.0, 0.002]  # 2 mm wall: well inside sigma_n = 10 mm
    pts = np.concatenate([top, bottom])
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(top), 1)), np.tile([0.0, 0.0, -1.0], (len(top), 1))])
    cfg = DisplacementConfig()
    without = dirichlet_field(pts, C, Nn, U, R, act, c, cfg)["constrained"].data[0]
    withn = dirichlet_field(pts, C, Nn, U, R, act, c, cfg, surface_normals=normals)["constrained"].data[0]
    assert without[len(top):].any()  # geometry alone catches the far face of a thin wall
    assert not withn[len(top):].any() and withn[:len(top)].sum() == without[:len(top)].sum()


# ----------------------------------------------------------------------------------------------- runtime
def test_runtime_90_frames_5_fingers_3000_points(sphere, capsys):
    T = 90
    rng = np.random.default_rng(0)
    dirs = np.array([[-1, 0, 0], [1, 0, 0.6], [1, 0, 0.2], [1, 0, -0.2], [1, 0, -0.6]], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    P = 0.045 * dirs[None] + rng.normal(0.0, 5e-4, (T, F, 3))  # a grasp: thumb opposite four fingers
    a = np.broadcast_to(-dirs, (T, F, 3)).copy()
    c = np.clip(np.sin(np.pi * np.linspace(0, 1, T))[:, None] * [1.2, 1.1, 1.0, 0.8, 0.6], 0, None)
    t0 = time.perf_counter()
    out = run(sphere, P, a, c)
    t1 = time.perf_counter()
    field = dirichlet_field(sphere["surface_points"], out["patch_centers"], out["patch_normals"], out["patch_axes"],
                            out["patch_radii"], out["patch_active"], c, DisplacementConfig(),
                            surface_normals=sphere["surface_normals"])
    t2 = time.perf_counter()
    with capsys.disabled():
        print(f"\n[timing] contact_patches {T} frames x {F} fingers x {S_POINTS} points: {t1 - t0:.3f} s; "
              f"dirichlet_field: {t2 - t1:.3f} s")
    assert out["patch_active"][T // 2].all()
    assert field["constrained"].data[T // 2].any()
    # adjacent fingers on the same side do not overlap much (criterion as in the two-finger test)
    for i, j in ((1, 2), (2, 3), (3, 4)):
        xi, xj = out["patch_centers"][T // 2, i], out["patch_centers"][T // 2, j]
        ri = directional_radius(out["patch_axes"][T // 2, i], out["patch_radii"][T // 2, i], xj - xi)
        rj = directional_radius(out["patch_axes"][T // 2, j], out["patch_radii"][T // 2, j], xi - xj)
        assert np.linalg.norm(xj - xi) >= 0.9 * (ri + rj)
