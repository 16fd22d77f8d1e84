"""Object model: what the method needs from one object config.

:func:`build_object_model` is a pure function (numpy/scipy/trimesh; no Prefect, no zarr); the
cached Prefect step :data:`object_model_step` at the bottom only wraps it for :mod:`flows.pipeline`.

VirSqueezer (paper sec. "Squeezing Control Mapping" and "Physics Simulation") represents an object twice:

* **3D Gaussians on the surface** (Kerbl et al. 2023): their means are the surface samples on which contact
  patches (SC-CAE, eq. 2) and the displacement field (eq. 3) are evaluated, so each sample also carries its
  outward normal, principal curvatures/directions and the area it represents;
* **MPM volume particles** of the object's own material (MLS-MPM, Hu et al. 2018; PhysGaussian, Xie et al.
  2024 fills the volume in the same way), plus, for filled containers, particles of the interior material: the
  physics stage's fill (:mod:`tasks.physics.particle_fill`, step ``mpm_particles``), since which particles a wall
  gets depends on the MPM grid (``mpm.dx``) and the control chain's keys must not.

:func:`build_object_model` returns the Gaussians for a procedural shape (:mod:`tasks.control.sources.procedural`,
shapes of :mod:`tasks.control.geometry`), a triangle mesh (``kind: mesh``, :mod:`tasks.control.sources.mesh`) or a
3DGS PLY (``kind: ply``, :mod:`tasks.control.sources.ply`).  All lengths
are metres, areas m^2, volumes m^3; positions are float32.

A mesh or PLY is centred at the origin and scaled uniformly to fit ``geometry.size`` (m), the size the physics
uses: :mod:`flows.preflight` prints the scale factor when it is not 1 and refuses a factor outside
``FIT_SCALE_RANGE`` (a file of 1 km or 1 um is a units mistake); a flat (zero-volume) mesh is refused.

A mesh must be one closed surface: an open (non-watertight) mesh or one that intersects itself (e.g. a body and
a head modelled as two overlapping closed shells) is refused, not repaired.  Both leave inside and outside
undefined where it matters: the enclosed volume (divergence theorem) counts an overlap twice, the
voxel fill and the signed distance disagree there, and surface samples - the Gaussians the fingers touch and
the contact patches - would lie on faces buried inside the body.  A silent repair (hole filling, boolean
union) would change the user's geometry without saying so; the error names the file and the repair to do.
Self-intersection is found by :func:`tasks.control.geometry.crossing_triangle_pairs` (exact triangle-triangle
crossings; coplanar overlaps and folds between neighbouring faces are not detected).

Discretisation choices (documented here because downstream steps rely on them):

* Surface samples are blue-noise: random area-uniform candidates (5 per sample) thinned by greedy Poisson-disk
  selection in random order (dart throwing restricted to the candidates, Cook 1986) to exactly
  ``sampling.surface_points`` samples.  ``surface_area`` is each sample's Voronoi share of the surface (the
  area measure of the fine marching-tetrahedra mesh, or of dense samples, assigned to the nearest sample), so
  it sums to the total area.
* Curvature: analytic (sphere, cup) or from the implicit function's Hessian (procedural shapes), or from a
  weighted least-squares quadric fit ``h = a x^2 + b x y + c y^2 + d x + e y`` over the 16 nearest samples in
  the tangent frame (mesh, ply); sign: convex = positive; magnitudes are clamped to ``2 / sqrt(area_i)`` (the
  representation cannot resolve sharper features, e.g. the cup's bottom crease).
* Gaussians: tangent standard deviations ``0.6 sqrt(area_i)`` (neighbours overlap at ~1 sigma), normal std
  ``0.1`` of that; rotation maps local (x, y, z) to (k1 direction, k2 direction, normal).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from tasks.control.curvature import matrix_to_quaternion, resolved_curvature, unit_vectors
from tasks.control.object_config import ObjectModelError, config_value, sampling_seed, validate_object
from tasks.control.sources.by_kind import open_source
from tasks.control.sources.mesh import MeshSource
from tasks.control.sources.ply import PlySource
from tasks.control.surface_colors import surface_colors
from tasks.control.surface_sampling import blue_noise, voronoi_area
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step

__all__ = ["ObjectModelError", "build_object_model", "OBJECT_OUTPUTS", "object_model_step"]

_TANGENT_SIGMA = 0.6  # x sqrt(area_i)
_NORMAL_SIGMA = 0.1  # x tangent sigma
_CANDIDATES_PER_SAMPLE = 5


def build_object_model(obj: Any, sampling: Any) -> tuple[dict[str, Array], dict[str, Any]]:
    """Surface Gaussians of one object (see the module doc for every choice).

    Args:
        obj: an ``ObjectConfig`` (dataclass or OmegaConf node; read by attribute).
        sampling: a ``SamplingConfig`` (``surface_points``, ``particle_spacing`` m, ``seed``, ``thin_wall_layers``).
    Returns:
        ``(arrays, attrs)``: the arrays of :data:`OBJECT_OUTPUTS` as :class:`tasks.core.artifacts.Array`, and JSON
        attrs ``kind``, ``bbox_min``/``bbox_max`` (m), ``surface_area_total`` (m^2), ``enclosed_volume`` (m^3) and
        ``wall_thickness``/``particle_spacing`` (m).
    Raises:
        ObjectModelError: one line naming the input and the fix.
    """
    kind, size, t, s, n_surf, seed, _ = validate_object(obj, sampling)
    geom, app = config_value(obj, "geometry"), config_value(obj, "appearance")
    # the five streams of the object's seed (the particle fill draws from the same ones: tasks.physics.particle_fill)
    rng_surf, rng_area, _, _, rng_misc = (np.random.default_rng(c) for c in sampling_seed(obj, seed).spawn(5))
    src = open_source(kind, geom, size, s, n_surf, t, rng_misc)
    A = src.area_total

    # surface samples = Gaussian means
    if isinstance(src, PlySource):
        pts, nrm = src.means, src.mean_normals
        area = src.point_area.copy()
        g = src.gauss
        gscales, grot = g["scales"], g["rotations"]
        opac = np.clip(g["opacities"], 1e-4, 1 - 1e-4)
        rgb = np.clip(g["colors"], 0.0, 1.0)
        kcurv, kdirs = src.curvature(pts, nrm)
    else:
        cand = src.candidates(_CANDIDATES_PER_SAMPLE * n_surf, rng_surf)
        sel = blue_noise(cand, n_surf, A, rng_surf)
        pts, nrm = src.finalize(cand[sel])
        mpts, mw = src.area_measure(rng_area)
        area = voronoi_area(pts, mpts, mw)
        kcurv, kdirs = src.curvature(pts, nrm)
        sig_t = _TANGENT_SIGMA * np.sqrt(area)
        gscales = np.stack([sig_t, sig_t, _NORMAL_SIGMA * sig_t], axis=1)
        R = np.stack([kdirs[:, 0], kdirs[:, 1], nrm], axis=2)  # columns: local x, y, z -> t1, t2, n
        grot = matrix_to_quaternion(R)
        opac = np.full(len(pts), float(np.clip(float(config_value(app, "opacity", 0.98)), 1e-3, 0.999)))
        rgb = src.colors_at(pts) if isinstance(src, MeshSource) else None
        if rgb is None:
            rgb = surface_colors(str(config_value(app, "pattern", "solid")), kind, pts, nrm, src.bbox_min,
                                 src.bbox_max, list(config_value(app, "base_color", [0.8, 0.8, 0.8])),
                                 list(config_value(app, "accent_color", [0.2, 0.2, 0.2])), src.regions(pts), seed)
    kcurv = resolved_curvature(kcurv, area)
    kcurv = -np.sort(-kcurv, axis=1)

    f32 = np.float32
    arrays = {
        "surface_points": Array(pts.astype(f32), ("point", "xyz"), "m",
                                "surface samples = 3D Gaussian means (blue-noise, area-uniform)"),
        "surface_normals": Array(unit_vectors(nrm).astype(f32), ("point", "xyz"), "1", "outward unit normals"),
        "surface_curvature": Array(kcurv.astype(f32), ("point", "principal"), "1/m",
                                   "principal curvatures k1 >= k2 (convex positive)"),
        "surface_principal_dirs": Array(kdirs.astype(f32), ("point", "principal", "xyz"), "1",
                                        "unit tangent directions of k1 and k2"),
        "surface_area": Array(area.astype(f32), ("point",), "m^2", "surface area each sample represents"),
        "gaussian_scales": Array(gscales.astype(f32), ("point", "xyz"), "m",
                                 "per-Gaussian standard deviations along local x, y, z"),
        "gaussian_rotations": Array(grot.astype(f32), ("point", "quat"), "1",
                                    "unit quaternion w, x, y, z: local axes -> (t1, t2, normal)"),
        "gaussian_opacities": Array(opac.astype(f32), ("point",), "1", "opacity in (0, 1)"),
        "gaussian_colors": Array(rgb.astype(f32), ("point", "rgb"), "1", "linear RGB in [0, 1]"),
    }
    attrs = {
        "kind": kind,
        "bbox_min": [float(v) for v in src.bbox_min],
        "bbox_max": [float(v) for v in src.bbox_max],
        "surface_area_total": float(A),
        "enclosed_volume": float(src.enclosed_volume),
        "wall_thickness": float(t),
        "particle_spacing": float(s),
    }
    return arrays, attrs


OBJECT_OUTPUTS = ("surface_points", "surface_normals", "surface_area", "surface_curvature", "surface_principal_dirs",
                  "gaussian_scales", "gaussian_rotations", "gaussian_colors", "gaussian_opacities")


@artifact_step("object_model",
               reads=("object.name", "object.geometry", "object.appearance", "object.filled", "object.interior",
                      "sampling"),
               files=("object.geometry.path",),
               outputs=OBJECT_OUTPUTS)
def object_model_step(inputs, params):
    """The object model of one object: its surface 3D Gaussians (no inputs; a ply/mesh file is read from
    ``object.geometry.path``, whose content digest is in the key).  Its MPM particles are the physics stage's
    ``mpm_particles`` step."""
    obj = {key: params[f"object.{key}"] for key in ("name", "geometry", "appearance", "filled", "interior")}
    return build_object_model(obj, params["sampling"])
