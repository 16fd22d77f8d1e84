"""The released material's free flight (paper sec. 3.2: released particles "subjected to viscosity, gravity, and
other grid forces"), measured so that its answer is known: g.

Free flight means no force but gravity.  In MLS-MPM a particle only exchanges momentum with the grid nodes of its
quadratic B-spline stencil (the 3 x 3 x 3 nodes from ``floor((x - origin) / dx - 0.5)``), so two particles are
coupled exactly when their stencils share a node (stencil bases at most 2 apart on every axis); the domain walls
and the fingers act on nodes too, and so does the table on the body's velocity field, while on the released field
(and under surface contact) it is a plane acting on the particles whose surface touches it.  A *free blob* is a
connected set of released particles (linked by shared nodes) none of which shares a node with the body, a boundary
point, a wall or floor node, or touches the table plane (:func:`touches_table`).  Its internal
forces (pressure, viscosity, elasticity) cancel: P2G, grid update and G2P conserve its linear momentum (the APIC
transfer is exact for it), and the only external force is its weight, so its centre of mass accelerates at
exactly ``g sum m_phys / sum m`` (= g: released material keeps its physical mass under selective mass scaling).
A particle of a jet whose front hits the table feels that impact through its neighbours' pressure although it is
itself far from the table: its blob is not free.  Each set of particles that stays one free blob (or splits into
free pieces that touch nothing else) for consecutive samples is one flight, fitted by a parabola.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
from scipy.ndimage import maximum_filter1d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

STENCIL_REACH = 2  # two quadratic B-spline stencils (3 nodes per axis) share a node when their bases differ by <= 2


def stencil_bases(x: np.ndarray, origin: np.ndarray, dx: float) -> np.ndarray:
    """(n, 3) int: the lowest node of each particle's quadratic B-spline stencil, ``floor((x - origin)/dx - 0.5)``
    (the solver's :func:`tasks.physics.mpm.boundary.bspline_stencil`); ``x`` (n, 3) m, ``origin`` (3,) m the grid's
    node 0, ``dx`` m."""
    return np.floor((np.asarray(x, np.float64) - np.asarray(origin, np.float64)) / dx - 0.5).astype(np.int64)


def shares_node(bases: np.ndarray, holder_bases: np.ndarray) -> np.ndarray:
    """(n,) bool: whether each stencil of ``bases`` (n, 3) shares a grid node with any stencil of ``holder_bases``
    (m, 3) (Chebyshev distance of the bases <= 2): the holders' bases marked on a box of cells, dilated by 2 cells
    along each axis, looked up."""
    b, h = np.asarray(bases, np.int64).reshape(-1, 3), np.asarray(holder_bases, np.int64).reshape(-1, 3)
    if not len(b) or not len(h):
        return np.zeros(len(b), bool)
    lo = np.minimum(b.min(axis=0), h.min(axis=0)) - STENCIL_REACH
    hi = np.maximum(b.max(axis=0), h.max(axis=0)) + STENCIL_REACH
    reach = np.zeros(hi - lo + 1, bool)
    reach[tuple((h - lo).T)] = True
    for axis in range(3):
        reach = maximum_filter1d(reach, 2 * STENCIL_REACH + 1, axis=axis, mode="constant")
    return reach[tuple((b - lo).T)]


def held_by_boundary(bases: np.ndarray, dims: np.ndarray, padding: int,
                     floor_node: float | np.ndarray) -> np.ndarray:
    """(n,) bool: stencils reaching a node the grid update constrains (:func:`tasks.physics.mpm.kernels.grid.
    fixed_boundaries`): a wall node (within ``padding`` nodes of a face of the ``dims`` grid) or a floor node
    (z index <= ``floor_node``, the table's height in grid units, a scalar or one per stencil; -inf: no table or,
    for that particle, none on the grid)."""
    b = np.asarray(bases)
    return (np.any(b < padding, axis=1) | np.any(b + 2 >= np.asarray(dims) - padding, axis=1)
            | (b[:, 2] <= floor_node + 1e-4))


TABLE_GAP = 0.25  # a particle touches the table plane when its surface is within this fraction of its radius


def touches_table(z: np.ndarray, radius: np.ndarray, height: float) -> np.ndarray:
    """(n,) bool: particles (centre heights ``z`` (n,) m, ``radius`` (n,) m: half their undeformed spacing) whose
    surface z - radius is within ``TABLE_GAP`` radius of the table plane at ``height`` m, or below it: the ones the
    plane collider is acting on (:func:`tasks.physics.mpm.kernels.contact.contact_velocity` pushes a particle whose gap would
    close within the substep; a resting one keeps a gap of ~0)."""
    return np.asarray(z) - np.asarray(radius) - height <= TABLE_GAP * np.asarray(radius)


def coupled_components(bases: np.ndarray) -> np.ndarray:
    """(n,) int: the connected components of particles linked by a shared grid node (``bases`` (n, 3)), found on
    the distinct stencil bases (particles with the same base share all their nodes)."""
    if not len(bases):
        return np.zeros(0, np.int64)
    cells, inverse = np.unique(np.asarray(bases), axis=0, return_inverse=True)
    pairs = cKDTree(cells).query_pairs(STENCIL_REACH, p=np.inf, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(cells), len(cells)))
    return connected_components(graph, directed=False)[1][np.ravel(inverse)]


def blob_held(bases: np.ndarray, held: np.ndarray) -> np.ndarray:
    """(n,) bool: the particles (stencil ``bases`` (n, 3)) whose blob, the component linked by shared grid nodes
    (:func:`coupled_components`), holds a particle that is ``held`` (n,) bool itself.  A particle whose own stencil
    touches nothing but released material is still pushed by that material's pressure, viscosity and elasticity,
    which carry the body's push or the table's stop along a jet: only a blob none of whose particles is held falls
    free.  (Per particle, the orange's squirted juice had 275 'free' samples at a median -12.3 m/s^2 and a mass
    mean -13.4, +25-37 % over g, every one of them in a jet still linked to the crushed fruit; issue 50.)"""
    held = np.asarray(held, bool)
    if not held.any() or held.all():
        return held.copy()
    comp = coupled_components(bases)
    touched = np.zeros(comp.max() + 1, bool)
    touched[comp[held]] = True
    return touched[comp]


def prune_held(positions: np.ndarray, held: np.ndarray, origin: np.ndarray, dx: float,
               attached: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A smaller record with the same flights (:func:`blob_flights`): the particles ``attached`` (default ``held``)
    at every sample are dropped, and a kept particle counts as held where it shares a grid node with a held particle
    (a dropped one was held there, so whatever it linked is held).  ``positions`` (sample, particle, xyz) m, ``held``
    and ``attached`` (sample, particle) bool.  Returns (kept (particle,) bool, held (sample, kept particle) bool)."""
    held = np.asarray(held, bool)
    kept = ~np.asarray(held if attached is None else attached, bool).all(axis=0)
    near = np.zeros((len(held), int(kept.sum())), bool)
    for s in range(len(held)):
        b = stencil_bases(positions[s], origin, dx)
        near[s] = (held[s] | shares_node(b, b[held[s]]))[kept]
    return kept, near


@dataclass
class BlobFlight:
    """One free flight: the released particles ``members`` (indices into the recorded particles), free from sample
    ``start`` to ``stop`` (exclusive); ``times`` (s) and the centre of mass ``height`` (m) there, the fitted
    acceleration ``acceleration`` and the one its momentum balance predicts, ``expected`` (m/s^2, z up)."""

    members: np.ndarray
    start: int
    stop: int
    times: np.ndarray
    height: np.ndarray
    acceleration: float
    expected: float

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])


