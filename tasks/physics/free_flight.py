"""The released material's flight (paper sec. 3.2: released particles "subjected to viscosity, gravity, and other
grid forces"): which released particles fly free, their mean height per frame and their vertical acceleration,
to be plotted against the free-fall parabola and checked against g."""
from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree


def free_flying(positions: np.ndarray, released: np.ndarray, box_min: np.ndarray, box_max: np.ndarray,
                floor: float, margin: float, domain_min: np.ndarray | None = None,
                domain_max: np.ndarray | None = None, linked: bool = True,
                body_reach: float | None = None) -> np.ndarray:
    """Which released particles fly free in each frame.

    A particle flies free when it is released, lies outside the object's rest box grown by ``margin`` (m) on every
    side, and is more than ``margin`` above the table plane z = ``floor`` (m).  When the simulation domain's inner
    faces ``domain_min``/``domain_max`` (m) are given, support is also excluded: released material linked (any two
    particles within ``margin``) to something that holds it is not in free flight, i.e. every cluster of released
    particles with a member within ``margin`` of the table, of a domain wall or of a particle that is not released
    (the body).  This keeps a pool on the table, spray piled in a corner of the domain or sliding down a wall, and
    a stream still attached to the object out of the measure; a blob flying clear of all of them stays in.  With
    ``linked`` False only the particle's own distance counts: a particle of a continuous jet that is itself more
    than ``margin`` from the table, the walls and the body flies free although the jet's foot is on the table (the
    juice of the default scenes leaves the opening as one jet that reaches the table before it leaves the object's
    box: linked, none of it ever flies free).  ``body_reach`` (m, with ``linked`` False): a particle is held by the
    body when a body particle lies within that distance of it on every axis (Chebyshev distance) instead of within
    ``margin``: with quadratic B-splines two particles share grid nodes, so the grid couples them, when they are less
    than 3 dx apart on every axis (their stencils reach 1.5 dx each way), further than a 2 dx sphere reaches.

    Args:
        positions: (frame, particle, xyz) m.
        released: (particle,) bool, the released material.
        box_min, box_max: (3,) m, the object's rest bounding box.
        domain_min, domain_max: (3,) m, the inner faces of the domain walls (optional, see above).
    Returns:
        (frame, particle) bool.
    """
    x = np.asarray(positions, np.float64)
    rel = np.asarray(released, bool)
    lo, hi = np.asarray(box_min, np.float64) - margin, np.asarray(box_max, np.float64) + margin
    outside = np.any((x < lo) | (x > hi), axis=-1)
    free = outside & (x[..., 2] > floor + margin) & rel[None, :]
    if domain_min is None or domain_max is None or not rel.any():
        return free
    dlo, dhi = np.asarray(domain_min, np.float64) + margin, np.asarray(domain_max, np.float64) - margin
    for f in range(len(x)):
        if not free[f].any():
            continue
        idx = np.flatnonzero(rel if linked else free[f])  # not linked: only the candidates' own distances count
        xr = x[f, idx]
        held = (xr[:, 2] <= floor + margin) | np.any((xr <= dlo) | (xr >= dhi), axis=1)
        if (~rel).any():
            if linked or body_reach is None:
                held |= cKDTree(x[f, ~rel]).query(xr, distance_upper_bound=margin)[0] <= margin
            else:
                held |= cKDTree(x[f, ~rel]).query(xr, p=np.inf, distance_upper_bound=body_reach)[0] < body_reach
        if not linked:
            free[f, idx[held]] = False
            continue
        pairs = cKDTree(xr).query_pairs(margin, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(idx), len(idx)))
        _, cluster = connected_components(graph, directed=False)
        free[f, idx[np.isin(cluster, cluster[held])]] = False
    return free


def mean_free_height(z: np.ndarray, free: np.ndarray) -> np.ndarray:
    """(sample,) m: the mean height of the particles flying free at each sample (NaN when none); ``z`` (sample,
    particle) m, ``free`` (sample, particle) bool."""
    count = free.sum(axis=1)
    height = np.full(len(z), np.nan)
    height[count > 0] = (z * free).sum(axis=1)[count > 0] / count[count > 0]
    return height


def released_flight(positions: np.ndarray, free: np.ndarray, frame_dt: float) -> tuple[np.ndarray, float]:
    """Mean height of the free-flying particles per frame and their fitted vertical acceleration.

    Args:
        positions: (frame, particle, xyz) m.
        free: (frame, particle) bool from :func:`free_flying`.
        frame_dt: s between frames.
    Returns:
        height: (frame,) m, mean z of the particles flying free in that frame (NaN when none);
        acceleration: m/s^2, the median over particles of each particle's median second difference
        (z[f+1] - 2 z[f] + z[f-1]) / frame_dt^2 over the frames f with f-1, f, f+1 all in free flight (NaN when
        no particle flies free for three consecutive frames); g = -9.81 for material in free fall.
    """
    z = np.asarray(positions, np.float64)[..., 2]
    height = mean_free_height(z, free)
    if len(z) < 3:
        return height, float("nan")
    accel = (z[2:] - 2.0 * z[1:-1] + z[:-2]) / frame_dt ** 2  # (frame - 2, particle)
    flying = free[2:] & free[1:-1] & free[:-2]
    per_particle = [np.median(accel[flying[:, p], p]) for p in np.flatnonzero(flying.any(axis=0))]
    return height, float(np.median(per_particle)) if per_particle else float("nan")


def free_runs(free: np.ndarray) -> list[tuple[int, int]]:
    """The runs of consecutive True samples of ``free`` (sample,) bool as [start, stop) index pairs."""
    edges = np.diff(np.concatenate([[0], np.asarray(free, np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def flight_acceleration(times: np.ndarray, z: np.ndarray, free: np.ndarray,
                        min_samples: int = 3) -> tuple[float, np.ndarray]:
    """Vertical acceleration of the free-flying particles from densely sampled heights (the rollout's sub-frame
    flight recorder): every run of at least ``min_samples`` consecutive samples in which a particle flies free is
    fitted by least squares with the parabola z = z0 + v0 t + a t^2 / 2; a particle's acceleration is the median
    of its runs' a, the result the median over particles.

    Args:
        times: (sample,) s, increasing (any spacing).
        z: (sample, particle) m.
        free: (sample, particle) bool, e.g. from :func:`free_flying`.
        min_samples: fewest samples of a run that is fitted (>= 3: a parabola has three parameters).
    Returns:
        (acceleration m/s^2, NaN when no run is long enough; the per-particle accelerations it is the median of,
        m/s^2).
    """
    t = np.asarray(times, np.float64)
    z = np.asarray(z, np.float64)
    per_particle = []
    for p in np.flatnonzero(np.asarray(free).any(axis=0)):
        runs = [(a, b) for a, b in free_runs(free[:, p]) if b - a >= min_samples]
        if runs:
            per_particle.append(np.median([2.0 * np.polyfit(t[a:b] - t[a], z[a:b, p], 2)[0] for a, b in runs]))
    return (float(np.median(per_particle)) if per_particle else float("nan")), np.array(per_particle)
