"""Video metrics of one object, variant and effect backend (paper sec. 4.1 Table 1, sec. 4.2.2 Table 3).

The paper's video metrics rest on models we cannot ship (MUSIQ, AMT-S, VideoCon-Physics).  This step computes,
on every run and without downloaded weights, metrics defined exactly in :mod:`tasks.evaluation.video_quality`
(each named as what it is, never as the VBench number) on the final video of every view:

* temporal flicker, motion smoothness (RIFE or DIS interpolation; ``video_metrics.smoothness_views=view0``
  scores view 0 only), imaging quality (BRISQUE proxy): means over the views of the final video (the generated frames, or the simulated render when no effect was generated);
* what the physics lets us measure exactly: fidelity outside the refined mask (PSNR/SSIM against the simulated
  render: exact by construction for a backend that composites the render outside the mask), effect placement (IoU
  of the changed pixels with the refined mask), multi-view consistency of the 4D Gaussians in held-out views over
  the refined mask (``video_metrics.multiview_dilation_px``, default 0: no dilation) before the refinement (0
  iterations) and after it, with the gain, and the control coupling of the effect's visible
  area with the force coefficients of the fingers that caused the release.

A metric that does not apply gets NaN and a reason in ``reasons`` (e.g. no released material: no effect metrics).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from conf.hand import FINGERS
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.evaluation.metric_ranges import check_metrics
from tasks.evaluation.video_quality import (
    DEFINITIONS,
    control_coupling,
    effect_placement_iou,
    imaging_quality_brisque,
    masked_fidelity,
    motion_smoothness,
    multiview_consistency,
    temporal_flicker,
)
from tasks.generation.final_video import final_video
from tasks.render.device import torch_device

VIDEO_METRICS = ("temporal_flicker", "motion_smoothness", "imaging_quality_brisque", "outside_mask_psnr_db",
                 "outside_mask_ssim", "effect_placement_iou", "multiview_psnr_db", "multiview_mae",
                 "multiview_psnr_db_initial", "multiview_psnr_gain_db",
                 "control_coupling_pearson", "control_coupling_spearman", "control_coupling_lag_frames")


def json_metric(x: float | None) -> float | str | None:
    """A metric as a JSON value: None for NaN (see ``reasons``), the string "inf" for +inf (a PSNR of identical
    pixels), else the float."""
    if x is None or math.isnan(x):
        return None
    return "inf" if math.isinf(x) else float(x)


def video_metrics(final: np.ndarray, simulated: np.ndarray, refined_mask: np.ndarray, has_effect: bool,
                  refined_rgb: np.ndarray | None, held_out_views: list[int], force_coefficients: np.ndarray,
                  release_fingers: list[int], cfg: dict[str, Any], initial_rgb: np.ndarray | None = None,
                  scene: str = "this scene") -> tuple[dict[str, float], dict[str, str], dict[str, np.ndarray], str]:
    """All metrics of one scene.  final, simulated, refined_rgb: (view, frame, y, x, 3) uint8 sRGB; refined_mask
    (view, frame, y, x) bool; force_coefficients (frame, finger) at the rendered frames; initial_rgb (held-out view,
    frame, y, x, 3): the 4D Gaussians before refinement in the ``held_out_views``.  Returns (values,
    reasons for NaN values, per-frame arrays, the motion-smoothness interpolator used); a value outside its
    documented range is a bug named with ``scene`` (:func:`tasks.evaluation.metric_ranges.check_metrics`)."""
    values, reasons, per_frame, interpolator = _scene_metrics(
        final, simulated, refined_mask, has_effect, refined_rgb, held_out_views, force_coefficients, release_fingers,
        cfg, initial_rgb)
    check_metrics(values, scene)
    if "effect_placement_iou" in per_frame:
        check_metrics({"effect_placement_iou": per_frame["effect_placement_iou"]}, scene)
    return values, reasons, per_frame, interpolator


def _scene_metrics(final, simulated, refined_mask, has_effect, refined_rgb, held_out_views, force_coefficients,
                   release_fingers, cfg, initial_rgb):
    """:func:`video_metrics` before the range check."""
    values: dict[str, float] = {}
    reasons: dict[str, str] = {}
    n_views = final.shape[0]
    # 1. quality of the final video, mean over views
    values["temporal_flicker"] = float(np.mean([temporal_flicker(final[v]) for v in range(n_views)]))
    smooth, views = [], list(range(n_views)) if cfg["smoothness_views"] == "all" else [0]
    for v in views:  # frame interpolation: the costliest metric, so the step reports progress per view
        smooth.append(motion_smoothness(final[v], cfg["interpolator"]))
        report_progress(len(smooth), len(views), unit="view")
    values["motion_smoothness"] = float(np.mean([s.score for s in smooth]))
    per_view = max(1, cfg["brisque_max_frames"] // n_views)
    iq = [imaging_quality_brisque(final[v], per_view).proxy for v in range(n_views)]
    values["imaging_quality_brisque"] = float(mean_over_views(np.array(iq)))
    # 2. what the physics lets us measure exactly
    per_frame: dict[str, np.ndarray] = {"effect_area_px": refined_mask.sum(axis=(0, 2, 3)).astype(np.float64)}
    effect_keys = ("outside_mask_psnr_db", "outside_mask_ssim", "effect_placement_iou", "control_coupling_pearson",
                   "control_coupling_spearman", "control_coupling_lag_frames")
    if not has_effect:
        for key in effect_keys + ("multiview_psnr_db", "multiview_mae", "multiview_psnr_db_initial",
                                  "multiview_psnr_gain_db"):
            values[key], reasons[key] = math.nan, "no effect generated for this scene"
        return values, reasons, per_frame, smooth[0].interpolator
    fid = masked_fidelity(final.reshape(-1, *final.shape[2:]), simulated.reshape(-1, *simulated.shape[2:]),
                          refined_mask.reshape(-1, *refined_mask.shape[2:]))
    values["outside_mask_psnr_db"], values["outside_mask_ssim"] = fid.psnr_db, fid.ssim
    iou = [effect_placement_iou(final[v], simulated[v], refined_mask[v], cfg["change_threshold"])
           for v in range(n_views)]
    per_frame["effect_placement_iou"] = mean_over_views(np.stack([i.per_frame for i in iou]))
    values["effect_placement_iou"] = float(mean_over_views(np.array([i.mean for i in iou])))
    if refined_rgb is not None and held_out_views:
        mv = multiview_consistency(refined_rgb[held_out_views], final[held_out_views],
                                   refined_mask[held_out_views], cfg["multiview_dilation_px"])
        values["multiview_psnr_db"], values["multiview_mae"] = mv.psnr_db, mv.mae
        if initial_rgb is not None:  # the same held-out views before refinement (0 iterations)
            mv0 = multiview_consistency(initial_rgb, final[held_out_views], refined_mask[held_out_views],
                                        cfg["multiview_dilation_px"])
            values["multiview_psnr_db_initial"] = mv0.psnr_db
            values["multiview_psnr_gain_db"] = mv.psnr_db - mv0.psnr_db
        else:
            for key in ("multiview_psnr_db_initial", "multiview_psnr_gain_db"):
                values[key], reasons[key] = math.nan, "no 0-iteration render of the held-out views (older artifact)"
    else:
        for key in ("multiview_psnr_db", "multiview_mae", "multiview_psnr_db_initial", "multiview_psnr_gain_db"):
            values[key] = math.nan
            reasons[key] = "no refined 4D Gaussians or no held-out view (refinement.held_out_views)"
    fingers = [FINGERS[k] for k in release_fingers] or None
    cc = control_coupling(per_frame["effect_area_px"], force_coefficients, fingers, cfg["coupling_max_lag_frames"])
    values["control_coupling_pearson"], values["control_coupling_spearman"] = cc.pearson, cc.spearman
    values["control_coupling_lag_frames"] = float(cc.lag_frames) if cc.lag_frames >= 0 else math.nan  # -1: undefined
    if cc.reason:
        for key in ("control_coupling_pearson", "control_coupling_spearman", "control_coupling_lag_frames"):
            reasons[key] = cc.reason
    return values, reasons, per_frame, smooth[0].interpolator


def mean_over_views(per_view: np.ndarray) -> np.ndarray:
    """The mean over the views (axis 0) of the finite values, NaN where no view has one (e.g. the frames before the
    effect appears, where every view's placement IoU is undefined); like ``np.nanmean`` without its warning."""
    per_view = np.asarray(per_view, np.float64)
    finite = np.isfinite(per_view)
    count = finite.sum(axis=0)
    total = np.where(finite, per_view, 0.0).sum(axis=0)
    return np.divide(total, count, out=np.full(np.shape(count), np.nan), where=count > 0)


@artifact_step("video_metrics",
               inputs=("gbuffer", "conditions", "effect", "appearance_refinement", "force_coefficients"),
               reads=("video_metrics", "render.device"),
               outputs=("effect_area_px", "effect_placement_iou?"))
def video_metrics_step(inputs, params):
    """Table 1 / Table 3 video metrics of one object, variant and backend (definitions in the attrs)."""
    torch_device(params["render.device"])  # thread count for the RIFE interpolator
    g, cond, effect, refined = (inputs[k] for k in ("gbuffer", "conditions", "effect", "appearance_refinement"))
    has_effect = "frames" in effect
    final = final_video(effect, g)
    forces = inputs["force_coefficients"]["force_coefficients"][g["frame_index"]]
    values, reasons, per_frame, interpolator = video_metrics(
        final, g["rgb"], cond["refined_mask"], has_effect, refined["rgb"] if "rgb" in refined else None,
        list(refined.attrs.get("held_out_views") or []), forces, list(g.attrs.get("release_fingers") or []),
        dict(params["video_metrics"]), refined["rgb_initial"] if "rgb_initial" in refined else None,
        scene=f"{effect.ref.scope} ({effect.attrs.get('backend')} effect)")
    arrays = {"effect_area_px": Array(per_frame["effect_area_px"], ("frame",), "px",
                                      "refined-mask area summed over the views")}
    if "effect_placement_iou" in per_frame:
        arrays["effect_placement_iou"] = Array(per_frame["effect_placement_iou"], ("frame",), "1",
                                               "IoU of changed pixels and refined mask, mean over views")
    definitions = {k: DEFINITIONS[k] for k in DEFINITIONS if not k.startswith("motion_smoothness")}
    definitions["motion_smoothness"] = DEFINITIONS[f"motion_smoothness_{interpolator}"]
    attrs = {"backend": effect.attrs.get("backend"), "effect_label": effect.attrs.get("label"),
             "skipped_effect": effect.attrs.get("skipped"),
             "metrics": {k: json_metric(v) for k, v in values.items()}, "reasons": reasons,
             "motion_smoothness_label": f"motion smoothness, {interpolator.upper()} interpolation"
                                        + (", view 0" if params["video_metrics"]["smoothness_views"] == "view0" else ""),
             "definitions": definitions}
    return arrays, attrs
