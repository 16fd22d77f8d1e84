"""Procedural surface colours of the object model's Gaussians (linear RGB in [0, 1]) from ``appearance.pattern``."""
from __future__ import annotations

import math

import numpy as np

from tasks.control.curvature import unit_vectors
from tasks.control.object_config import ObjectModelError

__all__ = ["PATTERNS", "surface_colors"]

PATTERNS = ("solid", "bands", "label", "speckle", "dimples", "stripes", "fur")
SILVER = np.array([0.62, 0.63, 0.66])  # linear RGB of brushed aluminium
DARK = np.array([0.02, 0.02, 0.02])


def _smooth_noise(p: np.ndarray, wavelength: float, seed: int, waves: int = 12) -> np.ndarray:
    """Band-limited 3-D noise in about [-1, 1]: a sum of ``waves`` random plane waves of the given wavelength
    (m) with random directions and phases (deterministic from ``seed``)."""
    rng = np.random.default_rng([seed, 7919])
    d = unit_vectors(rng.normal(size=(waves, 3)))
    freq = 2 * np.pi / wavelength * rng.uniform(0.7, 1.3, size=waves)
    ph = rng.uniform(0, 2 * np.pi, size=waves)
    return np.sin(p @ (d * freq[:, None]).T + ph).sum(axis=1) * math.sqrt(2.0 / waves)


def surface_colors(pattern: str, kind: str, points: np.ndarray, normals: np.ndarray, bbox_min: np.ndarray,
                   bbox_max: np.ndarray, base, accent, regions: dict[str, np.ndarray] | None = None,
                   seed: int = 0) -> np.ndarray:
    """Linear-RGB colours (N, 3) in [0, 1] of surface samples from a procedural pattern.

    Coordinates are normalised to the bbox: ``c = (p - centre) / half_extent`` in [-1, 1]^3, ``theta`` the
    azimuth about z, ``phi`` the polar angle from +z.

    * ``solid``   the base colour.
    * ``label``   beverage can: silver (brushed aluminium) lid, rims and bottom (the shape's ``top``/``bottom``
                  regions or ``|c_z| > 0.85``), base-coloured body with an accent-coloured wavy label ribbon
                  ``|c_z - 0.12 sin(2 theta)| < 0.16``.
    * ``bands``   paper cup: base colour with an accent band over ``c_z`` in [-0.35, 0.25] and a thin accent
                  line just below the rim ``c_z`` in [0.80, 0.88].
    * ``speckle`` base colour mottled by +-10 % (smooth noise, 8 mm) and small flecks; on sphere/ellipsoid
                  kinds the accent colour draws a star-shaped calyx (5 sepals) around the top pole (a fruit).
    * ``dimples`` base colour with darker peel pores (noise at 3 mm wavelength, up to -22 %) and an
                  accent-coloured stem scar at the top pole (``phi < 0.09``).
    * ``stripes`` six meridional segments alternating base and accent (a beach-ball style rubber ball).
    * ``fur``     base colour with per-sample brightness jitter (+-18 %) and 12 mm mottling.
    Part regions of the shape then override: ``bill``/``ears`` -> accent, ``muzzle``/``paws`` -> base lightened
    40 % towards white, ``eyes``/``nose`` -> near black.
    """
    if pattern not in PATTERNS:
        raise ObjectModelError(f"appearance.pattern {pattern!r} is unknown: use one of {list(PATTERNS)}")
    base = np.clip(np.asarray(base, float).reshape(3), 0, 1)
    accent = np.clip(np.asarray(accent, float).reshape(3), 0, 1)
    p = np.asarray(points, float)
    n_pts = len(p)
    mid = 0.5 * (bbox_min + bbox_max)
    half = np.maximum(0.5 * (bbox_max - bbox_min), 1e-9)
    c = (p - mid) / half
    theta = np.arctan2(c[:, 1], c[:, 0])
    phi = np.arccos(np.clip(c[:, 2] / np.maximum(np.linalg.norm(c, axis=1), 1e-12), -1, 1))
    regions = regions or {}
    rgb = np.tile(base, (n_pts, 1))
    hash_rng = np.random.default_rng([seed, 104729])

    if pattern == "label":
        silver = (np.abs(c[:, 2]) > 0.85)
        if "top" in regions:
            silver = regions["top"] | regions["bottom"]
        ribbon = np.abs(c[:, 2] - 0.12 * np.sin(2 * theta)) < 0.16
        rgb[ribbon & ~silver] = accent
        rgb[silver] = SILVER * (1 + 0.05 * _smooth_noise(p, 0.004, seed))[silver, None]
    elif pattern == "bands":
        band = (c[:, 2] > -0.35) & (c[:, 2] < 0.25)
        line = (c[:, 2] > 0.80) & (c[:, 2] < 0.88)
        rgb[band | line] = accent
    elif pattern == "speckle":
        mottle = 1 + 0.10 * _smooth_noise(p, 0.008, seed) + 0.05 * hash_rng.uniform(-1, 1, n_pts)
        rgb = rgb * mottle[:, None]
        if kind in ("sphere", "ellipsoid"):
            star = 0.10 + 0.32 * (0.5 + 0.5 * np.cos(5 * theta)) ** 3
            rgb[phi < star] = accent * (1 + 0.08 * _smooth_noise(p, 0.005, seed + 1))[phi < star, None]
    elif pattern == "dimples":
        pores = np.clip(_smooth_noise(p, 0.003, seed), 0, None)
        rgb = rgb * (1 - 0.22 * np.minimum(pores, 1.0))[:, None]
        rgb[phi < 0.09] = accent
    elif pattern == "stripes":
        seg = np.floor((theta + np.pi) / (2 * np.pi) * 6).astype(int) % 2 == 1
        rgb[seg] = accent
    elif pattern == "fur":
        mottle = (1 + 0.18 * hash_rng.uniform(-1, 1, n_pts)) * (1 + 0.08 * _smooth_noise(p, 0.012, seed))
        rgb = rgb * mottle[:, None]

    for name, mask in regions.items():
        if name in ("bill", "ears"):
            rgb[mask] = accent * (1 + 0.08 * hash_rng.uniform(-1, 1, int(mask.sum())))[:, None] \
                if pattern == "fur" else accent
        elif name in ("muzzle", "paws"):
            rgb[mask] = base + 0.4 * (1 - base)
        elif name in ("eyes", "nose"):
            rgb[mask] = DARK
    return np.clip(rgb, 0.0, 1.0)

