"""The weight-free ("physics") secondary-effect backend of paper sec. 3.3: render the released interior material
so it reads as what it is, and blend it into the simulated render by the refined mask of eq. 6.

Liquids (juice, cola) go through screen-space fluid rendering (:mod:`tasks.generation.fluid_render`), stuffing
through the strand renderer (:mod:`tasks.generation.strand_render`).  The output has the shape of what the
diffusion backend produces (one RGB frame per view and frame), so blending, 4D refinement (eq. 7) and the video
metrics treat both alike; reports must label these frames "physics-rendered".
"""
from __future__ import annotations

import os
import time
from typing import Literal

import cv2
import numpy as np

from tasks.generation.anisotropic import YU_TURK, Ellipsoids, anisotropic_kernels, bridge_particles
from tasks.generation.fluid_render import COLA, JUICE, LiquidAppearance, render_liquid
from tasks.generation.impostors import EffectFrame
from tasks.generation.strand_render import STUFFING, StuffingAppearance, render_stuffing

EffectKind = Literal["liquid", "stuffing"]
PARTICLE_RADIUS_FACTOR = 0.75  # sphere radius of a released particle = this x cbrt(its volume): neighbours overlap
# released liquid particles closer than this many radii are bridged by render particles (docs/results/videos.md)
LIQUID_BRIDGE_REACH = 4.0

# the material oracle's effects that release interior material -> (renderer, appearance)
EFFECT_APPEARANCES: dict[str, tuple[EffectKind, LiquidAppearance | StuffingAppearance]] = {
    "juice": ("liquid", JUICE),
    "cola_spray": ("liquid", COLA),
    "stuffing_spill": ("stuffing", STUFFING),
}


def render_effect(kind: EffectKind, positions: np.ndarray, radii: np.ndarray | float, viewmat: np.ndarray,
                  K: np.ndarray, background_rgb: np.ndarray, surface_depth: np.ndarray,
                  appearance: LiquidAppearance | StuffingAppearance | None = None, seed: int = 0,
                  kernels: Ellipsoids | None = None) -> EffectFrame:
    """One frame of the released material, rendered by its kind (paper sec. 3.3, weight-free backend).

    kind: "liquid" (screen-space fluid rendering) or "stuffing" (fibrous strands); positions: (particle, xyz) world
    metres of the released particles; radii: (particle,) or scalar metres; viewmat: (4, 4) world-to-camera (x right,
    y down, z forward); K: (3, 3) pixels; background_rgb: (y, x, 3) linear RGB in [0, 1], the simulated render;
    surface_depth: (y, x) metres of the object's surface without the released material, +inf where none;
    appearance: defaults to juice for a liquid and cream fibrefill for stuffing; seed: fixes the strands; kernels:
    a liquid's anisotropic kernels of ``positions`` (:func:`liquid_kernels`, once per frame for every view; None:
    computed here).
    Returns (rgb (y, x, 3), depth (y, x) metres, coverage (y, x) in [0, 1]) as an :class:`EffectFrame`.
    """
    if kind == "liquid":
        appearance = JUICE if appearance is None else appearance
        if not isinstance(appearance, LiquidAppearance):
            raise ValueError(f"kind 'liquid' needs a LiquidAppearance, got {type(appearance).__name__}")
        return render_liquid(positions, radii, viewmat, K, background_rgb, surface_depth, appearance,
                             YU_TURK if kernels is None else kernels)
    if kind == "stuffing":
        appearance = STUFFING if appearance is None else appearance
        if not isinstance(appearance, StuffingAppearance):
            raise ValueError(f"kind 'stuffing' needs a StuffingAppearance, got {type(appearance).__name__}")
        return render_stuffing(positions, radii, viewmat, K, background_rgb, surface_depth, appearance, seed)
    raise ValueError(f"effect kind {kind!r} is unknown: use 'liquid' or 'stuffing'")


def liquid_kernels(kind: EffectKind, positions: np.ndarray, radii: np.ndarray | float,
                   bridge_reach: float = LIQUID_BRIDGE_REACH) -> Ellipsoids | None:
    """The kernels a liquid is drawn with, in world coordinates, one computation per frame shared by every view
    (None for stuffing): the released particles bridged to their neighbours within ``bridge_reach`` radii
    (:func:`tasks.generation.anisotropic.bridge_particles`; 0: no bridges), then Yu & Turk's anisotropic kernels
    (TOG 2013, :func:`tasks.generation.anisotropic.anisotropic_kernels`)."""
    if kind != "liquid":
        return None
    if bridge_reach > 0:
        positions, radii = bridge_particles(positions, radii, bridge_reach)
    return anisotropic_kernels(positions, radii, YU_TURK)


