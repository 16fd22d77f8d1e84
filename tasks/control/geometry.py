"""Procedural signed-distance shapes for the eight squeezable objects (numpy, vectorised, SI metres).

Every shape is a closed solid given by an implicit function ``f(p)`` (m) that is negative inside, zero on the
surface and positive outside; for the primitives it is the exact or a close approximation of the Euclidean
signed distance (Hart 1996, "Sphere tracing"; Quilez, "distance functions" catalogue), for the blended shapes
the polynomial smooth minimum of Quilez ("smooth minimum", k = blend radius in m).  The shape's axis-aligned
bounding box is ``[-size/2, size/2]`` (centred at the origin, z up) for every kind.

Kinds (``GeometryConfig.kind``):

* ``can``      cylinder with rounded rims (rim radius 12 % of the radius) and a recessed lid (a beverage can).
* ``cup``      paper cup: conical frustum, open top, closed bottom; bottom radius = 0.6875 x top radius
               (55 / 80 mm, a standard 8 oz cup; the schema has no taper field).  Its surface is the open
               sheet (side + bottom), the thin wall lies on it (mid-surface), see :attr:`Shape.open_top`.
* ``sphere``   radius ``size/2`` (unequal size components make it an ellipsoid).
* ``ellipsoid`` semi-axes ``size/2`` (Quilez's first-order distance estimate).
* ``duck``     rubber duck: body ellipsoid (flat bottom) + raised tail + head sphere + flattened bill,
               smooth-min blended, +x is the bill direction.
* ``plush``    sitting teddy bear: body + head + ears + muzzle + arms + legs, smooth-min blended, facing -y.
* ``block``    box with rounded edges (edge radius 12 % of the smallest side), e.g. modelling clay.

The blended shapes are built in a canonical frame of real-world proportions and mapped affinely onto ``size``
(``f(p) = g(p / s) * min(s)``: the zero level set is exact, the distance magnitude is approximate).

Surface sampling is generic: a marching-tetrahedra mesh of the zero level set (Freudenthal/Kuhn 6-tetrahedra
split of each grid cube, Doi & Koide 1991) gives the area, the enclosed volume (divergence theorem) and
area-weighted random samples, which are then projected onto the exact surface by Newton steps
``p <- p - f grad f / |grad f|^2``.  Normals are ``grad f / |grad f|`` by central differences; principal
curvatures are the eigenvalues of the shape operator of an implicit surface, ``P H P / |grad f|`` with
``P = I - n n^T`` and ``H`` the finite-difference Hessian (Goldman 2005, "Curvature formulas for implicit
curves and surfaces"); sign convention: convex = positive (a sphere of radius R has k1 = k2 = 1/R).
"""
from __future__ import annotations

from functools import lru_cache
from typing import Callable

import numpy as np

__all__ = [
    "SHAPE_KINDS", "Shape", "make_shape", "marching_tetrahedra", "smin", "smax",
    "tangent_basis", "CUP_BOTTOM_RATIO", "crossing_triangle_pairs",
]

SHAPE_KINDS = ("can", "cup", "sphere", "ellipsoid", "duck", "plush", "block")
CUP_BOTTOM_RATIO = 0.055 / 0.080  # 1, bottom / top radius of a standard paper cup
MESH_CELLS = 64  # marching-tetrahedra cells along the longest bbox side


