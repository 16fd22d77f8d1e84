"""The geometry source of an object config's ``geometry.kind``, and the check of a user's geometry file (its fit into
``geometry.size``: :func:`tasks.control.sources.base.fit_statement`)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tasks.control.gaussian_ply import read_gaussian_ply
from tasks.control.geometry import SHAPE_KINDS, make_shape
from tasks.control.object_config import ObjectModelError, config_value
from tasks.control.sources.base import GeometrySource, SampledSource
from tasks.control.sources.mesh import MeshSource, load_checked_mesh
from tasks.control.sources.ply import PlySource
from tasks.control.sources.procedural import ProceduralSource
from tasks.control.splat_content import check_splat_content

__all__ = ["open_source", "geometry_file_bounds"]


def open_source(kind: str, geom: Any, size: np.ndarray, spacing: float, surface_points: int, wall_thickness: float,
                rng: np.random.Generator) -> GeometrySource:
    """The source of ``kind``: a procedural shape of ``size`` (m), a mesh (``geom.path``, dense samples 20 x
    ``surface_points`` drawn from ``rng``) or a 3DGS PLY (``geom.path``), the files voxelised at ``spacing`` / 2 (m).
    A file-based source looks up exact distances to the depth ``wall_thickness + 2 spacing`` (m) that the wall and
    cavity split needs."""
    if kind in SHAPE_KINDS:
        return ProceduralSource(make_shape(kind, size))
    if kind == "mesh":
        src: SampledSource = MeshSource(config_value(geom, "path"), size, spacing, 20 * surface_points, rng)
    else:
        src = PlySource(config_value(geom, "path"), size, spacing)
    src.refine_dist = wall_thickness + 2 * spacing
    return src


def geometry_file_bounds(kind: str, path: str | None) -> tuple[np.ndarray, np.ndarray, str] | None:
    """Read and check a user geometry file: a closed, non-flat, consistently wound mesh (``kind: mesh``) or a
    readable 3DGS PLY (``kind: ply``) whose content makes a visible object (:func:`check_splat_content`).  Returns
    the bounds of its points (file units) and what it is ("mesh <file>" or "PLY <file>"), None for a procedural
    kind.  Raises :class:`ObjectModelError` or :class:`GaussianPlyError` (one line, file and fix)."""
    if kind == "mesh":
        mesh = load_checked_mesh(path)
        return mesh.bounds[0], mesh.bounds[1], f"mesh {Path(str(path)).expanduser()}"
    if kind == "ply":
        if not path:
            raise ObjectModelError("object.geometry.path is required for geometry.kind 'ply': set it to a 3DGS .ply")
        p = Path(str(path)).expanduser()
        g = read_gaussian_ply(p)
        check_splat_content(p, g["means"], g["scales"], g["opacities"])
        return g["means"].min(0), g["means"].max(0), f"PLY {p}"
    return None

