"""Screen-space fluid rendering of released liquid (juice, cola): the weight-free stand-in for the diffusion
backend of paper sec. 3.3 (``generation=physics``).

Method: van der Laan, Green & Sainz, "Screen Space Fluid Rendering with Curvature Flow", I3D 2009, and Green,
"Screen Space Fluid Rendering for Games", GDC 2010:

1. splat particles as impostors: front depth (z-buffer) and thickness (summed chords) - by default the anisotropic
   kernels of Yu & Turk (TOG 2013, :mod:`tasks.generation.anisotropic`), which stretch along a stream and flatten
   in a puddle so that close particles draw one continuous body; ``kernels=None``: one sphere per particle;
2. smooth the depth with a bilateral filter (background at far, so the silhouette is kept);
3. normals from the smoothed depth (view-space positions, one-sided differences across the silhouette);
4. shade: Beer-Lambert absorption through the thickness, a turbid body colour, refraction of the background by a
   normal-dependent offset, Schlick Fresnel reflection of a sky gradient and Blinn-Phong specular, both faded by
   thickness so isolated droplets get no bright rims.

Units: metres, pixels, linear RGB in [0, 1]; absorption in 1/m (Beer-Lambert: transmittance exp(-sigma_a t)).
Camera conventions: see :mod:`tasks.generation.impostors`.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tasks.generation.anisotropic import YU_TURK, AnisotropySettings, Ellipsoids, anisotropic_kernels
from tasks.generation.impostors import (
    EffectFrame,
    check_frame_inputs,
    project_particles,
    splat_ellipsoid_impostors,
    splat_sphere_impostors,
)
from tasks.generation.liquid_kernels import liquid_colour, normals_pixels, shading_geometry


@dataclass(frozen=True)
class LiquidAppearance:
    """Optical parameters of a released liquid.  Colours linear RGB in [0, 1]; directions in camera coordinates."""

    absorption_per_m: tuple[float, float, float]  # Beer-Lambert sigma_a per channel, 1/m
    body_colour: tuple[float, float, float]  # colour scattered back by the turbid body
    turbidity: float  # in [0, 1]: how much of the light absorbed on the way through is replaced by body colour
    ior: float = 1.33  # index of refraction (water); sets Schlick's F0 and the refraction offset
    sky_zenith: tuple[float, float, float] = (0.55, 0.70, 0.95)
    sky_horizon: tuple[float, float, float] = (0.95, 0.95, 0.92)
    specular: float = 0.8  # Blinn-Phong coefficient
    shininess: float = 120.0  # Blinn-Phong exponent
    ambient: float = 0.35  # share of the body colour lit regardless of the normal
    light_direction: tuple[float, float, float] = (-0.35, -0.75, -0.55)  # towards the light: up-left, camera side
    max_refraction_gap_m: float = 0.05  # longest distance behind the liquid over which the background is displaced
    smoothing_iterations: int = 3  # bilateral passes


# Orange juice: 0.3, 1.5, 5.0 per cm (a 1 cm stream transmits 74 %, 22 %, 0.7 %: orange), strongly turbid.
JUICE = LiquidAppearance(absorption_per_m=(30.0, 150.0, 500.0), body_colour=(0.95, 0.45, 0.04), turbidity=0.75)
# Cola: 2, 4, 7 per cm (1 mm films are light brown, a 1 cm stream is near black), clear.
COLA = LiquidAppearance(absorption_per_m=(200.0, 400.0, 700.0), body_colour=(0.09, 0.03, 0.01), turbidity=0.15)


# bilateral filter's spatial sigma cap (px): in a close-up a particle spans tens of pixels and an uncapped kernel
# cost 0.9 s per pass at 384 px; the anisotropic kernels already make the surface smooth at that scale
MAX_SMOOTHING_SIGMA_PX = 4.0
_BOX_MARGIN_PX = 8  # least background kept around the liquid's bounding box (refraction lookups, filter support)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def smooth_depth(depth: np.ndarray, covered: np.ndarray, sigma_depth_m: float, sigma_space_px: float,
                 iterations: int) -> np.ndarray:
    """Bilateral smoothing of the splatted depth (the bilateral filter van der Laan et al. 2009 compare with).

    depth: (y, x) metres, valid where ``covered``; the rest is set to a far value 20 ``sigma_depth_m`` behind the
    deepest particle, so its range weight vanishes and the silhouette is kept.  ``sigma_space_px`` (px) should be
    about the particles' screen radius.  Returns (y, x) float32 metres, +inf outside ``covered``.
    """
    if not covered.any():
        return np.full(depth.shape, np.inf, np.float32)
    far = float(depth[covered].max()) + 20.0 * sigma_depth_m
    smoothed = np.where(covered, depth, far).astype(np.float32)
    sigma_space_px = min(sigma_space_px, MAX_SMOOTHING_SIGMA_PX)
    diameter = 2 * int(np.ceil(1.5 * sigma_space_px)) + 1  # cv2's default (-1) grows the kernel to 6 sigma
    for _ in range(iterations):
        smoothed = cv2.bilateralFilter(smoothed, diameter, sigma_depth_m, sigma_space_px)
    return np.where(covered, smoothed, np.inf).astype(np.float32)


def normals_from_depth(depth: np.ndarray, covered: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Unit surface normals (y, x, xyz) in camera coordinates from a (y, x) depth map in metres, facing the camera
    (n_z < 0), via the cross product of one-sided position differences; (0, 0, -1) outside ``covered``.

    Per pixel, along x and y, of the forward and backward differences of the view-space positions whose neighbour is
    covered, the one with the smaller depth change (van der Laan et al. 2009); a flat pixel footprint (z / f) where
    neither; normal = -unit(ddx x ddy) (x right, y down: ddx x ddy points away from the camera).  A Warp kernel
    (:mod:`tasks.generation.liquid_kernels`), float64, bit-identical to the numpy formulation it replaced."""
    return normals_pixels(depth, covered, K[0, 0], K[1, 1], K[0, 2], K[1, 2])