# ----------------------------------------------------------------------------------------------- primitives
def _norm(v: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (of length 3)."""
    return np.sqrt(v[..., 0] ** 2 + v[..., 1] ** 2 + v[..., 2] ** 2)


def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum (Quilez): union of two implicit solids blended over ``k`` metres."""
    if k <= 0:
        return np.minimum(a, b)
    h = np.maximum(k - np.abs(a - b), 0.0) / k
    return np.minimum(a, b) - h * h * k * 0.25


def smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth maximum: intersection / subtraction blended over ``k`` metres."""
    return -smin(-a, -b, k)


def _cols(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    p = np.asarray(p, dtype=np.float64)
    return np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]), np.ascontiguousarray(p[:, 2])


def sd_sphere(P, c, r: float) -> np.ndarray:
    """Exact signed distance (m) to a sphere of centre ``c`` and radius ``r`` (m); ``P`` = (x, y, z) columns."""
    x, y, z = P
    return np.sqrt((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2) - r


def sd_ellipsoid(P, c, radii) -> np.ndarray:
    """Signed distance estimate (m) to an axis-aligned ellipsoid, Quilez's ``k0 (k0 - 1) / k1`` (exact on the
    surface and for spheres, first order near it); ``P`` = (x, y, z) columns."""
    x, y, z = P
    a, b, cc = (float(v) for v in radii)
    dx, dy, dz = x - c[0], y - c[1], z - c[2]
    k0 = np.sqrt((dx / a) ** 2 + (dy / b) ** 2 + (dz / cc) ** 2)
    k1 = np.maximum(np.sqrt((dx / (a * a)) ** 2 + (dy / (b * b)) ** 2 + (dz / (cc * cc)) ** 2), 1e-12)
    return k0 * (k0 - 1.0) / k1


def sd_capsule(P, a, b, r: float) -> np.ndarray:
    """Exact signed distance (m) to a capsule (segment a-b swept by a ball of radius r)."""
    x, y, z = P
    ax, ay, az = (float(v) for v in a)
    bax, bay, baz = b[0] - ax, b[1] - ay, b[2] - az
    pax, pay, paz = x - ax, y - ay, z - az
    h = np.clip((pax * bax + pay * bay + paz * baz) / (bax * bax + bay * bay + baz * baz), 0.0, 1.0)
    return np.sqrt((pax - h * bax) ** 2 + (pay - h * bay) ** 2 + (paz - h * baz) ** 2) - r


def sd_round_box(P, half, r: float) -> np.ndarray:
    """Exact signed distance (m) to a box of half extents ``half`` whose edges are rounded with radius r."""
    qx, qy, qz = (np.abs(P[i]) - (half[i] - r) for i in range(3))
    outside = np.sqrt(np.maximum(qx, 0) ** 2 + np.maximum(qy, 0) ** 2 + np.maximum(qz, 0) ** 2)
    return outside + np.minimum(np.maximum(np.maximum(qx, qy), qz), 0.0) - r


def sd_polygon_2d(q: np.ndarray, verts) -> np.ndarray:
    """Exact signed distance (m) from 2-D points ``q`` (N, 2) to a closed simple polygon (Quilez sdPolygon)."""
    v = np.asarray(verts, float)
    d = np.sum((q - v[0]) ** 2, axis=1)
    s = np.ones(len(q))
    n = len(v)
    for i in range(n):
        a, b = v[i - 1], v[i]  # edge from v[i-1] to v[i]
        e = a - b
        w = q - b
        t = np.clip((w @ e) / (e @ e), 0.0, 1.0)
        dd = w - t[:, None] * e
        d = np.minimum(d, np.sum(dd * dd, axis=1))
        c1 = q[:, 1] >= b[1]
        c2 = q[:, 1] < a[1]
        c3 = e[0] * w[:, 1] > e[1] * w[:, 0]
        flip = (c1 & c2 & c3) | (~c1 & ~c2 & ~c3)
        s = np.where(flip, -s, s)
    return s * np.sqrt(d)


def dist_polyline_2d(q: np.ndarray, verts) -> np.ndarray:
    """Unsigned distance (m) from 2-D points to an open polyline."""
    v = np.asarray(verts, float)
    d = np.full(len(q), np.inf)
    for a, b in zip(v[:-1], v[1:]):
        e = b - a
        w = q - a
        t = np.clip((w @ e) / (e @ e), 0.0, 1.0)
        d = np.minimum(d, np.hypot(*(w - t[:, None] * e).T))
    return d


def tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (u, v) with (u, v, n) right-handed, chosen deterministically from n (N, 3)."""
    a = np.where((np.abs(n[:, 0]) < 0.9)[:, None], np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    u = a - np.sum(a * n, axis=1, keepdims=True) * n
    u /= _norm(u)[:, None]
    v = np.cross(n, u)
    return u, v


# ----------------------------------------------------------------------------------------------- meshing
# Freudenthal split of the unit cube into 6 tetrahedra along the 0-7 diagonal; corner id = dx + 2 dy + 4 dz.
_TETS = np.array([[0, 1, 3, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 6, 7], [0, 4, 5, 7], [0, 1, 5, 7]])
_CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)])


def marching_tetrahedra(values: np.ndarray, origin, h: float, level: float = 0.0) -> np.ndarray:
    """Triangle soup (T, 3, 3) of the ``level`` set of a sampled scalar field, outward = towards larger values.

    ``values[i, j, k]`` is the field at ``origin + h * (i, j, k)``.  Each grid cube is split into six
    tetrahedra (consistent across cubes), each tetrahedron crossing the level contributes one triangle or a
    quad (two triangles) with vertices interpolated linearly on its edges (Doi & Koide 1991).  Triangles are
    oriented so that their normal points to increasing values, so for a signed distance the soup is a closed,
    outward-oriented surface whose signed volume is the enclosed volume.
    """
    g = np.asarray(values, dtype=np.float64) - level
    origin = np.asarray(origin, dtype=np.float64)
    nx, ny, nz = g.shape
    neg = g < 0
    views = [neg[dx:nx - 1 + dx, dy:ny - 1 + dy, dz:nz - 1 + dz] for dx, dy, dz in _CORNERS]
    any_neg = np.logical_or.reduce(views)
    all_neg = np.logical_and.reduce(views)
    ii, jj, kk = np.nonzero(any_neg & ~all_neg)
    if ii.size == 0:
        return np.zeros((0, 3, 3))
    # corner values and positions of the active cubes, then of their six tetrahedra
    cidx = np.stack([ii, jj, kk], axis=1)
    cpos = cidx[:, None, :] + _CORNERS[None, :, :]  # (C, 8, 3)
    cval = g[cpos[..., 0], cpos[..., 1], cpos[..., 2]]  # (C, 8)
    tv = cval[:, _TETS].reshape(-1, 4)  # (C*6, 4)
    tpos = cpos[:, _TETS].reshape(-1, 4, 3)
    code = (tv[:, 0] < 0) * 1 + (tv[:, 1] < 0) * 2 + (tv[:, 2] < 0) * 4 + (tv[:, 3] < 0) * 8
    active = (code > 0) & (code < 15)
    tv, tpos, code = tv[active], tpos[active], code[active]
    tx = origin + h * tpos.astype(np.float64)
    out = []
    for c in range(1, 15):
        sel = np.nonzero(code == c)[0]
        if sel.size == 0:
            continue
        ins = [b for b in range(4) if (c >> b) & 1]
        outs = [b for b in range(4) if not (c >> b) & 1]
        v = tv[sel]
        x = tx[sel]

        def cut(a: int, b: int) -> np.ndarray:
            t = v[:, a] / (v[:, a] - v[:, b])
            return x[:, a] + t[:, None] * (x[:, b] - x[:, a])

        # direction from the negative to the positive vertices: the outward side
        up = x[:, outs].mean(axis=1) - x[:, ins].mean(axis=1)
        if len(ins) == 1 or len(outs) == 1:
            lone, others = (ins[0], outs) if len(ins) == 1 else (outs[0], ins)
            tris = [np.stack([cut(lone, o) for o in others], axis=1)]
        else:
            a, b = ins
            c_, d = outs
            p_ac, p_ad, p_bd, p_bc = cut(a, c_), cut(a, d), cut(b, d), cut(b, c_)
            tris = [np.stack([p_ac, p_ad, p_bd], axis=1), np.stack([p_ac, p_bd, p_bc], axis=1)]
        for tri in tris:
            nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            flip = np.einsum("ij,ij->i", nrm, up) < 0
            tri[flip] = tri[flip][:, [0, 2, 1]]
            out.append(tri)
    return np.concatenate(out)


