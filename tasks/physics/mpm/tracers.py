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
    """Rotation part R (det +1) of the polar decomposition F = R S, batched (N,3,3).

    Uses the SVD F = U S V^T with the sign of the smallest singular value flipped when det F < 0, so R is a proper
    rotation (the closest one to F).
    """
    F = np.asarray(F, dtype=np.float64)
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
