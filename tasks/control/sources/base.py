"""What the object model needs from a geometry source, and what the file-based sources share.

:class:`GeometrySource`: surface candidates, an approximate signed distance, area and volume measures, normals,
curvature.  :class:`SampledSource`: a geometry known by dense oriented surface samples plus a filled occupancy
grid (meshes, :mod:`tasks.control.sources.mesh`; 3DGS PLY files, :mod:`tasks.control.sources.ply`).  A file is
centred at the origin and scaled uniformly to fit ``geometry.size`` (m) (:func:`fit_transform`,
:func:`fit_statement`).  Lengths m, areas m^2, volumes m^3.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from tasks.control.curvature import quadric_curvature
from tasks.control.geometry import marching_tetrahedra, soup_volume
from tasks.control.object_config import ObjectModelError
from tasks.control.surface_sampling import poisson_disk

__all__ = ["GeometrySource", "SampledSource", "FIT_SCALE_RANGE", "fit_statement", "fit_transform"]


class GeometrySource:
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



class SampledSource(GeometrySource):
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


FIT_SCALE_RANGE = (1e-4, 1e2)  # file-to-geometry.size scale factors outside this are a units mistake


def fit_statement(what: str, lo: Any, hi: Any, size: Any) -> str | None:
    """How a user's geometry is fitted into ``geometry.size`` (m): ``None`` when it keeps its size (within 1 %),
    else one line stating the scale factor; :class:`ObjectModelError` when the factor is outside
    ``FIT_SCALE_RANGE`` (a 1 km or 1 um file is a units mistake, not a hand-held object).  ``what`` names the file."""
    ext = np.asarray(hi, float) - np.asarray(lo, float)
    _, scale = fit_transform(np.asarray(lo, float), np.asarray(hi, float), np.asarray(size, float))
    spans = " x ".join(f"{e:.3g}" for e in ext)
    box = "[" + ", ".join(f"{v:g}" for v in size) + "] m"
    if not FIT_SCALE_RANGE[0] <= scale <= FIT_SCALE_RANGE[1]:
        raise ObjectModelError(f"{what} spans {spans} (file units) and would be scaled by {scale:.3g} to fit "
                               f"geometry.size {box}: export it in metres or millimetres, or set geometry.size "
                               f"to the object's real size")
    if abs(scale - 1.0) <= 0.01:
        return None
    return f"{what} spans {spans} (file units): scaled by {scale:.4g} to fit geometry.size {box}"


def fit_transform(lo: np.ndarray, hi: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, float]:
    """(translation, uniform scale) that centres a bbox at the origin and fits it inside ``size``."""
    ext = np.maximum(hi - lo, 1e-12)
    return -0.5 * (lo + hi), float(np.min(size / ext))

