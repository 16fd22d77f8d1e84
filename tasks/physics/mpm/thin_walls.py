"""Thin walls in the engine: a wall thinner than the grid spacing sampled in Gauss layers through its thickness
(:func:`gauss_layers`), its particles' rest normals (plane stress, ``membrane_normals``), its normal fibres joining
the layers (``membrane_fibres``), the layers' shared mid-surface stencil offsets and how far each layer's surface
reaches a collider; and the conversion of a membrane's normal row when its particle changes between an elastic
and a von Mises material.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, NamedTuple, Optional

import numpy as np

from .model import VON_MISES

if TYPE_CHECKING:
    from .solver import MPMSolver


def gauss_layers(layers: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """A thin wall's particle layers through its thickness t (``sampling.thin_wall_layers``): each layer's height
    above the mid-surface / t, in the order outer, inner[, middle], and its share of the wall's volume.  One layer
    on the mid-surface; two or three at the Gauss-Legendre points of [-t/2, t/2], +-1 / (2 sqrt 3) with 1/2 each, or
    +-sqrt(3/5) / 2 with 5/18 and 0 with 8/18: exact for a strain linear (two) or also quadratic (three) through
    the wall."""
    if layers == 1:
        return (0.0,), (1.0,)
    if layers == 2:
        h = 1.0 / (2.0 * math.sqrt(3.0))
        return (h, -h), (0.5, 0.5)
    if layers == 3:
        h = 0.5 * math.sqrt(0.6)
        return (h, -h, 0.0), (5.0 / 18.0, 5.0 / 18.0, 8.0 / 18.0)
    raise ValueError(f"a thin wall has 1, 2 or 3 Gauss layers, got {layers}")


def gauss_layer_face(layers: int) -> float:
    """A wall's outer Gauss layer's distance to its face / the distance between its outer and inner layers, (1/2 -
    h) / (2 h) for the heights +-h t of :func:`gauss_layers`: (sqrt 3 - 1) / 2 in two layers, (sqrt(5/3) - 1) / 2 in
    three (the closed forms, as the solver has always rounded them)."""
    if layers not in (2, 3):
        raise ValueError(f"a wall's face lies outside its outer Gauss layer in 2 or 3 layers, got {layers}")
    return (math.sqrt(3.0) - 1.0) / 2.0 if layers == 2 else (math.sqrt(5.0 / 3.0) - 1.0) / 2.0


def membrane_normals_checked(normals: Optional[np.ndarray], n: int) -> Optional[np.ndarray]:
    """The solver's ``membrane_normals`` as float32 (n, 3), or None; rows must be unit vectors (a membrane particle)
    or zero (a solid one).  A bad array is one ValueError line naming what is wrong."""
    if normals is None:
        return None
    a = np.asarray(normals, np.float32)
    if a.shape != (n, 3):
        raise ValueError(f"membrane_normals must have shape ({n}, 3), one row per particle; got {a.shape}")
    norm = np.linalg.norm(a, axis=1)
    bad = ~np.isfinite(norm) | ((norm > 0) & (np.abs(norm - 1.0) > 1e-3))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"membrane_normals: {int(bad.sum())} rows are neither unit vectors nor zero (row {i}: "
                         f"{a[i].tolist()}); give the rest unit normal of a thin wall's particle, 0 elsewhere")
    return np.ascontiguousarray(a)


class WallFibres(NamedTuple):
    """A thin wall's normal fibres as the solver holds them (:func:`membrane_fibres_checked`): per fibre its outer
    and inner Gauss layers' particles (``first``, ``second``, int32), their rest distance (``rest``, m, float32) and,
    in a wall of three Gauss layers, its middle layer's particle (``middle``, int32; None in two layers)."""
    first: np.ndarray
    second: np.ndarray
    rest: np.ndarray
    middle: Optional[np.ndarray]


def membrane_fibres_checked(fibres: Optional[np.ndarray], membrane_rows: np.ndarray, x: np.ndarray
                            ) -> Optional[WallFibres]:
    """The solver's ``membrane_fibres`` ((P, 2) or (P, 3) particle indices: outer, inner and, in three Gauss layers,
    middle) as :class:`WallFibres`, or None; every fibre joins membrane particles of one thin wall, no particle is
    in two fibres, and its ends are apart.  A bad array is one ValueError line naming what is wrong."""
    if fibres is None or len(fibres) == 0:
        return None
    a = np.asarray(fibres)
    n = len(membrane_rows)
    if a.ndim != 2 or a.shape[1] not in (2, 3) or not np.issubdtype(a.dtype, np.integer):
        raise ValueError("membrane_fibres must be integer particle indices of shape (P, 2) or (P, 3) (outer, inner, "
                         f"middle Gauss layer); got {a.dtype} {a.shape}")
    if a.min() < 0 or a.max() >= n:
        raise ValueError(f"membrane_fibres: indices must lie in [0, {n}); got {int(a.min())}..{int(a.max())}")
    if len(np.unique(a)) != a.size:
        raise ValueError("membrane_fibres: a particle is in two fibres (or twice in one); each wall particle lies on "
                         "one fibre, with its wall's other Gauss layers")
    if not membrane_rows[a].all():
        raise ValueError(f"membrane_fibres: {int((~membrane_rows[a]).any(axis=1).sum())} fibres join a particle "
                         "without a membrane normal; join only the Gauss layers of a thin wall (membrane_normals)")
    rest = np.linalg.norm(x[a[:, 0]].astype(np.float64) - x[a[:, 1]], axis=1)
    if not rest.min() > 0:
        raise ValueError(f"membrane_fibres: fibre {int(np.argmin(rest))}'s outer and inner particles lie at the "
                         "same position")
    return WallFibres(np.ascontiguousarray(a[:, 0], np.int32), np.ascontiguousarray(a[:, 1], np.int32),
                      rest.astype(np.float32), np.ascontiguousarray(a[:, 2], np.int32) if a.shape[1] == 3 else None)


