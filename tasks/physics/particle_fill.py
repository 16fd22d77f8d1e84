"""The MPM volume particles of one object (paper sec. "Physics Simulation"; MLS-MPM, Hu et al. 2018; PhysGaussian,
Xie et al. 2024 fills the volume in the same way): the object's own material, plus, for filled containers, the
interior's.  Pure functions (numpy/scipy); the cached step is :mod:`tasks.physics.mpm_particles`.

They are the physics stage's, not the object model's (:mod:`tasks.control.object_model`, the surface Gaussians):
which particles a wall gets depends on the MPM grid spacing dx (:func:`tasks.physics.wall_resolution.grid_spacing`),
and the control chain's keys must not.  The geometry is the object model's (the same source,
:mod:`tasks.control.sources`), sampled from the same seed's streams, so the particles are those of one builder that
made both.  All lengths are metres, volumes m^3; positions are float32.

Volume particles on a cell-centred grid of spacing ``s = sampling.particle_spacing`` jittered by +-0.2 s
(deterministic from ``sampling.seed`` and the object's geometry, not its name: :func:`~tasks.control.object_config.sampling_seed`):
- ``filled: true``: every grid point inside the body; volumes = ``s^3`` rescaled to the enclosed volume;
- hollow with ``wall_thickness t`` at least the grid spacing dx (``mpm.dx``, or ``s x cbrt(mpm.particles_per_cell)``
  as the rollout chooses it): grid points with ``-t < sdf < 0`` (the wall), volumes rescaled to the wall volume
  ``V(sdf < 0) - V(sdf < -t)``;
- hollow with ``t < dx`` (``thin_wall``: the solver holds such a wall in plane stress, ``mpm.thin_walls``, and the
  grid cannot resolve its thickness; before 2026-12-03 only ``t < s``, which left the orange's 4 mm peel on the
  default 8 mm grid a one-layer membrane with no bending): one layer of Poisson-disk particles (spacing ~ s) on the wall's
  mid-surface (``t/2`` inside the outer surface; on the sheet itself for the open cup), each with volume =
  its Voronoi area share x the depth volume of Steiner's formula, ``t - (k1 + k2) t^2 / 2 + k1 k2 t^3 / 3`` at its
  principal curvatures (:func:`shell_depth_volume`), so the total is the exact shell's and the wall mass is
  physical (before 2026-12-04 area x t, 11 % heavy on the orange's peel, 9 % on the ball's wall); on the open cup's
  sheet, its own mid-surface, area x t; with
  ``sampling.thin_wall_layers: 2`` (the default) that layer is split into two at the thickness's Gauss points,
  ``+-t / (2 sqrt 3)`` along the normal, each particle with half the volume: the two-point rule integrates a
  strain linear through the thickness exactly, so a plane-stress wall (``mpm.thin_walls: membrane``) carries the
  bending energy ``E t^3 / (12 (1 - nu^2)) kappa^2 / 2`` per area of a curvature kappa of the grid's field (two
  layers at +-t/2 would carry 3x); with ``3`` into three, at ``0`` and ``+-sqrt(3/5) t / 2`` with 8/18 and 5/18
  of the volume (:func:`~tasks.physics.mpm.thin_walls.gauss_layers`), which also integrate the strain's quadratic
  part: a wall near a cell's
  thickness, whose grid field has one, bends too easily in two (a clamped strip 0.86 of a cell thick sags 1.23x
  Euler-Bernoulli in two layers, 1.03x in three, where the grid's clamp makes 1.04x; docs/limits/thin-walls.md);
  ``wall_fibres`` (fibre, layer) joins each outer particle to its inner twin (and the middle one), the wall's normal
  fibre, whose ends the solver keeps at their rest distance (``mpm.wall_fibres``); empty otherwise;
- ``interior`` set: grid points with ``sdf < -max(t, s/2)`` (half a spacing clear of the wall layer), volumes
  rescaled to the cavity volume ``V(sdf < 0) - wall volume``.  These cavity particles are the object's geometry
  only: the rollout fills them with the oracle's ``core`` (fruit flesh, stuffing: part of the body) or, without
  a core, with the interior material itself, and only when it can be released.
``particle_normals`` is the outward normal of the object's outer surface nearest to each particle
(``grad sdf``), also for particles inside a thick wall.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from tasks.control.curvature import shell_depth_volume, unit_vectors
from tasks.control.object_config import ObjectModelError, config_value, sampling_seed, validate_object
from tasks.control.sources.by_kind import open_source
from tasks.control.sources.ply import PlySource
from tasks.control.surface_sampling import poisson_disk, voronoi_area
from tasks.core.artifacts import Array
from tasks.physics.mpm.thin_walls import gauss_layers

__all__ = ["build_mpm_particles", "PARTICLE_OUTPUTS", "jittered_grid"]

_JITTER = 0.2  # fraction of the spacing
PARTICLE_OUTPUTS = ("particle_positions", "particle_volumes", "particle_normals", "wall_fibres", "interior_positions",
                    "interior_volumes")


def jittered_grid(lo: np.ndarray, hi: np.ndarray, s: float, rng: np.random.Generator) -> np.ndarray:
    """Cell-centred grid of spacing ``s`` (m) tiling the box [lo, hi] (centred on it), jittered by +-0.2 s."""
    size = hi - lo
    n = np.maximum(np.ceil(size / s - 1e-9).astype(int), 1) + 2  # one spare cell each side
    start = 0.5 * (lo + hi) - 0.5 * n * s + 0.5 * s
    if np.prod(n) > 30_000_000:
        raise ObjectModelError(f"sampling.particle_spacing {s} m gives {int(np.prod(n))} grid points for a "
                               f"{size.round(4).tolist()} m object: use a coarser spacing")
    axes = [start[i] + s * np.arange(n[i]) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    return pts + rng.uniform(-_JITTER, _JITTER, size=pts.shape) * s


def build_mpm_particles(obj: Any, sampling: Any, grid_spacing: float | None = None) -> tuple[dict[str, Array],
                                                                                          dict[str, Any]]:
    """MPM particles of one object (see the module doc for every choice).

    Args:
        obj: an ``ObjectConfig`` (dataclass or OmegaConf node; read by attribute).
        sampling: a ``SamplingConfig`` (``surface_points``, ``particle_spacing`` m, ``seed``, ``thin_wall_layers``).
        grid_spacing: the MPM grid's dx (m) the wall is judged against (thin below it); None: the particle spacing.
    Returns:
        ``(arrays, attrs)``: the arrays of :data:`PARTICLE_OUTPUTS` as :class:`tasks.core.artifacts.Array`, and JSON
        attrs ``wall_thickness``/``particle_spacing``/``grid_spacing`` (m), ``thin_wall``, ``thin_wall_layers``,
        ``n_particles``, ``n_interior``, and ``wall_volume``/``interior_volume`` (m^3, sums of the particle volumes).
    Raises:
        ObjectModelError: one line naming the input and the fix.
    """
    kind, size, t, s, n_surf, seed, layers = validate_object(obj, sampling)  # layers: of a thin wall
    name = str(config_value(obj, "name", "object"))
    filled = bool(config_value(obj, "filled", False))
    interior = config_value(obj, "interior")
    _, rng_area, rng_part, rng_grid, rng_misc = (np.random.default_rng(c) for c in sampling_seed(obj, seed).spawn(5))
    src = open_source(kind, config_value(obj, "geometry"), size, s, n_surf, t, rng_misc)
    A = src.area_total
    V_body = float(src.enclosed_volume)
    thin = (not filled) and t < max(s, grid_spacing or s)
    grid = None
    fibres = np.zeros((0, 2), np.int64)  # a thin wall's normal fibres (pairs of its two Gauss layers' particles)
    if thin:
        if isinstance(src, PlySource):
            cand_p = src.means
        else:
            cand_p = src.candidates(max(5 * int(A / s ** 2), 200), rng_part)
            src.area_measure(rng_area)  # the stream's first draw is the surface samples' (object model): skipped
        idx = poisson_disk(cand_p, 0.7 * s, rng_part)  # ~A / s^2 particles from 5 A / s^2 candidates
        ppos, pnrm = src.finalize(cand_p[idx]) if not isinstance(src, PlySource) else (cand_p[idx], src.mean_normals[idx])
        mpts, mw = src.area_measure(rng_area)
        parea = voronoi_area(ppos, mpts, mw)
        pvol = parea * t  # the open sheet: its own area is the mid-surface's
        if not src.open_top:
            pvol = parea * shell_depth_volume(src.curvature(ppos, pnrm)[0], t, parea)
            ppos = ppos - 0.5 * t * pnrm
        V_wall = float(pvol.sum())
        if layers > 1:  # the thickness's Gauss points; fibre k: particle k (outer), its inner [and middle] twin
            heights, shares = gauss_layers(layers)
            n = len(ppos)
            fibres = np.arange(layers * n).reshape(layers, n).T
            ppos = np.concatenate([ppos + h * t * pnrm for h in heights])
            pnrm = np.concatenate([pnrm] * layers)
            pvol = np.concatenate([w * pvol for w in shares])
    else:
        grid = jittered_grid(src.bbox_min, src.bbox_max, s, rng_grid)
        d = src.sdf(grid)
        if filled:
            mask = d < 0
            V_wall = V_body
        elif src.open_top:
            mask = src.open_distance(grid) < 0.5 * t
            V_wall = A * t
        else:
            mask = (d < 0) & (d > -t)
            # same discretisation for both levels so that their errors cancel
            V_wall = max(src.volume_below(0.0) - src.volume_below(-t), 0.0)
        ppos = grid[mask]
        if len(ppos) == 0:
            raise ObjectModelError(f"object {name}: no particle of the spacing {s} m falls inside the "
                                   f"{'body' if filled else 'wall'}: use a finer sampling.particle_spacing")
        pnrm = src.normals(ppos)
        pvol = np.full(len(ppos), V_wall / len(ppos))

    # interior (cavity) particles
    if interior and not filled:
        if grid is None:
            grid = jittered_grid(src.bbox_min, src.bbox_max, s, rng_grid)
            d = src.sdf(grid)
        clear = max(0.5 * t if src.open_top else t, 0.5 * s)
        ipos = grid[d < -clear]
        V_cav = max(V_body - (0.5 * V_wall if src.open_top else V_wall), 0.0)
        ivol = np.full(len(ipos), V_cav / max(len(ipos), 1))
    else:
        ipos = np.zeros((0, 3))
        ivol = np.zeros(0)

    f32 = np.float32
    arrays = {
        "particle_positions": Array(ppos.astype(f32), ("particle", "xyz"), "m",
                                    "MPM particles of the object's own (shell/body) material"),
        "particle_volumes": Array(pvol.astype(f32), ("particle",), "m^3", "real material volume per particle"),
        "particle_normals": Array(unit_vectors(pnrm).astype(f32), ("particle", "xyz"), "1",
                                  "outward normal of the nearest outer surface"),
        "wall_fibres": Array(fibres.astype(np.int32), ("fibre", "layer"), "1",
                             "particle indices of each normal fibre of a wall in two or three Gauss layers: outer, "
                             "inner[, middle] (the solver keeps outer and inner at their rest distance, "
                             "mpm.wall_fibres); none otherwise"),
        "interior_positions": Array(ipos.astype(f32), ("interior_particle", "xyz"), "m",
                                    "MPM particles of the interior material (cavity)"),
        "interior_volumes": Array(ivol.astype(f32), ("interior_particle",), "m^3", "volume per interior particle"),
    }
    attrs = {
        "wall_thickness": float(t),
        "particle_spacing": float(s),
        "grid_spacing": float(grid_spacing or s),
        "thin_wall": bool(thin),
        "thin_wall_layers": int(layers) if thin else 0,
        "n_particles": int(len(ppos)),
        "n_interior": int(len(ipos)),
        "wall_volume": float(pvol.sum()),
        "interior_volume": float(ivol.sum()),
    }
    return arrays, attrs
