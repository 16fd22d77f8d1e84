"""Eq. 6 conditions: mask refinement R(.) on masks with known defects, and the gated normalised depth."""
import numpy as np
import pytest

from tasks.render.conditions import gated_depth, normalise_depth, refine_mask, scale_refinement_pixels

H = W = 128


def _disc(radius: float, centre=(64.0, 64.0)) -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 <= radius ** 2


def _boundary_distance(mask: np.ndarray) -> np.ndarray:
    """Per pixel, distance (px) to the boundary of ``mask`` (a disc of radius 30 at (64, 64))."""
    yy, xx = np.mgrid[0:H, 0:W]
    return np.abs(np.hypot(yy - 64.0, xx - 64.0) - 30.0)


def test_isolated_speckles_are_removed_and_the_disc_is_kept():
    clean = _disc(30)
    rng = np.random.default_rng(0)
    noisy = clean.copy()
    ys, xs = rng.integers(0, H, 60), rng.integers(0, W, 60)
    outside = ~_disc(34)[ys, xs]
    noisy[ys[outside], xs[outside]] = True  # single-pixel speckles away from the disc
    refined = refine_mask(noisy, min_component_px=12, closing_radius_px=2)
    assert noisy.sum() > clean.sum() + 40
    np.testing.assert_array_equal(refined, clean)


def test_a_hole_is_filled():
    holed = _disc(30) & ~_disc(8, centre=(60.0, 66.0))
    refined = refine_mask(holed, min_component_px=12, closing_radius_px=0)
    np.testing.assert_array_equal(refined, _disc(30))
    assert not refine_mask(holed, min_component_px=12, closing_radius_px=0, fill_holes=False)[60, 66]


def test_a_ragged_edge_is_closed_to_the_clean_disc():
    clean = _disc(30)
    yy, xx = np.mgrid[0:H, 0:W]
    angle = np.arctan2(yy - 64.0, xx - 64.0)
    radius = np.hypot(yy - 64.0, xx - 64.0)
    notch = (np.floor((angle + np.pi) / (2 * np.pi) * 90).astype(int) % 3 == 0)  # 30 notches ~2 px wide
    ragged = clean & ~(notch & (radius > 26.5))  # notches 3.5 px deep
    refined = refine_mask(ragged, min_component_px=12, closing_radius_px=2)
    missing_before = (clean & ~ragged).sum()
    wrong_after = refined ^ clean
    assert missing_before > 150
    assert wrong_after.sum() < 0.2 * missing_before  # the residue: single pixels on the discrete rim
    assert (_boundary_distance(clean)[wrong_after] <= 1.5).all()


def test_components_at_or_above_the_size_are_kept_exactly():
    mask = np.zeros((H, W), bool)
    mask[10:15, 10:16] = True  # 30 px, kept
    mask[40:44, 40:45] = True  # 20 px, dropped
    mask[80:81, 80:100] = True  # 20 px line, dropped
    refined = refine_mask(mask, min_component_px=25, closing_radius_px=2)
    expected = np.zeros_like(mask)
    expected[10:15, 10:16] = True
    np.testing.assert_array_equal(refined, expected)


def test_empty_mask_stays_empty_and_shape_is_kept_per_frame():
    stack = np.zeros((3, H, W), np.float32)
    stack[1] = _disc(20) * 0.9  # float weights above the threshold
    stack[2] = _disc(20) * 0.3  # below the threshold
    refined = refine_mask(stack)
    assert refined.shape == stack.shape and refined.dtype == bool
    assert not refined[0].any() and not refined[2].any()
    np.testing.assert_array_equal(refined[1], _disc(20))


def test_bad_mask_shape_is_a_value_error():
    with pytest.raises(ValueError, match="mask"):
        refine_mask(np.zeros((2, 3, 4, 5)))


def test_pixel_parameters_scale_with_resolution():
    assert scale_refinement_pixels(256, 12, 2) == (12, 2)
    assert scale_refinement_pixels(512, 12, 2) == (48, 4)
    assert scale_refinement_pixels(128, 12, 2) == (3, 1)


def test_gated_depth_on_a_ramp_is_exact():
    depth = np.tile(np.linspace(1.0, 2.0, W), (H, 1))  # 1 m at the left edge, 2 m at the right
    valid = np.ones_like(depth, bool)
    mask = np.zeros_like(valid)
    mask[:, : W // 2] = True
    gated = gated_depth(depth, valid, mask)
    expected = (1.0 / depth - 0.5) / (1.0 - 0.5)  # inverse depth, near (1 m) -> 1, far (2 m) -> 0
    np.testing.assert_allclose(gated[:, : W // 2], expected[:, : W // 2], atol=1e-6)
    assert (gated[:, W // 2:] == 0).all()
    assert gated[0, 0] == pytest.approx(1.0) and gated.dtype == np.float32


def test_normalise_depth_ranges_invalid_pixels_and_fixed_range():
    depth = np.stack([np.full((4, 4), 1.0), np.full((4, 4), 2.0)])  # frame 0 near, frame 1 far
    alpha = np.ones_like(depth)
    alpha[:, 0, 0] = 0.1  # an empty pixel
    depth[:, 0, 0] = 0.0  # whose depth is meaningless
    seq = normalise_depth(depth, alpha)
    assert seq[0, 1, 1] == pytest.approx(1.0) and seq[1, 1, 1] == pytest.approx(0.0)
    assert seq[0, 0, 0] == 0.0 and seq[1, 0, 0] == 0.0
    per_frame = normalise_depth(depth, alpha, per_frame=True)
    assert per_frame[1, 1, 1] == pytest.approx(1.0)  # one depth per frame: degenerate range -> 1
    fixed = normalise_depth(depth, alpha, depth_range_m=(1.0, 4.0))
    assert fixed[1, 1, 1] == pytest.approx((0.5 - 0.25) / (1.0 - 0.25))
    with pytest.raises(ValueError, match="depth"):
        normalise_depth(depth, np.ones_like(depth, bool))  # a zero depth marked valid
