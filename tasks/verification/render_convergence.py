"""Error against run time of the render and effect knobs (``python -m flows.studies.render_convergence``; issue 14):
what a cheaper G-buffer resolution, frame stride or eq. 7 refinement budget costs in fidelity, against a reference
setting of the same knob, with the time the stage took.

Pure functions (numpy/OpenCV; no Prefect): the error measures, the study's tables and writing the study (the run
report's section, :mod:`tasks.reporting.render_knobs`, reads the latest).  :mod:`flows.studies.render_convergence`
runs the cached steps per setting.

Knobs and error measures (images are the steps' 8-bit sRGB renders, compared in [0, 1]):

* ``resolution`` (``render.width`` = ``render.height``): each setting's G-buffer ``rgb`` bilinearly resized to the
  reference's (the largest) size, ``rgb_error`` = mean |I - I_ref| over views, frames, pixels and channels and
  ``psnr_db`` = 10 log10(1 / mean (I - I_ref)^2): what a viewer of the reference-sized frame loses.  Time: the
  ``gbuffer`` step.
* ``frame_stride`` (``render.frame_stride``): the stride-s video shown at the reference's frame rate (every frame,
  stride 1) holds each rendered frame until the next: the error is taken over every simulated frame against the
  stride-1 render at the same resolution (frames rendered by both are identical).  Time: the ``gbuffer`` step.
* ``refinement`` (``refinement.iterations``, eq. 7): the refined 4D Gaussians' renders against those of the
  reference (the most iterations), over the refined mask of eq. 6 (the released material; elsewhere every setting
  is the simulated render); plus the reconstruction loss L_rec after refinement on the training and held-out views.
  Time: the ``appearance_refinement`` step.
* ``generation.steps`` (diffusion denoising steps): not measured - its error needs the real diffusion weights,
  which are not on this machine; the tiny random components of the tests cost time per step but say nothing about
  quality.

The cost of resolution and stride downstream of the G-buffer (conditions, effect, refinement, video metrics all
scale with pixels x frames) is not included: each run report's profile table has it per stage.
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from tasks.core.tables import markdown_table
from tasks.evaluation.video_quality import psnr_db

STUDY_DIR = "render_convergence"   # under paths.reports: <run>/render_knobs.json and render_knobs.md
STUDY_FILE = "render_knobs.json"
KNOBS = {  # knob -> (config key it sets, what its error compares, the stage whose time is reported)
    "resolution": ("render.width = render.height (px)", "G-buffer RGB resized to the reference's size", "gbuffer"),
    "frame_stride": ("render.frame_stride", "G-buffer RGB held between rendered frames, every simulated frame",
                     "gbuffer"),
    "refinement": ("refinement.iterations", "refined renders over the refined mask (eq. 6)", "appearance_refinement"),
}
DIFFUSION_NOTE = ("generation.steps (diffusion denoising steps): not measured: needs weights (the SD-1.5 "
                  "AnimateDiff/ControlNet weights are not on this machine; the tiny random test components cost "
                  "time per step but say nothing about quality)")


def _unit(rgb: np.ndarray) -> np.ndarray:
    return np.asarray(rgb, np.float64) / 255.0


def image_errors(rgb: np.ndarray, reference: np.ndarray, region: np.ndarray | None = None) -> dict[str, float]:
    """``rgb_error`` (mean |I - I_ref|) and ``psnr_db`` of two (..., y, x, channel) 8-bit sRGB stacks of one shape,
    over ``region`` (..., y, x) bool when given (NaN when the region is empty).  Identical stacks: 0 and inf."""
    a, b = _unit(rgb), _unit(reference)
    if a.shape != b.shape:
        raise ValueError(f"images of shape {a.shape} cannot be compared with the reference's {b.shape}")
    diff = a - b if region is None else (a - b)[np.asarray(region, bool)]
    if diff.size == 0:
        return {"rgb_error": math.nan, "psnr_db": math.nan}
    return {"rgb_error": float(np.mean(np.abs(diff))), "psnr_db": psnr_db(float(np.mean(diff ** 2)))}


def resized(rgb: np.ndarray, height: int, width: int) -> np.ndarray:
    """(view, frame, y, x, 3) uint8 resized bilinearly (pixel centres aligned) to (view, frame, height, width, 3)."""
    flat = np.asarray(rgb).reshape(-1, *np.shape(rgb)[-3:])
    out = np.stack([cv2.resize(im, (width, height), interpolation=cv2.INTER_LINEAR) for im in flat])
    return out.reshape(*np.shape(rgb)[:-3], height, width, np.shape(rgb)[-1])


def held_frames(rgb: np.ndarray, frame_index: Sequence[int], reference_index: Sequence[int]) -> np.ndarray:
    """The (view, frame, y, x, 3) renders of ``frame_index`` (simulated frames, increasing) shown at every frame of
    ``reference_index``: each reference frame gets the latest rendered frame at or before it."""
    frames, wanted = np.asarray(frame_index), np.asarray(reference_index)
    if len(frames) == 0 or wanted.min() < frames[0]:
        raise ValueError(f"rendered frames {frames.tolist()[:3]}... start after the reference's first frame")
    return np.asarray(rgb)[:, np.searchsorted(frames, wanted, side="right") - 1]


def knob_row(knob: str, setting: Any, seconds: float, errors: Mapping[str, float], *, default: Any,
             reference: Any, **extra: Any) -> dict[str, Any]:
    """One table row: knob, setting, the stage's seconds, the errors, and whether it is the default / reference."""
    return {"knob": knob, "setting": setting, "seconds": float(seconds), **{k: float(v) for k, v in errors.items()},
            "default": setting == default, "reference": setting == reference, **extra}


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        if math.isnan(x):
            return "-"
        if math.isinf(x):
            return "inf"
        return f"{x:.3g}"
    return str(x)


