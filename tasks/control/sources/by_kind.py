"""The geometry source of an object config's ``geometry.kind``, and the check of a user's geometry file."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from tasks.control.gaussian_ply import read_gaussian_ply
from tasks.control.geometry import SHAPE_KINDS, make_shape
from tasks.control.object_config import ObjectModelError, config_value
from tasks.control.sources.base import GeometrySource, SampledSource, fit_statement
from tasks.control.sources.mesh import MeshSource, load_checked_mesh
from tasks.control.sources.ply import PlySource
from tasks.control.sources.procedural import ProceduralSource
from tasks.control.splat_content import check_splat_content

__all__ = ["open_source", "check_geometry_file"]


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


def check_geometry_file(kind: str, path: str | None, size: Any = None) -> str | None:
    """Check a user geometry file before anything runs: a closed, non-flat, consistently wound mesh (``kind: mesh``)
    or a readable 3DGS PLY (``kind: ply``) whose content makes a visible object (:func:`check_splat_content`), and,
    with ``size`` (m), its fit into ``geometry.size`` (:func:`fit_statement`: the line stating the rescale, or
    None).  Raises :class:`ObjectModelError` or :class:`GaussianPlyError` (one line, file and fix)."""
    if kind == "mesh":
        mesh = load_checked_mesh(path)
        lo, hi, what = mesh.bounds[0], mesh.bounds[1], f"mesh {Path(str(path)).expanduser()}"
    elif kind == "ply":
        if not path:
            raise ObjectModelError("object.geometry.path is required for geometry.kind 'ply': set it to a 3DGS .ply")
        p = Path(str(path)).expanduser()
        g = read_gaussian_ply(p)
        check_splat_content(p, g["means"], g["scales"], g["opacities"])
        lo, hi, what = g["means"].min(0), g["means"].max(0), f"PLY {p}"
    else:
        return None
    return None if size is None else fit_statement(what, lo, hi, size)
