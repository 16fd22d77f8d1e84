"""Finite-sphere reference for the Hertz case: a linear-elastic sphere between two frictionless rigid flats by
axisymmetric finite elements (small strain; 6-node triangles, 7-point Gauss rule; active-set Signorini contact).

Hertz's F = 4/3 E* sqrt(R) d^1.5 treats each contact as a half-space, so its approach d is measured from points at
infinity; in a sphere the approach is measured from the centre, a distance R from the contact, which moves with the
contact by ~ F / (E R).  That shortens d at a given force by a fraction ~ sqrt(d / R) (= a / R): this solver gives
F / F_Hertz - 1 = +2.5 / +4.0 / +8.1 / +11.6 / +14.3 / +16.6 % at d = 0.1 / 0.25 / 1 / 2 / 3 / 4 mm for the issue's
sphere (R = 35 mm, nu = 0.45), i.e. ~0.48 sqrt(d / R), the same at three times the nodes, and tends to Hertz as
d / R -> 0.  At nu = 0 the leading term nearly vanishes and the excess grows faster: -0.3 / +0.1 / +1.4 / +6.6 / +22 %
at d = 0.05 / 0.1 / 0.25 / 1 / 4 mm.  :func:`tasks.verification.contact.hertz_case` is compared with both.

The quarter disk 0 <= r, 0 <= z, r^2 + z^2 <= R^2 is meshed: z = 0 is the equator (a symmetry plane: u_z = 0),
r = 0 the axis (u_r = 0); the flat sits at z = R - d.  Units SI (m, Pa, N).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from scipy.spatial import Delaunay

# 7-point rule on the reference triangle (degree 5; weights include its area 1/2)
_A1, _B1, _A2, _B2 = 0.0597158717, 0.4701420641, 0.7974269853, 0.1012865073
_GP = np.array([[1 / 3, 1 / 3], [_A1, _B1], [_B1, _A1], [_B1, _B1], [_A2, _B2], [_B2, _A2], [_B2, _B2]])
_GW = np.array([0.225] + [0.1323941527] * 3 + [0.1259391805] * 3) / 2


def quarter_disk_mesh(R: float, h_min: float, growth: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """6-node triangles on the quarter disk of radius R (m), graded from the pole (0, R): nodes on arcs about the
    pole with spacing max(h_min, growth * distance) (m), plus the matching boundary nodes on the sphere, the axis
    and the equator; curved-edge midside nodes lie on the sphere.  Returns nodes (n, 2: r, z) and elements (e, 6:
    corners, then the midsides of edges 01, 12, 20)."""
    pole = np.array([0.0, R])
    pts = [pole[None], np.array([[R, 0.0], [0.0, 0.0]])]
    rho = 0.0
    while rho < 2 * R:
        step = max(h_min, growth * rho)
        rho += step
        th = np.linspace(0.0, np.pi, max(4, int(np.ceil(np.pi * rho / step))) + 1)
        P = pole + rho * np.stack([np.sin(th), -np.cos(th)], 1)
        inside = (P[:, 0] > 0.3 * step) & (P[:, 1] > 0.3 * step) & (np.hypot(P[:, 0], P[:, 1]) < R - 0.3 * step)
        pts.append(P[inside])
        phi = 2.0 * np.arcsin(min(rho / (2 * R), 1.0))  # the sphere's point at chord rho from the pole
        if phi <= np.pi / 2:
            pts.append(np.array([[R * np.sin(phi), R * np.cos(phi)]]))
        if rho <= R:
            pts.append(np.array([[0.0, R - rho]]))
        if R <= rho <= np.sqrt(2.0) * R:
            pts.append(np.array([[np.sqrt(rho * rho - R * R), 0.0]]))
    P = np.unique(np.round(np.concatenate(pts), 12), axis=0)
    tri = Delaunay(P).simplices
    tri = tri[np.hypot(*P[tri].mean(1).T) < R]
    on_sphere = np.abs(np.hypot(P[:, 0], P[:, 1]) - R) < 1e-9 * R
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), 1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mid = P[unique].mean(1)
    curved = on_sphere[unique[:, 0]] & on_sphere[unique[:, 1]]
    mid[curved] *= R / np.hypot(mid[curved, 0], mid[curved, 1])[:, None]
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


def axisymmetric_stiffness(X: np.ndarray, T: np.ndarray, E: float, nu: float) -> sp.csr_matrix:
    """Global stiffness (N/m) of the solid of revolution (full 2 pi) of the mesh (X, T): dofs (u_r, u_z) per node;
    strains e_rr, e_zz, e_tt = u_r / r, g_rz; isotropic E (Pa), nu."""
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    D = np.array([[lam + 2 * mu, lam, lam, 0], [lam, lam + 2 * mu, lam, 0], [lam, lam, lam + 2 * mu, 0],
                  [0, 0, 0, mu]])
    xe = X[T]
    Ke = np.zeros((len(T), 12, 12))
    for (xi, eta), w in zip(_GP, _GW):
        N, dN = _shape(xi, eta)
        J = np.einsum("ai,eaj->eij", dN, xe)  # J[i, j] = d x_j / d xi_i
        dNx = np.einsum("ak,ejk->eaj", dN, np.linalg.inv(J))
        r = xe[:, :, 0] @ N
        B = np.zeros((len(T), 4, 12))
        B[:, 0, 0::2] = dNx[:, :, 0]
        B[:, 1, 1::2] = dNx[:, :, 1]
        B[:, 2, 0::2] = N[None] / r[:, None]
        B[:, 3, 0::2] = dNx[:, :, 1]
        B[:, 3, 1::2] = dNx[:, :, 0]
        Ke += np.einsum("eki,kl,elj->eij", B, D, B) * (2 * np.pi * r * np.abs(np.linalg.det(J)) * w)[:, None, None]
    dof = np.stack([2 * T, 2 * T + 1], 2).reshape(len(T), 12)
    return sp.csr_matrix((Ke.ravel(), (np.repeat(dof, 12, 1).ravel(), np.tile(dof, (1, 12)).ravel())),
                         shape=(2 * len(X), 2 * len(X)))


def sphere_between_flats(depths, R: float, E: float, nu: float, h_min: float | None = None,
                         growth: float = 0.05) -> dict:
    """Force (N) on each flat and contact radius (m) of a linear-elastic sphere (radius R, m; E, Pa; nu) whose
    two frictionless flats each approach its centre by d, for each d in ``depths`` (m).  ``h_min`` (m; default
    a / 30 at the smallest depth, a = sqrt(R d)) and ``growth``: mesh spacing at the pole and its growth with
    distance.  Contact by active sets: a sphere node is held at the flat while its reaction pushes, released when
    it pulls, and held when it would cross the flat.  Returns ``at``, ``force``, ``radius`` and ``nodes``."""
    at = np.atleast_1d(np.asarray(depths, float))
    X, T = quarter_disk_mesh(R, h_min or np.sqrt(R * at.min()) / 30, growth)
    K = axisymmetric_stiffness(X, T, E, nu)
    held = np.concatenate([2 * np.flatnonzero(X[:, 0] < 1e-12 * R), 2 * np.flatnonzero(X[:, 1] < 1e-12 * R) + 1])
    surface = np.flatnonzero(np.abs(np.hypot(X[:, 0], X[:, 1]) - R) < 1e-9 * R)
    force, radius = [], []
    for d in at:
        cand = surface[X[surface, 1] > R - 3 * d]
        gap = (R - d) - X[cand, 1]  # u_z <= gap
        active = gap < 0
        for _ in range(50):
            fixed = np.concatenate([held, 2 * cand[active] + 1])
            u = np.zeros(2 * len(X))
            u[fixed[len(held):]] = gap[active]
            free = np.setdiff1d(np.arange(2 * len(X)), fixed)
            u[free] = spl.spsolve(K[free][:, free].tocsc(), -(K[free][:, fixed] @ u[fixed]))
            fz, uz = (K @ u)[2 * cand + 1], u[2 * cand + 1]
            new = (active & (fz <= 0)) | (~active & (uz > gap + 1e-12 * R))
            if np.array_equal(new, active):
                break
            active = new
        force.append(-float(fz[active].sum()))
        radius.append(float(X[cand[active], 0].max()))
    return {"at": at, "force": np.array(force), "radius": np.array(radius), "nodes": len(X)}
