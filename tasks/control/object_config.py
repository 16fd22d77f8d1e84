"""The object config as the object model reads it: the one-line error, config access, validation and the seed.

Shared by the object model (:mod:`tasks.control.object_model`: the surface Gaussians) and the MPM particle fill
(:mod:`tasks.physics.particle_fill`), which sample the same geometry from the same seed.
"""
from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from tasks.control.geometry import SHAPE_KINDS
from tasks.core.params import file_sha256

__all__ = ["ObjectModelError", "config_value", "validate_object", "sampling_seed"]


class ObjectModelError(ValueError):
    """An object config or input file that cannot be turned into an object model (one line, names the fix)."""


def config_value(node: Any, name: str, default: Any = None) -> Any:
    """``node.name`` of a config node or dataclass, ``node[name]`` of a plain mapping (step params)."""
    if node is None:
        return default
    if isinstance(node, Mapping):
        return node.get(name, default)
    return getattr(node, name, default)


def validate_object(obj: Any, sampling: Any) -> tuple[str, np.ndarray, float, float, int, int, int]:
    """The object's and the sampling's values checked before any work: (kind, size (3,) m, wall thickness t m,
    particle spacing s m, surface points, seed, thin-wall layers); :class:`ObjectModelError` (one line, the fix)."""
    name = str(config_value(obj, "name", "object"))
    geom = config_value(obj, "geometry")
    kind = str(config_value(geom, "kind"))
    try:
        size = np.asarray(list(config_value(geom, "size")), dtype=np.float64)
    except (TypeError, ValueError):
        raise ObjectModelError(f"object {name}: geometry.size must be three lengths in m") from None
    if size.shape != (3,) or np.any(~np.isfinite(size)) or np.any(size <= 0):
        raise ObjectModelError(f"object {name}: geometry.size must be three positive lengths in m, got {size.tolist()}")
    t = float(config_value(geom, "wall_thickness", 0.0) or 0.0)
    s = float(config_value(sampling, "particle_spacing"))
    n_surf = int(config_value(sampling, "surface_points"))
    seed = int(config_value(sampling, "seed", 0) or 0)
    layers = int(config_value(sampling, "thin_wall_layers", 2) or 2)
    filled = bool(config_value(obj, "filled", False))
    interior = config_value(obj, "interior")
    if not (s > 0 and math.isfinite(s)):
        raise ObjectModelError(f"sampling.particle_spacing must be > 0 m, got {s}")
    if n_surf < 10:
        raise ObjectModelError(f"sampling.surface_points must be >= 10, got {n_surf}")
    if layers not in (1, 2, 3):
        raise ObjectModelError(f"sampling.thin_wall_layers must be 1, 2 or 3, got {layers}")
    if t < 0 or not math.isfinite(t):
        raise ObjectModelError(f"object {name}: geometry.wall_thickness must be >= 0 m, got {t}")
    if not filled and t <= 0:
        raise ObjectModelError(f"object {name}: geometry.wall_thickness is 0 but filled is false: give the shell "
                               "thickness in m, or set filled: true for a solid body")
    if filled and interior:
        raise ObjectModelError(f"object {name}: filled is true (solid body) but interior is {interior!r}: "
                               "set filled: false with a wall_thickness, or interior: null")
    if not filled and t >= 0.5 * size.min():
        raise ObjectModelError(f"object {name}: wall_thickness {t} m is not thinner than half the smallest side "
                               f"({0.5 * size.min()} m): set filled: true or a thinner wall")
    if kind not in SHAPE_KINDS + ("ply", "mesh"):
        raise ObjectModelError(f"object {name}: geometry.kind {kind!r} is unknown: use one of "
                               f"{list(SHAPE_KINDS) + ['ply', 'mesh']}")
    return kind, size, t, s, n_surf, seed, layers


def sampling_seed(obj: Any, seed: int) -> np.random.SeedSequence:
    """The seed sequence of every random draw of :func:`build_object_model`: the explicit ``sampling.seed`` and the
    object's *content*, never its name or label, so the same object under two names gets bitwise identical
    Gaussians and particles.  Content = the geometry that is sampled: ``kind``, ``size`` (m), ``wall_thickness``
    (m), ``filled``, whether it has an interior, and for a mesh or PLY the SHA-256 of the file."""
    geom = config_value(obj, "geometry")
    kind, path = str(config_value(geom, "kind")), config_value(geom, "path")
    content = {"kind": kind, "size": [float(x) for x in config_value(geom, "size")],
               "wall_thickness": float(config_value(geom, "wall_thickness", 0.0) or 0.0),
               "filled": bool(config_value(obj, "filled", False)), "interior": bool(config_value(obj, "interior")),
               "file": file_sha256(path) if kind in ("ply", "mesh") and path and Path(path).expanduser().is_file()
               else None}  # a missing file is refused by its loader, with the fix
    digest = hashlib.sha256(json.dumps(content, sort_keys=True).encode()).digest()
    return np.random.SeedSequence([int(seed), *np.frombuffer(digest[:16], dtype=np.uint32).tolist()])

