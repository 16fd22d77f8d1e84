"""Tracers (surface 3D Gaussians) embedded in the material: each is bound at rest to its nearest particles and
placed from their positions and deformation gradients when read, so it cannot drift off the material; deform
covariances with :func:`deform_covariances` (F Sigma F^T) and rotate with :func:`polar_rotation`.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Optional

import numpy as np
import warp as wp

from .kernels.tracers import k_tracer_embed

if TYPE_CHECKING:
    from .solver import MPMSolver


# Particles each tracer (surface Gaussian) is embedded in (:func:`bind_tracers`): the 4 nearest span a
# volume around a surface point (3 could be collinear on a one-particle shell's lattice) and stay within ~1 spacing.
TRACER_ANCHORS = 4


def deform_covariances(F: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariances of deformed Gaussians: F Sigma F^T (F: (N,3,3), cov: (N,3,3))."""
    return np.einsum("nij,njk,nlk->nil", F, cov, F)


def polar_rotation(F: np.ndarray) -> np.ndarray:
    """Rotation part R (det +1) of the polar decomposition F = R S, batched (N,3,3), float64.

    For det F > 0 the orthogonal polar factor, by Higham's scaled Newton iteration X <- (z X + X^-T / z) / 2
    (Higham 1986; z = sqrt(|X^-1| / |X|), Frobenius norms), vectorised over the batch: the same R as the SVD's U V^T
    to ~1e-15 in 6-9 iterations, at 1/10 of the cost of a batched LAPACK SVD (the rollout records the Gaussians'
    rotations every frame).  Rows with det F <= 0, a condition number beyond 1e6 or no convergence take the SVD
    F = U S V^T with the sign of the smallest singular value flipped when det F < 0, so R is a proper rotation (the
    closest one to F).
    """
    F = np.asarray(F, dtype=np.float64)
    R = np.empty_like(F)
    fast = np.zeros(F.shape[:-2], bool)
    if F.ndim == 3 and len(F):
        X, fast = _polar_newton(F)
        R[fast] = X[fast]
    if not fast.all():
        R[~fast] = _polar_svd(F[~fast])
    return R


def _polar_newton(F: np.ndarray, max_iterations: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """(X, ok): Higham's scaled Newton iteration for the orthogonal polar factor of each F (N,3,3) with det F > 0
    and |F| |F^-1| <= 1e6 (Frobenius norms); ``ok`` marks the rows that converged (last step <= 1e-10, which leaves ~1e-20)."""
    X = F.copy()
    ok = np.zeros(len(F), bool)
    live = np.ones(len(F), bool)
    for k in range(max_iterations):
        c0, c1, c2 = X[live, :, 0], X[live, :, 1], X[live, :, 2]
        cof = np.stack([np.cross(c1, c2), np.cross(c2, c0), np.cross(c0, c1)], axis=-1)  # cof(X) = det X X^-T
        det = np.einsum("ni,ni->n", c0, cof[:, :, 0])
        if k == 0:
            norm = np.sqrt(np.einsum("nij,nij->n", X[live], X[live]))
            good = det > 0.0
            good[good] &= norm[good] * np.sqrt(np.einsum("nij,nij->n", cof[good], cof[good])) / det[good] <= 1e6
            idx = np.flatnonzero(live)
            live[idx[~good]] = False
            cof, det = cof[good], det[good]
        inv_t = cof / det[:, None, None]
        Y = X[live]
        z = np.sqrt(np.sqrt(np.einsum("nij,nij->n", inv_t, inv_t) / np.einsum("nij,nij->n", Y, Y)))[:, None, None]
        Xn = 0.5 * (z * Y + inv_t / z)
        step = np.abs(Xn - Y).max(axis=(1, 2))
        idx = np.flatnonzero(live)
        X[idx] = Xn
        done = step <= 1e-10  # quadratic convergence: the error left is ~step^2, below round-off
        ok[idx[done]] = True
        live[idx[done]] = False
        if not live.any():
            break
    return X, ok


def _polar_svd(F: np.ndarray) -> np.ndarray:
    """Proper rotation of the polar decomposition by the SVD (see :func:`polar_rotation`)."""
    U, _, Vt = np.linalg.svd(F)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    D = np.ones(F.shape[:-1])
    D[..., -1] = d
    return (U * D[..., None, :]) @ Vt


def rotate_quaternions(R: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """Compose rotation matrices R (N,3,3) with Gaussian orientations q (N,4, w first): returns R*q (w first)."""
    from scipy.spatial.transform import Rotation

    r = Rotation.from_matrix(R)
    qx = np.concatenate([q_wxyz[:, 1:], q_wxyz[:, :1]], axis=1)
    out = (r * Rotation.from_quat(qx)).as_quat()
    return np.concatenate([out[:, 3:], out[:, :3]], axis=1)


def rebind_tracers_to_preload(solver: MPMSolver) -> None:
    """After :meth:`MPMSolver.preload_gravity`: each tracer's rest offsets become F0_k^-1 r_tk (F0_k its anchor's preloaded
    F), so it sits at its given position, and its reported F is relative to its preloaded F."""
    if not solver.n_tracers:
        return
    anchor, weight, offset = solver._anchor
    near, r = anchor.numpy(), offset.numpy().astype(np.float64)
    F0 = solver.F.numpy().astype(np.float64)
    solver._anchor = (anchor, weight, wp.array(np.einsum("tkij,tkj->tki", np.linalg.inv(F0[near]), r)
                                               .astype(np.float32), dtype=wp.vec3, device=solver.device))
    place_tracers(solver)
    solver._tracer_F0_inv = np.linalg.inv(solver.tF.numpy()[: solver.n_tracers].astype(np.float64))


def bind_tracers(solver: MPMSolver, x: np.ndarray, vol: np.ndarray, tr: Optional[np.ndarray],
                  anchors: Optional[np.ndarray]) -> None:
    """Bind every tracer to its ``TRACER_ANCHORS`` nearest anchor particles at rest (see :func:`k_tracer_embed`):
    weights w_k proportional to 1 / (d_k + h / 2) (d_k its distance to particle k, h the mean particle spacing,
    m; sum 1) and the rest offsets X_t - X_k.  Several anchors average out a single particle's rotation noise;
    all of them lie within about a particle spacing of a surface Gaussian."""
    if not solver.n_tracers:
        solver._anchor = None
        return
    from scipy.spatial import cKDTree

    mask = np.ones(len(x), bool) if anchors is None else np.asarray(anchors, bool).reshape(len(x))
    if not mask.any():
        raise ValueError("tracer_anchors selects no particle: tracers need particles to be embedded in")
    idx = np.flatnonzero(mask)
    k = min(TRACER_ANCHORS, len(idx))
    dist, near = cKDTree(x[idx].astype(np.float64)).query(tr.astype(np.float64), k=k)
    dist, near = dist.reshape(len(tr), k), idx[near.reshape(len(tr), k)]
    h = float(np.cbrt(vol.astype(np.float64)).mean())
    w = 1.0 / (dist + 0.5 * h)
    w /= w.sum(axis=1, keepdims=True)
    d = solver.device
    solver._anchor = (wp.array(near.astype(np.int32), dtype=wp.int32, device=d),
                      wp.array(w.astype(np.float32), dtype=float, device=d),
                      wp.array((tr[:, None, :] - x[near]).astype(np.float32), dtype=wp.vec3, device=d))


def place_tracers(solver: MPMSolver) -> None:
    if solver.n_tracers:
        wp.launch(k_tracer_embed, dim=solver.n_tracers, device=solver.device,
                  inputs=[solver.x, solver.F, *solver._anchor, solver.tx, solver.tF])
