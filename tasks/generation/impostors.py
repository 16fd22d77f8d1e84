"""Released particles seen by a pinhole camera: projection and sphere-impostor splatting (z-buffer and thickness).

The shared first stage of the weight-free effect renderers (:mod:`tasks.generation.fluid_render`,
:mod:`tasks.generation.strand_render`).  Camera conventions are gsplat's / OpenCV's: ``viewmat`` (4, 4) maps world
to camera coordinates with x right, y down, z forward (metres); ``K`` (3, 3) holds fx, fy, cx, cy in pixels; the
pixel in row i, column j covers [j, j + 1) x [i, i + 1), so its centre is at (j + 0.5, i + 0.5).  A sphere of
radius r at camera depth z projects to a disc of radius fx r / z pixels (the small-angle form used by screen-space
fluid rendering; the exact outline is a slightly larger ellipse off-axis).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from tasks.generation.impostor_kernels import splat_ellipsoid_pixels


class EffectFrame(NamedTuple):
    """One rendered frame of a secondary effect, laid out like the G-buffer it replaces.

    rgb: (y, x, channel=3) float32 linear RGB in [0, 1], the background with the effect drawn over it.
    depth: (y, x) float32 metres along the camera axis, the effect's depth where it covers the pixel, else the
        surface depth passed in (+inf where nothing is seen).
    coverage: (y, x) float32 in [0, 1], the effect's opacity per pixel (0 where it is absent).
    """

    rgb: np.ndarray
    depth: np.ndarray
    coverage: np.ndarray


@dataclass(frozen=True)
class ProjectedParticles:
    """Particles in front of the camera, projected; every array is (particle,) and ``index`` maps back to the
    caller's particle order (used to seed per-particle randomness so it does not change between frames)."""

    index: np.ndarray  # int64, position in the caller's particle array
    u: np.ndarray  # px, image x of the centre
    v: np.ndarray  # px, image y of the centre
    z: np.ndarray  # m, camera depth of the centre
    radius_m: np.ndarray  # m
    radius_px: np.ndarray  # px, fx * radius_m / z


def check_frame_inputs(background_rgb: np.ndarray, surface_depth: np.ndarray) -> tuple[int, int]:
    """Validate a frame's ``background_rgb`` (y, x, 3) in [0, 1] and ``surface_depth`` (y, x) metres; returns (H, W)."""
    if background_rgb.ndim != 3 or background_rgb.shape[2] != 3:
        raise ValueError(f"background_rgb must be (y, x, 3) linear RGB, got shape {background_rgb.shape}")
    if surface_depth.shape != background_rgb.shape[:2]:
        raise ValueError(f"surface_depth must be (y, x) = {background_rgb.shape[:2]}, got {surface_depth.shape}")
    if np.isnan(surface_depth).any():
        raise ValueError("surface_depth holds NaN: use +inf where no surface is rendered")
    return background_rgb.shape[0], background_rgb.shape[1]