def composite_effect(sim_rgb: np.ndarray, effect_rgb: np.ndarray, refined_mask: np.ndarray) -> np.ndarray:
    """The final blend of paper sec. 3.3: the effect inside the refined mask M~ of eq. 6, the simulated render
    outside it, bit for bit.

    sim_rgb, effect_rgb: (..., y, x, channel) with equal shapes (any leading axes, e.g. view and frame), float in
    [0, 1]; refined_mask: (..., y, x), bool or a weight in [0, 1] (a soft edge blends linearly).
    Returns, in ``sim_rgb``'s dtype: ``effect_rgb`` where m >= 1, ``sim + m (effect - sim)`` where 0 < m < 1,
    and ``sim_rgb`` itself where m == 0.
    """
    sim_rgb, effect_rgb, refined_mask = np.asarray(sim_rgb), np.asarray(effect_rgb), np.asarray(refined_mask)
    if sim_rgb.shape != effect_rgb.shape or refined_mask.shape != sim_rgb.shape[:-1]:
        raise ValueError(f"sim_rgb {sim_rgb.shape}, effect_rgb {effect_rgb.shape} and refined_mask "
                         f"{refined_mask.shape} must be (..., y, x, channel) twice and (..., y, x)")
    weight = refined_mask.astype(np.float32)[..., None]
    effect_rgb = effect_rgb.astype(sim_rgb.dtype)
    blended = np.where(weight >= 1, effect_rgb, sim_rgb + weight * (effect_rgb - sim_rgb))
    return np.where(weight > 0, blended, sim_rgb).astype(sim_rgb.dtype)


def appearance_for_effect(effect: str) -> tuple[EffectKind, LiquidAppearance | StuffingAppearance]:
    """(kind, appearance) of a material-oracle effect that releases interior material (``EFFECT_APPEARANCES``)."""
    if effect not in EFFECT_APPEARANCES:
        raise ValueError(f"effect {effect!r} releases no interior material: "
                         f"expected one of {sorted(EFFECT_APPEARANCES)}")
    return EFFECT_APPEARANCES[effect]


def _benchmark_scene(n_particles: int, size_px: int, seed: int = 0):
    """A falling stream of released particles in front of a textured background, camera 0.4 m away."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n_particles)
    positions = np.stack([0.03 * np.sin(4.0 * s), 0.1 * s - 0.05, np.full_like(s, 0.4)], -1)
    positions += rng.normal(0.0, 0.006, positions.shape)
    focal = size_px / (2.0 * np.tan(np.radians(20.0)))
    K = np.array([[focal, 0, size_px / 2], [0, focal, size_px / 2], [0, 0, 1]])
    yy, xx = np.mgrid[0:size_px, 0:size_px] / size_px
    background = np.stack([0.2 + 0.6 * xx, 0.3 + 0.4 * yy, 0.5 + 0.2 * np.sin(20 * xx)], -1).astype(np.float32)
    surface = np.where(xx > 0.7, 0.38, np.inf)  # an object edge on the right hides some particles
    return positions, 0.002, np.eye(4), K, background, surface


def benchmark(n_particles: int = 500, size_px: int = 256, repeats: int = 10) -> dict[str, float]:
    """Prints and returns the best and median wall milliseconds and the median CPU milliseconds per frame of each
    effect kind on :func:`_benchmark_scene`, with OpenCV on ``VIRSQUEEZER_TORCH_THREADS`` threads (default 1).
    CPU time is the better figure on a shared machine."""
    cv2.setNumThreads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))
    scene = _benchmark_scene(n_particles, size_px)
    figures = {}
    for kind in ("liquid", "stuffing"):
        wall, cpu = [], []
        for _ in range(repeats):
            wall_start, cpu_start = time.perf_counter(), time.process_time()
            render_effect(kind, *scene)
            wall.append(1e3 * (time.perf_counter() - wall_start))
            cpu.append(1e3 * (time.process_time() - cpu_start))
        figures.update({f"{kind}_best_ms": min(wall), f"{kind}_median_ms": float(np.median(wall)),
                        f"{kind}_median_cpu_ms": float(np.median(cpu))})
        print(f"{kind}: {n_particles} particles at {size_px}x{size_px}: wall best {min(wall):.1f} ms, "
              f"median {np.median(wall):.1f} ms; CPU median {np.median(cpu):.1f} ms per frame")
    return figures


if __name__ == "__main__":
    benchmark()
