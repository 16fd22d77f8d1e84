"""Finite-sphere reference for the Hertz case: an elastic sphere between two frictionless rigid flats by
axisymmetric finite elements (6-node triangles, 7-point Gauss rule; active-set Signorini contact), at small strain
(linear) or at finite strain with the MPM solver's own model (fixed-corotated; Newton-GMRES on the linear
stiffness as preconditioner).

Hertz's F = 4/3 E* sqrt(R) d^1.5 treats each contact as a half-space, so its approach d is measured from points at
infinity; in a sphere the approach is measured from the centre, a distance R from the contact, which moves with the
contact by ~ F / (E R).  That shortens d at a given force by a fraction ~ sqrt(d / R) (= a / R): the linear solver
gives F / F_Hertz - 1 = +2.5 / +4.0 / +8.1 / +11.6 / +14.3 / +16.6 % at d = 0.1 / 0.25 / 1 / 2 / 3 / 4 mm for the
issue's sphere (R = 35 mm, nu = 0.45), i.e. ~0.48 sqrt(d / R), the same at three times the nodes, and tends to
Hertz as d / R -> 0.  At nu = 0 the leading term nearly vanishes and the linear excess grows faster: -0.3 / +0.1 /
+1.4 / +6.6 / +22 % at d = 0.05 / 0.1 / 0.25 / 1 / 4 mm.  Finite strain (strains up to ~0.2 at the contact's edge
at 4 mm) takes part of that back: fixed-corotated reads +1.8 / +6.0 / +9.1 / +11.8 / +14.5 % at d = 0.1 / 1 / 2 /
3 / 4 mm (nu = 0.45) and -0.8 / +2.6 / +5.8 / +8.6 / +11.2 % (nu = 0), within 0.4 % at 3x and 9x the nodes.
:func:`tasks.verification.contact.hertz_case` (the MPM sphere, a finite-strain solver) is compared with it.

The quarter disk 0 <= r, 0 <= z, r^2 + z^2 <= R^2 is meshed: z = 0 is the equator (a symmetry plane: u_z = 0),
r = 0 the axis (u_r = 0); the flat sits at z = R - d.  Units SI (m, Pa, N).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from scipy.spatial import Delaunay

# 7-point rule on the reference triangle (degree 5; weights include its area 1/2)
_A1, _B1, _A2, _B2 = 0.0597158717, 0.4701420641, 0.7974269853, 0.1012865073
_GP = np.array([[1 / 3, 1 / 3], [_A1, _B1], [_B1, _A1], [_B1, _B1], [_A2, _B2], [_B2, _A2], [_B2, _B2]])
_GW = np.array([0.225] + [0.1323941527] * 3 + [0.1259391805] * 3) / 2


def quarter_disk_mesh(R: float, h_min: float, growth: float = 0.05, inner: float = 0.0,
                      h_max: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
    """6-node triangles on the quarter disk of radius R (m), or with ``inner`` > 0 on the quarter annulus inner <=
    |x| <= R (a hollow sphere's wall), graded from the pole (0, R): nodes on arcs about the pole with spacing
    min(h_max, max(h_min, growth * distance)) (m), plus the matching boundary nodes on the sphere(s), the axis and
    the equator; curved-edge midside nodes lie on the sphere(s).  Returns nodes (n, 2: r, z) and elements (e, 6:
    corners, then the midsides of edges 01, 12, 20)."""
    if not 0.0 <= inner < R:
        raise ValueError(f"quarter_disk_mesh: inner radius must be in [0, R = {R}), got {inner}")
    pole = np.array([0.0, R])
    pts = [pole[None], np.array([[R, 0.0], [inner, 0.0] if inner > 0 else [0.0, 0.0]])]
    if inner > 0:
        pts.append(np.array([[0.0, inner]]))
    rho = 0.0
    while rho < 2 * R:
        step = min(h_max, max(h_min, growth * rho))
        rho += step
        th = np.linspace(0.0, np.pi, max(4, int(np.ceil(np.pi * rho / step))) + 1)
        P = pole + rho * np.stack([np.sin(th), -np.cos(th)], 1)
        radius = np.hypot(P[:, 0], P[:, 1])
        inside = (P[:, 0] > 0.3 * step) & (P[:, 1] > 0.3 * step) & (radius < R - 0.3 * step) & (
            radius > inner + 0.3 * step if inner > 0 else True)
        pts.append(P[inside])
        phi = 2.0 * np.arcsin(min(rho / (2 * R), 1.0))  # the sphere's point at chord rho from the pole
        if phi <= np.pi / 2:
            pts.append(np.array([[R * np.sin(phi), R * np.cos(phi)]]))
        if inner > 0:  # the inner sphere's point at distance rho from the pole
            c = (inner * inner + R * R - rho * rho) / (2 * R * inner)
            if 0.0 <= c <= 1.0:
                pts.append(np.array([[inner * np.sqrt(1 - c * c), inner * c]]))
        if rho <= R - inner:
            pts.append(np.array([[0.0, R - rho]]))
        if np.hypot(inner, R) <= rho <= np.sqrt(2.0) * R:
            pts.append(np.array([[np.sqrt(rho * rho - R * R), 0.0]]))
    P = np.unique(np.round(np.concatenate(pts), 12), axis=0)
    tri = Delaunay(P).simplices
    centre = np.hypot(*P[tri].mean(1).T)
    tri = tri[(centre < R) & (centre > inner)]
    size = np.hypot(P[:, 0], P[:, 1])
    on_sphere = np.abs(size - R) < 1e-9 * R
    on_inner = (np.abs(size - inner) < 1e-9 * R) if inner > 0 else np.zeros(len(P), bool)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), 1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = P[unique].mean(1)
    for on, radius in ((on_sphere, R), (on_inner, inner)):
        curved = on[unique[:, 0]] & on[unique[:, 1]]
        mid[curved] *= radius / np.hypot(mid[curved, 0], mid[curved, 1])[:, None]
    elements = np.concatenate([tri, inverse.reshape(3, len(tri)).T + len(P)], 1)
    return np.concatenate([P, mid]), elements


def _shape(xi: float, eta: float) -> tuple[np.ndarray, np.ndarray]:
    """Quadratic triangle shape functions (6,) and their reference derivatives (6, 2)."""
    L = np.array([1.0 - xi - eta, xi, eta])
    dL = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
    N = np.concatenate([L * (2 * L - 1), 4 * L * np.roll(L, -1)])
    dN = np.concatenate([(4 * L - 1)[:, None] * dL,
                         4 * (L[:, None] * np.roll(dL, -1, 0) + np.roll(L, -1)[:, None] * dL)])
    return N, dN


class Quadrature(NamedTuple):
    """The mesh's Gauss points: shape functions ``N`` (g, 6), their spatial derivatives ``dNx`` (e, g, 6, 2: d/dr,
    d/dz), radius ``r`` (e, g; m) and the volume each point carries in the full solid of revolution ``dV`` (e, g;
    2 pi r |det J| w, m^3)."""

    N: np.ndarray
    dNx: np.ndarray
    r: np.ndarray
    dV: np.ndarray


def quadrature(X: np.ndarray, T: np.ndarray) -> Quadrature:
    """The 7-point Gauss data of the mesh (X, T) (see :class:`Quadrature`)."""
    xe = X[T]
    N, dNx, r, dV = [], [], [], []
    for (xi, eta), w in zip(_GP, _GW):
        n, dN = _shape(xi, eta)
        J = np.einsum("ai,eaj->eij", dN, xe)  # J[i, j] = d x_j / d xi_i
        N.append(n)
        dNx.append(np.einsum("ak,ejk->eaj", dN, np.linalg.inv(J)))
        r.append(xe[:, :, 0] @ n)
        dV.append(2 * np.pi * r[-1] * np.abs(np.linalg.det(J)) * w)
    return Quadrature(np.array(N), np.stack(dNx, 1), np.stack(r, 1), np.stack(dV, 1))


def _dofs(T: np.ndarray) -> np.ndarray:
    """(e, 12) global dofs (u_r, u_z per node) of each element."""
    return np.stack([2 * T, 2 * T + 1], 2).reshape(len(T), 12)


def _lame(E: float, nu: float) -> tuple[float, float]:
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def axisymmetric_stiffness(X: np.ndarray, T: np.ndarray, E: float, nu: float) -> sp.csr_matrix:
    """Global stiffness (N/m) of the solid of revolution (full 2 pi) of the mesh (X, T): dofs (u_r, u_z) per node;
    strains e_rr, e_zz, e_tt = u_r / r, g_rz; isotropic E (Pa), nu."""
    mu, lam = _lame(E, nu)
    D = np.array([[lam + 2 * mu, lam, lam, 0], [lam, lam + 2 * mu, lam, 0], [lam, lam, lam + 2 * mu, 0],
                  [0, 0, 0, mu]])
    q = quadrature(X, T)
    B = np.zeros(q.dNx.shape[:2] + (4, 12))
    B[..., 0, 0::2] = q.dNx[..., 0]
    B[..., 1, 1::2] = q.dNx[..., 1]
    B[..., 2, 0::2] = q.N[None] / q.r[..., None]
    B[..., 3, 0::2] = q.dNx[..., 1]
    B[..., 3, 1::2] = q.dNx[..., 0]
    Ke = np.einsum("egki,kl,eglj,eg->eij", B, D, B, q.dV)
    dof = _dofs(T)
    return sp.csr_matrix((Ke.ravel(), (np.repeat(dof, 12, 1).ravel(), np.tile(dof, (1, 12)).ravel())),
                         shape=(2 * len(X), 2 * len(X)))


def deformation(u: np.ndarray, T: np.ndarray, q: Quadrature) -> tuple[np.ndarray, np.ndarray]:
    """Deformation gradient at the Gauss points of the displacement u (flat dofs u_r, u_z per node; m): the
    meridian block F2 (e, g, 2, 2; rows r, z) and the hoop stretch F_tt = 1 + u_r / r (e, g)."""
    ue = u.reshape(-1, 2)[T]
    F2 = np.eye(2) + np.einsum("eai,egaj->egij", ue, q.dNx)
    return F2, 1.0 + np.einsum("ea,ga->eg", ue[..., 0], q.N) / q.r


def corotated_energy_forces(u: np.ndarray, T: np.ndarray, q: Quadrature, mu: float, lam: float,
                            n_dofs: int) -> tuple[float, np.ndarray]:
    """Stored energy (J) and internal nodal forces dE/du (N, flat dofs) of fixed-corotated elasticity, the MPM
    solver's model (:func:`tasks.physics.mpm.constitutive.psi_fixed_corotated`), at finite strain:
    psi = mu sum_i (sigma_i - 1)^2 + lam / 2 (J - 1)^2.  In a solid of revolution F = diag(F2, F_tt); the meridian
    singular values give sigma_1^2 + sigma_2^2 = |F2|^2 and sigma_1 + sigma_2 = sqrt((F_rr + F_zz)^2 +
    (F_zr - F_rz)^2) (the trace of R^T F2, R the closest proper rotation)."""
    F2, Ft = deformation(u, T, q)
    p, s = F2[..., 0, 0] + F2[..., 1, 1], F2[..., 1, 0] - F2[..., 0, 1]
    S = np.hypot(p, s)
    det2 = F2[..., 0, 0] * F2[..., 1, 1] - F2[..., 0, 1] * F2[..., 1, 0]
    J = det2 * Ft
    psi = mu * ((F2 ** 2).sum((-2, -1)) - 2 * S + 2 + (Ft - 1) ** 2) + 0.5 * lam * (J - 1) ** 2
    dS = np.stack([np.stack([p, -s], -1), np.stack([s, p], -1)], -2) / S[..., None, None]
    cof = np.stack([np.stack([F2[..., 1, 1], -F2[..., 1, 0]], -1), np.stack([-F2[..., 0, 1], F2[..., 0, 0]], -1)], -2)
    P2 = 2 * mu * (F2 - dS) + (lam * (J - 1) * Ft)[..., None, None] * cof  # first Piola, meridian block (Pa)
    Pt = 2 * mu * (Ft - 1) + lam * (J - 1) * det2  # hoop component
    fe = np.einsum("egij,egaj,eg->eai", P2, q.dNx, q.dV)
    fe[..., 0] += np.einsum("eg,ga,eg->ea", Pt / q.r, q.N, q.dV)
    return float((psi * q.dV).sum()), np.bincount(_dofs(T).ravel(), fe.reshape(-1), minlength=n_dofs)


def _newton_step(internal, u: np.ndarray, f: np.ndarray, free: np.ndarray, lu, tol: float) -> np.ndarray:
    """The Newton step of the free dofs (m): GMRES on the tangent, whose products are finite differences of the
    internal forces, preconditioned by the linear stiffness (``lu``, its factorised free block).  The linear
    stiffness alone (modified Newton) is not enough: at 1 mm the tangent of the strained contact edge is ~2x it
    (strains up to 0.24), which makes the fixed-point iteration oscillate (factor -0.95 per step)."""
    h = 1e-7 * max(np.abs(u).max(), 1e-12)

    def tangent(v: np.ndarray) -> np.ndarray:
        size = max(np.abs(v).max(), 1e-300)  # the probe is h along v / size, so its step is h whatever v's size
        w = u.copy()
        w[free] += (h / size) * v
        return (internal(w) - f)[free] * (size / h)

    n = len(free)
    J = spl.LinearOperator((n, n), matvec=tangent)
    M = spl.LinearOperator((n, n), matvec=lu.solve)
    step, _ = spl.gmres(J, -f[free], M=M, rtol=min(1e-3, 1e3 * tol), restart=60, maxiter=5)
    return step


def sphere_between_flats(depths, R: float, E: float, nu: float, h_min: float | None = None,
                         growth: float = 0.05, model: str = "linear", tol: float = 1e-9, wall: float = 0.0,
                         h_max: float = np.inf) -> dict:
    """Force (N) on each flat and contact radius (m) of an elastic sphere (radius R, m; E, Pa; nu) whose two
    frictionless flats each approach its centre by d, for each d in ``depths`` (m, increasing).  ``h_min`` (m;
    default a / 30 at the smallest depth, a = sqrt(R d)) and ``growth``: mesh spacing at the pole and its growth
    with distance.  ``model``: ``linear`` (small strain, one linear solve per contact set) or ``fixed_corotated``
    (finite strain, the MPM solver's model: Newton-GMRES steps preconditioned by the linear stiffness,
    :func:`_newton_step`, until the free forces fall below ``tol`` x the contact force, starting from the previous
    depth's solution).  Contact by
    active sets: a sphere node is held at the flat (its height z + u_z = R - d, free to slide) while its reaction
    pushes, released when it pulls, and held when it would cross the flat.  ``wall`` (m, > 0): a hollow sphere of
    that wall thickness (the rubber ball's shell; no air inside), meshed with at most ``h_max`` (m) between nodes.
    Returns ``at``, ``force``, ``radius`` (the reference radius of the outermost node in contact), ``pole_gap`` (m,
    how far the pole, the node on the axis at the outer surface, lies from the flat: 0 while it touches, > 0 once
    the cap dimples away from it), ``nodes`` and ``iterations`` (Newton, all depths)."""
    if model not in ("linear", "fixed_corotated"):
        raise ValueError(f"sphere_between_flats: model must be linear or fixed_corotated, got {model!r}")
    at = np.atleast_1d(np.asarray(depths, float))
    X, T = quarter_disk_mesh(R, h_min or np.sqrt(R * at.min()) / 30, growth, inner=R - wall if wall > 0 else 0.0,
                             h_max=h_max)
    n_dofs = 2 * len(X)
    K = axisymmetric_stiffness(X, T, E, nu)
    q, (mu, lam) = quadrature(X, T), _lame(E, nu)
    held = np.concatenate([2 * np.flatnonzero(X[:, 0] < 1e-12 * R), 2 * np.flatnonzero(X[:, 1] < 1e-12 * R) + 1])
    surface = np.flatnonzero(np.abs(np.hypot(X[:, 0], X[:, 1]) - R) < 1e-9 * R)
    force, radius, pole_gap, u, iterations = [], [], [], np.zeros(n_dofs), 0
    pole = int(np.argmax(np.where(X[:, 0] < 1e-12 * R, X[:, 1], -np.inf)))

    def internal(u: np.ndarray) -> np.ndarray:
        return K @ u if model == "linear" else corotated_energy_forces(u, T, q, mu, lam, n_dofs)[1]

    for d in at:
        cand = surface[X[surface, 1] > R - 3 * d]
        gap = (R - d) - X[cand, 1]  # u_z <= gap
        active = (gap < 0) if model == "linear" else (u[2 * cand + 1] >= gap)
        for _ in range(50):
            fixed = np.concatenate([held, 2 * cand[active] + 1])
            free = np.setdiff1d(np.arange(n_dofs), fixed)
            step = np.zeros(n_dofs)  # the prescribed change and its linear response (the predictor)
            step[2 * cand[active] + 1] = gap[active] - u[2 * cand[active] + 1]
            lu = spl.splu(K[free][:, free].tocsc())
            u += step
            u[free] -= lu.solve((K @ step)[free])
            for _ in range(50):
                f = internal(u)
                scale = max(np.abs(f[2 * cand[active] + 1]).sum(), 1e-30)
                if np.abs(f[free]).max() <= tol * scale:
                    break
                u[free] += _newton_step(internal, u, f, free, lu, tol)
                iterations += 1
            else:
                raise RuntimeError(f"sphere_between_flats: Newton did not converge at d = {1e3 * d:g} mm "
                                   f"(free force {np.abs(f[free]).max():.3g} N)")
            fz, uz = f[2 * cand + 1], u[2 * cand + 1]
            new = (active & (fz <= 0)) | (~active & (uz > gap + 1e-12 * R))
            if np.array_equal(new, active):
                break
            active = new
        force.append(-float(fz[active].sum()))
        radius.append(float(X[cand[active], 0].max()))
        pole_gap.append(float((R - d) - (X[pole, 1] + u[2 * pole + 1])))
    return {"at": at, "force": np.array(force), "radius": np.array(radius), "pole_gap": np.array(pole_gap),
            "nodes": len(X), "iterations": iterations}