def project_particles(positions: np.ndarray, radii: np.ndarray | float, viewmat: np.ndarray, K: np.ndarray,
                      near_m: float = 1e-3) -> ProjectedParticles:
    """Pinhole projection of particle centres (OpenCV / gsplat camera, see the module doc).

    positions: (particle, xyz) world metres; radii: (particle,) or scalar, metres; viewmat: (4, 4) world-to-camera;
    K: (3, 3) intrinsics in pixels.  Particles whose front (z - r) is closer than ``near_m`` are dropped.
    """
    positions = np.asarray(positions, np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions must be (particle, 3) metres, got shape {positions.shape}")
    radii = np.broadcast_to(np.asarray(radii, np.float64), positions.shape[:1])
    if (radii <= 0).any() or not np.isfinite(positions).all():
        raise ValueError("radii must be > 0 metres and positions finite")
    viewmat, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    if viewmat.shape != (4, 4) or K.shape != (3, 3):
        raise ValueError(f"viewmat must be (4, 4) and K (3, 3), got {viewmat.shape} and {K.shape}")
    camera = positions @ viewmat[:3, :3].T + viewmat[:3, 3]
    front = camera[:, 2] - radii > near_m
    camera, index = camera[front], np.flatnonzero(front)
    z = camera[:, 2]
    return ProjectedParticles(index=index, u=K[0, 0] * camera[:, 0] / z + K[0, 2],
                              v=K[1, 1] * camera[:, 1] / z + K[1, 2], z=z, radius_m=radii[front],
                              radius_px=K[0, 0] * radii[front] / z)


def screen_boxes(u: np.ndarray, v: np.ndarray, radius_px: np.ndarray, width: int, height: int,
                 radius_y_px: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The pixel boxes around centres (u, v) +- radius_px along x and +- radius_y_px (default radius_px) along y,
    clipped to the image: ``(x0, x1, y0, y1)`` int64 arrays, x1 and y1 exclusive (empty where x1 <= x0 or y1 <= y0)."""
    radius_y_px = radius_px if radius_y_px is None else radius_y_px
    x0 = np.clip(np.floor(u - radius_px).astype(np.int64), 0, width)
    x1 = np.clip(np.ceil(u + radius_px).astype(np.int64) + 1, 0, width)
    y0 = np.clip(np.floor(v - radius_y_px).astype(np.int64), 0, height)
    y1 = np.clip(np.ceil(v + radius_y_px).astype(np.int64) + 1, 0, height)
    return x0, x1, y0, y1


def box_pixels(u: np.ndarray, v: np.ndarray, radius_px: np.ndarray, width: int, height: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every (particle, pixel) pair of the particles' screen boxes (:func:`screen_boxes`): ``(owner, px, py)`` int64
    arrays, one row per pair."""
    x0, x1, y0, y1 = screen_boxes(u, v, radius_px, width, height)
    box_w, box_h = x1 - x0, np.maximum(y1 - y0, 0)
    count = np.where(box_w > 0, box_w * box_h, 0)
    owner = np.repeat(np.arange(len(count)), count)
    local = np.arange(owner.size) - np.repeat(np.cumsum(count) - count, count)
    return owner, x0[owner] + local % np.maximum(box_w[owner], 1), y0[owner] + local // np.maximum(box_w[owner], 1)


def splat_sphere_impostors(particles: ProjectedParticles, surface_depth: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Sphere-impostor splatting (van der Laan, Green & Sainz, I3D 2009): z-buffered front depth and
    summed thickness of the particles, each drawn as the disc of its screen radius.

    At a pixel centre a normalised distance d (0 at the disc centre, 1 on its rim) from a particle, the sphere's
    front is at depth ``z - r sqrt(1 - d^2)`` and the chord through it is ``2 r sqrt(1 - d^2)`` long.  Fragments at
    or behind ``surface_depth`` (y, x) metres (the object's surface, +inf where none) are hidden.
    Returns ``(depth, thickness)``: (y, x) float64 metres; depth is +inf where no particle is seen, thickness 0.
    """
    height, width = surface_depth.shape
    # 1. enumerate the pixels of each particle's bounding box (one row per (particle, pixel) pair)
    owner, px, py = box_pixels(particles.u, particles.v, particles.radius_px, width, height)
    # 2. keep the pixel centres inside the disc and in front of the surface
    d2 = ((px + 0.5 - particles.u[owner]) ** 2 + (py + 0.5 - particles.v[owner]) ** 2) / particles.radius_px[owner] ** 2
    half_chord = particles.radius_m[owner] * np.sqrt(np.clip(1.0 - d2, 0.0, None))
    front = particles.z[owner] - half_chord
    keep = (d2 < 1.0) & (front < surface_depth[py, px])
    pixel = (py * width + px)[keep]
    # 3. z-buffer the front depth and sum the chords
    depth = np.full(height * width, np.inf)
    np.minimum.at(depth, pixel, front[keep])
    thickness = np.bincount(pixel, weights=2.0 * half_chord[keep], minlength=height * width)
    return depth.reshape(height, width), thickness.reshape(height, width)


def splat_ellipsoid_impostors(centres: np.ndarray, axes: np.ndarray, radii: np.ndarray, viewmat: np.ndarray,
                              K: np.ndarray, surface_depth: np.ndarray, near_m: float = 1e-3
                              ) -> tuple[np.ndarray, np.ndarray, float]:
    """Ellipsoid impostors (the anisotropic kernels of :mod:`tasks.generation.anisotropic`): z-buffered front depth
    and summed thickness, exact per pixel-centre ray.

    centres (n, 3) world m; axes (n, 3, 3) unit principal directions (columns), world; radii (n, 3) m; viewmat,
    K: the camera (module doc); surface_depth (y, x) m: fragments at or behind it are hidden.  For a ray x = t d
    (d = ((u - cx) / fx, (v - cy) / fy, 1), so t is the camera depth) and an ellipsoid (x - c)^T A (x - c) = 1,
    A = Q diag(radii^-2) Q^T: a t^2 - 2 b t + (c^T A c - 1) = 0 with a = d^T A d, b = d^T A c; the front is at
    (b - sqrt(b^2 - a (c^T A c - 1))) / a, the chord (t2 - t1) |d| long.
    Returns ``(depth, thickness, median screen radius px)``: (y, x) float64 metres (depth +inf where nothing).
    The per-ellipsoid set-up is numpy, the per-pixel work a Warp kernel (:mod:`tasks.generation.impostor_kernels`)."""
    height, width = surface_depth.shape
    viewmat, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    rot = viewmat[:3, :3]
    c = np.asarray(centres, np.float64) @ rot.T + viewmat[:3, 3]
    q = np.einsum("ij,njk->nik", rot, np.asarray(axes, np.float64))
    r = np.asarray(radii, np.float64)
    rmax = r.max(axis=1)
    front = c[:, 2] - rmax > near_m
    c, q, r, rmax = c[front], q[front], r[front], rmax[front]
    if len(c) == 0:
        return np.full((height, width), np.inf), np.zeros((height, width)), 1.0
    A = np.einsum("nik,nk,njk->nij", q, 1.0 / r ** 2, q)
    spread = np.einsum("nik,nk,njk->nij", q, r ** 2, q)  # A^-1: the ellipsoid's extent along x is sqrt(spread_xx)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u, v = fx * c[:, 0] / c[:, 2] + cx, fy * c[:, 1] / c[:, 2] + cy
    z_near = c[:, 2] - rmax
    # screen box: a point c + e of the ellipsoid projects |u - u_c| = |fx e_x - (u_c - cx) e_z| / (c_z + e_z) from
    # the centre's pixel, at most (fx E_x + |u_c - cx| E_z) / z_near with E the ellipsoid's extents along the axes
    extent = np.sqrt(np.einsum("nii->ni", spread))
    half_x = (fx * extent[:, 0] + np.abs(u - cx) * extent[:, 2]) / z_near + 1.0
    half_y = (fy * extent[:, 1] + np.abs(v - cy) * extent[:, 2]) / z_near + 1.0
    Ac = np.einsum("nij,nj->ni", A, c)
    quadric = np.column_stack([A[:, 0, 0], A[:, 1, 1], A[:, 2, 2], A[:, 0, 1], A[:, 0, 2], A[:, 1, 2], Ac,
                               np.einsum("ni,ni->n", c, Ac) - 1.0])
    box = np.column_stack(screen_boxes(u, v, half_x, width, height, half_y))
    depth, thickness = splat_ellipsoid_pixels(quadric, box, fx, fy, cx, cy, near_m, surface_depth)
    return depth, thickness, float(np.median(fx * rmax / z_near))
