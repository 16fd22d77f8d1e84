"""Object model: what the method needs from one object config.

:func:`build_object_model` and its helpers are pure functions (numpy/scipy/trimesh; no Prefect, no zarr); the
cached Prefect step :data:`object_model_step` at the bottom only wraps it for :mod:`flows.pipeline`.

VirSqueezer (paper sec. "Squeezing Control Mapping" and "Physics Simulation") represents an object twice:

* **3D Gaussians on the surface** (Kerbl et al. 2023): their means are the surface samples on which contact
  patches (SC-CAE, eq. 2) and the displacement field (eq. 3) are evaluated, so each sample also carries its
  outward normal, principal curvatures/directions and the area it represents;
* **MPM volume particles** of the object's own material (MLS-MPM, Hu et al. 2018; PhysGaussian, Xie et al.
  2024 fills the volume in the same way), plus, for filled containers, particles of the interior material.

:func:`build_object_model` returns both for a procedural shape (:mod:`tasks.control.geometry`), a triangle mesh
(``kind: mesh``, loaded with trimesh) or a 3DGS PLY (``kind: ply``, :mod:`tasks.control.gaussian_ply`).  All lengths
are metres, areas m^2, volumes m^3; positions are float32.

A mesh or PLY is centred at the origin and scaled uniformly to fit ``geometry.size`` (m), the size the physics
uses: :mod:`flows.preflight` prints the scale factor when it is not 1 and refuses a factor outside
``FIT_SCALE_RANGE`` (a file of 1 km or 1 um is a units mistake); a flat (zero-volume) mesh is refused.

A mesh must be one closed surface: an open (non-watertight) mesh or one that intersects itself (e.g. a body and
a head modelled as two overlapping closed shells) is refused, not repaired.  Both leave inside and outside
undefined where it matters: the enclosed volume (divergence theorem) counts an overlap twice, the
voxel fill and the signed distance disagree there, and surface samples - the Gaussians the fingers touch and
the contact patches - would lie on faces buried inside the body.  A silent repair (hole filling, boolean
union) would change the user's geometry without saying so; the error names the file and the repair to do.
Self-intersection is found by :func:`tasks.control.geometry.crossing_triangle_pairs` (exact triangle-triangle
crossings; coplanar overlaps and folds between neighbouring faces are not detected).

Discretisation choices (documented here because downstream steps rely on them):

* Surface samples are blue-noise: random area-uniform candidates (5 per sample) thinned by greedy Poisson-disk
  selection in random order (dart throwing restricted to the candidates, Cook 1986) to exactly
  ``sampling.surface_points`` samples.  ``surface_area`` is each sample's Voronoi share of the surface (the
  area measure of the fine marching-tetrahedra mesh, or of dense samples, assigned to the nearest sample), so
  it sums to the total area.
* Curvature: analytic (sphere, cup) or from the implicit function's Hessian (procedural shapes), or from a
  weighted least-squares quadric fit ``h = a x^2 + b x y + c y^2 + d x + e y`` over the 16 nearest samples in
  the tangent frame (mesh, ply); sign: convex = positive; magnitudes are clamped to ``2 / sqrt(area_i)`` (the
  representation cannot resolve sharper features, e.g. the cup's bottom crease).
* Gaussians: tangent standard deviations ``0.6 sqrt(area_i)`` (neighbours overlap at ~1 sigma), normal std
  ``0.1`` of that; rotation maps local (x, y, z) to (k1 direction, k2 direction, normal).
* Volume particles on a cell-centred grid of spacing ``s = sampling.particle_spacing`` jittered by +-0.2 s
  (deterministic from ``sampling.seed`` and the object's geometry, not its name: :func:`sampling_seed`):
  - ``filled: true``: every grid point inside the body; volumes = ``s^3`` rescaled to the enclosed volume;
  - hollow with ``wall_thickness t`` at least the grid spacing dx (``mpm.dx``, or ``s x cbrt(mpm.particles_per_cell)``
    as the rollout chooses it): grid points with ``-t < sdf < 0`` (the wall), volumes rescaled to the wall volume
    ``V(sdf < 0) - V(sdf < -t)``;
  - hollow with ``t < dx`` (``thin_wall``: the solver holds such a wall in plane stress, ``mpm.thin_walls``, and the
    grid cannot resolve its thickness; before 2026-12-03 only ``t < s``, which left the orange's 4 mm peel on the
    default 8 mm grid a one-layer membrane with no bending): one layer of Poisson-disk particles (spacing ~ s) on the wall's
    mid-surface (``t/2`` inside the outer surface; on the sheet itself for the open cup), each with volume =
    its Voronoi area share x the depth volume of Steiner's formula, ``t - (k1 + k2) t^2 / 2 + k1 k2 t^3 / 3`` at its
    principal curvatures (:func:`shell_depth_volume`), so the total is the exact shell's and the wall mass is
    physical (before 2026-12-04 area x t, 11 % heavy on the orange's peel, 9 % on the ball's wall); on the open cup's
    sheet, its own mid-surface, area x t; with
    ``sampling.thin_wall_layers: 2`` (the default) that layer is split into two at the thickness's Gauss points,
    ``+-t / (2 sqrt 3)`` along the normal, each particle with half the volume: the two-point rule integrates a
    strain linear through the thickness exactly, so a plane-stress wall (``mpm.thin_walls: membrane``) carries the
    bending energy ``E t^3 / (12 (1 - nu^2)) kappa^2 / 2`` per area of a curvature kappa of the grid's field (two
    layers at +-t/2 would carry 3x); with ``3`` into three, at ``0`` and ``+-sqrt(3/5) t / 2`` with 8/18 and 5/18
    of the volume (:func:`~tasks.physics.mpm.thin_walls.gauss_layers`), which also integrate the strain's quadratic
    part: a wall near a cell's
    thickness, whose grid field has one, bends too easily in two (a clamped strip 0.86 of a cell thick sags 1.23x
    Euler-Bernoulli in two layers, 1.03x in three, where the grid's clamp makes 1.04x; README, known limits);
    ``wall_fibres`` (fibre, layer) joins each outer particle to its inner twin (and the middle one), the wall's normal
    fibre, whose ends the solver keeps at their rest distance (``mpm.wall_fibres``); empty otherwise;
  - ``interior`` set: grid points with ``sdf < -max(t, s/2)`` (half a spacing clear of the wall layer), volumes
    rescaled to the cavity volume ``V(sdf < 0) - wall volume``.  These cavity particles are the object's geometry
    only: the rollout fills them with the oracle's ``core`` (fruit flesh, stuffing: part of the body) or, without
    a core, with the interior material itself, and only when it can be released.
  ``particle_normals`` is the outward normal of the object's outer surface nearest to each particle
  (``grad sdf``), also for particles inside a thick wall.
"""
from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from tasks.control.gaussian_ply import read_gaussian_ply
from tasks.control.geometry import (
    SHAPE_KINDS,
    Shape,
    crossing_triangle_pairs,
    make_shape,
    marching_tetrahedra,
    soup_area,
    soup_volume,
    tangent_basis,
)
from tasks.core.artifacts import Array
from tasks.core.excerpt import one_line
from tasks.core.params import file_sha256
from tasks.core.step import artifact_step
from tasks.physics.mpm.thin_walls import gauss_layers
from tasks.physics.wall_resolution import grid_spacing

__all__ = [
    "ObjectModelError", "build_object_model", "poisson_disk", "quadric_curvature", "matrix_to_quaternion",
    "surface_colors", "PATTERNS",
]

PATTERNS = ("solid", "bands", "label", "speckle", "dimples", "stripes", "fur")
SILVER = np.array([0.62, 0.63, 0.66])  # linear RGB of brushed aluminium
DARK = np.array([0.02, 0.02, 0.02])
_JITTER = 0.2  # fraction of the spacing
_TANGENT_SIGMA = 0.6  # x sqrt(area_i)
_NORMAL_SIGMA = 0.1  # x tangent sigma
_CANDIDATES_PER_SAMPLE = 5


