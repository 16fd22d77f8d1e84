"""Blue-noise surface samples and the area each represents (the object model's 3D Gaussian means).

Surface samples are blue-noise: random area-uniform candidates thinned by greedy Poisson-disk selection in random
order (dart throwing restricted to the candidates, Cook 1986) to exactly the number asked; each sample's area is
its Voronoi share of an area measure (points with weights), so the areas sum to the total.  Lengths m, areas m^2.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["poisson_disk", "blue_noise", "voronoi_area"]


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


def blue_noise(points: np.ndarray, n: int, area: float, rng: np.random.Generator) -> np.ndarray:
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



def voronoi_area(sites: np.ndarray, measure_pts: np.ndarray, measure_w: np.ndarray, floor: float = 0.25) -> np.ndarray:
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

