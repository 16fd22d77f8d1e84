"""The simulated object of one frame as renderable Gaussians (paper sec. 3.2, last paragraph): the deformed surface
Gaussians of the MPM rollout plus the released interior material, with an indicator channel from which the
rasteriser composites the particle mask M of sec. 3.3.

Everything is numpy; ``GaussianScene`` fields go to ``splat.rasterization(means, None, None, opacities, colors,
..., covars=covars)`` after ``torch.from_numpy``.
"""

from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np

# sigma = RELEASED_SCALE_FACTOR * cbrt(particle volume). On a lattice of spacing s = cbrt(V), isotropic Gaussians
# with sigma = k s sum to sum_i exp(-|x - p_i|^2 / (2 sigma^2)) = (2 pi)^(3/2) k^3 (1 + ripple(x)) (Poisson
# summation), |ripple| ~ 6 exp(-2 pi^2 k^2): 0.5 % at k = 0.6, 4 % at k = 0.5, 28 % at k = 0.4.
RELEASED_SCALE_FACTOR = 0.6

# A drawn surface Gaussian's axes are at most MAX_SURFACE_STRETCH x its largest rest scale (standard deviation).
# The squeezes of the default grid stretch no surface Gaussian beyond 3.04x (plush toy; rubber duck 2.95x, clay
# 1.28x), so the bound leaves them as simulated; torn skin flakes stretched plastically up to 2e4x (tomato: a 30 m
# axis on a 1.8 mm Gaussian) drew long streaks over the whole image.
MAX_SURFACE_STRETCH = 4.0


class GaussianScene(NamedTuple):
    """Renderable Gaussians. means (G, 3) m; covars (G, 6) m^2 xx xy xz yy yz zz; colors (G, 4) linear RGB in
    [0, 1] then is_released (1 for released interior material, 0 for the surface); opacities (G,) in [0, 1].
    All float32."""

    means: np.ndarray
    covars: np.ndarray
    colors: np.ndarray
    opacities: np.ndarray


