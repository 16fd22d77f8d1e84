"""The generation conditions of eq. 6 (paper sec. 3.3): the refined particle mask and the gated depth.

    M~ = R(M),    D~ = Norm(D) * M~

``M`` is the composited weight of the released interior material in a G-buffer frame, ``D`` the frame's depth.

* ``R`` (:func:`refine_mask`) is "connectivity checking and boundary repair": threshold, drop connected components
  smaller than a pixel area, close the boundary with an elliptical kernel, fill enclosed holes (OpenCV).
* ``Norm`` (:func:`normalise_depth`) maps depth to what a depth ControlNet was trained on: the annotators of
  ``lllyasviel/sd-controlnet-depth`` and ``control_v11f1p_sd15_depth`` (MiDaS / DPT) output *relative inverse
  depth* min-max scaled to [0, 1], so near is bright (1) and far is dark (0).  Pixels without a surface are 0.

Pixel parameters and resolution: ``min_component_px`` is an area and scales with the square of the image width,
``closing_radius_px`` is a length and scales linearly; :func:`scale_refinement_pixels` converts values chosen at
the reference width of 256 px.  At 256 px the defaults 12 px and 2 px drop isolated blobs smaller than about a
4x3 px speck and close notches up to about 4 px wide.
"""
from __future__ import annotations

import cv2
import numpy as np

from tasks.core.artifacts import Array
from tasks.core.step import artifact_step

REFERENCE_WIDTH_PX = 256
DEFAULT_MIN_COMPONENT_PX = 12  # px^2 at REFERENCE_WIDTH_PX
DEFAULT_CLOSING_RADIUS_PX = 2  # px at REFERENCE_WIDTH_PX


def scale_refinement_pixels(width_px: int, min_component_px: float = DEFAULT_MIN_COMPONENT_PX,
                            closing_radius_px: float = DEFAULT_CLOSING_RADIUS_PX,
                            reference_width_px: int = REFERENCE_WIDTH_PX) -> tuple[int, int]:
    """The ``(min_component_px, closing_radius_px)`` of :func:`refine_mask` at an image width of ``width_px``.

    The inputs are chosen at ``reference_width_px``; the area scales by (width / reference)^2, the radius by
    width / reference, both rounded to whole pixels (eq. 6's R(.) must mean the same at every resolution)."""
    if width_px <= 0 or reference_width_px <= 0:
        raise ValueError(f"width_px={width_px} and reference_width_px={reference_width_px} must be positive")
    scale = width_px / reference_width_px
    return int(round(min_component_px * scale ** 2)), int(round(closing_radius_px * scale))


def _as_frames(image: np.ndarray, name: str) -> np.ndarray:
    """``image`` (y, x) or (frame, y, x) as (frame, y, x); raises ValueError on other ranks."""
    if image.ndim not in (2, 3):
        raise ValueError(f"{name} must be (y, x) or (frame, y, x), got shape {image.shape}")
    return image[None] if image.ndim == 2 else image


def _refine_frame(mask: np.ndarray, min_component_px: int, kernel: np.ndarray | None, fill_holes: bool) -> np.ndarray:
    """R(.) on one thresholded (y, x) uint8 {0, 1} mask; returns (y, x) bool."""
    # 1. connectivity check: drop 8-connected components smaller than min_component_px pixels
    if min_component_px > 1:
        n_labels, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        keep = stats[:, cv2.CC_STAT_AREA] >= min_component_px
        keep[0] = False  # label 0 is the background
        mask = keep[labels].astype(np.uint8)
    # 2. boundary repair: morphological closing (dilate then erode) with an elliptical kernel
    if kernel is not None:
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    # 3. hole filling: background not 4-connected to the image border is enclosed by the mask
    if fill_holes:
        padded = np.pad(mask, 1)
        flood = np.zeros((padded.shape[0] + 2, padded.shape[1] + 2), np.uint8)
        cv2.floodFill(padded, flood, (0, 0), 2)
        mask = (padded[1:-1, 1:-1] != 2).astype(np.uint8)
    return mask.astype(bool)


