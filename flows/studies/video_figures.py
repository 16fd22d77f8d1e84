"""Figures of the released material in the videos (issue 44), before / after, per scene with released material:

    python -m flows.studies.video_figures BEFORE_ARTIFACTS AFTER_ARTIFACTS

For every effect artifact (the composite the metrics score, G-buffer resolution) and, in AFTER, every display_video
artifact (the watched video): the median over frames of the connected components (8-connected) of the effect mask,
the mean share of effect pixels in the largest component, and the share of the released material's footprint that
still shows the raw Gaussian blobs (G-buffer mask > 0.5 where the final frame is the G-buffer's pixel).  The effect
mask is where the effect changed the frame (effect step) or its coverage > 0.5 (display).  The display draws no
released Gaussian, so its blob share is 0 by construction.
"""
from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

from tasks.core.artifacts import ArtifactRef, read_artifact, read_group_attrs

SKIP: set[str] = set()  # artifact folder names of BEFORE, left out of AFTER (an AFTER folder copied from BEFORE)


def _artifacts(root: Path, scope: str, step: str):
    for path in sorted((root / scope / step).glob("*.zarr")):
        if path.name in SKIP:
            continue
        ref = ArtifactRef(rel=f"{scope}/{step}/{path.name}", digest=read_group_attrs(path)["digest"], step=step,
                          scope=scope).at(root)
        yield read_artifact(ref)


def mask_figures(masks: np.ndarray) -> tuple[float, float]:
    """(median components per frame, mean share of the largest component) over frames with a non-empty mask;
    masks (frame, y, x) bool."""
    counts, shares = [], []
    for m in masks:
        if not m.any():
            continue
        n, _, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=8)
        areas = stats[1:, cv2.CC_STAT_AREA]
        counts.append(n - 1)
        shares.append(areas.max() / areas.sum())
    return (float(np.median(counts)), float(np.mean(shares))) if counts else (float("nan"), float("nan"))


def effect_rows(root: Path, scope: str) -> list[dict]:
    """One row per effect artifact with frames: its G-buffer found as the one whose render it keeps outside."""
    rows = []
    gbuffers = list(_artifacts(root, scope, "gbuffer"))
    for effect in _artifacts(root, scope, "effect"):
        if "frames" not in effect:
            continue
        frames = effect["frames"]
        g = max(gbuffers, key=lambda g: (g["rgb"].shape == frames.shape) and (g["rgb"] == frames).mean())
        drawn = (frames != g["rgb"]).any(axis=-1)
        footprint = g["mask"] > 0.5
        blobs = footprint & ~drawn
        count, share = mask_figures(drawn.reshape(-1, *drawn.shape[2:]))
        rows.append({"scene": scope, "what": "effect step", "components": count, "largest": share,
                     "blobs": float(blobs.sum() / max(footprint.sum(), 1))})
    return rows


def display_rows(root: Path, scope: str) -> list[dict]:
    rows = []
    for d in _artifacts(root, scope, "display_video"):
        cov = d["effect_coverage"] > 0.5
        if not cov.any():
            continue
        count, share = mask_figures(cov.reshape(-1, *cov.shape[2:]))
        rows.append({"scene": scope, "what": "display (384 px)", "components": count, "largest": share,
                     "blobs": 0.0})
    return rows


def main(before: str, after: str) -> None:
    print("| scene | artifacts | what | components per frame (median) | largest component share | raw-blob share |")
    print("|---|---|---|---|---|---|")
    for scope in ("tomato", "orange", "can", "plush_toy", "paper_cup", "rubber_duck", "clay", "rubber_ball"):
        for label, root, rows in (("before", Path(before), effect_rows), ("after", Path(after), effect_rows),
                                  ("after", Path(after), display_rows)):
            SKIP.clear()
            if label == "after":
                SKIP.update(p.name for p in Path(before).glob(f"{scope}/*/*.zarr"))
            for r in rows(root, scope):
                print(f"| {r['scene']} | {label} | {r['what']} | {r['components']:.0f} | {r['largest']:.2f} | "
                      f"{r['blobs']:.2f} |")


if __name__ == "__main__":
    main(*sys.argv[1:3])
