"""The screen-space liquid's normals and shading as Warp kernels (tasks.generation.liquid_kernels): bit for bit the
numpy formulation they replaced (kept below as the reference) on random inputs, a flat plane's normals and the
shading at a sphere's centre in closed form."""
from dataclasses import replace

import cv2
import numpy as np
import pytest

from tasks.generation.fluid_render import COLA, JUICE, normals_from_depth, shade_liquid

H, W, FOCAL = 40, 56, 90.0
K = np.array([[FOCAL, 0.0, W / 2 + 0.3], [0.0, FOCAL * 1.1, H / 2 - 0.2], [0.0, 0.0, 1.0]])


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _one_sided_reference(pos, covered, axis, step):
    forward, backward = np.zeros_like(pos), np.zeros_like(pos)
    ok_f, ok_b = np.zeros_like(covered), np.zeros_like(covered)
    lo = (slice(None), slice(0, -1)) if axis == 1 else (slice(0, -1), slice(None))
    hi = (slice(None), slice(1, None)) if axis == 1 else (slice(1, None), slice(None))
    forward[lo] = pos[hi] - pos[lo]
    ok_f[lo] = covered[hi]
    backward[hi] = pos[hi] - pos[lo]
    ok_b[hi] = covered[lo]
    cost_f = np.where(ok_f, np.abs(forward[..., 2]), np.inf)
    cost_b = np.where(ok_b, np.abs(backward[..., 2]), np.inf)
    chosen = np.where((cost_f <= cost_b)[..., None], forward, backward)
    return np.where((ok_f | ok_b)[..., None], chosen, step)


def _normals_reference(depth, covered, K):
    """The numpy ``normals_from_depth`` before the kernel (issue 51)."""
    height, width = depth.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = np.where(covered, depth, 1.0)
    x = (np.arange(width) + 0.5 - cx) / fx * z
    y = (np.arange(height)[:, None] + 0.5 - cy) / fy * z
    pos = np.stack([x, y, z], axis=-1)
    step_x = np.stack([z / fx, np.zeros_like(z), np.zeros_like(z)], axis=-1)
    step_y = np.stack([np.zeros_like(z), z / fy, np.zeros_like(z)], axis=-1)
    ddx = _one_sided_reference(pos, covered, 1, step_x)
    ddy = _one_sided_reference(pos, covered, 0, step_y)
    normal = -_unit(np.cross(ddx, ddy))
    return np.where(covered[..., None], normal, np.array([0.0, 0.0, -1.0]))


def _shade_reference(background_rgb, depth, thickness, normal, surface_depth, K, appearance, fade_thickness_m):
    """The numpy ``shade_liquid`` before the kernels (issue 51)."""
    height, width = depth.shape
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    shaded = np.isfinite(depth)
    z = np.where(shaded, depth, 1.0)
    t = thickness[..., None]
    gap = np.clip(np.where(np.isfinite(surface_depth), surface_depth - z, np.inf), 0.0, appearance.max_refraction_gap_m)
    shift_m = (1.0 - 1.0 / appearance.ior) * (thickness + gap)
    map_x = (np.arange(width, dtype=np.float32) - fx * normal[..., 0] * shift_m / z).astype(np.float32)
    map_y = (np.arange(height, dtype=np.float32)[:, None] - fy * normal[..., 1] * shift_m / z).astype(np.float32)
    refracted = cv2.remap(background_rgb.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)
    sigma = np.asarray(appearance.absorption_per_m)
    transmittance = np.exp(-sigma * t)
    turbid = appearance.turbidity * (1.0 - np.exp(-sigma.mean() * t))
    light = _unit(np.asarray(appearance.light_direction, np.float64))
    n_dot_l = np.clip(normal @ light, 0.0, None)[..., None]
    lit_body = np.asarray(appearance.body_colour) * (appearance.ambient + (1.0 - appearance.ambient) * n_dot_l)
    body = (1.0 - turbid) * transmittance * refracted + turbid * lit_body
    view = -_unit(np.stack([(np.arange(width) + 0.5 - cx) / fx * np.ones((height, 1)),
                            (np.arange(height)[:, None] + 0.5 - cy) / fy * np.ones((1, width)),
                            np.ones((height, width))], axis=-1))
    n_dot_v = np.clip(np.sum(normal * view, axis=-1), 0.0, 1.0)[..., None]
    fade = 1.0 - np.exp(-t / fade_thickness_m)
    f0 = ((appearance.ior - 1.0) / (appearance.ior + 1.0)) ** 2
    fresnel = fade * (f0 + (1.0 - f0) * (1.0 - n_dot_v) ** 5)
    reflected = 2.0 * n_dot_v * normal - view
    up = np.clip(-reflected[..., 1:2], 0.0, 1.0)
    horizon, zenith = np.asarray(appearance.sky_horizon), np.asarray(appearance.sky_zenith)
    sky = horizon + (zenith - horizon) * up
    half = _unit(view + light)
    specular = fade * appearance.specular * np.clip(np.sum(normal * half, axis=-1), 0.0, None)[..., None] ** \
        appearance.shininess
    rgb = (1.0 - fresnel) * body + fresnel * sky + specular
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def _bumpy_liquid(rng, dtype):
    """A rough depth field (m) over a blotchy coverage with holes, isolated pixels and the image border."""
    covered = cv2.GaussianBlur(rng.uniform(0, 1, (H, W)), (0, 0), 2.0) > 0.5
    covered[rng.uniform(0, 1, (H, W)) < 0.05] ^= True
    covered[0, :], covered[:, -1] = True, True
    depth = 0.4 + 0.05 * cv2.GaussianBlur(rng.normal(0, 1, (H, W)), (0, 0), 1.5) + rng.normal(0, 2e-4, (H, W))
    return np.where(covered, depth, np.inf).astype(dtype), covered


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_normals_equal_the_numpy_formulation_bit_for_bit(dtype):
    rng = np.random.default_rng(7)
    depth, covered = _bumpy_liquid(rng, dtype)
    assert 0.2 < covered.mean() < 0.8
    normal = normals_from_depth(depth, covered, K)
    expected = _normals_reference(depth, covered, K)
    assert normal.dtype == np.float64 and normal.shape == (H, W, 3)
    assert np.array_equal(normal, expected)
    assert np.allclose(np.linalg.norm(normal, axis=-1), 1.0) and (normal[..., 2] < 0).mean() > 0.95


