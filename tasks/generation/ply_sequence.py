"""The 4D result as standard 3DGS PLY files, one per rendered frame (any splat viewer opens them).

Per frame: the object's surface Gaussians as the MPM deformed them (covariance F Sigma F^T decomposed into per-axis
scales and a rotation) with their colours and opacities, followed by the released particles visible in that frame
with the appearance refined by eq. 7 (per-axis scales along the world axes, no rotation).  Written with
:func:`tasks.control.gaussian_ply.write_gaussian_ply` in the reference 3DGS layout (SH degree 3 with the 45
``f_rest_*`` zeros: the colour is view-independent; normals ``nx ny nz`` present, zero), colours as display sRGB,
so the official loader and web splat viewers show the colours our renderer shows.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from tasks.control.gaussian_ply import write_gaussian_ply


def covariance_to_scale_rotation(covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 6) xx xy xz yy yz zz m^2 -> per-axis standard deviations (N, 3) m and quaternions (N, 4) w, x, y, z with
    R diag(s^2) R^T = the covariance (eigen-decomposition; a reflection is turned into a rotation)."""
    c = np.asarray(covariances, np.float64)
    full = np.stack([np.stack([c[:, 0], c[:, 1], c[:, 2]], -1), np.stack([c[:, 1], c[:, 3], c[:, 4]], -1),
                     np.stack([c[:, 2], c[:, 4], c[:, 5]], -1)], axis=1)
    values, vectors = np.linalg.eigh(full)
    vectors[np.linalg.det(vectors) < 0, :, 0] *= -1.0
    xyzw = Rotation.from_matrix(vectors).as_quat()
    return np.sqrt(np.clip(values, 1e-20, None)), np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)


def write_ply_sequence(out_dir: str | Path, surface_positions: np.ndarray, surface_covariances: np.ndarray,
                       surface_colors: np.ndarray, surface_opacities: np.ndarray, particle_positions: np.ndarray,
                       visible: np.ndarray, released_colors: np.ndarray, released_opacities: np.ndarray,
                       released_scales: np.ndarray, frame_index: np.ndarray) -> list[Path]:
    """One ``frame_XXXX.ply`` per rendered frame in ``out_dir``.

    surface_positions (frame, point, 3) m, surface_covariances (frame, point, 6) m^2, surface_colors (point, 3)
    linear RGB, surface_opacities (point,); particle_positions (frame, released, 3) m of the released particles,
    visible (frame, released) bool, released_colors (released, 3), released_opacities (released,),
    released_scales (released, 3) m; frame_index (frame,) the simulated frame numbers used in the file names."""
    paths = []
    for f, sim_frame in enumerate(frame_index):
        scales, quats = covariance_to_scale_rotation(surface_covariances[f])
        shown = visible[f]
        n = int(shown.sum())
        identity = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
        paths.append(write_gaussian_ply(
            Path(out_dir) / f"frame_{int(sim_frame):04d}.ply",
            np.concatenate([surface_positions[f], particle_positions[f][shown]]),
            np.concatenate([scales, released_scales[shown]]), np.concatenate([quats, identity]),
            np.clip(np.concatenate([surface_opacities, released_opacities[shown]]), 1e-4, 1 - 1e-4),
            np.concatenate([surface_colors, released_colors[shown]])))
    return paths
