"""Ellipsoid impostors drawn by the Warp kernel (tasks.generation.impostor_kernels): a sphere's closed form, and every
pixel of a small scene against a brute-force ray-ellipsoid intersection of every (pixel, ellipsoid) pair."""
import numpy as np
import pytest

from tasks.generation.impostors import splat_ellipsoid_impostors

SIZE, FOCAL = 48, 80.0
K = np.array([[FOCAL, 0.0, SIZE / 2], [0.0, FOCAL, SIZE / 2], [0.0, 0.0, 1.0]])
VIEW = np.eye(4)  # camera = world: x right, y down, z forward


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.diag(r))


def _brute_force(centres, axes, radii, surface_depth):
    """Every pixel-centre ray t d, d = ((x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, 1), against every ellipsoid
    (x - c)^T A (x - c) = 1 with A = Q diag(r^-2) Q^T, no screen boxes: the nearest front in front of the surface
    and the sum of the chords |d| (t2 - t1) of the ellipsoids whose front is in front of it."""
    ys, xs = np.mgrid[:SIZE, :SIZE]
    d = np.stack([(xs + 0.5 - K[0, 2]) / K[0, 0], (ys + 0.5 - K[1, 2]) / K[1, 1], np.ones((SIZE, SIZE))], -1)
    depth, thickness = np.full((SIZE, SIZE), np.inf), np.zeros((SIZE, SIZE))
    for c, q, r in zip(centres, axes, radii):
        A = q @ np.diag(r ** -2.0) @ q.T
        a = np.einsum("yxi,ij,yxj->yx", d, A, d)
        b = d @ (A @ c)
        disc = b * b - a * (c @ A @ c - 1.0)
        root = np.sqrt(np.clip(disc, 0.0, None))
        front = (b - root) / a
        seen = (disc > 0) & (front > 1e-3) & (front < surface_depth)
        depth = np.where(seen, np.minimum(depth, front), depth)
        thickness += np.where(seen, 2.0 * root / a * np.linalg.norm(d, axis=-1), 0.0)
    return depth, thickness


def test_a_sphere_on_the_axis_gives_its_front_and_diameter():
    z, r = 0.5, 0.05  # screen radius f r / z = 8 px around the image centre (a pixel corner)
    depth, thickness, radius_px = splat_ellipsoid_impostors(np.array([[0.0, 0.0, z]]), np.eye(3)[None],
                                                            np.full((1, 3), r), VIEW, K, np.full((SIZE, SIZE), np.inf))
    # the four pixels round the centre: ray t d, |d|^2 = 1 + 2 (0.5 / f)^2, meets |t d - (0, 0, z)| = r at
    # t = (z -+ sqrt(z^2 - |d|^2 (z^2 - r^2))) / |d|^2
    d2 = 1.0 + 2 * (0.5 / FOCAL) ** 2
    root = np.sqrt(z * z - d2 * (z * z - r * r))
    assert depth[23:25, 23:25] == pytest.approx(np.full((2, 2), (z - root) / d2), abs=1e-12)
    assert thickness[23:25, 23:25] == pytest.approx(np.full((2, 2), 2 * root / np.sqrt(d2)), abs=1e-12)
    assert depth.min() == depth[23, 23] > z - r  # no pixel centre on the axis itself
    assert radius_px == pytest.approx(FOCAL * r / (z - r))
    covered = np.isfinite(depth)
    assert np.sqrt(covered.sum() / np.pi) == pytest.approx(FOCAL * r / z, rel=0.05)
    assert (thickness[~covered] == 0).all() and (thickness[covered] > 0).all()


def test_every_pixel_matches_a_brute_force_intersection():
    rng = np.random.default_rng(3)
    n = 24
    centres = np.column_stack([rng.uniform(-0.15, 0.15, n), rng.uniform(-0.15, 0.15, n), rng.uniform(0.45, 0.7, n)])
    axes = np.stack([_rotation(rng) for _ in range(n)])
    radii = rng.uniform(0.005, 0.06, (n, 3))  # needles to discs, many overlapping
    surface = np.full((SIZE, SIZE), np.inf)
    surface[:, : SIZE // 2] = 0.55  # an object surface across the left half hides what lies behind it
    depth, thickness, _ = splat_ellipsoid_impostors(centres, axes, radii, VIEW, K, surface)
    expected_depth, expected_thickness = _brute_force(centres, axes, radii, surface)
    covered = np.isfinite(expected_depth)
    assert 0.2 < covered.mean() < 0.9 and (thickness > 2 * radii.max()).any()  # overlaps summed, background left
    assert np.array_equal(np.isfinite(depth), covered)  # no screen box cuts an ellipsoid
    assert np.abs(depth[covered] - expected_depth[covered]).max() <= 1e-12
    assert np.abs(thickness - expected_thickness).max() <= 1e-12
    assert (depth[covered] < surface[covered]).all()