def shade_liquid(background_rgb: np.ndarray, depth: np.ndarray, thickness: np.ndarray, normal: np.ndarray,
                 surface_depth: np.ndarray, K: np.ndarray, appearance: LiquidAppearance,
                 fade_thickness_m: float) -> np.ndarray:
    """Liquid colour per pixel (Green, GDC 2010; Beer-Lambert absorption; Schlick 1994 Fresnel; Blinn-Phong).

    background_rgb: (y, x, 3) linear RGB seen through the liquid; depth, thickness: (y, x) metres (depth finite
    where shaded); normal: (y, x, 3) unit, camera coordinates; surface_depth: (y, x) metres of what lies behind
    (+inf: nothing).  With transmittance tau = exp(-sigma_a t), turbid share beta = turbidity (1 - exp(-mean(sigma_a)
    t)), Fresnel F = fade (F0 + (1 - F0)(1 - n.v)^5), fade = 1 - exp(-t / fade_thickness_m):
        rgb = (1 - F) [(1 - beta) tau B(x + offset) + beta body (ambient + (1 - ambient) max(n.l, 0))]
              + F sky(reflect(-v, n)) + fade specular max(n.h, 0)^shininess
    where B is the background displaced by offset = -(1 - 1/ior) n_xy (t + gap) f / z pixels (gap: distance to the
    surface behind, capped).  Returns (y, x, 3) float32, clipped to [0, 1]; meaningful where depth is finite.

    The per-pixel geometry and colour are Warp kernels (:mod:`tasks.generation.liquid_kernels`); the remap, the
    exponentials, the powers and n.l stay in numpy and OpenCV: bit-identical to the numpy formulation it replaced.
    """
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    shaded = np.isfinite(depth)
    z = np.where(shaded, depth, 1.0)
    t = thickness[..., None]
    # 1. refraction: the background displaced along the normal by the path through and behind the liquid
    gap = np.clip(np.where(np.isfinite(surface_depth), surface_depth - z, np.inf), 0.0, appearance.max_refraction_gap_m)
    shift_m = (1.0 - 1.0 / appearance.ior) * (thickness + gap)
    light = _unit(np.asarray(appearance.light_direction, np.float64))
    map_x, map_y, n_dot_v, grazing, n_dot_h = shading_geometry(normal, shift_m, z, light, fx, fy, cx, cy)
    refracted = cv2.remap(background_rgb.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REFLECT)
    # 2. body: Beer-Lambert transmission of the refracted background plus the turbid body colour, diffusely lit
    sigma = np.asarray(appearance.absorption_per_m)
    transmittance = np.exp(-sigma * t)
    turbid = appearance.turbidity * (1.0 - np.exp(-sigma.mean() * t))
    # 3. surface: Schlick Fresnel reflection of a sky gradient and Blinn-Phong specular, faded by thickness
    fade = 1.0 - np.exp(-t / fade_thickness_m)
    f0 = ((appearance.ior - 1.0) / (appearance.ior + 1.0)) ** 2
    horizon, zenith = np.asarray(appearance.sky_horizon), np.asarray(appearance.sky_zenith)
    optics = np.concatenate([[appearance.ambient, 1.0 - appearance.ambient, f0, 1.0 - f0, appearance.specular],
                             np.asarray(appearance.body_colour), horizon, zenith - horizon])
    return liquid_colour(normal, refracted, transmittance, turbid[..., 0], normal @ light, n_dot_v, grazing ** 5,
                         fade[..., 0], n_dot_h ** appearance.shininess, optics, fx, fy, cx, cy)


