"""A closed triangle mesh (``geometry.kind: mesh``, loaded with trimesh) as a geometry source.

The mesh must be one closed, consistently wound surface: an open (non-watertight) mesh, one with a face wound
against its neighbours (its outward normal is ambiguous) or one that intersects itself is refused, not repaired
(:func:`load_checked_mesh`; :mod:`tasks.control.object_model` says why); a NaN vertex is named as such.  Self-intersection is found by
:func:`tasks.control.geometry.crossing_triangle_pairs`.  Colours come from the mesh's own vertex/face colours or
texture when it has them.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from tasks.control.gaussian_ply import srgb_to_linear
from tasks.control.geometry import crossing_triangle_pairs
from tasks.control.object_config import ObjectModelError
from tasks.control.sources.base import SampledSource, fit_transform
from tasks.core.excerpt import one_line

__all__ = ["MeshSource", "load_checked_mesh"]

_FLAT_VOLUME = 1e-9  # enclosed volume / largest extent^3 below this: a flat mesh


def load_checked_mesh(path: str | None):
    """The closed triangle mesh at ``path`` (a ``trimesh.Trimesh``), or :class:`ObjectModelError` naming the file
    and the fix: missing file, unreadable, empty, NaN/inf vertices, not watertight, inconsistently wound (a face
    flipped against its neighbours), flat, or intersecting itself (see the module doc)."""
    import trimesh

    if not path:
        raise ObjectModelError("object.geometry.path is required for geometry.kind 'mesh': "
                               "set it to an OBJ/PLY/STL/GLB file")
    p = Path(str(path)).expanduser()
    if not p.is_file():
        raise ObjectModelError(f"mesh {p} does not exist: set object.geometry.path to an existing OBJ/PLY/STL/GLB file")
    try:
        mesh = trimesh.load(str(p), force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types
        raise ObjectModelError(f"mesh {p} could not be loaded ({type(exc).__name__}: {one_line(exc)}): "
                               "export it as OBJ, PLY, STL or GLB") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ObjectModelError(f"mesh {p} is empty (0 faces): export the object's surface as triangles "
                               "(a point cloud or 3DGS splat needs geometry.kind 'ply')")
    open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
    if open_edges or not mesh.is_watertight:
        _refuse_non_finite(p)  # trimesh drops the faces of a NaN vertex on load: holes whose cause is the NaN
        raise ObjectModelError(f"mesh {p} is not watertight ({open_edges} open edges): repair it, e.g. "
                               "trimesh.repair.fill_holes, or export a closed mesh")
    twice = trimesh.grouping.group_rows(mesh.edges, require_count=2)  # a directed edge in two faces: a flip
    if len(twice):
        i, j = sorted(int(k) // 3 for k in twice[0])
        raise ObjectModelError(f"mesh {p} has inconsistent winding ({len(twice)} of its {len(mesh.edges_unique)} "
                               f"edges join two faces wound opposite ways, e.g. faces {i} and {j}): inside and outside "
                               "are ambiguous; make the winding consistent, e.g. trimesh.repair.fix_winding (or "
                               "Blender's Mesh > Normals > Recalculate Outside), and export again")
    ext = mesh.bounds[1] - mesh.bounds[0]
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh divides by the volume for the centre of mass
        volume = abs(float(mesh.volume))
    if volume <= _FLAT_VOLUME * float(ext.max()) ** 3:
        raise ObjectModelError(f"mesh {p} encloses no volume ({volume:.3g} within a "
                               f"{' x '.join(f'{e:.3g}' for e in ext)} box, file units): it is flat (a sheet); give "
                               "it a thickness (e.g. Blender's Solidify modifier) and export a closed solid")
    crossing = crossing_triangle_pairs(mesh.vertices, mesh.faces, limit=100)
    if len(crossing):
        i, j = (int(x) for x in crossing[0])
        more = "100 or more" if len(crossing) >= 100 else str(len(crossing))
        raise ObjectModelError(f"mesh {p} intersects itself ({more} pairs of faces pass through each other, "
                               f"e.g. faces {i} and {j}): inside and outside are ambiguous; merge the "
                               "overlapping parts into one closed surface (a boolean union, e.g. Blender's "
                               "Boolean modifier) and export again")
    return mesh


def _refuse_non_finite(p: Path) -> None:
    """Raise :class:`ObjectModelError` naming the NaN/inf vertices of the mesh file ``p``, if it has any."""
    import trimesh

    vertices = np.asarray(trimesh.load(str(p), force="mesh", process=False).vertices)
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if len(bad):
        what = "1 vertex" if len(bad) == 1 else f"{len(bad)} vertices"
        raise ObjectModelError(f"mesh {p} has {what} with NaN/inf coordinates (e.g. vertex {int(bad[0])}): fix or "
                               "delete them in the modelling tool and export again")


class MeshSource(SampledSource):
    kind = "mesh"

    def __init__(self, path: str | None, size: np.ndarray, spacing: float, n_dense: int, rng: np.random.Generator):
        import trimesh

        mesh = load_checked_mesh(path)
        p = Path(str(path)).expanduser()
        if mesh.volume < 0:
            mesh.invert()
        shift, scale = fit_transform(mesh.bounds[0], mesh.bounds[1], size)
        mesh.apply_translation(shift)
        mesh.apply_scale(scale)
        self.mesh, self.path, self.scale = mesh, p, scale
        self.bbox_min, self.bbox_max = mesh.bounds[0].copy(), mesh.bounds[1].copy()
        self.area_total = float(mesh.area)
        self.enclosed_volume = float(mesh.volume)
        pitch = spacing / 2
        vox = mesh.voxelized(pitch=pitch).fill()
        occ = np.asarray(vox.matrix, bool)
        origin = np.asarray(vox.transform[:3, 3], float) - pitch / 2  # transform maps indices to voxel centres
        seed = int(rng.integers(2**31))
        pts, face = trimesh.sample.sample_surface(mesh, n_dense, seed=seed)
        self.dense_pts = np.asarray(pts, float)
        self.dense_nrm = np.asarray(mesh.face_normals[face], float)
        self._dense_tree = cKDTree(self.dense_pts)
        self._setup_sdf(self.dense_pts, self.dense_nrm, occ, origin, pitch)
        self._rgb = self._mesh_colors(mesh, self.dense_pts, face)

    @staticmethod
    def _mesh_colors(mesh, pts: np.ndarray, face: np.ndarray) -> np.ndarray | None:
        """Linear RGB of the dense samples from the mesh's own vertex/face colours or texture, else None."""
        import trimesh

        vis = mesh.visual
        try:
            if isinstance(vis, trimesh.visual.texture.TextureVisuals):
                vis = vis.to_color()
            kind = getattr(vis, "kind", None)
            if kind == "vertex":
                bary = trimesh.triangles.points_to_barycentric(mesh.triangles[face], pts)
                vc = np.asarray(vis.vertex_colors, float)[:, :3] / 255.0
                srgb = np.einsum("nk,nkc->nc", bary, vc[mesh.faces[face]])
            elif kind == "face":
                srgb = np.asarray(vis.face_colors, float)[face, :3] / 255.0
            else:
                return None
        except Exception:  # a visual trimesh cannot convert: fall back to the procedural pattern
            return None
        return srgb_to_linear(srgb)  # the file's colours are display sRGB, as a PLY's f_dc (gaussian_ply)

    def candidates(self, n, rng):
        if n >= len(self.dense_pts):
            return self.dense_pts
        return self.dense_pts[rng.choice(len(self.dense_pts), size=n, replace=False)]

    def finalize(self, pts):
        _, i = self._dense_tree.query(pts, k=1)  # candidates are dense samples: their own face normal
        return pts, self.dense_nrm[i]

    def area_measure(self, rng):
        return self.dense_pts, np.full(len(self.dense_pts), self.area_total / len(self.dense_pts))

    def colors_at(self, pts: np.ndarray) -> np.ndarray | None:
        if self._rgb is None:
            return None
        _, i = self._dense_tree.query(pts, k=1)
        return self._rgb[i]

