"""A 3DGS PLY (``geometry.kind: ply``, read by :mod:`tasks.control.gaussian_ply`) as a geometry source: its
Gaussians are the surface samples, its volume the filled occupancy of their means."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from tasks.control.curvature import unit_vectors
from tasks.control.gaussian_ply import read_gaussian_ply
from tasks.control.geometry import soup_area, soup_volume
from tasks.control.object_config import ObjectModelError
from tasks.control.sources.base import SampledSource, fit_transform
from tasks.control.splat_content import check_splat_content

__all__ = ["PlySource"]


class PlySource(SampledSource):
    """A 3DGS PLY: the Gaussians are the surface samples; the volume is the filled occupancy of their means."""

    kind = "ply"

    def __init__(self, path: str | None, size: np.ndarray, spacing: float):
        if not path:
            raise ObjectModelError("object.geometry.path is required for geometry.kind 'ply': set it to a 3DGS .ply file")
        p = Path(str(path)).expanduser()
        try:
            g = read_gaussian_ply(p)
            check_splat_content(p, g["means"], g["scales"], g["opacities"])
        except ValueError as exc:
            raise ObjectModelError(str(exc)) from None
        means = g["means"].astype(np.float64)
        shift, scale = fit_transform(means.min(0), means.max(0), size)
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
        return unit_vectors(np.where(flat[:, None], axis_n, pca))

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

