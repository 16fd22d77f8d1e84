"""Weight-free secondary-effect backend: sphere impostors, screen-space fluid shading, strands, composite."""
from dataclasses import replace

import numpy as np
import pytest

from tasks.generation.fluid_render import (
    COLA,
    JUICE,
    LiquidAppearance,
    normals_from_depth,
    render_liquid,
    shade_liquid,
    smooth_depth,
)
from tasks.generation.impostors import project_particles, splat_sphere_impostors
from tasks.generation.physics_effect import appearance_for_effect, composite_effect, render_effect
from tasks.generation.strand_render import STUFFING, StuffingAppearance, render_stuffing, strand_polylines

SIZE, FOCAL = 64, 100.0
K = np.array([[FOCAL, 0.0, SIZE / 2], [0.0, FOCAL, SIZE / 2], [0.0, 0.0, 1.0]])
VIEW = np.eye(4)
NO_SURFACE = np.full((SIZE, SIZE), np.inf)
GREY = np.full((SIZE, SIZE, 3), 0.5, np.float32)


def _on_pixel_centre(z: float, col: int = 32, row: int = 32) -> np.ndarray:
    """World position (camera = world) at depth z projecting onto the centre (col + 0.5, row + 0.5)."""
    return np.array([[(col + 0.5 - K[0, 2]) * z / FOCAL, (row + 0.5 - K[1, 2]) * z / FOCAL, z]])


def test_sphere_impostor_depth_thickness_and_disc_radius():
    z, r = 0.5, 0.05  # screen radius f r / z = 10 px
    depth, thickness = splat_sphere_impostors(project_particles(_on_pixel_centre(z), r, VIEW, K), NO_SURFACE)
    assert depth[32, 32] == pytest.approx(z - r, abs=1e-12)
    assert thickness[32, 32] == pytest.approx(2 * r, abs=1e-12)
    covered = np.isfinite(depth)
    assert np.sqrt(covered.sum() / np.pi) == pytest.approx(FOCAL * r / z, abs=0.15)
    yy, xx = np.nonzero(covered)
    assert np.hypot(yy - 32, xx - 32).max() < FOCAL * r / z
    assert not covered[32, 32 + 11] and covered[32, 32 + 9]
    assert (thickness[~covered] == 0).all() and (thickness[covered] > 0).all()


def test_overlapping_impostors_z_buffer_the_front_and_sum_the_chords():
    positions = np.concatenate([_on_pixel_centre(0.5), _on_pixel_centre(0.6)])
    depth, thickness = splat_sphere_impostors(project_particles(positions, 0.02, VIEW, K), NO_SURFACE)
    assert depth[32, 32] == pytest.approx(0.48, abs=1e-12)
    assert thickness[32, 32] == pytest.approx(0.08, abs=1e-12)


def test_a_particle_behind_the_object_surface_is_hidden():
    position, r = _on_pixel_centre(0.5), 0.02
    wall = np.full((SIZE, SIZE), 0.45)  # the object's surface, in front of the particle
    for kind in ("liquid", "stuffing"):
        hidden = render_effect(kind, position, r, VIEW, K, GREY, wall)
        assert hidden.coverage.max() == 0 and np.array_equal(hidden.rgb, GREY)
        seen = render_effect(kind, position, r, VIEW, K, GREY, np.full((SIZE, SIZE), 0.6))
        assert seen.coverage.max() > 0.5
        front = 0.5 - r if kind == "liquid" else 0.5  # the sphere's front (then smoothed) or the strands' particle
        assert front - 1e-6 <= seen.depth[32, 32] < 0.5 + 1e-6


