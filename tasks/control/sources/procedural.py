"""A procedural shape (:mod:`tasks.control.geometry`) as a geometry source: analytic samples on the sphere and
the cup, a marching-tetrahedra mesh of the implicit function otherwise; curvature from the shape itself."""
from __future__ import annotations

import numpy as np

from tasks.control.geometry import Shape
from tasks.control.sources.base import GeometrySource

__all__ = ["ProceduralSource"]


class ProceduralSource(GeometrySource):
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

