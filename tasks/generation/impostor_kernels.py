"""The per-pixel work of the ellipsoid impostors (:func:`tasks.generation.impostors.splat_ellipsoid_impostors`) as a
Warp kernel on the CPU: every pixel centre of an ellipsoid's screen box is intersected with the ellipsoid (the ray
quadric of that function's docstring), z-buffered into the front depth and its chord added to the thickness.

One thread per ellipsoid walks its box row by row.  Warp runs a CPU launch's threads one after another in index
order, so each pixel's thickness is summed in ellipsoid order, as ``np.bincount`` over the (ellipsoid, pixel) pairs
summed it; the arithmetic is float64 with the same operations in the same order (Warp's CPU code contracts no
multiply-add), so depth and thickness are bit-identical to the numpy formulation it replaces
(``tests/generation/test_impostor_kernels.py``).  Units: metres, pixels.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from tasks.render.warp_numpy import numpy_view

wp.set_module_options({"enable_backward": False})

_f64 = wp.float64


@wp.kernel
def _splat_ellipsoids(quadric: wp.array2d(dtype=_f64), box: wp.array2d(dtype=wp.int32), camera: wp.array(dtype=_f64),
                      surface_depth: wp.array2d(dtype=_f64), depth: wp.array2d(dtype=_f64),
                      thickness: wp.array2d(dtype=_f64)):
    """Ellipsoid n: quadric[n] = (A_xx, A_yy, A_zz, A_xy, A_xz, A_yz, (A c)_x, (A c)_y, (A c)_z, c^T A c - 1) in camera
    coordinates; box[n] = (x0, x1, y0, y1) px, clipped (x1, y1 exclusive); camera = (fx, fy, cx, cy, near_m)."""
    n = wp.tid()
    fx, fy, cx, cy, near = camera[0], camera[1], camera[2], camera[3], camera[4]
    axx, ayy, azz = quadric[n, 0], quadric[n, 1], quadric[n, 2]
    axy, axz, ayz = quadric[n, 3], quadric[n, 4], quadric[n, 5]
    acx, acy, acz, cc = quadric[n, 6], quadric[n, 7], quadric[n, 8], quadric[n, 9]
    half, two, one = _f64(0.5), _f64(2.0), _f64(1.0)
    for py in range(box[n, 2], box[n, 3]):
        dy = (_f64(py) + half - cy) / fy
        for px in range(box[n, 0], box[n, 1]):
            dx = (_f64(px) + half - cx) / fx
            # a = d^T A d, b = d^T A c for the ray x = t d, d = (dx, dy, 1); the sums in the numpy order
            a = axx * dx * dx + ayy * dy * dy + azz + two * (axy * dx * dy + axz * dx + ayz * dy)
            b = acx * dx + acy * dy + acz
            disc = b * b - a * cc
            if disc > _f64(0.0):
                root = wp.sqrt(disc)
                t_front = (b - root) / a
                if t_front > near and t_front < surface_depth[py, px]:
                    depth[py, px] = wp.min(depth[py, px], t_front)
                    thickness[py, px] = thickness[py, px] + two * root / a * wp.sqrt(dx * dx + dy * dy + one)


def splat_ellipsoid_pixels(quadric: np.ndarray, box: np.ndarray, fx: float, fy: float, cx: float, cy: float,
                           near_m: float, surface_depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Front depth and summed chord (metres) of ellipsoids drawn over their screen boxes (module doc).

    quadric: (n, 10) float64, per ellipsoid A_xx, A_yy, A_zz, A_xy, A_xz, A_yz, (A c)_xyz, c^T A c - 1 (camera
    coordinates, A = Q diag(radii^-2) Q^T, c the centre); box: (n, 4) int (x0, x1, y0, y1) px clipped to the image;
    fx, fy, cx, cy: intrinsics px; near_m: nearest kept front depth; surface_depth (y, x) m: fragments at or behind
    it are hidden.  Returns ``(depth, thickness)`` (y, x) float64: depth +inf where nothing is drawn, thickness 0."""
    height, width = surface_depth.shape
    depth = np.full((height, width), np.inf)
    thickness = np.zeros((height, width))
    if len(quadric) == 0:
        return depth, thickness
    wp.init()   # no-op once Warp is up
    arrays = [numpy_view(quadric), numpy_view(box, wp.int32), numpy_view(np.array([fx, fy, cx, cy, near_m])),
              numpy_view(surface_depth)]
    outputs = [numpy_view(a, output=True) for a in (depth, thickness)]
    wp.launch(_splat_ellipsoids, dim=len(quadric), inputs=arrays + outputs, device="cpu")
    return depth, thickness