def released_gaussians(positions: np.ndarray, volumes: np.ndarray, colour: np.ndarray, opacity: float,
                       scale_factor: float = RELEASED_SCALE_FACTOR) -> GaussianScene:
    """Isotropic Gaussians for MPM particles of released interior material.

    positions: (particle, 3) m; volumes: (particle,) m^3, the material volume each particle carries;
    colour: (3,) linear RGB in [0, 1]; opacity in [0, 1]; scale_factor k: sigma = k cbrt(volume) m, so particles
    at their natural spacing s = cbrt(volume) overlap into a smooth density (ripple ~ 6 exp(-2 pi^2 k^2), see
    RELEASED_SCALE_FACTOR). Returns a GaussianScene with is_released = 1.
    """
    positions = np.asarray(positions, dtype=np.float64)
    volumes = np.asarray(volumes, dtype=np.float64)
    colour = np.asarray(colour, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != 3 or volumes.shape != (len(positions),):
        raise ValueError(f"positions must be (particle, 3) and volumes (particle,), got {positions.shape}, "
                         f"{volumes.shape}")
    if colour.shape != (3,) or np.any(volumes < 0) or not 0.0 <= opacity <= 1.0 or not scale_factor > 0:
        raise ValueError("need colour (3,), volumes >= 0, opacity in [0, 1] and scale_factor > 0")
    n = len(positions)
    variance = (scale_factor * np.cbrt(volumes)) ** 2
    covars = np.zeros((n, 6))
    covars[:, [0, 3, 5]] = variance[:, None]
    colors = np.concatenate([np.broadcast_to(colour, (n, 3)), np.ones((n, 1))], axis=1)
    return _float32(GaussianScene(positions, covars, colors, np.full(n, float(opacity))))


def released_visibility(released: np.ndarray, release_frame: int | None, n_frames: int) -> np.ndarray:
    """(frame, particle) bool: a released particle is drawn from the frame of its release on.

    released: (particle,) bool, the rollout's ``released``; release_frame: the rollout's threshold event frame
    (None when the threshold was never crossed: nothing is drawn).
    """
    released = np.asarray(released, dtype=bool)
    if release_frame is None:
        return np.zeros((n_frames, len(released)), dtype=bool)
    return (np.arange(n_frames) >= release_frame)[:, None] & released[None, :]


def frame_scene(surface_positions: np.ndarray, surface_covariances: np.ndarray, surface_colors: np.ndarray,
                surface_opacities: np.ndarray, particle_positions: np.ndarray, particle_volumes: np.ndarray,
                visible_released: np.ndarray, released_colour: np.ndarray, released_opacity: float,
                scale_factor: float = RELEASED_SCALE_FACTOR) -> GaussianScene:
    """Surface Gaussians followed by the visible released particles of one frame.

    surface_positions: (point, 3) m and surface_covariances: (point, 6) m^2 (the rollout's gaussian_positions /
    gaussian_covariances at this frame); surface_colors: (point, 3) linear RGB; surface_opacities: (point,);
    particle_positions: (particle, 3) m at this frame; particle_volumes: (particle,) m^3; visible_released:
    (particle,) bool (a row of ``released_visibility``); released_colour (3,), released_opacity and scale_factor
    as in ``released_gaussians``. The 4th colour channel is 1 for released material, 0 for the surface: rendered
    with background 0 it is the composited weight of released Gaussians, the particle mask M (sec. 3.3).
    """
    surface_positions = np.asarray(surface_positions, dtype=np.float64)
    n = len(surface_positions)
    shapes = (np.shape(surface_covariances), np.shape(surface_colors), np.shape(surface_opacities))
    if surface_positions.shape != (n, 3) or shapes != ((n, 6), (n, 3), (n,)):
        raise ValueError(f"surface arrays must be (point, 3), (point, 6), (point, 3), (point,); got "
                         f"{surface_positions.shape}, {shapes}")
    visible_released = np.asarray(visible_released, dtype=bool)
    if visible_released.shape != (len(particle_positions),):
        raise ValueError(f"visible_released must be (particle,) = ({len(particle_positions)},), got "
                         f"{visible_released.shape}")
    surface = GaussianScene(surface_positions, np.asarray(surface_covariances, dtype=np.float64),
                            np.concatenate([surface_colors, np.zeros((n, 1))], axis=1),
                            np.asarray(surface_opacities, dtype=np.float64))
    released = released_gaussians(np.asarray(particle_positions)[visible_released],
                                  np.asarray(particle_volumes)[visible_released], released_colour,
                                  released_opacity, scale_factor)
    return _float32(GaussianScene(*(np.concatenate([a, b]) for a, b in zip(surface, released))))


def drawn_covariances(covariances: np.ndarray, rest_scales: np.ndarray,
                      max_stretch: float = MAX_SURFACE_STRETCH) -> np.ndarray:
    """The covariances surface Gaussians are drawn with: F Sigma F^T with every axis length capped.

    covariances: (..., point, 6) m^2 xx xy xz yy yz zz, the rollout's ``gaussian_covariances`` (F Sigma F^T);
    rest_scales: (point, 3) m, the object model's ``gaussian_scales`` (standard deviations at rest).  Each
    covariance keeps its principal axes (eigenvectors) and every axis length (sqrt of an eigenvalue) is capped at
    ``max_stretch`` x the Gaussian's largest rest scale, so no Gaussian becomes a streak whatever its (plastic)
    stretch: a torn flake draws as a bounded splat, an opening as a gap.  Gaussians within the bound are drawn
    exactly as simulated (the rotation polar(F) q0 with a clamped stretch would alter every sheared one).
    Returns (..., point, 6) m^2 float32.
    """
    cov = np.asarray(covariances, dtype=np.float64)
    rest = np.asarray(rest_scales, dtype=np.float64)
    if cov.shape[-1] != 6 or rest.shape != (cov.shape[-2], 3) or not max_stretch > 0:
        raise ValueError(f"covariances must be (..., point, 6) and rest_scales (point, 3) with max_stretch > 0; "
                         f"got {cov.shape}, {rest.shape}, {max_stretch}")
    i, j = (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)
    full = np.zeros(cov.shape[:-1] + (3, 3))
    full[..., i, j] = cov
    full[..., j, i] = cov
    w, q = np.linalg.eigh(full)
    cap = (max_stretch * rest.max(axis=1)) ** 2
    w = np.clip(w, 0.0, cap[:, None])
    bounded = np.einsum("...ik,...k,...jk->...ij", q, w, q)
    return bounded[..., i, j].astype(np.float32)


def _float32(scene: GaussianScene) -> GaussianScene:
    return GaussianScene(*(np.ascontiguousarray(a, dtype=np.float32) for a in scene))


def released_appearance(render: Mapping[str, Any], interior_name: str | None) -> dict[str, Any]:
    """The look of released interior material: the first key of ``render.released`` that is a word of the
    oracle's interior name (case-insensitive), else ``render.released_default``."""
    name = (interior_name or "").lower()
    for key, look in render["released"].items():
        if key.lower() in name:
            return dict(look)
    return dict(render["released_default"])


def rollout_particle_volumes(particles: Mapping[str, np.ndarray], n_particles: int) -> np.ndarray:
    """(particle,) m^3 of the rollout's particles (``particles``: the ``mpm_particles`` arrays): the object's own
    particles, then its cavity particles (core or interior), in the order the rollout concatenates them."""
    return np.concatenate([particles["particle_volumes"], particles["interior_volumes"]])[:n_particles]