def blob_flights(times: np.ndarray, positions: np.ndarray, held: np.ndarray, origin: np.ndarray, dx: float,
                 mass: np.ndarray, physical_mass: np.ndarray, gravity: float = -9.81,
                 min_samples: int = 4) -> list[BlobFlight]:
    """The free flights of released material (module doc) from a sub-frame record.

    At every sample the recorded particles are grouped into components linked by shared grid nodes; a component is
    free when none of its particles is ``held`` (shares a node with the body, a boundary point, a wall or the
    table).  A flight is a set of particles that is a free component at its first sample and stays closed and free
    (the components its particles belong to hold no other particle and are all free; a free blob may split) until
    the sample before it is not; a free component not inside a running flight starts a new one.  Each flight of at
    least ``min_samples`` samples is fitted by least squares with z = z0 + v0 t + a t^2 / 2, z its centre of mass
    (weighted by the inertial ``mass``: the momentum the grid conserves).

    Args:
        times: (sample,) s, increasing.
        positions: (sample, particle, xyz) m, the recorded (released) particles.
        held: (sample, particle) bool.
        origin, dx: the grid's node 0 (3,) m and spacing m.
        mass, physical_mass: (particle,) kg, inertial (mass-scaled) and physical; a free blob's centre of mass
            accelerates at ``gravity`` sum physical_mass / sum mass (m/s^2, z up).
        min_samples: fewest samples of a fitted flight (>= 3: a parabola has three parameters).
    Returns:
        the flights, longest first.
    """
    t = np.asarray(times, np.float64)
    x = np.asarray(positions, np.float64)
    held = np.asarray(held, bool)
    m = np.asarray(mass, np.float64)
    running: dict[frozenset, int] = {}
    spans: list[tuple[np.ndarray, int, int]] = []
    for s in range(len(t)):
        comp = coupled_components(stencil_bases(x[s], origin, dx))
        free_comp = np.ones(comp.max(initial=-1) + 1, bool)
        free_comp[comp[held[s]]] = False
        size = np.bincount(comp, minlength=len(free_comp))
        kept: dict[frozenset, int] = {}
        covered = np.zeros(len(free_comp), bool)
        for members, start in running.items():
            ids = np.fromiter(members, np.int64)
            comps = np.unique(comp[ids])
            if free_comp[comps].all() and size[comps].sum() == len(ids):
                kept[members] = start
                covered[comps] = True
            else:
                spans.append((np.sort(ids), start, s))
        order = np.argsort(comp, kind="stable")
        groups = np.split(order, np.cumsum(size)[:-1])
        for c in np.flatnonzero(free_comp & ~covered & (size > 0)):
            kept[frozenset(groups[c].tolist())] = s
        running = kept
    spans += [(np.sort(np.fromiter(ids, np.int64)), start, len(t)) for ids, start in running.items()]
    flights = []
    for ids, a, b in spans:
        if b - a < max(min_samples, 3):
            continue
        w = m[ids]
        z = x[a:b, ids, 2] @ w / w.sum()
        accel = 2.0 * np.polyfit(t[a:b] - t[a], z, 2)[0]
        expected = gravity * float(np.asarray(physical_mass, np.float64)[ids].sum() / w.sum())
        flights.append(BlobFlight(ids, a, b, t[a:b], z, float(accel), expected))
    return sorted(flights, key=lambda fl: (-(fl.stop - fl.start), -len(fl.members)))


