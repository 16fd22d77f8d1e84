"""Anisotropic particle kernels for rendering a released liquid as one body (Yu & Turk, "Reconstructing Surfaces of
Particle-Based Fluids Using Anisotropic Kernels", ACM TOG 32(1), 2013), rendering only: the particles' simulated
positions are not changed in any artifact.

For each particle i, over its neighbours j within the support ``h`` (isotropic weight w_ij = 1 - (r_ij / h)^3):

1. weighted mean x^w_i = sum_j w_ij x_j / sum_j w_ij and covariance C_i = sum_j w_ij (x_j - x^w_i)(x_j - x^w_i)^T /
   sum_j w_ij (the principal axes of the neighbourhood);
2. with at least ``min_neighbours`` neighbours, the kernel's axis lengths follow sqrt of C_i's eigenvalues, the
   shorter ones clamped to at least 1 / ``max_ratio`` of the longest (Yu & Turk's k_r), scaled so that the
   ellipsoid keeps the volume of the particle's own sphere (axes' product = radius^3); fewer neighbours: a sphere
   of ``lonely_scale`` x the radius (an isolated drop);
3. Laplacian smoothing of the kernel centres, x~_i = (1 - lambda) x_i + lambda x^w_i (Yu & Turk's lambda = 0.9), which
   flattens the surface of a sheet or a puddle.

Along a stream a particle's neighbours lie on a line: its kernel stretches along the stream and thins across it, so
neighbouring kernels overlap into one continuous body; in a puddle on the table they lie in a plane: the kernels
become discs.  Units: metres.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class AnisotropySettings:
    """Yu & Turk's parameters: support h = ``support_radii`` x the particle radius; k_r = ``max_ratio``; N_eps =
    ``min_neighbours``; lambda = ``smoothing``; an isolated particle's sphere is ``lonely_scale`` x its radius;
    ``inflate`` scales every kernel (1: the particle's own volume)."""

    support_radii: float = 4.0
    max_ratio: float = 4.0
    min_neighbours: int = 4
    smoothing: float = 0.9
    lonely_scale: float = 0.8
    inflate: float = 1.25


YU_TURK = AnisotropySettings()
BRIDGE_NEIGHBOURS = 3  # nearest neighbours a released particle is bridged to (bridge_particles)


class Ellipsoids(NamedTuple):
    """Kernel ellipsoids: centres (n, 3) m, axes (n, 3, 3) unit principal directions as columns, radii (n, 3) m."""

    centres: np.ndarray
    axes: np.ndarray
    radii: np.ndarray


def anisotropic_kernels(positions: np.ndarray, radii: np.ndarray | float,
                        settings: AnisotropySettings = YU_TURK) -> Ellipsoids:
    """Yu & Turk's anisotropic kernels (module doc) for particles at ``positions`` (n, 3) m with sphere radii
    ``radii`` (n,) or scalar, m.  Returns :class:`Ellipsoids`."""
    x = np.asarray(positions, np.float64)
    n = len(x)
    r = np.broadcast_to(np.asarray(radii, np.float64), (n,)).copy()
    if n == 0:
        return Ellipsoids(np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)))
    h = settings.support_radii * float(np.median(r))
    pairs = cKDTree(x).query_pairs(h, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
    j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
    dist = np.linalg.norm(x[i] - x[j], axis=1)
    w = 1.0 - (dist / h) ** 3
    total = np.bincount(i, weights=w, minlength=n)
    mean = np.stack([np.bincount(i, weights=w * x[j, c], minlength=n) for c in range(3)], -1) / total[:, None]
    d = x[j] - mean[i]
    cov = np.zeros((n, 3, 3))
    for a in range(3):
        for b in range(a, 3):
            cov[:, a, b] = cov[:, b, a] = np.bincount(i, weights=w * d[:, a] * d[:, b], minlength=n) / total
    neighbours = np.bincount(i, minlength=n) - 1
    values, vectors = np.linalg.eigh(cov)  # ascending
    lengths = np.sqrt(np.clip(values, 0.0, None))
    longest = lengths[:, 2:3]
    lengths = np.maximum(lengths, longest / settings.max_ratio)
    shaped = (neighbours >= settings.min_neighbours) & (longest[:, 0] > 0)
    norm = np.cbrt(np.prod(np.where(shaped[:, None], lengths, 1.0), axis=1))
    unit = np.where(shaped[:, None], lengths / np.where(norm > 0, norm, 1.0)[:, None], 1.0)
    scale = settings.inflate * r * np.where(shaped, 1.0, settings.lonely_scale)
    centres = np.where(shaped[:, None], (1.0 - settings.smoothing) * x + settings.smoothing * mean, x)
    return Ellipsoids(centres, vectors, unit * scale[:, None])


def bridge_particles(positions: np.ndarray, radii: np.ndarray | float, reach: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """More render particles than simulation particles, along the released flow (rendering only): between each
    particle and each of its ``BRIDGE_NEIGHBOURS`` nearest neighbours closer than ``reach`` x their mean radius
    whose spheres leave a gap (centres farther apart than 1.5 radii), render particles evenly spaced on the segment
    joining them, one per 1.5 radii of its length, with the smaller of the two radii.  Particles that the simulation keeps together (a stream, a sheet, a puddle spread
    on the table) then draw as one body; particles farther apart stay separate drops.

    positions (n, 3) m, radii (n,) or scalar m.  Returns ``(positions, radii)`` of the originals followed by the
    bridges, (n + m, 3) and (n + m,) m."""
    x = np.asarray(positions, np.float64)
    r = np.broadcast_to(np.asarray(radii, np.float64), (len(x),)).copy()
    if len(x) < 2:
        return x, r
    k = min(BRIDGE_NEIGHBOURS, len(x) - 1)
    dist, near = cKDTree(x).query(x, k=k + 1, distance_upper_bound=reach * float(np.max(r)))
    i = np.repeat(np.arange(len(x)), k)
    j, dist = near[:, 1:].ravel(), dist[:, 1:].ravel()
    found = np.isfinite(dist)
    i, j, dist = i[found], j[found], dist[found]
    i, j = np.minimum(i, j), np.maximum(i, j)
    unique = np.unique(i * len(x) + j, return_index=True)[1]  # a pair found from both ends is bridged once
    i, j, dist = i[unique], j[unique], dist[unique]
    mean_r = 0.5 * (r[i] + r[j])
    keep = (dist < reach * mean_r) & (dist > 1.5 * mean_r)
    i, j, dist, mean_r = i[keep], j[keep], dist[keep], mean_r[keep]
    count = np.ceil(dist / (1.5 * mean_r)).astype(np.int64) - 1  # inner points per segment
    owner = np.repeat(np.arange(len(i)), count)
    step = np.arange(owner.size) - np.repeat(np.cumsum(count) - count, count) + 1
    t = step / (count[owner] + 1.0)
    bridges = x[i[owner]] + t[:, None] * (x[j[owner]] - x[i[owner]])
    return np.concatenate([x, bridges]), np.concatenate([r, np.minimum(r[i], r[j])[owner]])