class ObjectModelError(ValueError):
    """An object config or input file that cannot be turned into an object model (one line, names the fix)."""


# ----------------------------------------------------------------------------------------------- helpers
def _get(node: Any, name: str, default: Any = None) -> Any:
    """``node.name`` of a config node or dataclass, ``node[name]`` of a plain mapping (step params)."""
    if node is None:
        return default
    if isinstance(node, Mapping):
        return node.get(name, default)
    return getattr(node, name, default)


def _unit(v: np.ndarray, fallback=(0.0, 0.0, 1.0)) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    out = np.where(n > 1e-12, v / np.maximum(n, 1e-300), np.asarray(fallback, float))
    return out


def poisson_disk(points: np.ndarray, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Indices (sorted) of a maximal subset of ``points`` with pairwise distances >= ``radius`` (m): the greedy
    dart-throwing result for random priorities, computed in parallel rounds (a point is kept when its priority
    beats every still-undecided neighbour's, Luby-style); deterministic for a given generator state."""
    m = len(points)
    prio = rng.permutation(m)
    if m == 0:
        return np.zeros(0, dtype=np.int64)
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return np.arange(m)
    src = np.concatenate([pairs[:, 0], pairs[:, 1]])
    dst = np.concatenate([pairs[:, 1], pairs[:, 0]])
    state = np.zeros(m, np.int8)  # 0 undecided, 1 kept, -1 removed
    while True:
        und = state == 0
        if not und.any():
            break
        live = und[src] & und[dst]
        s_, d_ = src[live], dst[live]
        best = np.full(m, m, dtype=prio.dtype)
        np.minimum.at(best, s_, prio[d_])
        keep = und & (prio < best)
        state[keep] = 1
        state[d_[keep[s_]]] = -1
    return np.nonzero(state == 1)[0]


def _thin_to(points: np.ndarray, idx: np.ndarray, n: int) -> np.ndarray:
    """Drop samples from ``points[idx]`` until ``n`` remain, always one of the currently closest pairs."""
    idx = np.asarray(idx)
    while len(idx) > n:
        excess = len(idx) - n
        d, j = cKDTree(points[idx]).query(points[idx], k=2)
        order = np.argsort(d[:, 1], kind="stable")
        drop = np.zeros(len(idx), bool)
        protected = np.zeros(len(idx), bool)
        budget = max(1, min(excess, len(idx) // 20))
        for i in order:
            if budget == 0:
                break
            if protected[i] or drop[i]:
                continue
            drop[i] = True
            protected[j[i, 1]] = True
            budget -= 1
        idx = idx[~drop]
    return idx


def _blue_noise(points: np.ndarray, n: int, area: float, rng: np.random.Generator) -> np.ndarray:
    """Exactly ``n`` well-spread indices into area-uniform candidate ``points`` covering ``area`` m^2."""
    if len(points) <= n:
        return np.arange(len(points))
    r = math.sqrt(0.46 * area / n)  # ~1.03 n selected from a pool of 5 n candidates
    for _ in range(8):
        idx = poisson_disk(points, r, rng)
        if len(idx) >= n:
            return _thin_to(points, idx, n)
        r *= math.sqrt(len(idx) / (1.04 * n))
    # not enough with any radius tried (tiny candidate set): random extra candidates
    rest = np.setdiff1d(np.arange(len(points)), idx)
    return np.sort(np.concatenate([idx, rng.choice(rest, n - len(idx), replace=False)]))


def resolved_curvature(curvature: np.ndarray, area: np.ndarray) -> np.ndarray:
    """Principal curvatures (1/m, shape (n, 2)) clamped to +-2 / sqrt(area) (area m^2 per sample: the representation
    resolves no sharper feature, e.g. the cup's bottom crease)."""
    kmax = 2.0 / np.sqrt(np.maximum(area, 1e-30))
    return np.clip(curvature, -kmax[:, None], kmax[:, None])


def shell_depth_volume(curvature: np.ndarray, t: float, area: np.ndarray) -> np.ndarray:
    """Volume (m^3) per m^2 of outer surface of a wall of thickness ``t`` (m) below a surface patch of principal
    curvatures ``curvature`` (1/m, shape (n, 2), convex positive): Steiner's formula for the inward parallel surfaces,
    int_0^t (1 - k1 d)(1 - k2 d) dd = t - (k1 + k2) t^2 / 2 + k1 k2 t^3 / 3 (a sphere's shell: 4 pi (R^3 - (R - t)^3)
    / 3 exactly; area x t overstates the orange's peel by 11 % at t / R = 0.1).  Curvatures are clamped to
    ``2 / sqrt(area)`` (:func:`resolved_curvature`) and the depth to the centre of curvature ``1 / k``, so a crease
    sharper than the wall keeps a positive volume."""
    k = resolved_curvature(curvature, area)
    k1, k2 = k[:, 0], k[:, 1]
    d = np.minimum(t, 1.0 / np.maximum(np.maximum(k1, k2), 1e-30))  # no parallel surface past a focal point
    return d - (k1 + k2) * d ** 2 / 2 + k1 * k2 * d ** 3 / 3


def _voronoi_area(sites: np.ndarray, measure_pts: np.ndarray, measure_w: np.ndarray, floor: float = 0.25) -> np.ndarray:
    """Area (m^2) of each site: the area measure (points with weights) assigned to the nearest site; each share
    is floored at ``floor`` x the mean and the result renormalised to the measure's total.  The measure is
    first lumped into cubic bins of 0.4 x the mean site spacing (weighted centroids) to bound the cost."""
    total = float(measure_w.sum())
    bin_size = 0.4 * math.sqrt(total / max(len(sites), 1))
    if len(measure_pts) > 4 * len(sites) and bin_size > 0:
        key = np.floor((measure_pts - measure_pts.min(0)) / bin_size).astype(np.int64)
        dims = key.max(0) + 1
        flat = (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]
        _, inv = np.unique(flat, return_inverse=True)
        w = np.bincount(inv, weights=measure_w)
        c = np.stack([np.bincount(inv, weights=measure_w * measure_pts[:, i]) for i in range(3)], 1)
        measure_pts, measure_w = c / np.maximum(w, 1e-300)[:, None], w
    _, nearest = cKDTree(sites).query(measure_pts, k=1)
    a = np.bincount(nearest, weights=measure_w, minlength=len(sites))
    a = np.maximum(a, floor * total / len(sites))
    return a * (total / a.sum())


def quadric_curvature(points: np.ndarray, normals: np.ndarray, query: np.ndarray, query_normals: np.ndarray,
                      k: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Principal curvatures (Q, 2) 1/m (k1 >= k2, convex positive) and directions (Q, 2, 3) at ``query`` points
    from a Gaussian-weighted least-squares fit of ``h = a x^2 + b x y + c y^2 + d x + e y`` to the ``k`` nearest
    of ``points`` in the tangent frame (x, y, h along the outward normal) of each query (osculating quadric,
    e.g. Cazals & Pouget 2005 "jet fitting").  Shape operator ``-[[2a, b], [b, 2c]]`` (linear terms absorb
    a tilted normal)."""
    k = int(min(k, len(points) - 1))
    if k < 5:
        z = np.zeros((len(query), 2))
        u, v = tangent_basis(query_normals)
        return z, np.stack([u, v], axis=1)
    _, idx = cKDTree(points).query(query, k=k + 1)
    nb = points[idx] - query[:, None, :]
    n = query_normals
    u, v = tangent_basis(n)
    x = np.einsum("qkj,qj->qk", nb, u)
    y = np.einsum("qkj,qj->qk", nb, v)
    h = np.einsum("qkj,qj->qk", nb, n)
    r2 = x * x + y * y
    w = np.exp(-r2 / np.maximum(r2.mean(axis=1, keepdims=True), 1e-30))
    A = np.stack([x * x, x * y, y * y, x, y], axis=-1)
    scale = np.sqrt(np.maximum(r2.mean(axis=1), 1e-30))  # condition the system per query
    S = np.array([1, 1, 1, 0, 0])[None, :] * (1 / scale[:, None] ** 2) + np.array([0, 0, 0, 1, 1])[None, :] * (1 / scale[:, None])
    As = A * S[:, None, :]
    ATA = np.einsum("qki,qk,qkj->qij", As, w, As) + 1e-9 * np.eye(5)
    ATb = np.einsum("qki,qk,qk->qi", As, w, h)
    coef = np.linalg.solve(ATA, ATb[..., None])[..., 0] * S
    a, b, c = coef[:, 0], coef[:, 1], coef[:, 2]
    Wm = -np.stack([np.stack([2 * a, b], -1), np.stack([b, 2 * c], -1)], -2)
    evals, evecs = np.linalg.eigh(Wm)
    kk = evals[:, ::-1]
    d1 = evecs[:, 0, 1][:, None] * u + evecs[:, 1, 1][:, None] * v
    d1 = _unit(d1)
    d2 = np.cross(n, d1)
    return kk, np.stack([d1, d2], axis=1)


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (N, 4) ``w, x, y, z`` (w >= 0) of rotation matrices (N, 3, 3) (Shepperd's method)."""
    R = np.asarray(R, dtype=np.float64)
    m00, m11, m22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    tr = m00 + m11 + m22
    q = np.zeros((len(R), 4))
    c0 = tr > 0
    c1 = ~c0 & (m00 >= m11) & (m00 >= m22)
    c2 = ~c0 & ~c1 & (m11 >= m22)
    c3 = ~c0 & ~c1 & ~c2
    s = np.sqrt(np.maximum(tr[c0] + 1, 1e-30)) * 2
    q[c0] = np.stack([0.25 * s, (R[c0, 2, 1] - R[c0, 1, 2]) / s, (R[c0, 0, 2] - R[c0, 2, 0]) / s,
                      (R[c0, 1, 0] - R[c0, 0, 1]) / s], 1)
    s = np.sqrt(np.maximum(1 + m00[c1] - m11[c1] - m22[c1], 1e-30)) * 2
    q[c1] = np.stack([(R[c1, 2, 1] - R[c1, 1, 2]) / s, 0.25 * s, (R[c1, 0, 1] + R[c1, 1, 0]) / s,
                      (R[c1, 0, 2] + R[c1, 2, 0]) / s], 1)
    s = np.sqrt(np.maximum(1 + m11[c2] - m00[c2] - m22[c2], 1e-30)) * 2
    q[c2] = np.stack([(R[c2, 0, 2] - R[c2, 2, 0]) / s, (R[c2, 0, 1] + R[c2, 1, 0]) / s, 0.25 * s,
                      (R[c2, 1, 2] + R[c2, 2, 1]) / s], 1)
    s = np.sqrt(np.maximum(1 + m22[c3] - m00[c3] - m11[c3], 1e-30)) * 2
    q[c3] = np.stack([(R[c3, 1, 0] - R[c3, 0, 1]) / s, (R[c3, 0, 2] + R[c3, 2, 0]) / s,
                      (R[c3, 1, 2] + R[c3, 2, 1]) / s, 0.25 * s], 1)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ----------------------------------------------------------------------------------------------- colours
def _smooth_noise(p: np.ndarray, wavelength: float, seed: int, waves: int = 12) -> np.ndarray:
    """Band-limited 3-D noise in about [-1, 1]: a sum of ``waves`` random plane waves of the given wavelength
    (m) with random directions and phases (deterministic from ``seed``)."""
    rng = np.random.default_rng([seed, 7919])
    d = _unit(rng.normal(size=(waves, 3)))
    freq = 2 * np.pi / wavelength * rng.uniform(0.7, 1.3, size=waves)
    ph = rng.uniform(0, 2 * np.pi, size=waves)
    return np.sin(p @ (d * freq[:, None]).T + ph).sum(axis=1) * math.sqrt(2.0 / waves)


def surface_colors(pattern: str, kind: str, points: np.ndarray, normals: np.ndarray, bbox_min: np.ndarray,
                   bbox_max: np.ndarray, base, accent, regions: dict[str, np.ndarray] | None = None,
                   seed: int = 0) -> np.ndarray:
    """Linear-RGB colours (N, 3) in [0, 1] of surface samples from a procedural pattern.

    Coordinates are normalised to the bbox: ``c = (p - centre) / half_extent`` in [-1, 1]^3, ``theta`` the
    azimuth about z, ``phi`` the polar angle from +z.

    * ``solid``   the base colour.
    * ``label``   beverage can: silver (brushed aluminium) lid, rims and bottom (the shape's ``top``/``bottom``
                  regions or ``|c_z| > 0.85``), base-coloured body with an accent-coloured wavy label ribbon
                  ``|c_z - 0.12 sin(2 theta)| < 0.16``.
    * ``bands``   paper cup: base colour with an accent band over ``c_z`` in [-0.35, 0.25] and a thin accent
                  line just below the rim ``c_z`` in [0.80, 0.88].
    * ``speckle`` base colour mottled by +-10 % (smooth noise, 8 mm) and small flecks; on sphere/ellipsoid
                  kinds the accent colour draws a star-shaped calyx (5 sepals) around the top pole (a fruit).
    * ``dimples`` base colour with darker peel pores (noise at 3 mm wavelength, up to -22 %) and an
                  accent-coloured stem scar at the top pole (``phi < 0.09``).
    * ``stripes`` six meridional segments alternating base and accent (a beach-ball style rubber ball).
    * ``fur``     base colour with per-sample brightness jitter (+-18 %) and 12 mm mottling.
    Part regions of the shape then override: ``bill``/``ears`` -> accent, ``muzzle``/``paws`` -> base lightened
    40 % towards white, ``eyes``/``nose`` -> near black.
    """
    if pattern not in PATTERNS:
        raise ObjectModelError(f"appearance.pattern {pattern!r} is unknown: use one of {list(PATTERNS)}")
    base = np.clip(np.asarray(base, float).reshape(3), 0, 1)
    accent = np.clip(np.asarray(accent, float).reshape(3), 0, 1)
    p = np.asarray(points, float)
    n_pts = len(p)
    mid = 0.5 * (bbox_min + bbox_max)
    half = np.maximum(0.5 * (bbox_max - bbox_min), 1e-9)
    c = (p - mid) / half
    theta = np.arctan2(c[:, 1], c[:, 0])
    phi = np.arccos(np.clip(c[:, 2] / np.maximum(np.linalg.norm(c, axis=1), 1e-12), -1, 1))
    regions = regions or {}
    rgb = np.tile(base, (n_pts, 1))
    hash_rng = np.random.default_rng([seed, 104729])

    if pattern == "label":
        silver = (np.abs(c[:, 2]) > 0.85)
        if "top" in regions:
            silver = regions["top"] | regions["bottom"]
        ribbon = np.abs(c[:, 2] - 0.12 * np.sin(2 * theta)) < 0.16
        rgb[ribbon & ~silver] = accent
        rgb[silver] = SILVER * (1 + 0.05 * _smooth_noise(p, 0.004, seed))[silver, None]
    elif pattern == "bands":
        band = (c[:, 2] > -0.35) & (c[:, 2] < 0.25)
        line = (c[:, 2] > 0.80) & (c[:, 2] < 0.88)
        rgb[band | line] = accent
    elif pattern == "speckle":
        mottle = 1 + 0.10 * _smooth_noise(p, 0.008, seed) + 0.05 * hash_rng.uniform(-1, 1, n_pts)
        rgb = rgb * mottle[:, None]
        if kind in ("sphere", "ellipsoid"):
            star = 0.10 + 0.32 * (0.5 + 0.5 * np.cos(5 * theta)) ** 3
            rgb[phi < star] = accent * (1 + 0.08 * _smooth_noise(p, 0.005, seed + 1))[phi < star, None]
    elif pattern == "dimples":
        pores = np.clip(_smooth_noise(p, 0.003, seed), 0, None)
        rgb = rgb * (1 - 0.22 * np.minimum(pores, 1.0))[:, None]
        rgb[phi < 0.09] = accent
    elif pattern == "stripes":
        seg = np.floor((theta + np.pi) / (2 * np.pi) * 6).astype(int) % 2 == 1
        rgb[seg] = accent
    elif pattern == "fur":
        mottle = (1 + 0.18 * hash_rng.uniform(-1, 1, n_pts)) * (1 + 0.08 * _smooth_noise(p, 0.012, seed))
        rgb = rgb * mottle[:, None]

    for name, mask in regions.items():
        if name in ("bill", "ears"):
            rgb[mask] = accent * (1 + 0.08 * hash_rng.uniform(-1, 1, int(mask.sum())))[:, None] \
                if pattern == "fur" else accent
        elif name in ("muzzle", "paws"):
            rgb[mask] = base + 0.4 * (1 - base)
        elif name in ("eyes", "nose"):
            rgb[mask] = DARK
    return np.clip(rgb, 0.0, 1.0)


# ----------------------------------------------------------------------------------------------- sources
class _Source:
    """What the builder needs from a geometry: surface candidates, an approximate signed distance, measures."""

    kind: str
    open_top = False
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    area_total: float
    enclosed_volume: float

    def candidates(self, n: int, rng: np.random.Generator) -> np.ndarray: ...
    def finalize(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def area_measure(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]: ...
    def curvature(self, pts: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...
    def sdf(self, p: np.ndarray) -> np.ndarray: ...
    def normals(self, p: np.ndarray) -> np.ndarray: ...
    def volume_below(self, level: float) -> float: ...
    def open_distance(self, p: np.ndarray) -> np.ndarray: return np.abs(self.sdf(p))
    def regions(self, p: np.ndarray) -> dict[str, np.ndarray]: return {}
    def colors(self, idx: np.ndarray) -> np.ndarray | None: return None


class _ProceduralSource(_Source):
    def __init__(self, shape: Shape) -> None:
        self.shape = shape
        self.kind = shape.kind
        self.open_top = shape.open_top
        self.bbox_min, self.bbox_max = shape.bbox_min.copy(), shape.bbox_max.copy()
        self.area_total = float(shape.surface_area())
        self.enclosed_volume = float(shape.enclosed_volume())

    def candidates(self, n, rng):
        if self.shape.kind in ("sphere", "cup"):
            return self.shape.sample_surface(n, rng)  # analytic, exact
        tris = self.shape.mesh(0.0)
        area = self.shape.triangle_areas()
        idx = rng.choice(len(tris), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        t = tris[idx]
        return (1 - s)[:, None] * t[:, 0] + (s * (1 - r2))[:, None] * t[:, 1] + (s * r2)[:, None] * t[:, 2]

    def finalize(self, pts):
        if self.shape.kind not in ("sphere", "cup"):
            pts = self.shape.project(pts)
        return pts, self.shape.normals(pts)

    def area_measure(self, rng):
        if self.shape.kind in ("sphere", "cup"):
            m = 40000
            return self.shape.sample_surface(m, rng), np.full(m, self.area_total / m)
        tris = self.shape.mesh(0.0)
        w = self.shape.triangle_areas()
        return tris.mean(axis=1), w * (self.area_total / w.sum())

    def curvature(self, pts, nrm):
        k, d, _ = self.shape.curvature(pts)
        return k, d

    def sdf(self, p):
        return self.shape.sdf(p)

    def normals(self, p):
        return self.shape.normals(p)

    def volume_below(self, level):
        return float(self.shape.volume_below(level))

    def open_distance(self, p):
        return self.shape.open_distance(p)

    def regions(self, p):
        return self.shape.regions(p)


class _SampledSource(_Source):
    """Geometry known by dense oriented surface samples plus a filled occupancy grid (mesh and ply inputs).

    Signed distance: first the distance to the surface sample nearest to the closest boundary voxel (feature
    transform of the occupancy boundary; within about a voxel of the truth), signed by the occupancy; where
    that is below ``refine_dist`` (the depths the wall/cavity split needs) the exact nearest sample is looked
    up (no kd-tree query deep inside, where it cannot prune): point-to-plane distance within 3 sample spacings
    of it (sign from its outward normal), else the Euclidean distance to it."""

    refine_dist = 0.0  # m, exact nearest-sample distances up to this depth (set by the builder: t + 2 s)

    def _setup_sdf(self, pts: np.ndarray, nrm: np.ndarray, occ: np.ndarray, origin: np.ndarray, pitch: float):
        # a blue-noise subset at spacing ~pitch/2 is enough for point-to-plane distances, keeps the kd-tree
        # small (queries from inside a closed surface prune poorly) and bounds the gaps between samples
        rng = np.random.default_rng(0)
        probe = pts[rng.choice(len(pts), min(len(pts), 2000), replace=False)]
        nn_all = float(np.median(cKDTree(pts).query(probe, k=2)[0][:, 1]))
        r = 0.5 * pitch
        if nn_all < 0.5 * r:
            keep = poisson_disk(pts, r, rng)
            pts, nrm = pts[keep], nrm[keep]
            cover = r + 2 * nn_all  # every surface point lies within this of a kept sample
        else:
            cover = 1.5 * float(np.median(cKDTree(pts).query(probe, k=2)[0][:, 1]))
        self._pts, self._nrm = pts, nrm
        self._tree = cKDTree(pts)
        self._sample_h = cover
        pad = 4
        occ = np.pad(np.asarray(occ, bool), pad)
        self._occ, self._origin, self._pitch = occ, np.asarray(origin, float) - pad * pitch, pitch
        boundary = (occ & ~ndimage.binary_erosion(occ)) | (ndimage.binary_dilation(occ) & ~occ)
        if not boundary.any():
            boundary[tuple(np.array(occ.shape) // 2)] = True
        _, inds = ndimage.distance_transform_edt(~boundary, return_indices=True)
        bidx = np.argwhere(boundary)
        _, bsample = self._tree.query(self._origin + (bidx + 0.5) * pitch, k=1)
        owner = np.zeros(occ.shape, dtype=np.int64)
        owner[boundary] = bsample
        self._nearest = owner[inds[0], inds[1], inds[2]]  # per voxel: a surface sample near its closest point

    def occupied(self, p: np.ndarray) -> np.ndarray:
        ijk = np.floor((p - self._origin) / self._pitch).astype(np.int64)
        ok = np.all((ijk >= 0) & (ijk < np.array(self._occ.shape)), axis=1)
        out = np.zeros(len(p), bool)
        out[ok] = self._occ[ijk[ok, 0], ijk[ok, 1], ijk[ok, 2]]
        return out

    def sdf(self, p):
        p = np.asarray(p, float)
        ijk = np.floor((p - self._origin) / self._pitch).astype(np.int64)
        ijk = np.clip(ijk, 0, np.array(self._occ.shape) - 1)
        j = self._nearest[ijk[:, 0], ijk[:, 1], ijk[:, 2]]
        far = np.linalg.norm(p - self._pts[j], axis=1)
        out = np.where(self.occupied(p), -far, far)
        near = far < max(2.5 * self._pitch, self.refine_dist)
        if near.any():
            q = p[near]
            d, i = self._tree.query(q, k=1, distance_upper_bound=max(4 * self._pitch, self.refine_dist + self._pitch))
            found = np.isfinite(d)
            i = np.where(found, i, 0)
            pp = np.einsum("ij,ij->i", q - self._pts[i], self._nrm[i])
            # point-to-plane (exact on a flat patch, but it underestimates beyond convex edges), bounded below by
            # the distance to the nearest sample less the lateral offset a sample spacing allows
            lower = np.sqrt(np.maximum(np.where(found, d, 0.0) ** 2 - self._sample_h ** 2, 0.0))
            mag = np.where(found, np.maximum(np.abs(pp), lower), np.abs(out[near]))
            sign = np.where(found, np.where(pp < 0, -1.0, 1.0), np.sign(out[near]))
            out[near] = sign * mag
        return out

    def normals(self, p):
        _, i = self._tree.query(np.asarray(p, float), k=1)
        return self._nrm[i]

    def _grid_values(self) -> tuple[np.ndarray, float, np.ndarray]:
        if getattr(self, "_grid_cache", None) is None:
            h = self._pitch
            lo, hi = self.bbox_min - 3 * h, self.bbox_max + 3 * h
            axes = [np.arange(lo[i], hi[i] + h, h) for i in range(3)]
            X, Y, Z = np.meshgrid(*axes, indexing="ij")
            vals = self.sdf(np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)).reshape(X.shape)
            self._grid_cache = (lo, h, vals)
        return self._grid_cache

    def level_mesh(self, level: float) -> np.ndarray:
        """Marching-tetrahedra soup of ``{sdf = level}`` on the occupancy pitch."""
        lo, h, vals = self._grid_values()
        return marching_tetrahedra(vals, lo, h, level)

    def volume_below(self, level):
        tris = self.level_mesh(level)
        return soup_volume(tris) if len(tris) else 0.0

    def curvature(self, pts, nrm):
        # fitted over the surface samples themselves: the curvature at the representation's resolution
        # (neighbours among dense mesh samples would only see the flat facets)
        return quadric_curvature(pts, nrm, pts, nrm, k=20)


_FLAT_VOLUME = 1e-9  # enclosed volume / largest extent^3 below this: a flat mesh
FIT_SCALE_RANGE = (1e-4, 1e2)  # file-to-geometry.size scale factors outside this are a units mistake


def fit_statement(what: str, lo: Any, hi: Any, size: Any) -> str | None:
    """How a user's geometry is fitted into ``geometry.size`` (m): ``None`` when it keeps its size (within 1 %),
    else one line stating the scale factor; :class:`ObjectModelError` when the factor is outside
    ``FIT_SCALE_RANGE`` (a 1 km or 1 um file is a units mistake, not a hand-held object).  ``what`` names the file."""
    ext = np.asarray(hi, float) - np.asarray(lo, float)
    _, scale = _fit_transform(np.asarray(lo, float), np.asarray(hi, float), np.asarray(size, float))
    spans = " x ".join(f"{e:.3g}" for e in ext)
    box = "[" + ", ".join(f"{v:g}" for v in size) + "] m"
    if not FIT_SCALE_RANGE[0] <= scale <= FIT_SCALE_RANGE[1]:
        raise ObjectModelError(f"{what} spans {spans} (file units) and would be scaled by {scale:.3g} to fit "
                               f"geometry.size {box}: export it in metres or millimetres, or set geometry.size "
                               f"to the object's real size")
    if abs(scale - 1.0) <= 0.01:
        return None
    return f"{what} spans {spans} (file units): scaled by {scale:.4g} to fit geometry.size {box}"


def _fit_transform(lo: np.ndarray, hi: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, float]:
    """(translation, uniform scale) that centres a bbox at the origin and fits it inside ``size``."""
    ext = np.maximum(hi - lo, 1e-12)
    return -0.5 * (lo + hi), float(np.min(size / ext))


def load_checked_mesh(path: str | None):
    """The closed triangle mesh at ``path`` (a ``trimesh.Trimesh``), or :class:`ObjectModelError` naming the file
    and the fix: missing file, unreadable, empty, not watertight, or intersecting itself (see the module doc)."""
    import trimesh

    if not path:
        raise ObjectModelError("object.geometry.path is required for geometry.kind 'mesh': "
                               "set it to an OBJ/PLY/STL/GLB file")
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise ObjectModelError(f"mesh {p} does not exist: set object.geometry.path to an existing OBJ/PLY/STL/GLB file")
    try:
        mesh = trimesh.load(str(p), force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types
        raise ObjectModelError(f"mesh {p} could not be loaded ({type(exc).__name__}: {one_line(exc)}): "
                               "export it as OBJ, PLY, STL or GLB") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ObjectModelError(f"mesh {p} is empty (0 faces): export the object's surface as triangles "
                               "(a point cloud or 3DGS splat needs geometry.kind 'ply')")
    open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
    if open_edges or not mesh.is_watertight:
        raise ObjectModelError(f"mesh {p} is not watertight ({open_edges} open edges): repair it, e.g. "
                               "trimesh.repair.fill_holes, or export a closed mesh")
    ext = mesh.bounds[1] - mesh.bounds[0]
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh divides by the volume for the centre of mass
        volume = abs(float(mesh.volume))
    if volume <= _FLAT_VOLUME * float(ext.max()) ** 3:
        raise ObjectModelError(f"mesh {p} encloses no volume ({volume:.3g} within a "
                               f"{' x '.join(f'{e:.3g}' for e in ext)} box, file units): it is flat (a sheet); give "
                               "it a thickness (e.g. Blender's Solidify modifier) and export a closed solid")
    crossing = crossing_triangle_pairs(mesh.vertices, mesh.faces, limit=100)
    if len(crossing):
        i, j = (int(x) for x in crossing[0])
        more = "100 or more" if len(crossing) >= 100 else str(len(crossing))
        raise ObjectModelError(f"mesh {p} intersects itself ({more} pairs of faces pass through each other, "
                               f"e.g. faces {i} and {j}): inside and outside are ambiguous; merge the "
                               "overlapping parts into one closed surface (a boolean union, e.g. Blender's "
                               "Boolean modifier) and export again")
    return mesh


class _MeshSource(_SampledSource):
    kind = "mesh"

    def __init__(self, path: str | None, size: np.ndarray, spacing: float, n_dense: int, rng: np.random.Generator):
        import trimesh

        mesh = load_checked_mesh(path)
        p = Path(str(path)).expanduser()
        if mesh.volume < 0:
            mesh.invert()
        shift, scale = _fit_transform(mesh.bounds[0], mesh.bounds[1], size)
        mesh.apply_translation(shift)
        mesh.apply_scale(scale)
        self.mesh, self.path, self.scale = mesh, p, scale
        self.bbox_min, self.bbox_max = mesh.bounds[0].copy(), mesh.bounds[1].copy()
        self.area_total = float(mesh.area)
        self.enclosed_volume = float(mesh.volume)
        pitch = spacing / 2
        vox = mesh.voxelized(pitch=pitch).fill()
        occ = np.asarray(vox.matrix, bool)
        origin = np.asarray(vox.transform[:3, 3], float) - pitch / 2  # transform maps indices to voxel centres
        seed = int(rng.integers(2**31))
        pts, face = trimesh.sample.sample_surface(mesh, n_dense, seed=seed)
        self.dense_pts = np.asarray(pts, float)
        self.dense_nrm = np.asarray(mesh.face_normals[face], float)
        self._dense_tree = cKDTree(self.dense_pts)
        self._setup_sdf(self.dense_pts, self.dense_nrm, occ, origin, pitch)
        self._rgb = self._mesh_colors(mesh, self.dense_pts, face)

    @staticmethod
    def _mesh_colors(mesh, pts: np.ndarray, face: np.ndarray) -> np.ndarray | None:
        """Linear RGB of the dense samples from the mesh's own vertex/face colours or texture, else None."""
        import trimesh

        vis = mesh.visual
        try:
            if isinstance(vis, trimesh.visual.texture.TextureVisuals):
                vis = vis.to_color()
            kind = getattr(vis, "kind", None)
            if kind == "vertex":
                bary = trimesh.triangles.points_to_barycentric(mesh.triangles[face], pts)
                vc = np.asarray(vis.vertex_colors, float)[:, :3] / 255.0
                srgb = np.einsum("nk,nkc->nc", bary, vc[mesh.faces[face]])
            elif kind == "face":
                srgb = np.asarray(vis.face_colors, float)[face, :3] / 255.0
            else:
                return None
        except Exception:  # a visual trimesh cannot convert: fall back to the procedural pattern
            return None
        srgb = np.clip(srgb, 0, 1)
        return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)

    def candidates(self, n, rng):
        if n >= len(self.dense_pts):
            return self.dense_pts
        return self.dense_pts[rng.choice(len(self.dense_pts), size=n, replace=False)]

    def finalize(self, pts):
        _, i = self._dense_tree.query(pts, k=1)  # candidates are dense samples: their own face normal
        return pts, self.dense_nrm[i]

    def area_measure(self, rng):
        return self.dense_pts, np.full(len(self.dense_pts), self.area_total / len(self.dense_pts))

    def colors_at(self, pts: np.ndarray) -> np.ndarray | None:
        if self._rgb is None:
            return None
        _, i = self._dense_tree.query(pts, k=1)
        return self._rgb[i]


class _PlySource(_SampledSource):
    """A 3DGS PLY: the Gaussians are the surface samples; the volume is the filled occupancy of their means."""

    kind = "ply"

    def __init__(self, path: str | None, size: np.ndarray, spacing: float):
        if not path:
            raise ObjectModelError("object.geometry.path is required for geometry.kind 'ply': set it to a 3DGS .ply file")
        p = Path(str(path)).expanduser()
        try:
            g = read_gaussian_ply(p)
        except ValueError as exc:
            raise ObjectModelError(str(exc)) from None
        means = g["means"].astype(np.float64)
        if len(means) < 8:
            raise ObjectModelError(f"PLY {p} holds only {len(means)} Gaussians: at least 8 are needed")
        shift, scale = _fit_transform(means.min(0), means.max(0), size)
        means = (means + shift) * scale
        self.path, self.scale = p, scale
        self.gauss = {
            "scales": g["scales"].astype(np.float64) * scale,
            "rotations": g["rotations"].astype(np.float64),
            "opacities": g["opacities"].astype(np.float64),
            "colors": g["colors"].astype(np.float64),
        }
        self.bbox_min, self.bbox_max = means.min(0), means.max(0)
        tree = cKDTree(means)
        dk, _ = tree.query(means, k=min(9, len(means)))
        nn = float(np.median(dk[:, 1]))
        pitch = max(spacing / 2, 1e-6)
        occ, origin = self._fill(means, pitch, nn)
        # per-Gaussian area from the local sample density: k neighbours in a disc of radius r_k -> pi r_k^2 / k
        kk = dk.shape[1] - 1
        self.point_area = np.pi * dk[:, -1] ** 2 / max(kk, 1)
        self.area_total = float(self.point_area.sum())
        self.enclosed_volume = float(occ.sum() * pitch ** 3)
        self.means = means
        self._occ, self._origin, self._pitch = occ, origin, pitch  # for _orient (before the sdf set-up)
        self.mean_normals = self._orient(means, self._normals(g, means, tree))
        self._setup_sdf(means, self.mean_normals, occ, origin, pitch)
        # totals from the level set of the signed distance (the voxel count and the k-NN areas are biased);
        # the k-NN areas keep their proportions
        self.refine_dist = 3 * pitch
        tris = self.level_mesh(0.0)
        if len(tris):
            self.area_total = float(soup_area(tris).sum())
            self.point_area *= self.area_total / self.point_area.sum()
            self.enclosed_volume = float(soup_volume(tris))
        self._grid_cache = None  # recomputed with the builder's refine_dist when a thick wall needs it

    def _fill(self, means: np.ndarray, pitch: float, nn: float) -> tuple[np.ndarray, np.ndarray]:
        """Filled occupancy of the splat: voxels holding means, closed by ``r`` voxels (r ~ sample spacing),
        holes filled, eroded back; convex hull of the means if that encloses nothing (a leaky splat)."""
        r = max(1, int(math.ceil(1.5 * nn / pitch)))
        origin = means.min(0) - (r + 2) * pitch
        shape = np.ceil((means.max(0) - origin) / pitch).astype(int) + r + 3
        occ = np.zeros(shape, bool)
        ijk = np.floor((means - origin) / pitch).astype(int)
        occ[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = True
        dil = ndimage.binary_dilation(occ, iterations=r)
        filled = ndimage.binary_fill_holes(dil)
        gained = filled.sum() - dil.sum()
        if gained > 0.1 * dil.sum():
            return ndimage.binary_erosion(filled, iterations=r) | occ, origin
        from scipy.spatial import Delaunay

        idx = np.indices(shape).reshape(3, -1).T
        centres = origin + (idx + 0.5) * pitch
        inside = Delaunay(means).find_simplex(centres) >= 0
        return inside.reshape(shape) | occ, origin

    @staticmethod
    def _normals(g: dict, means: np.ndarray, tree: cKDTree) -> np.ndarray:
        """File normals when present; else the shortest axis of flat Gaussians; else local PCA."""
        fn = g["normals"].astype(np.float64)
        ln = np.linalg.norm(fn, axis=1)
        if np.mean(ln > 0.5) > 0.99:
            return fn / ln[:, None]
        q = g["rotations"].astype(np.float64)
        w, x, y, z = q.T
        R = np.stack([
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ], -2)
        s = g["scales"].astype(np.float64)
        order = np.argsort(s, axis=1)
        axis_n = R[np.arange(len(q)), :, order[:, 0]]
        flat = s[np.arange(len(s)), order[:, 0]] < 0.5 * s[np.arange(len(s)), order[:, 1]]
        _, idx = tree.query(means, k=min(12, len(means)))
        nb = means[idx] - means[idx].mean(axis=1, keepdims=True)
        cov = np.einsum("nki,nkj->nij", nb, nb)
        _, vecs = np.linalg.eigh(cov)
        pca = vecs[:, :, 0]
        return _unit(np.where(flat[:, None], axis_n, pca))

    def _orient(self, means: np.ndarray, nrm: np.ndarray) -> np.ndarray:
        """Flip normals to point out of the filled occupancy (probe 1.5 voxels along +-n), else away from the
        centroid."""
        h = 1.5 * self._pitch
        out_plus = ~self.occupied(means + h * nrm)
        out_minus = ~self.occupied(means - h * nrm)
        flip = out_minus & ~out_plus
        undecided = out_plus == out_minus
        away = np.einsum("ij,ij->i", nrm, means - means.mean(0)) < 0
        flip |= undecided & away
        return np.where(flip[:, None], -nrm, nrm)

    def area_measure(self, rng):
        return self.means, self.point_area


# ----------------------------------------------------------------------------------------------- builder
def _grid_points(lo: np.ndarray, hi: np.ndarray, s: float, rng: np.random.Generator) -> np.ndarray:
    """Cell-centred grid of spacing ``s`` (m) tiling the box [lo, hi] (centred on it), jittered by +-0.2 s."""
    size = hi - lo
    n = np.maximum(np.ceil(size / s - 1e-9).astype(int), 1) + 2  # one spare cell each side
    start = 0.5 * (lo + hi) - 0.5 * n * s + 0.5 * s
    if np.prod(n) > 30_000_000:
        raise ObjectModelError(f"sampling.particle_spacing {s} m gives {int(np.prod(n))} grid points for a "
                               f"{size.round(4).tolist()} m object: use a coarser spacing")
    axes = [start[i] + s * np.arange(n[i]) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    return pts + rng.uniform(-_JITTER, _JITTER, size=pts.shape) * s


def _validate(obj: Any, sampling: Any) -> tuple[str, np.ndarray, float, float, int, int, int]:
    name = str(_get(obj, "name", "object"))
    geom = _get(obj, "geometry")
    kind = str(_get(geom, "kind"))
    try:
        size = np.asarray(list(_get(geom, "size")), dtype=np.float64)
    except (TypeError, ValueError):
        raise ObjectModelError(f"object {name}: geometry.size must be three lengths in m") from None
    if size.shape != (3,) or np.any(~np.isfinite(size)) or np.any(size <= 0):
        raise ObjectModelError(f"object {name}: geometry.size must be three positive lengths in m, got {size.tolist()}")
    t = float(_get(geom, "wall_thickness", 0.0) or 0.0)
    s = float(_get(sampling, "particle_spacing"))
    n_surf = int(_get(sampling, "surface_points"))
    seed = int(_get(sampling, "seed", 0) or 0)
    layers = int(_get(sampling, "thin_wall_layers", 2) or 2)
    filled = bool(_get(obj, "filled", False))
    interior = _get(obj, "interior")
    if not (s > 0 and math.isfinite(s)):
        raise ObjectModelError(f"sampling.particle_spacing must be > 0 m, got {s}")
    if n_surf < 10:
        raise ObjectModelError(f"sampling.surface_points must be >= 10, got {n_surf}")
    if layers not in (1, 2, 3):
        raise ObjectModelError(f"sampling.thin_wall_layers must be 1, 2 or 3, got {layers}")
    if t < 0 or not math.isfinite(t):
        raise ObjectModelError(f"object {name}: geometry.wall_thickness must be >= 0 m, got {t}")
    if not filled and t <= 0:
        raise ObjectModelError(f"object {name}: geometry.wall_thickness is 0 but filled is false: give the shell "
                               "thickness in m, or set filled: true for a solid body")
    if filled and interior:
        raise ObjectModelError(f"object {name}: filled is true (solid body) but interior is {interior!r}: "
                               "set filled: false with a wall_thickness, or interior: null")
    if not filled and t >= 0.5 * size.min():
        raise ObjectModelError(f"object {name}: wall_thickness {t} m is not thinner than half the smallest side "
                               f"({0.5 * size.min()} m): set filled: true or a thinner wall")
    if kind not in SHAPE_KINDS + ("ply", "mesh"):
        raise ObjectModelError(f"object {name}: geometry.kind {kind!r} is unknown: use one of "
                               f"{list(SHAPE_KINDS) + ['ply', 'mesh']}")
    return kind, size, t, s, n_surf, seed, layers


def sampling_seed(obj: Any, seed: int) -> np.random.SeedSequence:
    """The seed sequence of every random draw of :func:`build_object_model`: the explicit ``sampling.seed`` and the
    object's *content*, never its name or label, so the same object under two names gets bitwise identical
    Gaussians and particles.  Content = the geometry that is sampled: ``kind``, ``size`` (m), ``wall_thickness``
    (m), ``filled``, whether it has an interior, and for a mesh or PLY the SHA-256 of the file."""
    geom = _get(obj, "geometry")
    kind, path = str(_get(geom, "kind")), _get(geom, "path")
    content = {"kind": kind, "size": [float(x) for x in _get(geom, "size")],
               "wall_thickness": float(_get(geom, "wall_thickness", 0.0) or 0.0),
               "filled": bool(_get(obj, "filled", False)), "interior": bool(_get(obj, "interior")),
               "file": file_sha256(path) if kind in ("ply", "mesh") and path and Path(path).expanduser().is_file()
               else None}  # a missing file is refused by its loader, with the fix
    digest = hashlib.sha256(json.dumps(content, sort_keys=True).encode()).digest()
    return np.random.SeedSequence([int(seed), *np.frombuffer(digest[:16], dtype=np.uint32).tolist()])


def build_object_model(obj: Any, sampling: Any, grid_spacing: float | None = None) -> tuple[dict[str, Array],
                                                                                        dict[str, Any]]:
    """Surface Gaussians and MPM particles of one object (see the module doc for every choice).

    Args:
        obj: an ``ObjectConfig`` (dataclass or OmegaConf node; read by attribute).
        sampling: a ``SamplingConfig`` (``surface_points``, ``particle_spacing`` m, ``seed``, ``thin_wall_layers``).
        grid_spacing: the MPM grid's dx (m) the wall is judged against (thin below it); None: the particle spacing.
    Returns:
        ``(arrays, attrs)``: the arrays named in the module doc as :class:`tasks.core.artifacts.Array`, and JSON
        attrs ``bbox_min``/``bbox_max`` (m), ``surface_area_total`` (m^2), ``enclosed_volume`` (m^3),
        ``wall_thickness``/``particle_spacing`` (m), ``thin_wall``, ``n_particles``, ``n_interior``, plus
        ``wall_volume``/``interior_volume`` (m^3, sums of the particle volumes) and ``kind``.
    Raises:
        ObjectModelError: one line naming the input and the fix.
    """
    kind, size, t, s, n_surf, seed, layers = _validate(obj, sampling)  # layers: of a thin wall
    name = str(_get(obj, "name", "object"))
    geom, app = _get(obj, "geometry"), _get(obj, "appearance")
    filled = bool(_get(obj, "filled", False))
    interior = _get(obj, "interior")
    ss = sampling_seed(obj, seed)
    rng_surf, rng_area, rng_part, rng_grid, rng_misc = (np.random.default_rng(c) for c in ss.spawn(5))

    if kind in SHAPE_KINDS:
        src: _Source = _ProceduralSource(make_shape(kind, size))
    elif kind == "mesh":
        src = _MeshSource(_get(geom, "path"), size, s, 20 * n_surf, rng_misc)
    else:
        src = _PlySource(_get(geom, "path"), size, s)
    A = src.area_total
    if isinstance(src, _SampledSource):
        src.refine_dist = t + 2 * s

    # ---------------------------------------------------------------- surface samples = Gaussian means
    if isinstance(src, _PlySource):
        pts, nrm = src.means, src.mean_normals
        area = src.point_area.copy()
        g = src.gauss
        gscales, grot = g["scales"], g["rotations"]
        opac = np.clip(g["opacities"], 1e-4, 1 - 1e-4)
        rgb = np.clip(g["colors"], 0.0, 1.0)
        kcurv, kdirs = src.curvature(pts, nrm)
    else:
        cand = src.candidates(_CANDIDATES_PER_SAMPLE * n_surf, rng_surf)
        sel = _blue_noise(cand, n_surf, A, rng_surf)
        pts, nrm = src.finalize(cand[sel])
        mpts, mw = src.area_measure(rng_area)
        area = _voronoi_area(pts, mpts, mw)
        kcurv, kdirs = src.curvature(pts, nrm)
        sig_t = _TANGENT_SIGMA * np.sqrt(area)
        gscales = np.stack([sig_t, sig_t, _NORMAL_SIGMA * sig_t], axis=1)
        R = np.stack([kdirs[:, 0], kdirs[:, 1], nrm], axis=2)  # columns: local x, y, z -> t1, t2, n
        grot = matrix_to_quaternion(R)
        opac = np.full(len(pts), float(np.clip(float(_get(app, "opacity", 0.98)), 1e-3, 0.999)))
        rgb = src.colors_at(pts) if isinstance(src, _MeshSource) else None
        if rgb is None:
            rgb = surface_colors(str(_get(app, "pattern", "solid")), kind, pts, nrm, src.bbox_min, src.bbox_max,
                                 list(_get(app, "base_color", [0.8, 0.8, 0.8])),
                                 list(_get(app, "accent_color", [0.2, 0.2, 0.2])), src.regions(pts), seed)
    kcurv = resolved_curvature(kcurv, area)
    kcurv = -np.sort(-kcurv, axis=1)

    # ---------------------------------------------------------------- volume particles
    V_body = float(src.enclosed_volume)
    thin = (not filled) and t < max(s, grid_spacing or s)
    grid = None
    fibres = np.zeros((0, 2), np.int64)  # a thin wall's normal fibres (pairs of its two Gauss layers' particles)
    if thin:
        if isinstance(src, _PlySource):
            cand_p = src.means
        else:
            cand_p = src.candidates(max(5 * int(A / s ** 2), 200), rng_part)
        idx = poisson_disk(cand_p, 0.7 * s, rng_part)  # ~A / s^2 particles from 5 A / s^2 candidates
        ppos, pnrm = src.finalize(cand_p[idx]) if not isinstance(src, _PlySource) else (cand_p[idx], src.mean_normals[idx])
        mpts, mw = src.area_measure(rng_area)
        parea = _voronoi_area(ppos, mpts, mw)
        pvol = parea * t  # the open sheet: its own area is the mid-surface's
        if not src.open_top:
            pvol = parea * shell_depth_volume(src.curvature(ppos, pnrm)[0], t, parea)
            ppos = ppos - 0.5 * t * pnrm
        V_wall = float(pvol.sum())
        if layers > 1:  # the thickness's Gauss points; fibre k: particle k (outer), its inner [and middle] twin
            heights, shares = gauss_layers(layers)
            n = len(ppos)
            fibres = np.arange(layers * n).reshape(layers, n).T
            ppos = np.concatenate([ppos + h * t * pnrm for h in heights])
            pnrm = np.concatenate([pnrm] * layers)
            pvol = np.concatenate([w * pvol for w in shares])
    else:
        grid = _grid_points(src.bbox_min, src.bbox_max, s, rng_grid)
        d = src.sdf(grid)
        if filled:
            mask = d < 0
            V_wall = V_body
        elif src.open_top:
            mask = src.open_distance(grid) < 0.5 * t
            V_wall = A * t
        else:
            mask = (d < 0) & (d > -t)
            # same discretisation for both levels so that their errors cancel
            V_wall = max(src.volume_below(0.0) - src.volume_below(-t), 0.0)
        ppos = grid[mask]
        if len(ppos) == 0:
            raise ObjectModelError(f"object {name}: no particle of the spacing {s} m falls inside the "
                                   f"{'body' if filled else 'wall'}: use a finer sampling.particle_spacing")
        pnrm = src.normals(ppos)
        pvol = np.full(len(ppos), V_wall / len(ppos))

    # ---------------------------------------------------------------- interior (cavity) particles
    if interior and not filled:
        if grid is None:
            grid = _grid_points(src.bbox_min, src.bbox_max, s, rng_grid)
            d = src.sdf(grid)
        clear = max(0.5 * t if src.open_top else t, 0.5 * s)
        ipos = grid[d < -clear]
        V_cav = max(V_body - (0.5 * V_wall if src.open_top else V_wall), 0.0)
        ivol = np.full(len(ipos), V_cav / max(len(ipos), 1))
    else:
        ipos = np.zeros((0, 3))
        ivol = np.zeros(0)

    f32 = np.float32
    arrays = {
        "surface_points": Array(pts.astype(f32), ("point", "xyz"), "m",
                                "surface samples = 3D Gaussian means (blue-noise, area-uniform)"),
        "surface_normals": Array(_unit(nrm).astype(f32), ("point", "xyz"), "1", "outward unit normals"),
        "surface_curvature": Array(kcurv.astype(f32), ("point", "principal"), "1/m",
                                   "principal curvatures k1 >= k2 (convex positive)"),
        "surface_principal_dirs": Array(kdirs.astype(f32), ("point", "principal", "xyz"), "1",
                                        "unit tangent directions of k1 and k2"),
        "surface_area": Array(area.astype(f32), ("point",), "m^2", "surface area each sample represents"),
        "gaussian_scales": Array(gscales.astype(f32), ("point", "xyz"), "m",
                                 "per-Gaussian standard deviations along local x, y, z"),
        "gaussian_rotations": Array(grot.astype(f32), ("point", "quat"), "1",
                                    "unit quaternion w, x, y, z: local axes -> (t1, t2, normal)"),
        "gaussian_opacities": Array(opac.astype(f32), ("point",), "1", "opacity in (0, 1)"),
        "gaussian_colors": Array(rgb.astype(f32), ("point", "rgb"), "1", "linear RGB in [0, 1]"),
        "particle_positions": Array(ppos.astype(f32), ("particle", "xyz"), "m",
                                    "MPM particles of the object's own (shell/body) material"),
        "particle_volumes": Array(pvol.astype(f32), ("particle",), "m^3", "real material volume per particle"),
        "particle_normals": Array(_unit(pnrm).astype(f32), ("particle", "xyz"), "1",
                                  "outward normal of the nearest outer surface"),
        "wall_fibres": Array(fibres.astype(np.int32), ("fibre", "layer"), "1",
                             "particle indices of each normal fibre of a wall in two or three Gauss layers: outer, "
                             "inner[, middle] (the solver keeps outer and inner at their rest distance, "
                             "mpm.wall_fibres); none otherwise"),
        "interior_positions": Array(ipos.astype(f32), ("interior_particle", "xyz"), "m",
                                    "MPM particles of the interior material (cavity)"),
        "interior_volumes": Array(ivol.astype(f32), ("interior_particle",), "m^3", "volume per interior particle"),
    }
    attrs = {
        "kind": kind,
        "bbox_min": [float(v) for v in src.bbox_min],
        "bbox_max": [float(v) for v in src.bbox_max],
        "surface_area_total": float(A),
        "enclosed_volume": V_body,
        "wall_thickness": float(t),
        "particle_spacing": float(s),
        "thin_wall": bool(thin),
        "thin_wall_layers": int(layers) if thin else 0,
        "n_particles": int(len(ppos)),
        "n_interior": int(len(ipos)),
        "wall_volume": float(pvol.sum()),
        "interior_volume": float(ivol.sum()),
    }
    return arrays, attrs


# ----------------------------------------------------------------------------------------------- Prefect step


def check_geometry_file(kind: str, path: str | None, size: Any = None) -> str | None:
    """Check a user geometry file before anything runs: a closed, non-flat mesh (``kind: mesh``) or a readable 3DGS
    PLY (``kind: ply``), and, with ``size`` (m), its fit into ``geometry.size`` (:func:`fit_statement`: the line
    stating the rescale, or None).  Raises :class:`ObjectModelError` or :class:`GaussianPlyError` (one line, file
    and fix)."""
    if kind == "mesh":
        mesh = load_checked_mesh(path)
        lo, hi, what = mesh.bounds[0], mesh.bounds[1], f"mesh {Path(str(path)).expanduser()}"
    elif kind == "ply":
        if not path:
            raise ObjectModelError("object.geometry.path is required for geometry.kind 'ply': set it to a 3DGS .ply")
        means = read_gaussian_ply(path)["means"]
        lo, hi, what = means.min(0), means.max(0), f"PLY {Path(str(path)).expanduser()}"
    else:
        return None
    return None if size is None else fit_statement(what, lo, hi, size)


OBJECT_OUTPUTS = ("surface_points", "surface_normals", "surface_area", "surface_curvature", "surface_principal_dirs",
                  "gaussian_scales", "gaussian_rotations", "gaussian_colors", "gaussian_opacities",
                  "particle_positions", "particle_volumes", "particle_normals", "wall_fibres", "interior_positions",
                  "interior_volumes")


@artifact_step("object_model",
               reads=("object.name", "object.geometry", "object.appearance", "object.filled", "object.interior",
                      "sampling", "mpm.dx", "mpm.particles_per_cell"),
               files=("object.geometry.path",),
               outputs=OBJECT_OUTPUTS)
def object_model_step(inputs, params):
    """The object model of one object: surface 3D Gaussians and MPM volume particles (no inputs; a ply/mesh file
    is read from ``object.geometry.path``, whose content digest is in the key)."""
    obj = {key: params[f"object.{key}"] for key in ("name", "geometry", "appearance", "filled", "interior")}
    mpm = {"dx": params["mpm.dx"], "particles_per_cell": params["mpm.particles_per_cell"]}
    return build_object_model(obj, params["sampling"], grid_spacing(mpm, float(params["sampling"]["particle_spacing"])))