def flight_summary(flights: list[BlobFlight]) -> dict:
    """The measured free fall over ``flights`` (:func:`blob_flights`): ``acceleration`` m/s^2 the median of the
    flights' fitted accelerations (None: no flight), its ``error`` relative to the median ``expected`` one, the
    10th/90th percentiles, the number of flights, of distinct particles in them, and the longest flight (s)."""
    if not flights:
        return {"acceleration": None, "expected": None, "error": None, "p10_p90": None, "flights": 0,
                "particles": 0, "longest_flight": 0.0}
    a = np.array([fl.acceleration for fl in flights])
    expected = float(np.median([fl.expected for fl in flights]))
    return {"acceleration": float(np.median(a)), "expected": expected,
            "error": float(np.median(a) / expected - 1.0), "p10_p90": np.percentile(a, [10, 90]).tolist(),
            "flights": len(flights), "particles": int(len(np.unique(np.concatenate([fl.members for fl in flights])))),
            "longest_flight": max(fl.duration for fl in flights)}


def rollout_flights(arrays: Mapping[str, np.ndarray], fall: Mapping[str, Any], min_samples: int = 4
                    ) -> list[BlobFlight]:
    """The flights (:func:`blob_flights`) recomputed from a stored rollout: its ``released_flight_*`` arrays (the
    flight recorder's samples) and its ``released_free_fall`` attrs ``fall`` (the grid: ``grid_origin``, ``dx``,
    ``gravity``)."""
    return blob_flights(arrays["released_flight_time"], arrays["released_flight_positions"],
                        arrays["released_flight_held"], np.asarray(fall["grid_origin"]), float(fall["dx"]),
                        arrays["released_flight_mass"], arrays["released_flight_physical_mass"],
                        float(fall["gravity"]), min_samples)