def refine_mask(mask: np.ndarray, min_component_px: int = DEFAULT_MIN_COMPONENT_PX,
                closing_radius_px: int = DEFAULT_CLOSING_RADIUS_PX, fill_holes: bool = True,
                threshold: float = 0.5) -> np.ndarray:
    """Mask refinement R(.) of eq. 6 (paper sec. 3.3): connectivity checking and boundary repair.

    mask: (y, x) or (frame, y, x), bool or float weight in [0, 1] (the composited weight of the released
        interior Gaussians); a float pixel belongs to the material where ``mask > threshold``.
    min_component_px: 8-connected components with fewer pixels are dropped as speckles (px^2; 0 or 1 keeps all).
    closing_radius_px: radius of the elliptical closing kernel, size 2 r + 1 (px; 0 skips the closing).
    fill_holes: fill background regions that do not touch the image border (4-connected).
    Each frame is refined on its own.  Pixel sizes scale with resolution (:func:`scale_refinement_pixels`).
    Returns the refined mask M~, bool, same shape as ``mask``.
    """
    mask = np.asarray(mask)
    frames = _as_frames(mask, "mask")
    if min_component_px < 0 or closing_radius_px < 0:
        raise ValueError(f"min_component_px={min_component_px} and closing_radius_px={closing_radius_px} "
                         "must be >= 0")
    if mask.dtype != bool and not np.isfinite(mask).all():
        raise ValueError("mask holds NaN or inf; pass the composited weight in [0, 1]")
    binary = (frames > threshold) if frames.dtype != bool else frames
    kernel = (cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * closing_radius_px + 1,) * 2)
              if closing_radius_px > 0 else None)
    refined = np.stack([_refine_frame(f.astype(np.uint8), int(min_component_px), kernel, fill_holes)
                        for f in binary])
    return refined.reshape(mask.shape)


def _valid_pixels(valid: np.ndarray, shape: tuple[int, ...], alpha_threshold: float) -> np.ndarray:
    """``valid`` as a bool mask: a bool mask as is, a float alpha as ``alpha > alpha_threshold``."""
    valid = np.asarray(valid)
    if valid.shape != shape:
        raise ValueError(f"valid has shape {valid.shape}, depth has {shape}: pass one value per depth pixel")
    return valid if valid.dtype == bool else valid > alpha_threshold


def normalise_depth(depth: np.ndarray, valid: np.ndarray, *, per_frame: bool = False,
                    depth_range_m: tuple[float, float] | None = None, alpha_threshold: float = 0.5) -> np.ndarray:
    """Norm(.) of eq. 6 (paper sec. 3.3): relative inverse depth in [0, 1], near = 1, as a depth ControlNet expects.

    depth: (y, x) or (frame, y, x) depth along the camera axis, metres (> 0 where valid).
    valid: same shape; bool, or the rendered alpha in [0, 1] (valid where ``alpha > alpha_threshold``).
    depth_range_m: (near, far) in metres fixes the scale (depths outside are clipped), so all views and objects
        share one mapping; without it the range is the min/max of 1/depth over the valid pixels of the whole
        sequence (temporally stable: a video model sees no brightness flicker when the range changes), or of
        each frame when ``per_frame`` (what the MiDaS annotator does per image).
    Value: (1/D - 1/D_far) / (1/D_near - 1/D_far) on valid pixels, 1 where the range is degenerate (all valid
    pixels at one depth), 0 on invalid pixels.  Returns float32, same shape as ``depth``.
    """
    depth = np.asarray(depth, np.float64)
    frames = _as_frames(depth, "depth")
    ok = _valid_pixels(valid, depth.shape, alpha_threshold).reshape(frames.shape)
    if ok.any() and not (np.isfinite(frames[ok]).all() and (frames[ok] > 0).all()):
        raise ValueError("depth must be finite and > 0 (metres) wherever valid is set; mark empty pixels invalid")
    inverse = np.where(ok, 1.0 / np.where(ok, frames, 1.0), 0.0)
    if depth_range_m is not None:
        near, far = depth_range_m
        if not 0 < near < far:
            raise ValueError(f"depth_range_m={depth_range_m} must be (near, far) with 0 < near < far, metres")
        lo, hi = np.full((len(frames), 1, 1), 1.0 / far), np.full((len(frames), 1, 1), 1.0 / near)
    else:
        axes = (1, 2) if per_frame else (0, 1, 2)
        lo = np.min(np.where(ok, inverse, np.inf), axis=axes, keepdims=True)
        hi = np.max(np.where(ok, inverse, -np.inf), axis=axes, keepdims=True)
    span = hi - lo
    scaled = np.where(span > 0, (inverse - lo) / np.where(span > 0, span, 1.0), 1.0)
    normalised = np.where(ok, np.clip(scaled, 0.0, 1.0), 0.0)
    return normalised.astype(np.float32).reshape(depth.shape)