def wall_offsets(x: np.ndarray, normals: np.ndarray, fibres: WallFibres) -> np.ndarray:
    """(particle,) float32 m: each thin wall's outer and inner Gauss layer's signed rest distance from its wall's
    mid-surface along its normal, (x - midpoint of its fibre's ends) . normal, 0 for every other particle (a middle
    layer lies on the mid-surface): :func:`tasks.physics.mpm.kernels.walls.particle_stencil` gives every layer of a wall
    the stencil of its mid-surface."""
    out = np.zeros(len(x), np.float64)
    mid = 0.5 * (x[fibres.first].astype(np.float64) + x[fibres.second])
    for idx in (fibres.first, fibres.second):
        out[idx] = np.einsum("pi,pi->p", x[idx] - mid, normals[idx])
    return out.astype(np.float32)


def contact_reach(volume: np.ndarray, fibres: Optional[WallFibres] = None) -> np.ndarray:
    """(particle,) float32 m: how far each particle's surface reaches a collider (surface contact,
    :func:`tasks.physics.mpm.kernels.contact.contact_velocity`): half its undeformed spacing, cbrt(V0) / 2; for the outer and
    inner Gauss layers of a wall thinner than the grid (``fibres`` as from :func:`membrane_fibres_checked`) its
    distance to its own face (:func:`~tasks.physics.mpm.thin_walls.gauss_layer_face` x their rest distance), for a
    middle layer half the wall's
    thickness.  With cbrt(V0) / 2 the ball's outer layer (V0 21 mm^3: 1.38 mm) touched a flat 0.74 mm outside the
    wall's face (0.63 mm), its inner layer never, and the ball between surface flats read 1.10-1.37x the FE at 1-6 mm
    on the default grid; at the face 1.09-1.21x."""
    reach = 0.5 * np.cbrt(np.asarray(volume, np.float64))
    if fibres is not None:
        face = gauss_layer_face(2 if fibres.middle is None else 3)
        reach[fibres.first] = face * fibres.rest
        reach[fibres.second] = face * fibres.rest
        if fibres.middle is not None:
            reach[fibres.middle] = (0.5 + face) * fibres.rest
    return reach.astype(np.float32)


def convert_membrane_normals(solver: MPMSolver, ids: np.ndarray) -> None:
    """A membrane particle's normal row is its rest normal N under an elastic model and its current normal n
    under von Mises (``membrane_normals``); one changing between the two gets the other, through its stored F:
    n = cof(F) N / |cof(F) N| (Nanson), N = F^T n / |F^T n|."""
    codes = np.array([m.code for m in solver.materials])
    was, now = codes[solver._mid_host] == VON_MISES, codes[ids] == VON_MISES
    rows = np.flatnonzero(solver._membrane_rows & (was != now))
    if not len(rows):
        return
    F = solver.F.numpy()[rows].astype(np.float64)
    normals = solver.normal.numpy()
    given = normals[rows].astype(np.float64)
    to_current = now[rows]
    c1, c2, c3 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
    cof = np.stack([np.cross(c2, c3), np.cross(c3, c1), np.cross(c1, c2)], axis=2)  # columns: det(F) F^-T
    moved = np.where(to_current[:, None], np.einsum("nij,nj->ni", cof, given),
                     np.einsum("nji,nj->ni", F, given))
    size = np.linalg.norm(moved, axis=1, keepdims=True)
    normals[rows] = np.where(size > 1e-6, moved / np.maximum(size, 1e-12), given).astype(np.float32)
    solver.normal.assign(normals)


def check_membranes(solver: MPMSolver, ids: np.ndarray) -> None:
    """Every particle of a ``membrane`` material needs a rest normal: its stable step is the plane-stress wave's,
    which a particle in 3D stress would exceed (ValueError naming the material)."""
    for i, m in enumerate(solver.materials):
        missing = int(np.count_nonzero((ids == i) & ~solver._membrane_rows)) if m.membrane else 0
        if missing:
            raise ValueError(f"material '{m.name}' is a membrane but {missing} of its particles have no rest "
                             "normal (membrane_normals): give one per particle, or membrane=False")