def knob_tables(rows: Sequence[Mapping[str, Any]], current: Mapping[str, Any] | None = None) -> str:
    """Markdown: one table per knob (setting, stage time, errors), the default and the reference marked, and the
    setting of ``current`` (knob -> value of the run being reported) marked "this run" when it differs."""
    md = []
    for knob, (key, compares, stage) in KNOBS.items():
        own = [r for r in rows if r["knob"] == knob]
        if not own:
            continue
        extra = [c for c in own[0] if c not in ("knob", "setting", "seconds", "rgb_error", "psnr_db", "default",
                                                "reference")]
        table = []
        for r in own:
            marks = [m for m, on in (("default", r["default"]), ("reference", r["reference"]),
                                     ("this run", current is not None and current.get(knob) == r["setting"]
                                      and not r["default"])) if on]
            label = f"{r['setting']}" + (f" ({', '.join(marks)})" if marks else "")
            table.append([label, *(_fmt(r[c]) for c in ("seconds", "rgb_error", "psnr_db", *extra))])
        md += [f"**{key}** ({compares}; time: the `{stage}` step)", "",
               markdown_table(["setting", "time (s)", "error: mean abs sRGB", "PSNR (dB)", *extra], table), ""]
    return "\n".join(md + [f"- {DIFFUSION_NOTE}"])


def write_study(report_dir: str | Path, rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> Path:
    """Write ``render_knobs.json`` (meta + rows) and ``render_knobs.md`` into report_dir; returns the JSON path."""
    out = Path(report_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / STUDY_FILE
    path.write_text(json.dumps({"meta": dict(meta), "rows": list(rows)}, indent=1, default=str))  # NaN, Infinity
    (out / "render_knobs.md").write_text("\n".join([
        f"# Render and effect knobs: error against run time ({meta.get('object')}, {meta.get('variant')})", "",
        f"- machine: {meta.get('machine')}; written {meta.get('written')}; times are the steps' compute seconds "
        "(a cached step keeps the time it took when computed)", "", knob_tables(rows), ""]))
    return path


# ----------------------------------------------------------------------------------------------- per-knob rows
def _rgb(ref: Any, *names: str):
    from tasks.core.artifacts import read_artifact

    return read_artifact(ref, names=["rgb", *names])


def resolution_rows(gbuffers: Mapping[int, Any], default: int) -> list[dict[str, Any]]:
    """Rows of the ``resolution`` knob from its G-buffer artifacts (width px -> ArtifactRef); the reference is the
    largest width."""
    reference = max(gbuffers)
    ref_rgb = _rgb(gbuffers[reference])["rgb"]
    rows = []
    for width, ref in sorted(gbuffers.items()):
        rgb = _rgb(ref)["rgb"]
        errors = image_errors(resized(rgb, *ref_rgb.shape[2:4]), ref_rgb)
        rows.append(knob_row("resolution", width, ref.compute_seconds, errors, default=default, reference=reference,
                             frames=int(rgb.shape[1])))
    return rows


def stride_rows(gbuffers: Mapping[int, Any], default: int) -> list[dict[str, Any]]:
    """Rows of the ``frame_stride`` knob from its G-buffer artifacts (stride -> ArtifactRef); the reference is the
    smallest stride."""
    reference = min(gbuffers)
    ref = _rgb(gbuffers[reference], "frame_index")
    rows = []
    for stride, art_ref in sorted(gbuffers.items()):
        art = _rgb(art_ref, "frame_index")
        errors = image_errors(held_frames(art["rgb"], art["frame_index"], ref["frame_index"]), ref["rgb"])
        rows.append(knob_row("frame_stride", stride, art_ref.compute_seconds, errors, default=default,
                             reference=reference, frames=len(art["frame_index"])))
    return rows


def refinement_rows(refinements: Mapping[int, Any], conditions: Any, default: int) -> list[dict[str, Any]]:
    """Rows of the ``refinement`` knob from its appearance_refinement artifacts (iterations -> ArtifactRef) and the
    conditions artifact (its refined mask is the region compared); the reference is the most iterations.  Empty
    when the scene has nothing to refine (no released material)."""
    from tasks.core.artifacts import read_artifact

    reference = max(refinements)
    if read_artifact(refinements[reference], names=[]).attrs.get("skipped"):
        return []
    ref = _rgb(refinements[reference])
    region = read_artifact(conditions, names=["refined_mask"])["refined_mask"]
    rows = []
    for iterations, art_ref in sorted(refinements.items()):
        art = _rgb(art_ref)
        after = art.attrs.get("loss_after") or {}
        rows.append(knob_row("refinement", iterations, art_ref.compute_seconds,
                             image_errors(art["rgb"], ref["rgb"], region), default=default, reference=reference,
                             loss_train=_nan(after.get("train")), loss_held_out=_nan(after.get("held_out"))))
    return rows


def _nan(x: float | None) -> float:
    return math.nan if x is None else float(x)