@pytest.mark.parametrize("appearance", [JUICE, COLA], ids=["juice", "cola"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_shading_equals_the_numpy_formulation_bit_for_bit(appearance, dtype):
    rng = np.random.default_rng(11)
    depth, covered = _bumpy_liquid(rng, dtype)
    normal = normals_from_depth(depth, covered, K)
    thickness = np.where(covered, rng.uniform(0.0, 0.02, (H, W)), 0.0)
    surface = (0.42 + rng.uniform(-0.05, 0.08, (H, W))).astype(dtype)  # in front of and behind the liquid
    surface[rng.uniform(0, 1, (H, W)) < 0.3] = np.inf
    background = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    rgb = shade_liquid(background, depth, thickness, normal, surface, K, appearance, fade_thickness_m=0.004)
    expected = _shade_reference(background, depth, thickness, normal, surface, K, appearance, 0.004)
    assert rgb.dtype == np.float32 and rgb.shape == (H, W, 3)
    assert np.array_equal(rgb, expected)
    assert rgb[covered].std() > 0.01  # not a flat colour: the inputs vary


def test_a_flat_plane_facing_the_camera_has_normal_minus_z_up_to_its_border():
    depth = np.full((H, W), 0.5)
    covered = np.zeros((H, W), bool)
    covered[5:30, 10:40] = True
    covered[35, 3:50] = True  # a one-pixel row: no neighbour above or below, the flat footprint z / fy
    covered[2:20, 50] = True  # a one-pixel column: no neighbour left or right, the flat footprint z / fx
    normal = normals_from_depth(depth, covered, K)
    # positions ((x + 0.5 - cx) / fx z, (y + 0.5 - cy) / fy z, z): ddx = (z / fx, 0, 0), ddy = (0, z / fy, 0)
    np.testing.assert_allclose(normal[covered], np.broadcast_to([0.0, 0.0, -1.0], (covered.sum(), 3)), atol=1e-12)
    assert np.array_equal(normal[~covered], np.broadcast_to([0.0, 0.0, -1.0], ((~covered).sum(), 3)))


def test_the_shading_at_a_spheres_centre_has_its_closed_form():
    # a drop on the optical axis: at its centre pixel (cx, cy on that pixel's centre) n = (0, 0, -1) = v, so
    # F = fade f0, the reflected ray goes back along -z (sky = horizon), n.l = -l_z, h = unit(v + l)
    appearance = replace(JUICE, turbidity=0.4)
    k = np.array([[FOCAL, 0.0, 20.5], [0.0, FOCAL, 15.5], [0.0, 0.0, 1.0]])
    z0, r = 0.5, 0.03
    u = (np.arange(W) + 0.5 - k[0, 2]) / FOCAL
    v = (np.arange(H)[:, None] + 0.5 - k[1, 2]) / FOCAL
    d2 = u * u + v * v + 1.0
    disc = z0 * z0 - d2 * (z0 * z0 - r * r)
    covered = disc > 0
    t_front = (z0 - np.sqrt(np.where(covered, disc, 0.0))) / d2
    depth = np.where(covered, t_front, np.inf)
    chord = np.where(covered, 2.0 * np.sqrt(np.where(covered, disc, 0.0)) / d2 * np.sqrt(d2), 0.0)
    p = np.stack([u * t_front, v * t_front, t_front], -1)
    normal = np.where(covered[..., None], _unit(p - [0.0, 0.0, z0]), [0.0, 0.0, -1.0])  # the sphere's own normals
    assert np.array_equal(normal[15, 20], [0.0, 0.0, -1.0])
    grey = np.full((H, W, 3), 0.3, np.float32)
    fade_m = 0.01
    rgb = shade_liquid(grey, depth, chord, normal, np.full((H, W), np.inf), k, appearance, fade_m)
    t = 2.0 * r
    light = np.asarray(appearance.light_direction) / np.linalg.norm(appearance.light_direction)
    sigma = np.asarray(appearance.absorption_per_m)
    beta = appearance.turbidity * (1.0 - np.exp(-sigma.mean() * t))
    body = (1.0 - beta) * np.exp(-sigma * t) * 0.3 + beta * np.asarray(appearance.body_colour) * (
        appearance.ambient + (1.0 - appearance.ambient) * max(-light[2], 0.0))
    fade = 1.0 - np.exp(-t / fade_m)
    fresnel = fade * ((appearance.ior - 1.0) / (appearance.ior + 1.0)) ** 2
    half = (np.array([0.0, 0.0, -1.0]) + light) / np.linalg.norm(np.array([0.0, 0.0, -1.0]) + light)
    specular = fade * appearance.specular * max(-half[2], 0.0) ** appearance.shininess
    expected = (1.0 - fresnel) * body + fresnel * np.asarray(appearance.sky_horizon) + specular
    np.testing.assert_allclose(rgb[15, 20], np.clip(expected, 0.0, 1.0), atol=1e-6)