def test_beer_lambert_on_a_flat_slab_has_the_known_transmittance():
    clear = replace(JUICE, turbidity=0.0, specular=0.0, sky_zenith=(0, 0, 0), sky_horizon=(0, 0, 0))
    thin, thick = 0.002, 0.006
    thickness = np.full((SIZE, SIZE), thin)
    thickness[:, SIZE // 2:] = thick
    normal = np.broadcast_to(np.array([0.0, 0.0, -1.0]), (SIZE, SIZE, 3))
    rgb = shade_liquid(np.ones((SIZE, SIZE, 3), np.float32), np.full((SIZE, SIZE), 0.5), thickness, normal,
                       NO_SURFACE, K, clear, fade_thickness_m=1e-9)
    ratio = rgb[:, SIZE // 2 + 3].astype(np.float64) / rgb[:, SIZE // 2 - 3]  # the same view angle per row pair
    expected = np.exp(-np.array(clear.absorption_per_m) * (thick - thin))
    np.testing.assert_allclose(ratio[SIZE // 2], expected, rtol=1e-5)
    assert (rgb[:, SIZE // 2:] < rgb[:, : SIZE // 2].mean(axis=1, keepdims=True)).all()  # thicker is darker


def test_a_bigger_droplet_is_darker_at_its_centre_by_beer_lambert():
    clear = LiquidAppearance(absorption_per_m=(20.0, 60.0, 120.0), body_colour=(0, 0, 0), turbidity=0.0,
                             specular=0.0, sky_zenith=(0, 0, 0), sky_horizon=(0, 0, 0))
    white = np.ones((SIZE, SIZE, 3), np.float32)
    small = render_liquid(_on_pixel_centre(0.5), 0.01, VIEW, K, white, NO_SURFACE, clear).rgb[32, 32]
    large = render_liquid(_on_pixel_centre(0.5), 0.02, VIEW, K, white, NO_SURFACE, clear).rgb[32, 32]
    expected = np.exp(-np.array(clear.absorption_per_m) * 2 * (0.02 - 0.01))  # centre chords 2 r
    np.testing.assert_allclose(large / small, expected, rtol=1e-2)


def test_liquid_leaves_the_background_outside_its_coverage_and_is_deterministic():
    rng = np.random.default_rng(1)
    background = rng.uniform(0, 1, (SIZE, SIZE, 3)).astype(np.float32)
    positions = _on_pixel_centre(0.5) + rng.normal(0, 0.02, (40, 3))
    for appearance in (JUICE, COLA):
        first = render_liquid(positions, 0.006, VIEW, K, background, NO_SURFACE, appearance)
        again = render_liquid(positions, 0.006, VIEW, K, background, NO_SURFACE, appearance)
        outside = first.coverage == 0
        assert 0 < outside.mean() < 1
        assert np.array_equal(first.rgb[outside], background[outside])
        for a, b in zip(first, again):
            assert np.array_equal(a, b)
        assert np.isinf(first.depth[outside]).all() and np.isfinite(first.depth[~outside]).all()


def test_bilateral_smoothing_keeps_the_silhouette_depth():
    rng = np.random.default_rng(2)
    covered = np.zeros((SIZE, SIZE), bool)
    covered[16:48, 16:48] = True
    depth = np.where(covered, 0.5 + rng.normal(0, 0.002, covered.shape), np.inf)
    smoothed = smooth_depth(depth, covered, 0.004, 2.0, 3)
    assert np.isinf(smoothed[~covered]).all()
    assert smoothed[covered].max() <= depth[covered].max() + 1e-6  # the far background did not bleed in
    assert smoothed[covered].std() < 0.5 * depth[covered].std()


def test_normals_of_a_tilted_plane_are_exact_up_to_its_silhouette():
    plane = np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])  # faces the camera (n_z < 0)
    offset = plane @ np.array([0.0, 0.0, 0.5])  # passes through (0, 0, 0.5)
    ray_x = (np.arange(SIZE) + 0.5 - K[0, 2]) / FOCAL
    ray_y = (np.arange(SIZE)[:, None] + 0.5 - K[1, 2]) / FOCAL
    depth = offset / (plane[0] * ray_x + plane[1] * ray_y + plane[2])
    covered = np.zeros((SIZE, SIZE), bool)
    covered[10:50, 20:40] = True
    covered[30, 45] = True  # an isolated pixel: no neighbour, gets the fallback facing the camera
    normal = normals_from_depth(depth, covered, K)
    np.testing.assert_allclose(normal[10:50, 20:40], np.broadcast_to(plane, (40, 20, 3)), atol=1e-9)
    np.testing.assert_allclose(normal[30, 45], [0, 0, -1], atol=1e-12)


def test_composite_leaves_outside_mask_pixels_bit_identical():
    rng = np.random.default_rng(3)
    sim = rng.uniform(0, 1, (2, SIZE, SIZE, 3)).astype(np.float32)  # (frame, y, x, channel)
    effect = rng.uniform(0, 1, sim.shape).astype(np.float32)
    mask = np.zeros(sim.shape[:-1], bool)
    mask[:, 20:40, 10:30] = True
    out = composite_effect(sim, effect, mask)
    assert np.array_equal(out[~mask], sim[~mask]) and np.array_equal(out[mask], effect[mask])
    soft = np.where(mask, 0.25, 0.0)
    blended = composite_effect(sim, effect, soft)
    assert np.array_equal(blended[~mask], sim[~mask])
    np.testing.assert_allclose(blended[mask], 0.75 * sim[mask] + 0.25 * effect[mask], atol=1e-6)
    with pytest.raises(ValueError, match="refined_mask"):
        composite_effect(sim, effect, mask[0])


def test_strands_stay_near_their_particle_and_are_deterministic():
    z, r = 0.5, 0.008  # 1.6 px screen radius
    frame = render_stuffing(_on_pixel_centre(z), r, VIEW, K, GREY, NO_SURFACE, seed=5)
    bound = FOCAL * r / z * (0.6 + STUFFING.strand_length_radii) + STUFFING.line_width_px + 1.5
    yy, xx = np.nonzero(frame.coverage > 0)
    assert len(yy) > 10
    assert np.hypot(yy + 0.5 - 32.5, xx + 0.5 - 32.5).max() <= bound
    again = render_stuffing(_on_pixel_centre(z), r, VIEW, K, GREY, NO_SURFACE, seed=5)
    for a, b in zip(frame, again):
        assert np.array_equal(a, b)
    other_seed = render_stuffing(_on_pixel_centre(z), r, VIEW, K, GREY, NO_SURFACE, seed=6)
    assert not np.array_equal(frame.coverage, other_seed.coverage)


def test_strands_follow_their_particle_between_frames():
    z, r = 0.5, 0.008
    positions = np.concatenate([_on_pixel_centre(z, col=c, row=20 + 3 * c % 20) for c in range(10, 50, 5)])
    particles = project_particles(positions, r, VIEW, K)
    strands = strand_polylines(particles, STUFFING, seed=0)
    moved = project_particles(positions[2:] + np.array([2 * z / FOCAL, 0.0, 0.0]), r, VIEW, K)
    moved = replace(moved, index=moved.index + 2)  # the same particles, the first two no longer released
    shifted = strand_polylines(moved, STUFFING, seed=0)
    np.testing.assert_allclose(shifted, strands[2:] + np.array([2.0, 0.0]), atol=1e-9)


def test_stuffing_is_cream_and_casts_a_shadow():
    appearance = StuffingAppearance(shade_variation=0.0)
    frame = render_stuffing(_on_pixel_centre(0.5), 0.01, VIEW, K, GREY, NO_SURFACE, appearance)
    solid = frame.coverage > 0.99
    np.testing.assert_allclose(frame.rgb[solid], np.broadcast_to(appearance.colour, (solid.sum(), 3)), atol=1 / 255)
    shadowed = (frame.coverage == 0) & (frame.rgb[..., 0] < 0.5 - 1e-3)
    assert shadowed.sum() > 5 and (frame.rgb[frame.coverage == 0] <= 0.5).all()


def test_dispatcher_rejects_unknown_kinds_and_wrong_appearances():
    with pytest.raises(ValueError, match="kind"):
        render_effect("smoke", _on_pixel_centre(0.5), 0.01, VIEW, K, GREY, NO_SURFACE)
    with pytest.raises(ValueError, match="LiquidAppearance"):
        render_effect("liquid", _on_pixel_centre(0.5), 0.01, VIEW, K, GREY, NO_SURFACE, appearance=STUFFING)
    assert appearance_for_effect("cola_spray") == ("liquid", COLA)
    with pytest.raises(ValueError, match="rebound"):
        appearance_for_effect("rebound")