def gated_depth(depth: np.ndarray, valid: np.ndarray, refined_mask: np.ndarray, *, per_frame: bool = False,
                depth_range_m: tuple[float, float] | None = None, alpha_threshold: float = 0.5) -> np.ndarray:
    """D~ = Norm(D) * M~ of eq. 6 (paper sec. 3.3): the depth condition seen only where the refined mask is set.

    depth, valid: as in :func:`normalise_depth` (metres; bool or alpha); refined_mask: same shape, bool, the output
    of :func:`refine_mask`.  Returns float32 in [0, 1] (near = 1), 0 outside the refined mask.
    """
    refined_mask = np.asarray(refined_mask)
    if refined_mask.shape != np.shape(depth) or refined_mask.dtype != bool:
        raise ValueError(f"refined_mask must be bool with the depth's shape {np.shape(depth)}, got "
                         f"{refined_mask.dtype} {refined_mask.shape}; pass the output of refine_mask")
    normalised = normalise_depth(depth, valid, per_frame=per_frame, depth_range_m=depth_range_m,
                                 alpha_threshold=alpha_threshold)
    return normalised * refined_mask


@artifact_step("conditions", inputs=("gbuffer",),
               reads=("render.mask_threshold", "render.mask_min_component_px", "render.mask_closing_radius_px",
                      "render.depth_normalisation"),
               outputs=("refined_mask", "normalised_depth", "gated_depth"))
def conditions_step(inputs, params):
    """Eq. 6 per view: M~ = R(M) and D~ = Norm(D) * M~ (depth normalised over each view's whole clip, or per
    frame).  A G-buffer without released material gives empty masks and says that the effect is skipped."""
    g = inputs["gbuffer"]
    mask, depth, alpha = g["mask"], g["depth"], g["alpha"]
    n_views, _, _, width = mask.shape
    min_px, radius_px = scale_refinement_pixels(width, params["render.mask_min_component_px"],
                                                params["render.mask_closing_radius_px"])
    per_frame = params["render.depth_normalisation"] == "frame"
    refined = np.zeros(mask.shape, bool)
    normalised = np.zeros(depth.shape, np.float32)
    for v in range(n_views):
        normalised[v] = normalise_depth(depth[v], alpha[v], per_frame=per_frame)
        if g.attrs["has_released_material"]:
            refined[v] = refine_mask(mask[v], min_px, radius_px, threshold=params["render.mask_threshold"])
    dims = ("view", "frame", "y", "x")
    arrays = {"refined_mask": Array(refined, dims, "1", "M~ = R(M): the refined released-material mask"),
              "normalised_depth": Array(normalised, dims, "1", "Norm(D): relative inverse depth, near = 1"),
              "gated_depth": Array(normalised * refined, dims, "1", "D~ = Norm(D) * M~")}
    notes = [] if g.attrs["has_released_material"] else [
        "mask refinement and the effect skipped: no released material (" + "; ".join(g.attrs["notes"]) + ")"]
    return arrays, {"min_component_px": min_px, "closing_radius_px": radius_px, "notes": notes,
                    "mask_area_px": [int(x) for x in refined.sum(axis=(0, 2, 3))]}