def soup_area(tris: np.ndarray) -> np.ndarray:
    """Per-triangle area (m^2) of a triangle soup."""
    return 0.5 * _norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]))


def soup_volume(tris: np.ndarray) -> float:
    """Enclosed volume (m^3) of a closed, outward-oriented triangle soup (divergence theorem)."""
    return float(np.sum(np.einsum("ij,ij->i", tris[:, 0], np.cross(tris[:, 1], tris[:, 2]))) / 6.0)


def crossing_triangle_pairs(vertices, faces, limit: int = 1000) -> np.ndarray:
    """Pairs ``(i, j)`` (i < j) of faces of a triangle mesh that pass through each other: a self-intersection.

    Two non-coplanar triangles cross exactly when an edge of one passes through the other, so the test is:
    every pair of faces that share no vertex and whose bounding boxes overlap (found on a uniform grid of about
    the median face size; each face is binned into the cells its box touches) has each of its six edges
    intersected with the other face (Moller-Trumbore, strict: touching at a vertex or along an edge is not a
    crossing).  Approximate on purpose: two coplanar overlapping faces and a fold between faces that share a
    vertex are not reported.  Returns the first ``limit`` or more pairs found (int64, shape (k, 2), sorted);
    1-3 s per 100 000 faces on a 2-core machine.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if len(f) < 2:
        return np.zeros((0, 2), np.int64)
    tri = v[f]  # (F, 3, 3)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    scale = float(np.max(hi.max(axis=0) - lo.min(axis=0))) or 1.0
    h = max(float(np.median(np.max(hi - lo, axis=1))), 1e-9 * scale)
    origin = lo.min(axis=0)
    # cells per face; a few very large faces would flood the grid: coarsen until entries stay ~linear in F
    while True:
        c0 = np.floor((lo - origin) / h).astype(np.int64)
        c1 = np.floor((hi - origin) / h).astype(np.int64)
        span = c1 - c0 + 1
        count = np.prod(span, axis=1)
        if count.sum() <= 16 * len(f) + 4096:
            break
        h *= 2.0
    dims = c1.max(axis=0) + 1
    face_of = np.repeat(np.arange(len(f)), count)
    local = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    sy, sz = span[face_of, 1], span[face_of, 2]
    cell = c0[face_of] + np.stack([local // (sy * sz), (local // sz) % sy, local % sz], axis=1)
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    key, face_of = key[order], face_of[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    sizes = np.diff(np.r_[starts, len(key)])
    after = np.repeat(starts + sizes, sizes) - np.arange(len(key)) - 1  # entries after each in its cell
    found: list[np.ndarray] = []
    idx, d = np.flatnonzero(after > 0), 1
    while idx.size and sum(len(x) for x in found) < limit:  # entry k pairs with entry k + d of its cell
        for chunk in range(0, idx.size, 1 << 20):
            k = idx[chunk:chunk + (1 << 20)]
            a, b = face_of[k], face_of[k + d]
            i, j = np.minimum(a, b), np.maximum(a, b)  # a pair sharing several cells is tested once per cell
            ok = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
            ok &= ~(f[i][:, :, None] == f[j][:, None, :]).any(axis=(1, 2))
            i, j = i[ok], j[ok]
            hit = _edges_cross(tri[i], tri[j]) | _edges_cross(tri[j], tri[i])
            if hit.any():
                found.append(np.stack([i[hit], j[hit]], axis=1))
        idx, d = idx[after[idx] > d], d + 1
    if not found:
        return np.zeros((0, 2), np.int64)
    return np.unique(np.concatenate(found), axis=0)


def _edges_cross(a: np.ndarray, b: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """(N,) whether one of the three edges of triangle ``a[n]`` passes through the interior of ``b[n]``."""
    e1, e2 = b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]
    hit = np.zeros(len(a), bool)
    for s, t in ((0, 1), (1, 2), (2, 0)):
        p0, d = a[:, s], a[:, t] - a[:, s]
        pvec = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, pvec)
        ok = np.abs(det) > 1e-12 * _norm(e1) * _norm(e2) * _norm(d)  # not parallel to the plane
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = p0 - b[:, 0]
        u = np.einsum("ij,ij->i", tvec, pvec) * inv
        qvec = np.cross(tvec, e1)
        w = np.einsum("ij,ij->i", d, qvec) * inv
        along = np.einsum("ij,ij->i", e2, qvec) * inv
        hit |= ok & (u > eps) & (w > eps) & (u + w < 1 - eps) & (along > eps) & (along < 1 - eps)
    return hit


# ----------------------------------------------------------------------------------------------- shape base
class Shape:
    """A closed implicit solid with bounding box ``[-size/2, size/2]``.

    Subclasses implement :meth:`sdf`.  ``open_top`` marks a shape whose *surface* is an open sheet (the cup):
    its samples, area and wall refer to the sheet (side + bottom), while :meth:`sdf` is the closed solid the
    sheet bounds (used for the enclosed volume, the cavity and outward orientation).
    """

    kind = "shape"
    open_top = False

    def __init__(self, size) -> None:
        self.size = np.asarray(size, dtype=np.float64).reshape(3)
        if np.any(~np.isfinite(self.size)) or np.any(self.size <= 0):
            raise ValueError(f"geometry.size must be three positive lengths in m, got {self.size.tolist()}")
        self.bbox_min = -self.size / 2
        self.bbox_max = self.size / 2
        self.scale_len = float(self.size.max())
        self._grid_cache: tuple | None = None
        self._mesh_cache: dict[float, np.ndarray] = {}
        self._area_cache: np.ndarray | None = None

    # -- to implement
    def sdf(self, p: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """Signed distance (m) of points ``p`` (N, 3): < 0 inside the closed body."""
        raise NotImplementedError

    def regions(self, p: np.ndarray) -> dict[str, np.ndarray]:
        """Named boolean masks of recognisable parts (bill, ears, eyes ...) for the colouring; default none."""
        return {}

    def open_distance(self, p: np.ndarray) -> np.ndarray:
        """Unsigned distance (m) to the open surface sheet (only for ``open_top`` shapes)."""
        return np.abs(self.sdf(p))

    # -- differential geometry
    @property
    def fd_step(self) -> float:
        """Finite-difference step (m) for gradients and Hessians."""
        return 1e-4 * self.scale_len

    def gradient(self, p: np.ndarray, eps: float | None = None) -> np.ndarray:
        """Central-difference gradient of :meth:`sdf` (1), shape (N, 3)."""
        p = np.asarray(p, dtype=np.float64)
        e = self.fd_step if eps is None else eps
        n = len(p)
        stencil = np.concatenate([p + d for d in (np.eye(3) * e)] + [p - d for d in (np.eye(3) * e)])
        f = self.sdf(stencil).reshape(6, n)
        return ((f[:3] - f[3:]) / (2 * e)).T

    def normals(self, p: np.ndarray) -> np.ndarray:
        """Outward unit normals ``grad f / |grad f|`` (1), (N, 3); +z where the gradient vanishes."""
        g = self.gradient(p)
        ln = _norm(g)
        out = np.tile([0.0, 0.0, 1.0], (len(p), 1))
        ok = ln > 1e-9
        out[ok] = g[ok] / ln[ok, None]
        return out

    def project(self, p: np.ndarray, iters: int = 3) -> np.ndarray:
        """Newton projection onto the zero level set: ``p <- p - f grad f / |grad f|^2``."""
        p = np.array(p, dtype=np.float64)
        for _ in range(iters):
            f = self.sdf(p)
            g = self.gradient(p)
            g2 = np.maximum(np.sum(g * g, axis=1), 1e-12)
            p -= (f / g2)[:, None] * g
        return p

    def curvature(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Principal curvatures (N, 2) 1/m (k1 >= k2, convex positive), their unit directions (N, 2, 3) and the
        outward normals (N, 3) at surface points, from the shape operator ``P H P / |grad f|`` of the implicit
        function (Goldman 2005) with a finite-difference Hessian (step 1e-4 x the bbox's longest side)."""
        p = np.asarray(p, dtype=np.float64)
        n_pts = len(p)
        e = self.fd_step
        offs = [np.zeros(3)]
        I = np.eye(3)
        for i in range(3):
            offs += [I[i] * e, -I[i] * e]
        pairs = [(0, 1), (0, 2), (1, 2)]
        for i, j in pairs:
            offs += [(I[i] + I[j]) * e, (I[i] - I[j]) * e, (-I[i] + I[j]) * e, (-I[i] - I[j]) * e]
        f = self.sdf(np.concatenate([p + o for o in offs])).reshape(len(offs), n_pts)
        f0 = f[0]
        g = np.stack([(f[1 + 2 * i] - f[2 + 2 * i]) / (2 * e) for i in range(3)], axis=1)
        H = np.zeros((n_pts, 3, 3))
        for i in range(3):
            H[:, i, i] = (f[1 + 2 * i] - 2 * f0 + f[2 + 2 * i]) / (e * e)
        for m, (i, j) in enumerate(pairs):
            b = 7 + 4 * m
            hij = (f[b] - f[b + 1] - f[b + 2] + f[b + 3]) / (4 * e * e)
            H[:, i, j] = H[:, j, i] = hij
        gl = np.maximum(_norm(g), 1e-12)
        nrm = g / gl[:, None]
        u, v = tangent_basis(nrm)
        B = np.stack([u, v], axis=2)  # (N, 3, 2)
        S = np.einsum("nia,nij,njb->nab", B, H, B) / gl[:, None, None]
        S = 0.5 * (S + np.transpose(S, (0, 2, 1)))
        w, vec = np.linalg.eigh(S)  # ascending
        k = w[:, ::-1]
        d1 = np.einsum("nia,na->ni", B, vec[:, :, 1])
        d1 /= _norm(d1)[:, None]
        d2 = np.cross(nrm, d1)
        return k, np.stack([d1, d2], axis=1), nrm

    # -- meshing, sampling, measures
    def _grid(self) -> tuple[np.ndarray, float, np.ndarray]:
        if self._grid_cache is None:
            h = self.scale_len / MESH_CELLS
            lo = self.bbox_min - 3 * h
            counts = np.ceil((self.size + 6 * h) / h).astype(int) + 1
            axes = [lo[i] + h * np.arange(counts[i]) for i in range(3)]
            X, Y, Z = np.meshgrid(*axes, indexing="ij")
            vals = self.sdf(np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)).reshape(X.shape)
            self._grid_cache = (lo, h, vals)
        return self._grid_cache

    def mesh(self, level: float = 0.0) -> np.ndarray:
        """Marching-tetrahedra triangle soup (T, 3, 3) m of the ``level`` set (closed solid, outward)."""
        key = float(level)
        if key not in self._mesh_cache:
            lo, h, vals = self._grid()
            self._mesh_cache[key] = marching_tetrahedra(vals, lo, h, level)
        return self._mesh_cache[key]

    def volume_below(self, level: float = 0.0) -> float:
        """Volume (m^3) of ``{f < level}`` from the marching-tetrahedra mesh."""
        tris = self.mesh(level)
        return soup_volume(tris) if len(tris) else 0.0

    def enclosed_volume(self) -> float:
        """Volume (m^3) enclosed by the outer surface (for the cup: the frustum it bounds)."""
        return self.volume_below(0.0)

    def triangle_areas(self) -> np.ndarray:
        """Per-triangle areas (m^2) of the zero-level marching-tetrahedra mesh (cached)."""
        if self._area_cache is None:
            self._area_cache = soup_area(self.mesh(0.0))
        return self._area_cache

    def surface_area(self) -> float:
        """Total area (m^2) of the surface (for the cup: the open sheet)."""
        return float(self.triangle_areas().sum())

    def sample_surface(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` i.i.d. area-uniform random points on the surface (N, 3) m: area-weighted triangles of the
        marching-tetrahedra mesh, uniform barycentric points, Newton-projected onto the exact surface."""
        tris = self.mesh(0.0)
        area = self.triangle_areas()
        idx = rng.choice(len(tris), size=n, p=area / area.sum())
        r1, r2 = rng.random(n), rng.random(n)
        s = np.sqrt(r1)
        t = tris[idx]
        pts = (1 - s)[:, None] * t[:, 0] + (s * (1 - r2))[:, None] * t[:, 1] + (s * r2)[:, None] * t[:, 2]
        return self.project(pts)


# ----------------------------------------------------------------------------------------------- kinds
class Sphere(Shape):
    kind = "sphere"

    def __init__(self, size) -> None:
        super().__init__(size)
        self.radius = float(self.size[0] / 2)

    def sdf(self, p):
        return sd_sphere(_cols(p), (0.0, 0.0, 0.0), self.radius)

    def curvature(self, p):
        """Analytic: k1 = k2 = 1/R."""
        nrm = np.asarray(p, float) / np.maximum(_norm(p), 1e-12)[:, None]
        u, v = tangent_basis(nrm)
        k = np.full((len(p), 2), 1.0 / self.radius)
        return k, np.stack([u, v], axis=1), nrm

    def surface_area(self):
        return 4 * np.pi * self.radius ** 2

    def enclosed_volume(self):
        return 4 / 3 * np.pi * self.radius ** 3

    def volume_below(self, level=0.0):
        r = max(self.radius + level, 0.0)
        return 4 / 3 * np.pi * r ** 3

    def sample_surface(self, n, rng):
        d = rng.normal(size=(n, 3))
        return self.radius * d / _norm(d)[:, None]


class Ellipsoid(Shape):
    kind = "ellipsoid"

    def __init__(self, size) -> None:
        super().__init__(size)
        self.radii = self.size / 2

    def sdf(self, p):
        return sd_ellipsoid(_cols(p), (0.0, 0.0, 0.0), self.radii)


def _revolve(p: np.ndarray, yscale: float) -> np.ndarray:
    """(r, z) of points for a solid of revolution about z whose cross-section is stretched in y by yscale."""
    return np.stack([np.sqrt(p[:, 0] ** 2 + (p[:, 1] / yscale) ** 2), p[:, 2]], axis=1)


class Can(Shape):
    """Beverage can: rounded cylinder (rim radius ``0.12 R``) with a recessed lid (depth 2.5 % of H, inset to
    ``0.80 R``) blended with a 1.5 mm smooth maximum."""

    kind = "can"

    def __init__(self, size) -> None:
        super().__init__(size)
        self.R = float(self.size[0] / 2)
        self.H = float(self.size[2])
        self.yscale = float(self.size[1] / self.size[0])
        self.rim = 0.12 * self.R
        self.lid_r = 0.80 * self.R
        self.lid_depth = 0.025 * self.H
        self.blend = min(0.0015, 0.3 * self.rim)

    def sdf(self, p):
        q = _revolve(p, self.yscale)
        r, z = q[:, 0], q[:, 1]
        dx = r - (self.R - self.rim)
        dz = np.abs(z) - (self.H / 2 - self.rim)
        body = np.minimum(np.maximum(dx, dz), 0.0) + np.sqrt(np.maximum(dx, 0) ** 2 + np.maximum(dz, 0) ** 2) - self.rim
        # recess region {r < lid_r, z > H/2 - depth}: its signed distance, subtracted from the body
        ax = r - self.lid_r
        az = (self.H / 2 - self.lid_depth) - z
        recess = np.minimum(np.maximum(ax, az), 0.0) + np.sqrt(np.maximum(ax, 0) ** 2 + np.maximum(az, 0) ** 2)
        return smax(body, -recess, self.blend)

    def regions(self, p):
        z = p[:, 2] / (self.H / 2)
        return {"top": z > 1 - 2.4 * self.rim / self.H - 0.02, "bottom": z < -1 + 2.0 * self.rim / self.H + 0.02}


class Cup(Shape):
    """Paper cup: conical frustum (top radius ``size_x/2``, bottom ``CUP_BOTTOM_RATIO`` x that), open top.
    The surface is the sheet made of the conical side and the bottom disk; its area and samples are analytic."""

    kind = "cup"
    open_top = True

    def __init__(self, size) -> None:
        super().__init__(size)
        self.rt = float(self.size[0] / 2)
        self.rb = CUP_BOTTOM_RATIO * self.rt
        self.H = float(self.size[2])
        self.yscale = float(self.size[1] / self.size[0])
        zb, zt = -self.H / 2, self.H / 2
        self.poly = [(0.0, zb), (self.rb, zb), (self.rt, zt), (0.0, zt)]
        self.sheet = [(0.0, zb), (self.rb, zb), (self.rt, zt)]
        self.slant = float(np.hypot(self.rt - self.rb, self.H))

    def sdf(self, p):
        return sd_polygon_2d(_revolve(p, self.yscale), self.poly)

    def open_distance(self, p):
        return dist_polyline_2d(_revolve(p, self.yscale), self.sheet)

    def _areas(self) -> tuple[float, float]:
        side = np.pi * (self.rb + self.rt) * self.slant * self.yscale_factor
        bottom = np.pi * self.rb ** 2 * self.yscale
        return float(side), float(bottom)

    @property
    def yscale_factor(self) -> float:
        # lateral area of an elliptic frustum ~ circular area x mean of the semi-axes ratio (exact for yscale 1)
        return 0.5 * (1 + self.yscale)

    def surface_area(self):
        return sum(self._areas())

    def enclosed_volume(self):
        return float(np.pi * self.H / 3 * (self.rb ** 2 + self.rb * self.rt + self.rt ** 2) * self.yscale)

    def volume_below(self, level=0.0):
        if level == 0.0:
            return self.enclosed_volume()
        return super().volume_below(level)

    def sample_surface(self, n, rng):
        side, bottom = self._areas()
        on_side = rng.random(n) < side / (side + bottom)
        u = rng.random(n)
        th = rng.random(n) * 2 * np.pi
        # side: area element ~ r ds dtheta with r linear in s  ->  r^2 uniform between rb^2 and rt^2
        r_side = np.sqrt(self.rb ** 2 + u * (self.rt ** 2 - self.rb ** 2))
        z_side = -self.H / 2 + (r_side - self.rb) / (self.rt - self.rb) * self.H
        r_bot = self.rb * np.sqrt(u)
        r = np.where(on_side, r_side, r_bot)
        z = np.where(on_side, z_side, -self.H / 2)
        return np.stack([r * np.cos(th), r * np.sin(th) * self.yscale, z], axis=1)

    def _on_bottom(self, p: np.ndarray) -> np.ndarray:
        """True where the nearest part of the sheet is the bottom disk (else the conical side)."""
        q = _revolve(p, self.yscale)
        zb = -self.H / 2
        d_bot = np.hypot(np.maximum(q[:, 0] - self.rb, 0.0), q[:, 1] - zb)
        d_side = dist_polyline_2d(q, self.sheet[1:])
        return d_bot < d_side

    def curvature(self, p):
        """Analytic: the side is developable (k = 0 along the generator, cos(alpha) / r around it with alpha the
        cone half-angle), the bottom is flat; outward = away from the axis / downwards (y stretch ignored)."""
        p = np.asarray(p, float)
        r = np.maximum(np.sqrt(p[:, 0] ** 2 + (p[:, 1] / self.yscale) ** 2), 1e-9)
        on_bottom = self._on_bottom(p)
        alpha = np.arctan2(self.rt - self.rb, self.H)  # cone half-angle
        cx, cy = p[:, 0] / r, p[:, 1] / r
        axial = r < 1e-8
        cx, cy = np.where(axial, 1.0, cx), np.where(axial, 0.0, cy)
        nrm_side = np.stack([np.cos(alpha) * cx, np.cos(alpha) * cy, -np.sin(alpha) * np.ones_like(r)], axis=1)
        nrm = np.where(on_bottom[:, None], np.array([0.0, 0.0, -1.0]), nrm_side)
        nrm /= _norm(nrm)[:, None]
        circ = np.stack([-cy, cx, np.zeros_like(r)], axis=1)
        u, _ = tangent_basis(nrm)
        d1 = np.where(on_bottom[:, None], u, circ)
        d2 = np.cross(nrm, d1)
        k_circ = np.cos(alpha) / r
        k = np.where(on_bottom[:, None], 0.0, np.stack([k_circ, np.zeros_like(r)], axis=1))
        return k, np.stack([d1, d2], axis=1), nrm

    def normals(self, p):
        return self.curvature(p)[2] if len(p) else np.zeros((0, 3))

    def regions(self, p):
        return {}


class Block(Shape):
    kind = "block"

    def __init__(self, size) -> None:
        super().__init__(size)
        self.round = 0.12 * float(self.size.min())

    def sdf(self, p):
        return sd_round_box(_cols(p), self.size / 2, self.round)


class _Fitted(Shape):
    """A blended shape defined in a canonical frame (:meth:`canon_sdf`) and mapped onto ``size``."""

    def __init__(self, size) -> None:
        super().__init__(size)
        lo, hi = _canonical_bbox(type(self))
        self.c_lo, self.c_hi = lo, hi
        self.scale = self.size / (hi - lo)
        self.c_mid = 0.5 * (lo + hi)

    def to_canon(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, float) / self.scale + self.c_mid

    def sdf(self, p):
        return self.canon_sdf(self.to_canon(p)) * float(self.scale.min())

    @classmethod
    def canon_parts(cls, q: np.ndarray) -> dict[str, np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def canon_sdf(cls, q: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    CANON_EXTENT = 0.25  # m, a cube centred at the origin that contains the canonical shape


@lru_cache(maxsize=None)
def _canonical_bbox(cls: type) -> tuple[np.ndarray, np.ndarray]:
    """Tight bbox (m) of a canonical blended shape: marching tetrahedra at 2 mm, then the extreme vertices are
    moved along the surface towards each axis direction (projected ascent + Newton projection)."""
    ext, h = cls.CANON_EXTENT, 0.005
    ax = np.arange(-ext / 2, ext / 2 + h, h)
    X, Y, Z = np.meshgrid(ax, ax, ax, indexing="ij")
    vals = cls.canon_sdf(np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)).reshape(X.shape)
    v = marching_tetrahedra(vals, np.full(3, -ext / 2), h, 0.0).reshape(-1, 3)

    def project(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        e = 1e-6
        for _ in range(3):
            f = cls.canon_sdf(q)
            g = np.stack([(cls.canon_sdf(q + d) - cls.canon_sdf(q - d)) / (2 * e) for d in np.eye(3) * e], axis=1)
            q = q - (f / np.maximum(np.sum(g * g, axis=1), 1e-12))[:, None] * g
        return q, g / np.maximum(_norm(g), 1e-12)[:, None]

    lo, hi = v.min(0), v.max(0)
    dirs = np.concatenate([np.eye(3), -np.eye(3)])  # +x +y +z -x -y -z
    sel = [np.argsort(-(v @ d))[:16] for d in dirs]
    q = v[np.concatenate(sel)]
    e_dir = np.repeat(dirs, 16, axis=0)
    for it in range(16):
        q, n = project(q)
        t = e_dir - np.sum(n * e_dir, axis=1, keepdims=True) * n
        q = q + 0.3 * h * (0.8 ** it) * t
    q, _ = project(q)
    best = np.array([(q[i * 16:(i + 1) * 16] @ d).max() for i, d in enumerate(dirs)])
    hi = np.maximum(hi, best[:3])
    lo = np.minimum(lo, -best[3:])
    return lo, hi


class Duck(_Fitted):
    """Rubber duck (canonical 109 x 66 x 84 mm, +x = bill direction, z up): body ellipsoid with a flat
    bottom, raised tail, head sphere and a flattened bill, smooth-min blended."""

    kind = "duck"
    CANON_EXTENT = 0.15
    HEAD_C = np.array([0.018, 0.0, 0.030])
    HEAD_R = 0.021
    EYE_DIRS = np.array([[0.55, 0.62, 0.50], [0.55, -0.62, 0.50]])

    @classmethod
    def canon_parts(cls, q):
        P = _cols(q)
        body = smax(sd_ellipsoid(P, (-0.005, 0.0, -0.012), (0.043, 0.033, 0.027)), -(P[2] + 0.033), 0.004)
        return {
            "body": body,
            "tail": sd_ellipsoid(P, (-0.041, 0.0, 0.003), (0.013, 0.015, 0.012)),
            "head": sd_sphere(P, cls.HEAD_C, cls.HEAD_R),
            "bill": sd_ellipsoid(P, (0.041, 0.0, 0.024), (0.014, 0.012, 0.0055)),
        }

    @classmethod
    def canon_sdf(cls, q):
        p = cls.canon_parts(q)
        d = smin(p["body"], p["tail"], 0.010)
        d = smin(d, p["head"], 0.008)
        return smin(d, p["bill"], 0.003)

    def regions(self, p):
        q = self.to_canon(p)
        parts = self.canon_parts(q)
        eyes = np.zeros(len(q), bool)
        for d in self.EYE_DIRS:
            c = self.HEAD_C + self.HEAD_R * d / np.linalg.norm(d)
            eyes |= _norm(q - c) < 0.0042
        return {"bill": parts["bill"] < np.minimum(parts["head"], parts["body"]) - 0.0005, "eyes": eyes}


class Plush(_Fitted):
    """Sitting teddy bear (canonical 150 x 116 x 184 mm, facing -y, z up): body, head, ears, muzzle, arms and
    legs (capsules), smooth-min blended.  It sits as a teddy bear does: its seat (the body cut flat at ``SEAT_Z``)
    and the backs of its outstretched legs rest on one plane, under its centre of mass.  (Before 2026-12-06 its legs
    sloped down to its feet, 20 mm below its seat: it stood on its two feet with its centre of mass 45 mm behind
    them, held up only by the grid-node table's halo; docs/limits/table-contact.md.)"""

    kind = "plush"
    SEAT_Z = -0.072  # m, canonical: the plane the seat and the backs of the legs rest on
    HEAD_C = np.array([0.0, 0.0, 0.058])
    HEAD_R = 0.042

    @classmethod
    def canon_parts(cls, q):
        P = _cols(q)
        M = (np.abs(P[0]), P[1], P[2])  # mirror-symmetric parts (ears, arms, legs) use |x|
        return {
            "body": smax(sd_ellipsoid(P, (0.0, 0.0, -0.020), (0.048, 0.042, 0.058)), -(P[2] - cls.SEAT_Z), 0.006),
            "head": sd_sphere(P, cls.HEAD_C, cls.HEAD_R),
            "ears": sd_ellipsoid(M, (0.034, 0.004, 0.094), (0.017, 0.009, 0.017)),
            "muzzle": sd_ellipsoid(P, (0.0, -0.036, 0.046), (0.018, 0.014, 0.013)),
            "arms": sd_capsule(M, (0.038, -0.005, 0.012), (0.060, -0.024, -0.030), 0.015),
            "legs": sd_capsule(M, (0.026, -0.012, cls.SEAT_Z + 0.018), (0.032, -0.056, cls.SEAT_Z + 0.018), 0.018),
        }

    @classmethod
    def canon_sdf(cls, q):
        p = cls.canon_parts(q)
        d = smin(p["body"], p["head"], 0.012)
        d = smin(d, p["arms"], 0.010)
        d = smin(d, p["legs"], 0.010)
        d = smin(d, p["ears"], 0.005)
        return smin(d, p["muzzle"], 0.006)

    def regions(self, p):
        q = self.to_canon(p)
        parts = self.canon_parts(q)
        others = np.minimum(parts["head"], parts["body"])
        eyes = np.zeros(len(q), bool)
        for sx in (1, -1):
            d = np.array([0.36 * sx, -0.80, 0.40])
            c = self.HEAD_C + self.HEAD_R * d / np.linalg.norm(d)
            eyes |= _norm(q - c) < 0.0055
        nose = _norm(q - np.array([0.0, -0.049, 0.051])) < 0.0065
        return {
            "ears": parts["ears"] < others - 0.001,
            "muzzle": parts["muzzle"] < others - 0.001,
            "paws": (parts["legs"] < others - 0.001) & (q[:, 1] < -0.058),
            "eyes": eyes,
            "nose": nose,
        }


_KINDS: dict[str, Callable[..., Shape]] = {
    "can": Can, "cup": Cup, "ellipsoid": Ellipsoid, "duck": Duck, "plush": Plush, "block": Block,
}


def make_shape(kind: str, size) -> Shape:
    """The procedural shape ``kind`` (one of :data:`SHAPE_KINDS`) with bounding box ``size`` (m)."""
    if kind == "sphere":
        s = np.asarray(size, float).reshape(3)
        return Sphere(s) if np.ptp(s) <= 1e-9 * s.max() else Ellipsoid(s)
    if kind not in _KINDS:
        raise ValueError(f"geometry.kind {kind!r} is unknown: use one of {list(SHAPE_KINDS)} or 'ply' / 'mesh'")
    return _KINDS[kind](size)