def render_liquid(positions: np.ndarray, radii: np.ndarray | float, viewmat: np.ndarray, K: np.ndarray,
                  background_rgb: np.ndarray, surface_depth: np.ndarray,
                  appearance: LiquidAppearance = JUICE,
                  kernels: AnisotropySettings | Ellipsoids | None = YU_TURK) -> EffectFrame:
    """Screen-space fluid rendering of one frame of released liquid (van der Laan et al. 2009; module doc).

    positions: (particle, xyz) world metres; radii: (particle,) or scalar metres; viewmat (4, 4) world-to-camera,
    K (3, 3): see :mod:`tasks.generation.impostors`; background_rgb: (y, x, 3) linear RGB in [0, 1], the render
    the liquid is seen against (and refracts); surface_depth: (y, x) metres of the object's surface without the
    released material (+inf where none): particles behind it are hidden; kernels: the anisotropic kernels' settings,
    or the kernels themselves (:func:`tasks.generation.anisotropic.anisotropic_kernels` of ``positions``, world
    coordinates: computed once per frame, they serve every view), or None (a sphere per particle of its radius).
    Returns an :class:`EffectFrame`: rgb equals ``background_rgb`` (as float32) outside the coverage; depth is the
    smoothed liquid depth where covered; coverage is 1 where liquid is seen, else 0.
    """
    height, width = check_frame_inputs(background_rgb, surface_depth)
    background = background_rgb.astype(np.float32)
    particles = project_particles(positions, radii, viewmat, K)
    # 1. impostors (anisotropic kernels or spheres): z-buffered depth and thickness
    if kernels is None or len(particles.index) == 0:
        depth, thickness = splat_sphere_impostors(particles, surface_depth)
        radius_px = float(np.median(particles.radius_px)) if len(particles.index) else 0.5
    else:
        ellipsoids = kernels if isinstance(kernels, Ellipsoids) else anisotropic_kernels(positions, radii, kernels)
        depth, thickness, radius_px = splat_ellipsoid_impostors(*ellipsoids, viewmat, K, surface_depth)
    covered = np.isfinite(depth)
    if not covered.any():
        return EffectFrame(background, surface_depth.astype(np.float32), np.zeros((height, width), np.float32))
    # 2. crop to the liquid's bounding box, with room for the bilateral filter and the refraction lookups
    radius_m, radius_px = float(np.median(particles.radius_m)), max(radius_px, 0.5)
    margin = max(_BOX_MARGIN_PX, int(np.ceil(1.5 * radius_px)) + 1)
    rows, cols = np.flatnonzero(covered.any(axis=1)), np.flatnonzero(covered.any(axis=0))
    top, left = max(rows[0] - margin, 0), max(cols[0] - margin, 0)
    box = (slice(top, rows[-1] + 1 + margin), slice(left, cols[-1] + 1 + margin))
    K_box = np.asarray(K, np.float64).copy()
    K_box[0, 2] -= left
    K_box[1, 2] -= top
    # 3. bilateral depth smoothing at the particles' scale
    smoothed = smooth_depth(depth[box], covered[box], 2.0 * radius_m, radius_px, appearance.smoothing_iterations)
    # 4. normals from the smoothed depth and shading
    normal = normals_from_depth(smoothed, covered[box], K_box)
    colour = shade_liquid(background[box], smoothed, thickness[box], normal, surface_depth[box], K_box,
                          appearance, fade_thickness_m=2.0 * radius_m)
    rgb = background.copy()
    rgb[box] = np.where(covered[box][..., None], colour, background[box])
    liquid_depth = surface_depth.astype(np.float32)
    liquid_depth[box] = np.where(covered[box], smoothed, liquid_depth[box])
    return EffectFrame(rgb, liquid_depth, covered.astype(np.float32))
