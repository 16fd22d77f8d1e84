"""Figures of the released liquid (issue 44), per scene with released material, for each way of drawing it:

    python -m flows.studies.video_figures ARTIFACTS [SCENE ...]      # default: tomato orange can plush_toy

Reads the newest ``gbuffer``, ``conditions``, ``mpm_rollout`` and ``mpm_particles`` artifacts of each scene under
``ARTIFACTS`` (a store that ran the scene once, e.g. ``flows.squeeze object=orange paths.artifacts=...``), re-renders
the effect step's composite (G-buffer resolution, inside the refined mask of eq. 6; nothing is written) with

* ``spheres``: one sphere per released particle (before issue 44);
* ``Yu-Turk``: Yu & Turk's anisotropic kernels (TOG 2013) of the released particles;
* ``bridged + Yu-Turk``: render particles bridging neighbours within ``LIQUID_BRIDGE_REACH`` radii, then the
  kernels (the default, :func:`tasks.generation.physics_effect.liquid_kernels`);

and prints, over every view and frame with liquid: the median number of 8-connected components of the drawn
effect, the mean share of its pixels in the largest component, and the share of the released footprint (G-buffer
mask M > 0.5) still showing the raw Gaussian blobs (not drawn over by the effect).  With ``--display`` it adds the
same component figures of the newest ``display_video`` artifact (the watched video; it draws no released Gaussian,
so its blob share is 0 by construction).  Stuffing is drawn by strands: one row, the renderer's own.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import cv2
import numpy as np

from tasks.core.artifacts import newest_artifact
from tasks.generation.fluid_render import render_liquid
from tasks.generation.physics_effect import (
    LIQUID_BRIDGE_REACH,
    PARTICLE_RADIUS_FACTOR,
    appearance_for_effect,
    liquid_kernels,
    render_effect,
)
from tasks.render.colour import srgb_uint8_to_linear
from tasks.render.scene import rollout_particle_volumes

SCENES = ("tomato", "orange", "can", "plush_toy")


def mask_figures(masks: list[np.ndarray]) -> tuple[float, float]:
    """(median components per mask, mean share of the largest component) over the non-empty (y, x) bool masks."""
    counts, shares = [], []
    for m in masks:
        if not m.any():
            continue
        n, _, stats, _ = cv2.connectedComponentsWithStats(m.astype(np.uint8), connectivity=8)
        areas = stats[1:, cv2.CC_STAT_AREA]
        counts.append(n - 1)
        shares.append(areas.max() / areas.sum())
    return (float(np.median(counts)), float(np.mean(shares))) if counts else (float("nan"), float("nan"))


def effect_figures(root: Path, scene: str, how: str) -> dict[str, float]:
    """The effect step's composite drawn ``how`` (module doc): components, largest share, raw-blob share, CPU s."""
    g, cond = newest_artifact(root, scene, "gbuffer"), newest_artifact(root, scene, "conditions")
    rollout, particles = newest_artifact(root, scene, "mpm_rollout"), newest_artifact(root, scene, "mpm_particles")
    kind, appearance = appearance_for_effect(g.attrs["effect"])
    sim = srgb_uint8_to_linear(g["rgb"])
    volumes = rollout_particle_volumes(particles.arrays, len(rollout["particle_material"]))
    radii = PARTICLE_RADIUS_FACTOR * np.cbrt(volumes)
    positions = rollout["particle_positions"][g["frame_index"]]
    visible, mask, footprint = g["released_visible"], cond["refined_mask"], g["mask"] > 0.5
    drawn_masks, blobs, area, cpu = [], 0, 0, time.process_time()
    for f in range(len(visible)):
        shown = visible[f]
        if not shown.any():
            continue
        x, r = positions[f][shown], radii[shown]
        kernels = None if how == "spheres" else liquid_kernels(
            kind, x, r, bridge_reach=0.0 if how == "Yu-Turk" else LIQUID_BRIDGE_REACH)
        for v in range(len(g["viewmats"])):
            if kind == "liquid" and how == "spheres":
                frame = render_liquid(x, r, g["viewmats"][v], g["Ks"][v], sim[v, f], g["surface_depth"][v, f],
                                      appearance, kernels=None)
            else:
                frame = render_effect(kind, x, r, g["viewmats"][v], g["Ks"][v], sim[v, f], g["surface_depth"][v, f],
                                      appearance, 0, kernels)
            drawn = mask[v, f] & (frame.coverage > 0)
            drawn_masks.append(drawn)
            blobs += int((footprint[v, f] & ~drawn).sum())
            area += int(footprint[v, f].sum())
    count, share = mask_figures(drawn_masks)
    return {"components": count, "largest": share, "blobs": blobs / max(area, 1),
            "cpu": time.process_time() - cpu}


def display_figures(root: Path, scene: str) -> dict[str, float]:
    d = newest_artifact(root, scene, "display_video")
    cov = d["effect_coverage"] > 0.5
    count, share = mask_figures([m for m in cov.reshape(-1, *cov.shape[2:])])
    return {"components": count, "largest": share, "blobs": 0.0, "cpu": float("nan")}


def main(argv: list[str]) -> None:
    if not argv:
        raise SystemExit(__doc__)
    display = "--display" in argv
    argv = [a for a in argv if a != "--display"]
    root, scenes = Path(argv[0]), argv[1:] or SCENES
    print("| scene | drawn with | components per frame (median) | largest component share | raw-blob share | CPU s |")
    print("|---|---|---|---|---|---|")
    for scene in scenes:
        kind = appearance_for_effect(newest_artifact(root, scene, "gbuffer").attrs["effect"])[0]
        for how in (("spheres", "Yu-Turk", "bridged + Yu-Turk") if kind == "liquid" else ("strands",)):
            r = effect_figures(root, scene, how)
            print(f"| {scene} | {how} (effect step) | {r['components']:.0f} | {r['largest']:.2f} | {r['blobs']:.2f} | "
                  f"{r['cpu']:.1f} |", flush=True)
        if display:
            r = display_figures(root, scene)
            print(f"| {scene} | display video | {r['components']:.0f} | {r['largest']:.2f} | 0 (by construction) | |")


if __name__ == "__main__":
    main(sys.argv[1:])
