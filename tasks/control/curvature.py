"""Principal curvatures and frames of surface samples (1/m; convex positive) and the wall volume they bound.

A weighted least-squares quadric fit in each sample's tangent frame (osculating quadric, Cazals & Pouget 2005 "jet
fitting"), the resolution clamp ``2 / sqrt(area)``, Steiner's formula for a wall's depth volume under a curved
patch, and the rotation (quaternion) of a sample's principal frame.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.control.geometry import tangent_basis

__all__ = ["unit_vectors", "resolved_curvature", "shell_depth_volume", "quadric_curvature", "matrix_to_quaternion"]


def unit_vectors(v: np.ndarray, fallback=(0.0, 0.0, 1.0)) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    out = np.where(n > 1e-12, v / np.maximum(n, 1e-300), np.asarray(fallback, float))
    return out



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
    d1 = unit_vectors(d1)
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

