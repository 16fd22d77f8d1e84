"""SC-CAE: squeezing-conditioned contact area estimation (paper sec. 3.1, eq. 2).

For every frame t and finger k the contact patch is the minimiser of the composite objective of eq. 2 over
the patch centre x (on the object surface S), its normal n and its anisotropic scale sigma = (sigma1, sigma2)
along the principal curvature directions::

    E_k,t(x, sigma) =   lambda_area      * (d(x, ray(P_k,t, a_k,t)) / L)^2                      (geometric fit)
                      + lambda_align     * |1 - a_k,t^T n_in(x)|                              (normal alignment)
                      + lambda_curvature * log(1 + L^2 (k1(x)^2 + k2(x)^2))                   (curvature)
                      + lambda_scale     * ||sigma - sigma0(c_k,t, k1, k2)||^2 / L^2          (force prior)
                      + lambda_overlap   * sum_j w_kj max(0, rho_k + rho_j - |x - x_j|)^2 / eps^2  (overlap)

Definitions and conventions (all lengths in metres; every term of E is dimensionless):

* ``L = cfg.sigma_max`` (m) is the length scale that makes the area and scale terms dimensionless, so the
  lambdas of ContactConfig are directly comparable (an offset of one maximum patch radius from the ray costs
  ``lambda_area``).
* ``d(x, ray)`` is the point-to-RAY distance: with ``s = (x - P)^T a``, ``d = |x - P - max(s, 0) a|``, so a
  point behind the fingertip (a fingertip that already penetrates the surface) is measured to ``P`` itself.
* ``n`` is not a free variable: it is the surface normal at ``x``.  The surface normals given to this module
  point OUTWARD, the squeeze direction ``a`` points from the fingertip INTO the object, so the alignment term
  uses the INWARD normal ``n_in = -n_out``: ``|1 - a^T n_in| = |1 + a^T n_out|`` is 0 for a ray that hits the
  surface head-on and 2 on the far side of the object (where the ray exits).  The paper writes
  ``|1 - a^T n|`` with ``n`` the patch normal in the squeezing sense; this is the same quantity.
* Curvature regularisation ``phi(k1, k2) = log(1 + L^2 (k1^2 + k2^2))``: equal to ``L^2 (k1^2 + k2^2)`` for
  gentle curvature (the paper's "avoid sharp high-curvature areas") but growing only logarithmically at
  sampled sharp edges (curvature ~ 1/sample spacing), so a noisy edge can nudge a patch aside but cannot drag
  it far from the finger.
* Force prior ``sigma0``: the equivalent radius ``r0(c) = sigma_min + (sigma_max - sigma_min) clip(c, 0, 1)``
  (m) fixes the patch AREA ``pi r0^2``; the aspect comes from Hertz-like contact of the object with a finger
  pad of radius ``pad_radius``: at indentation delta the contact ellipse has semi-axes
  ``a_i ~ sqrt(2 delta / kappa_i)`` with the relative curvature ``kappa_i = k_i + 1/pad_radius`` (floored at
  ``0.1/pad_radius`` for strongly concave directions), so ``sigma02 / sigma01 = sqrt(kappa_1 / kappa_2)``
  (clipped to ``MAX_ASPECT``) and ``sigma01 sigma02 = r0^2``.  The flatter principal direction (k2) gets the
  larger radius: on a cylinder the patch is longer along the axis.
* Overlap: ``rho_k`` is the radius of patch k's 1-sigma ellipse in the direction of patch j (direction
  projected into patch k's tangent plane), ``rho_j`` likewise; ``w_kj = max(0, n_k^T n_j)`` so patches on
  opposite faces (a pinch of a thin wall) never conflict.  The overlap is measured in units of
  ``eps = cfg.sigma_min`` (m), not ``L``: this makes the term a stiff (near-barrier) penalty relative to the
  area and scale terms (``(sigma_max/sigma_min)^2 ~ 14x`` at the defaults), as the paper says it "prevents
  overlap".  Only fingers that are active (below) enter other fingers' overlap terms.

* Reachability barrier (not in the paper; a hard constraint made soft): a sample the finger cannot touch gets
  ``+UNREACHABLE_PENALTY`` (10, far above any other term): samples facing away from the finger
  (``a^T n_in <= 0``) and samples OCCLUDED along the ray, i.e. lying more than ``sigma_max`` beyond the first
  surface crossing ahead of the fingertip (the nearest sample within one sample spacing of the ray).  Without
  it a ray that slips past the near surface of a concave object (or starts inside it) snaps to a facing
  surface far behind (e.g. a plush toy's leg 10 cm away): the alignment term costs at most
  ``2 lambda_align = 0.4``.  A patch on an unreachable sample is never active.

Solver (per frame):

1. Candidates (vectorised over all frames and fingers with matrix products, chunked): the ``cfg.candidates``
   samples of lowest separable cost (area + align + curvature + barrier), i.e. the reachable samples nearest
   the squeeze ray, plus a CONTINUOUS refinement of the best one: it is moved (at most one sample spacing)
   along its osculating quadric ``x0 + w - 0.5 (k1 w1^2 + k2 w2^2) n0`` (normal ``n0 + k1 w1 u1 + k2 w2 u2``)
   to where the ray crosses its tangent plane, so an unobstructed finger's patch lies on the ray, not on the
   nearest sample.
2. Fingers are solved in order of decreasing force coefficient by Gauss-Seidel coordinate-descent sweeps (up
   to ``sweeps``; stopped as soon as a sweep moves no patch by more than a quarter sample spacing or 1 % of
   its radii, or no two patches can interact).  Temporal warm start: in the first sweep the fingers not yet
   re-solved enter the overlap term with their previous-frame patches, and the candidate nearest a finger's
   previous centre gets a head start of ``hysteresis`` (0.02, objective units) so that two near-equal minima
   do not make the patch flicker between frames (the reported ``patch_cost`` is the true objective).
3. A finger with no neighbour patch in overlap range takes sigma = sigma0 and the candidate of lowest
   separable cost (exact).  Otherwise sigma is searched as per-axis shrink factors of sigma0 in
   [``SHRINK_MIN``, 1] (the scale prior is minimised at 1; only the overlap term shrinks a patch): all
   candidates on a 3x3 grid, the best 8 on a 7x7 grid, then two local 9x9 grids on the winner (resolution
   0.8 % of sigma0).

A patch is ACTIVE when ``c > cfg.activation`` AND the finger can reach it: the sample is reachable (above)
and ``d(x, ray) <= reach`` with ``reach = 2 sigma_max + standoff`` (``standoff = 5 mm`` default: finger pad
half-thickness / tracking error).  Inactive patches keep their centre, normal and axes (for plots) but have
zero radii and area and do not enter other fingers' overlap terms.

Limitations: how far the fingertip is from the surface ALONG the ray is not checked (the paper projects the
signals onto the surface), so a finger pointing at the object from afar is active; the search is a heuristic
(coordinate descent over a discrete candidate set), not a certified global optimum of eq. 2.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from conf.hand import FINGERTIP_PAD_RADIUS
from tasks.core.artifacts import Array, as_numpy, config_value
from tasks.core.step import artifact_step, report_progress

DEFAULT_PAD_RADIUS = FINGERTIP_PAD_RADIUS  # m, fingertip pad radius of curvature (Hertz aspect of the force prior)
DEFAULT_STANDOFF = 0.005  # m, reach = 2 sigma_max + standoff
MAX_ASPECT = 4.0  # 1, largest sigma2/sigma1 of the force prior
SHRINK_MIN = 0.25  # 1, smallest per-axis fraction of sigma0 the overlap term may shrink a patch to
_GRID = np.linspace(SHRINK_MIN, 1.0, 7)  # shrink factors searched per axis (step 0.125)
_FINE = np.arange(-4.0, 5.0)  # offsets of the local 9x9 refinement grids (in units of their step)
_KEEP = 8  # candidates kept from the coarse 3x3 stage for the full 7x7 grid
_FINE_ROUNDS = 2  # local grids at step 0.125/4 and 0.125/16 -> resolution 0.0078 of sigma0
DEFAULT_HYSTERESIS = 0.02  # 1, temporal head start of the previous frame's patch (see module doc)
UNREACHABLE_PENALTY = 10.0  # 1, barrier on samples the finger cannot touch (facing away or occluded)
_TINY = 1e-12


# ----------------------------------------------------------------------------------------------- helpers


def _normalise(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    norm = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(norm, _TINY), norm[..., 0]


def _tangent_frames(normals: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal (u1, u2) tangent to ``normals``, as close as possible to the given principal directions."""
    d1 = dirs[:, 0] - np.sum(dirs[:, 0] * normals, axis=-1, keepdims=True) * normals
    u1, n1 = _normalise(d1)
    bad = n1 < 1e-6
    if np.any(bad):  # principal direction missing or parallel to the normal: any tangent will do
        helper = np.where(np.abs(normals[bad, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        u1[bad] = _normalise(np.cross(normals[bad], helper))[0]
    u2 = np.cross(normals, u1)
    flip = np.sum(u2 * dirs[:, 1], axis=-1) < 0
    u2[flip] *= -1.0
    return u1, u2


def _ray_distance(x: np.ndarray, p: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Point-to-ray distance (m) of points ``x`` (..., 3) to rays (p, a); points behind p measure to p."""
    v = x - p
    s = np.maximum(np.sum(v * a, axis=-1), 0.0)
    return np.linalg.norm(v - s[..., None] * a, axis=-1)


class _Problem:
    """Constants of one call: weights, length scales and per-sample precomputations."""

    def __init__(self, cfg: Any, pad_radius: float, standoff: float):
        self.la = float(config_value(cfg, "lambda_area"))
        self.lal = float(config_value(cfg, "lambda_align"))
        self.lc = float(config_value(cfg, "lambda_curvature"))
        self.ls = float(config_value(cfg, "lambda_scale"))
        self.lo = float(config_value(cfg, "lambda_overlap"))
        self.sigma_min = float(config_value(cfg, "sigma_min"))
        self.sigma_max = float(config_value(cfg, "sigma_max"))
        self.activation = float(config_value(cfg, "activation"))
        self.n_candidates = int(config_value(cfg, "candidates"))
        if not (0.0 < self.sigma_min <= self.sigma_max):
            raise ValueError(f"need 0 < sigma_min <= sigma_max, got {self.sigma_min}, {self.sigma_max}")
        if pad_radius <= 0:
            raise ValueError(f"pad_radius must be > 0 m, got {pad_radius}")
        self.L = self.sigma_max  # m, length scale of the area and scale terms
        self.eps = self.sigma_min  # m, length scale of the overlap term
        self.kappa_pad = 1.0 / pad_radius
        self.reach = 2.0 * self.sigma_max + standoff
        self.occlusion = self.sigma_max  # m, depth tolerance of the first-hit (occlusion) test

    def r0(self, c: np.ndarray) -> np.ndarray:
        """Equivalent patch radius (m) of the force prior: sigma_min .. sigma_max for c in 0 .. 1."""
        return self.sigma_min + (self.sigma_max - self.sigma_min) * np.clip(c, 0.0, 1.0)

    def aspect(self, k: np.ndarray) -> np.ndarray:
        """Per-axis factors (f1, f2), f1 f2 = 1, of the Hertz-like prior: sigma0 = r0 (f1, f2)."""
        kappa = np.maximum(k + self.kappa_pad, 0.1 * self.kappa_pad)
        ratio = np.clip(np.sqrt(kappa[..., 0] / kappa[..., 1]), 1.0 / MAX_ASPECT, MAX_ASPECT)
        return np.stack([1.0 / np.sqrt(ratio), np.sqrt(ratio)], axis=-1)

    def curvature_cost(self, k: np.ndarray) -> np.ndarray:
        return np.log1p(self.L ** 2 * np.sum(k ** 2, axis=-1))

    def unreachable(self, n_dot_a, along, first_hit):
        """Samples the finger cannot touch: facing away (a^T n_in <= 0) or occluded (more than ``occlusion``
        m beyond the first surface crossing ``first_hit`` along the ray; ``along`` = (x - P)^T a)."""
        return (n_dot_a >= 0.0) | (along > first_hit + self.occlusion)

    def separable(self, d2, n_dot_a, phi_c, unreachable):
        """Area + align + curvature terms of eq. 2 (1) from the squared ray distance d2 (m^2), the dot product
        of the OUTWARD normal with the squeeze direction (|1 - a^T n_in| = |1 + a^T n_out|) and phi(k1, k2),
        plus the reachability barrier (``UNREACHABLE_PENALTY`` where ``unreachable``)."""
        return (self.la * d2 / self.L ** 2 + self.lal * np.abs(1.0 + n_dot_a) + self.lc * phi_c
                + UNREACHABLE_PENALTY * unreachable)


# ----------------------------------------------------------------------------------------------- overlap
def _pair_terms(xq, nq, uq, nbx, nbn, nbu, nbs):
    """Geometry of candidate patches (Q) against placed neighbour patches (J).

    ``uq`` (Q, 3, 2) holds the candidates' tangent axes as columns, ``nbu`` (J, 2, 3) the neighbours' axes as
    rows.  Returns dist (Q, J) m, the squared direction cosines of the neighbour direction in the candidate's
    tangent plane ec2 (Q, J, 2), the neighbours' 1-sigma radii towards the candidate rho_j (Q, J) m and the
    facing weight w (Q, J).  Coincident centres (no direction) use the candidate's first axis.
    """
    diff = nbx[None, :, :] - xq[:, None, :]  # (Q, J, 3)
    dist = np.sqrt(np.einsum("qjc,qjc->qj", diff, diff))
    own = np.matmul(diff, uq)  # (Q, J, 2): tangent coordinates in the candidate's frame
    own[..., 0] += 1e-15
    own *= own
    ec2 = own / own.sum(axis=-1, keepdims=True)
    other = np.einsum("qjc,jmc->qjm", diff, nbu)  # (Q, J, 2): ... in the neighbour's frame
    other[..., 0] += 1e-15
    other *= other
    rho_j = np.sqrt(other.sum(axis=-1) / (other / (nbs * nbs)[None]).sum(axis=-1))
    w = nq @ nbn.T
    np.maximum(w, 0.0, out=w)
    return dist, ec2, rho_j, w


def _sigma_cost(prob: _Problem, terms, s0, sig1, sig2):
    """Scale + overlap cost (1) on grids sig1 (Q, A), sig2 (Q, B) -> (Q, A, B)."""
    dist, ec2, rho_j, w = terms
    scale = (prob.ls / prob.L ** 2) * (((sig1 - s0[:, :1]) ** 2)[:, :, None] + ((sig2 - s0[:, 1:]) ** 2)[:, None, :])
    # rho_i = 1 / sqrt((e1/sigma1)^2 + (e2/sigma2)^2): radius of the candidate ellipse towards each neighbour
    g = ec2[:, :, 0, None, None] * (1.0 / sig1 ** 2)[:, None, :, None]
    g = g + ec2[:, :, 1, None, None] * (1.0 / sig2 ** 2)[:, None, None, :]
    np.sqrt(g, out=g)
    np.divide(1.0, g, out=g)
    g += (rho_j - dist)[:, :, None, None]  # overlap rho_i + rho_j - |x_i - x_j|
    np.maximum(g, 0.0, out=g)
    g *= g
    g *= (w * (prob.lo / prob.eps ** 2))[:, :, None, None]
    return scale + g.sum(axis=1)


def _solve_sigma(prob: _Problem, esep, s0, terms):
    """Best candidate and its sigma (coarse-to-fine search over per-axis shrink factors of sigma0).

    Stage A scores every candidate on a 3x3 grid, stage B the best ``_KEEP`` of them on the 7x7 grid, stage C
    polishes the winner on two local 9x9 grids (resolution 0.125/16 of sigma0).  Returns (q, sigma (2,), cost,
    interacting) where ``interacting`` tells whether any neighbour could overlap any candidate at all (if not,
    sigma = sigma0 and the best candidate is argmin esep).
    """
    dist, _, rho_j, w = terms
    # a neighbour can only matter if it faces a candidate closer than the sum of the largest radii
    near = (w > 0) & (dist < s0.max(axis=1, keepdims=True) + rho_j)
    if not np.any(near):
        q = int(np.argmin(esep))
        return q, s0[q].copy(), float(esep[q]), False
    cols = np.flatnonzero(near.any(axis=0))
    if cols.size < near.shape[1]:
        terms = tuple(v[:, cols] for v in terms)
    if esep.size > _KEEP:
        g = _GRID[::3]
        total = esep[:, None, None] + _sigma_cost(prob, terms, s0, s0[:, :1] * g, s0[:, 1:] * g)
        keep = np.argpartition(total.reshape(esep.size, -1).min(axis=1), _KEEP - 1)[:_KEEP]
    else:
        keep = np.arange(esep.size)
    sub = tuple(v[keep] for v in terms)
    total = esep[keep, None, None] + _sigma_cost(prob, sub, s0[keep], s0[keep, :1] * _GRID, s0[keep, 1:] * _GRID)
    k, g1, g2 = np.unravel_index(int(np.argmin(total)), total.shape)
    q = int(keep[k])
    best = float(total[k, g1, g2])
    s = np.array([_GRID[g1], _GRID[g2]])
    one = tuple(v[q:q + 1] for v in terms)
    step = _GRID[1] - _GRID[0]
    for _ in range(_FINE_ROUNDS):
        step /= 4.0
        c1 = np.clip(s[0] + step * _FINE, SHRINK_MIN, 1.0)
        c2 = np.clip(s[1] + step * _FINE, SHRINK_MIN, 1.0)
        tot = esep[q] + _sigma_cost(prob, one, s0[q:q + 1], s0[q, 0] * c1[None], s0[q, 1] * c2[None])[0]
        i1, i2 = np.unravel_index(int(np.argmin(tot)), tot.shape)
        if tot[i1, i2] < best:
            best = float(tot[i1, i2])
            s = np.array([c1[i1], c2[i2]])
    return q, s0[q] * s, best, True


def _refine_points(x0, n0, u1, u2, k, p, a, trust):
    """Move samples x0 (M, 3) along their osculating quadrics towards their rays (p, a) (M, 3).

    The target is the intersection of the ray with the tangent plane of x0 (when the ray crosses it ahead
    of the fingertip at more than ~11 degrees), else the foot of x0 on the ray; the tangential step w is
    clipped to ``trust`` (m) and mapped onto the quadric ``x0 + w - 0.5 (k1 w1^2 + k2 w2^2) n0`` with normal
    ``n0 + k1 w1 u1 + k2 w2 u2``.  Returns (x, n, u1, u2), all (M, 3).
    """
    an = np.sum(a * n0, axis=-1)
    s_plane = np.sum((x0 - p) * n0, axis=-1) / np.where(an < -0.2, an, -1.0)
    use_plane = (an < -0.2) & (s_plane >= 0.0)
    s_foot = np.maximum(np.sum((x0 - p) * a, axis=-1), 0.0)
    target = p + np.where(use_plane, s_plane, s_foot)[:, None] * a
    w1 = np.sum((target - x0) * u1, axis=-1)
    w2 = np.sum((target - x0) * u2, axis=-1)
    norm = np.hypot(w1, w2)
    scale = np.where(norm > trust, trust / np.maximum(norm, _TINY), 1.0)
    w1, w2 = w1 * scale, w2 * scale
    x = x0 + w1[:, None] * u1 + w2[:, None] * u2 - (0.5 * (k[:, 0] * w1 ** 2 + k[:, 1] * w2 ** 2))[:, None] * n0
    n, _ = _normalise(n0 + (k[:, 0] * w1)[:, None] * u1 + (k[:, 1] * w2)[:, None] * u2)
    v1, _ = _normalise(u1 - np.sum(u1 * n, axis=-1, keepdims=True) * n)
    v2 = np.cross(n, v1)
    v2 *= np.where(np.sum(v2 * u2, axis=-1) < 0.0, -1.0, 1.0)[:, None]
    return x, n, v1, v2


# ----------------------------------------------------------------------------------------------- main
@dataclass(frozen=True)
class PatchSearch:
    """Finger model and search options of SC-CAE (see the module doc); the objective's weights are in ``cfg``.

    pad_radius: m, finger pad radius of curvature for the Hertz aspect of sigma0.
    standoff: m, reach = 2 sigma_max + standoff.
    sweeps: maximum coordinate-descent sweeps over the fingers per frame.
    refine: continuous refinement of the centre on the local surface quadric.
    hysteresis: 1, objective head start of the candidate nearest the previous frame's centre (0 = off).
    """

    pad_radius: float = DEFAULT_PAD_RADIUS
    standoff: float = DEFAULT_STANDOFF
    sweeps: int = 6
    refine: bool = True
    hysteresis: float = DEFAULT_HYSTERESIS


@dataclass
class _Surface:
    """Per-sample precomputation: coordinates relative to ``origin`` (m, for round-off), unit outward normals,
    principal curvatures (k1 >= k2, 1/m), tangent frames, curvature cost phi, the force prior's aspect factors and
    the sample spacing (m)."""

    origin: np.ndarray  # (xyz,)
    x: np.ndarray  # (S, 3)
    n: np.ndarray  # (S, 3)
    k: np.ndarray  # (S, 2)
    u1: np.ndarray  # (S, 3)
    u2: np.ndarray  # (S, 3)
    phi: np.ndarray  # (S,)
    aspect: np.ndarray  # (S, 2)
    spacing: float


@dataclass
class _Candidates:
    """Candidate patches of every ray (frame t, finger k), Q per ray (stage 1 of the solver): centres x (m),
    normals, tangent axes, separable cost e, force-prior sigma0 s0 (m), the independent optimum ``best``, the
    candidates' spread around it and largest sigma0 (m), their ray distances (m) and reachability."""

    x: np.ndarray  # (T, F, Q, 3)
    n: np.ndarray  # (T, F, Q, 3)
    u1: np.ndarray  # (T, F, Q, 3)
    u2: np.ndarray  # (T, F, Q, 3)
    u: np.ndarray  # (T, F, Q, 3, 2) tangent axes as columns
    e: np.ndarray  # (T, F, Q)
    s0: np.ndarray  # (T, F, Q, 2)
    best: np.ndarray  # (T, F)
    spread: np.ndarray  # (T, F)
    s0max: np.ndarray  # (T, F)
    ray_d: np.ndarray  # (T, F, Q)
    reachable: np.ndarray  # (T, F, Q)


def contact_patches(
    surface_points,
    surface_normals,
    surface_curvature,
    surface_principal_dirs,
    surface_area,
    fingertip_positions,
    squeeze_directions,
    force_coefficients,
    cfg: Any,
    search: PatchSearch = PatchSearch(),
) -> dict[str, Array]:
    """SC-CAE contact patches, eq. 2, for every frame and finger (see the module doc for the objective).

    Args:
        surface_points: (S, 3) m, surface samples.
        surface_normals: (S, 3) 1, OUTWARD unit normals.
        surface_curvature: (S, 2) 1/m, principal curvatures (k1 >= k2; convex = positive).
        surface_principal_dirs: (S, 2, 3) 1, unit tangents of k1 and k2.
        surface_area: (S,) m^2, area represented by each sample (its sqrt is the sample spacing).
        fingertip_positions: (T, F, 3) m, P_k,t.
        squeeze_directions: (T, F, 3) 1, a_k,t, pointing from the fingertip into the object.
        force_coefficients: (T, F) 1, c_k,t of eq. 1.
        cfg: ContactConfig-like (lambdas, sigma_min/max in m, candidates, activation).
        search: finger model and search options (:class:`PatchSearch`).

    Returns:
        ``patch_centers`` (frame, finger, xyz) m, ``patch_normals`` (frame, finger, xyz) 1 (outward),
        ``patch_axes`` (frame, finger, principal, xyz) 1, ``patch_radii`` (frame, finger, principal) m
        (sigma1 along axis 0 = direction of k1, sigma2 along axis 1; 0 when inactive), ``patch_areas``
        (frame, finger) m^2 (pi sigma1 sigma2, 0 when inactive), ``patch_active`` (frame, finger) bool,
        ``patch_cost`` (frame, finger) 1 (value of the eq. 2 objective at the solution).
    """
    # 1. inputs and the objective's constants
    X, N_in, K, D, A, P, a_raw, c = _checked_inputs(surface_points, surface_normals, surface_curvature,
                                                    surface_principal_dirs, surface_area, fingertip_positions,
                                                    squeeze_directions, force_coefficients)
    prob = _Problem(cfg, search.pad_radius, search.standoff)
    # 2. per-sample precomputation
    surf = _prepare_surface(X, N_in, K, D, A, prob)
    # 3. rays and the force prior
    a, a_norm = _normalise(a_raw)
    valid = a_norm > 1e-6
    a[~valid] = 0.0
    active_force = valid & (c > prob.activation)
    # 4. candidates of every ray, then 5. the per-frame coordinate descent
    cands = _find_candidates(prob, surf, P - surf.origin, a, prob.r0(c), search.refine)
    centers, normals, axes, radii, costs, active = _solve_frames(prob, cands, c, active_force, surf.spacing,
                                                                 search.sweeps, search.hysteresis)
    # 6. the artifact arrays
    return _patch_arrays(centers + surf.origin, normals, axes, radii, costs, active)


def _checked_inputs(*arrays) -> tuple[np.ndarray, ...]:
    """The eight array inputs of :func:`contact_patches` as numpy (curvatures and directions copied), checked
    for shape and finiteness (ValueError naming the input)."""
    X, N_in, K, D, A, P, a_raw, c = (as_numpy(v) for v in arrays)
    K, D = K.copy(), D.copy()
    S = X.shape[0]
    if X.ndim != 2 or X.shape[1] != 3 or S == 0:
        raise ValueError(f"surface_points must be (S, 3) with S > 0, got {X.shape}")
    for name, arr, shape in (("surface_normals", N_in, (S, 3)), ("surface_curvature", K, (S, 2)),
                             ("surface_principal_dirs", D, (S, 2, 3)), ("surface_area", A, (S,))):
        if arr.shape != shape:
            raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if P.ndim != 3 or P.shape[2] != 3 or a_raw.shape != P.shape or c.shape != P.shape[:2]:
        raise ValueError(f"need fingertip_positions (T, F, 3), squeeze_directions (T, F, 3), "
                         f"force_coefficients (T, F); got {P.shape}, {a_raw.shape}, {c.shape}")
    for name, arr in (("surface_points", X), ("surface_normals", N_in), ("surface_curvature", K),
                      ("surface_principal_dirs", D), ("fingertip_positions", P),
                      ("squeeze_directions", a_raw), ("force_coefficients", c)):
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} contains non-finite values")
    return X, N_in, K, D, A, P, a_raw, c


def _prepare_surface(X: np.ndarray, N_in: np.ndarray, K: np.ndarray, D: np.ndarray, A: np.ndarray,
                     prob: _Problem) -> _Surface:
    """Per-sample precomputation (coordinates relative to the centroid for round-off); ``K`` and ``D`` are
    reordered in place so that k1 >= k2."""
    origin = X.mean(axis=0)
    X = X - origin
    N, _ = _normalise(N_in)
    swap = K[:, 0] < K[:, 1]  # enforce k1 >= k2 together with the directions
    K[swap] = K[swap][:, ::-1]
    D[swap] = D[swap][:, ::-1]
    U1, U2 = _tangent_frames(N, D)
    good_area = A[np.isfinite(A) & (A > 0)]
    if good_area.size:
        spacing = float(np.sqrt(np.median(good_area)))
    else:  # fall back to the median nearest-neighbour distance
        spacing = float(np.median(cKDTree(X).query(X, k=2)[0][:, 1]))
    return _Surface(origin=origin, x=X, n=N, k=K, u1=U1, u2=U2, phi=prob.curvature_cost(K), aspect=prob.aspect(K),
                    spacing=spacing)


def _exact_cost(prob: _Problem, first_hit: np.ndarray, x, n, phi, p, d):
    """Separable cost (1) and reachability of points x (M, ..., 3) for rays (p, d) (M, ..., 3); ``first_hit``
    (M,) m is each ray's first surface crossing."""
    nd = np.sum(n * d, axis=-1)
    along = np.sum((x - p) * d, axis=-1)
    blocked = prob.unreachable(nd, along, first_hit.reshape(first_hit.shape + (1,) * (nd.ndim - 1)))
    return prob.separable(_ray_distance(x, p, d) ** 2, nd, phi, blocked), ~blocked


def _find_candidates(prob: _Problem, surf: _Surface, P: np.ndarray, a: np.ndarray, r0: np.ndarray,
                     refine: bool) -> _Candidates:
    """Solver stage 1 (module doc): the ``cfg.candidates`` samples of lowest separable cost of every ray
    (fingertips ``P`` (T, F, 3) m relative to the surface origin, unit directions ``a``), plus the continuous
    refinement of the best one; ``r0`` (T, F) m the force prior's equivalent radius."""
    X, N, S = surf.x, surf.n, len(surf.x)
    T, F = r0.shape
    # 1. the samples of lowest separable cost, for every ray at once (chunked over rays)
    n_cand = min(prob.n_candidates, S)
    M = T * F
    Pm = P.reshape(M, 3)
    am = a.reshape(M, 3)
    cand = np.zeros((M, n_cand), dtype=np.int64)
    first_hit = np.full(M, np.inf)  # m, along-ray distance of the first surface crossing ahead of P
    X2 = np.sum(X ** 2, axis=1)
    chunk = max(1, int(1_000_000 // S))  # rays per block: (S, chunk) matrices of ~8 MB each
    for lo in range(0, M, chunk):
        p, d = Pm[lo:lo + chunk], am[lo:lo + chunk]
        s = X @ d.T - np.sum(p * d, axis=1)[None, :]
        v2 = X2[:, None] - 2.0 * (X @ p.T) + np.sum(p ** 2, axis=1)[None, :]
        d2 = np.maximum(v2 - np.where(s > 0.0, s * s, 0.0), 0.0)
        # first surface crossing ahead of the fingertip: nearest sample within one spacing of the ray
        hit = np.where((d2 < surf.spacing ** 2) & (s > 0.0), s, np.inf).min(axis=0)
        first_hit[lo:lo + chunk] = hit
        nd = N @ d.T
        cost = prob.separable(d2, nd, surf.phi[:, None], prob.unreachable(nd, s, hit[None, :]))
        if n_cand < S:
            part = np.argpartition(cost, n_cand - 1, axis=0)[:n_cand]
        else:
            part = np.broadcast_to(np.arange(S)[:, None], cost.shape)
        cand[lo:lo + chunk] = part.T

    # 2. exact separable cost of the candidates (the expansion above is only used for ranking)
    cand_e, _ = _exact_cost(prob, first_hit, X[cand], N[cand], surf.phi[cand], Pm[:, None], am[:, None])

    # 3. candidate geometry (M, Q, ...): the samples, plus the continuous refinement of the best one
    g_base = cand
    g_x, g_n, g_u1, g_u2, g_e = X[cand], N[cand], surf.u1[cand], surf.u2[cand], cand_e
    if refine:
        b = cand[np.arange(M), np.argmin(cand_e, axis=1)]
        xr, nr, r1, r2 = _refine_points(X[b], N[b], surf.u1[b], surf.u2[b], surf.k[b], Pm, am, surf.spacing)
        er, _ = _exact_cost(prob, first_hit, xr, nr, surf.phi[b], Pm, am)
        g_base = np.concatenate([cand, b[:, None]], axis=1)
        g_x = np.concatenate([g_x, xr[:, None]], axis=1)
        g_n = np.concatenate([g_n, nr[:, None]], axis=1)
        g_u1 = np.concatenate([g_u1, r1[:, None]], axis=1)
        g_u2 = np.concatenate([g_u2, r2[:, None]], axis=1)
        g_e = np.concatenate([g_e, er[:, None]], axis=1)

    # 4. what the frame solver needs per candidate, as (T, F, Q, ...)
    g_u = np.stack([g_u1, g_u2], axis=-1)  # (M, Q, 3, 2) tangent axes as columns
    g_s0 = r0.reshape(M, 1, 1) * surf.aspect[g_base]  # (M, Q, 2) m
    g_best = np.argmin(g_e, axis=1)  # independent (overlap-free) optimum of each ray
    g_spread = np.linalg.norm(g_x - g_x[np.arange(M), g_best][:, None], axis=-1).max(axis=1)
    g_s0max = g_s0.max(axis=(1, 2))
    ray_d = _ray_distance(g_x, Pm[:, None], am[:, None])  # (M, Q) m
    _, reachable = _exact_cost(prob, first_hit, g_x, g_n, 0.0, Pm[:, None], am[:, None])  # (M, Q)
    per_ray = {"x": g_x, "n": g_n, "u1": g_u1, "u2": g_u2, "u": g_u, "e": g_e, "s0": g_s0, "best": g_best,
               "spread": g_spread, "s0max": g_s0max, "ray_d": ray_d, "reachable": reachable}
    return _Candidates(**{k: v.reshape((T, F) + v.shape[1:]) for k, v in per_ray.items()})


class _FrameState:
    """The patches of the frame being solved (carried over to the next frame as warm start): chosen candidate
    slot q, centre x (m), normal n, axes u (rows), radii s (m) and eligibility (active and within reach: the
    patch enters the other fingers' overlap terms)."""

    def __init__(self, prob: _Problem, cands: _Candidates, active_force: np.ndarray, spacing: float,
                 hysteresis: float):
        F = active_force.shape[1]
        self.prob, self.cands, self.active_force, self.hysteresis = prob, cands, active_force, hysteresis
        self.q = np.full(F, -1, dtype=np.int64)  # chosen candidate slot
        self.x = np.zeros((F, 3))
        self.n = np.zeros((F, 3))
        self.u = np.zeros((F, 2, 3))
        self.s = np.zeros((F, 2))
        self.eligible = np.zeros(F, dtype=bool)  # active and within reach: enters the others' overlap terms
        self.prev_x = np.zeros((F, 3))  # centres of the previous frame (hysteresis)
        self.tol_x = 0.25 * spacing  # m, a patch that moved less than this (and ...
        self.tol_s = 0.01  # 1, ... whose radii changed by less than 1 %) counts as unchanged: the sweeps stop

    def assign(self, t: int, i: int, q: int, sig: np.ndarray) -> bool:
        """Place finger i's patch on candidate q with radii sig (m); returns True when the patch changed."""
        g = self.cands
        changed = float(np.abs(self.s[i] - sig).max()) > self.tol_s * float(sig.max()) \
            or float(np.abs(self.x[i] - g.x[t, i, q]).max()) > self.tol_x
        self.q[i] = q
        self.x[i] = g.x[t, i, q]
        self.n[i] = g.n[t, i, q]
        self.u[i, 0] = g.u1[t, i, q]
        self.u[i, 1] = g.u2[t, i, q]
        self.s[i] = sig
        self.eligible[i] = self.active_force[t, i] and g.ray_d[t, i, q] <= self.prob.reach and g.reachable[t, i, q]
        return changed

    def update(self, t: int, i: int, nb: np.ndarray) -> bool:
        """Re-solve finger i against the placed neighbours nb; returns True when its patch changed."""
        g = self.cands
        e = g.e[t, i]
        if t > 0 and self.hysteresis > 0.0:  # the candidate nearest last frame's centre gets a head start
            e = e.copy()
            e[np.argmin(np.sum((g.x[t, i] - self.prev_x[i]) ** 2, axis=1))] -= self.hysteresis
        if nb.size and self.active_force[t, i]:
            # cheap bound: can any candidate come within overlap range of any neighbour?
            gap = np.linalg.norm(self.x[nb] - g.x[t, i, g.best[t, i]], axis=1) - g.spread[t, i]
            if np.any(gap < g.s0max[t, i] + self.s[nb].max(axis=1)):
                terms = _pair_terms(g.x[t, i], g.n[t, i], g.u[t, i], self.x[nb], self.n[nb], self.u[nb], self.s[nb])
                q, sig, _, _ = _solve_sigma(self.prob, e, g.s0[t, i], terms)
                return self.assign(t, i, q, sig)
        q0 = int(np.argmin(e))
        return self.assign(t, i, q0, g.s0[t, i, q0])

    def objective(self, t: int, i: int) -> float:
        """Value of the eq. 2 objective of finger i at the final state (overlap against the final neighbours)."""
        g, F = self.cands, len(self.q)
        cost = g.e[t, i, self.q[i]]
        nb = np.arange(F)[(np.arange(F) != i) & self.eligible]
        if self.active_force[t, i] and nb.size:
            near = np.linalg.norm(self.x[nb] - self.x[i], axis=1) < g.s0max[t, i] + self.s[nb].max(axis=1)
            nb = nb[near]
        if self.active_force[t, i] and nb.size:
            terms = _pair_terms(self.x[i:i + 1], self.n[i:i + 1], np.swapaxes(self.u[i:i + 1], 1, 2),
                                self.x[nb], self.n[nb], self.u[nb], self.s[nb])
            s0 = g.s0[t, i, self.q[i]][None]
            cost += _sigma_cost(self.prob, terms, s0, self.s[i:i + 1, :1], self.s[i:i + 1, 1:])[0, 0, 0]
        return cost


def _solve_frames(prob: _Problem, cands: _Candidates, c: np.ndarray, active_force: np.ndarray, spacing: float,
                  sweeps: int, hysteresis: float) -> tuple[np.ndarray, ...]:
    """Solver stages 2-3 (module doc), frame by frame: Gauss-Seidel sweeps over the fingers in order of
    decreasing force coefficient ``c`` (T, F), warm-started from the previous frame.  Returns centres (T, F, 3)
    m relative to the surface origin, normals (T, F, 3), axes (T, F, 2, 3), radii (T, F, 2) m (0 when inactive),
    objective values (T, F) and activity (T, F)."""
    T, F = c.shape
    centers = np.zeros((T, F, 3))
    normals = np.zeros((T, F, 3))
    axes = np.zeros((T, F, 2, 3))
    radii = np.zeros((T, F, 2))
    costs = np.zeros((T, F))
    active = np.zeros((T, F), dtype=bool)
    st = _FrameState(prob, cands, active_force, spacing, hysteresis)
    all_f = np.arange(F)
    for t in range(T):
        report_progress(t, T)
        st.prev_x[:] = st.x
        order = np.argsort(-c[t], kind="stable")
        # 1. warm start: fingers eligible in the previous frame and still pushing enter the overlap terms with
        # their previous patches until this frame's first sweep reaches them
        placed = st.eligible & active_force[t] if t > 0 else np.zeros(F, dtype=bool)
        st.eligible &= placed
        n_active = int(active_force[t].sum())
        # 2. coordinate-descent sweeps until no patch changes or no two patches can interact
        for sweep in range(max(1, sweeps)):
            changed = False
            for i in order:
                if sweep > 0 and not active_force[t, i]:
                    continue
                nb = all_f[(all_f != i) & placed & st.eligible]
                changed |= st.update(t, i, nb)
                placed[i] = True
            if n_active <= 1 or not changed:
                break
            prior = cands.s0max[t]
            if not _any_interaction(st.x, st.n, np.maximum(prior, st.s.max(axis=1)), st.eligible):
                break
        # 3. the frame's patches and their objective values
        for i in range(F):
            costs[t, i] = st.objective(t, i)
        centers[t] = st.x
        normals[t] = st.n
        axes[t] = st.u
        active[t] = st.eligible
        radii[t] = np.where(st.eligible[:, None], st.s, 0.0)
    return centers, normals, axes, radii, costs, active


def _patch_arrays(centers, normals, axes, radii, costs, active) -> dict[str, Array]:
    """The contact_patches artifact arrays (axes and units named) from the solved patches (frame, finger, ...)."""
    areas = np.pi * radii[..., 0] * radii[..., 1]
    return {
        "patch_centers": Array(centers, ("frame", "finger", "xyz"), "m",
                               "contact patch centre x on the object surface (eq. 2)"),
        "patch_normals": Array(normals, ("frame", "finger", "xyz"), "1",
                               "outward unit surface normal at the patch centre; squeeze direction is its negative"),
        "patch_axes": Array(axes, ("frame", "finger", "principal", "xyz"), "1",
                            "unit tangent axes of the patch: 0 = direction of k1 (more curved), 1 = of k2"),
        "patch_radii": Array(radii, ("frame", "finger", "principal"), "m",
                             "anisotropic patch scale sigma along patch_axes (eq. 2); 0 when inactive"),
        "patch_areas": Array(areas, ("frame", "finger"), "m^2", "pi sigma1 sigma2 for active patches, else 0"),
        "patch_active": Array(active, ("frame", "finger"), "1",
                              "c > activation, patch reachable (facing, not occluded) and within reach of the ray"),
        "patch_cost": Array(costs, ("frame", "finger"), "1", "value of the eq. 2 objective at the solution"),
    }


def _any_interaction(x, n, radius, eligible) -> bool:
    """True when two eligible patches face each other closer than the sum of their largest (prior) radii."""
    idx = np.flatnonzero(eligible)
    if idx.size < 2:
        return False
    xs, ns, ss = x[idx], n[idx], radius[idx]
    dist = np.linalg.norm(xs[:, None] - xs[None], axis=-1)
    close = (dist < ss[:, None] + ss[None]) & ((ns @ ns.T) > 0)
    np.fill_diagonal(close, False)
    return bool(close.any())


# ----------------------------------------------------------------------------------------------- Prefect step


SURFACE = ("surface_points", "surface_normals", "surface_curvature", "surface_principal_dirs", "surface_area")


@artifact_step("contact_patches", inputs=("object_model", "signal_smoothing", "force_coefficients"),
               reads=("control.contact",),
               outputs=("patch_centers", "patch_normals", "patch_axes", "patch_radii", "patch_areas", "patch_active",
                        "patch_cost"))
def contact_patches_step(inputs, params):
    """SC-CAE (eq. 2) per finger and frame: the object's surface, the smoothed fingertips and squeeze directions,
    and the force coefficients of eq. 1."""
    obj, frames = inputs["object_model"], inputs["signal_smoothing"]
    out = contact_patches(*(obj[name] for name in SURFACE), frames["fingertip_positions"],
                          frames["squeeze_directions"], inputs["force_coefficients"]["force_coefficients"],
                          params["control.contact"])
    return out, {"active_fraction": float(out["patch_active"].data.mean())}
