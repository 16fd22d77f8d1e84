"""Grid coordinates and the quadratic B-spline stencil of a point (index safety: a coordinate outside the grid's
safe band is clamped into it and flagged), and the APIC gather / scatter over a stencil.
"""
from __future__ import annotations

import warp as wp

from .structs import KERNEL_OPTIONS, POINT_OUT, G2PResult, GridInfo, Stencil

wp.set_module_options(KERNEL_OPTIONS)


@wp.func
def raise_flag(flags: wp.array(dtype=wp.int32), code: int, substep: int, index: int):
    wp.atomic_add(flags, code, 1)
    wp.atomic_min(flags, 4 + code, substep)
    wp.atomic_max(flags, 8 + code, index)


@wp.func
def clamp_band(g: float, lo_b: float, hi_b: float) -> float:
    """Clamp g into [lo_b, hi_b]; NaN maps to lo_b."""
    if g >= lo_b:
        if g <= hi_b:
            return g
        return hi_b
    return lo_b


@wp.func
def to_grid(x: wp.vec3, gi: GridInfo) -> wp.vec3:
    return (x - gi.lo) * gi.inv_dx


@wp.func
def in_band(g: wp.vec3, gi: GridInfo) -> bool:
    # written so that NaN compares as "outside"
    ok = g[0] >= gi.safe_lo[0] and g[0] <= gi.safe_hi[0]
    ok = ok and g[1] >= gi.safe_lo[1] and g[1] <= gi.safe_hi[1]
    ok = ok and g[2] >= gi.safe_lo[2] and g[2] <= gi.safe_hi[2]
    return ok


@wp.func
def clamp_to_band(g: wp.vec3, gi: GridInfo) -> wp.vec3:
    return wp.vec3(
        clamp_band(g[0], gi.safe_lo[0], gi.safe_hi[0]),
        clamp_band(g[1], gi.safe_lo[1], gi.safe_hi[1]),
        clamp_band(g[2], gi.safe_lo[2], gi.safe_hi[2]),
    )


@wp.func
def checked_grid_coord(xp: wp.vec3, gi: GridInfo, flags: wp.array(dtype=wp.int32), code: int, substep: int,
                       index: int) -> wp.vec3:
    """Grid coordinate of the world point xp (m); outside the safe band it raises flag ``code`` and is clamped."""
    g = to_grid(xp, gi)
    if not in_band(g, gi):
        raise_flag(flags, code, substep, index)
        g = clamp_to_band(g, gi)
    return g


@wp.func
def clamped_grid_coord(xp: wp.vec3, gi: GridInfo) -> wp.vec3:
    """Grid coordinate of xp clamped into the safe band, without a flag (the point was checked earlier)."""
    return clamp_to_band(to_grid(xp, gi), gi)


@wp.func
def bspline_w(f: float) -> wp.vec3:
    """Quadratic B-spline weights of the 3 nodes base, base+1, base+2 for f = g - base in [0.5, 1.5)."""
    a = 1.5 - f
    b = f - 1.0
    c = f - 0.5
    return wp.vec3(0.5 * a * a, 0.75 - b * b, 0.5 * c * c)


@wp.func
def base_index(g: wp.vec3) -> wp.vec3i:
    """Lower stencil node: floor(g - 0.5) (floor, not truncation)."""
    return wp.vec3i(int(wp.floor(g[0] - 0.5)), int(wp.floor(g[1] - 0.5)), int(wp.floor(g[2] - 0.5)))


@wp.func
def frac(g: wp.vec3, b: wp.vec3i) -> wp.vec3:
    return wp.vec3(g[0] - float(b[0]), g[1] - float(b[1]), g[2] - float(b[2]))


@wp.func
def stencil_at(g: wp.vec3) -> Stencil:
    """Quadratic B-spline stencil (base node and per-axis weights) of the grid coordinate g (grid units)."""
    return stencil_on(g, base_index(g))


@wp.func
def stencil_on(g: wp.vec3, base: wp.vec3i) -> Stencil:
    """The stencil of the grid coordinate g on the 3 x 3 x 3 nodes from ``base``: weights the quadratic B-spline's
    polynomial pieces at f = g - base (:func:`bspline_w`).  For any f they sum to 1, reproduce linear functions and
    have the second moment dx^2 / 4 I that the APIC matrix assumes, so the transfers stay exact for affine fields;
    for f in [0.5, 1.5) they are the B-spline's own weights, and they are positive for |f - 1| < 0.866."""
    s = Stencil()
    s.base = base
    s.f = frac(g, s.base)
    s.wx = bspline_w(s.f[0])
    s.wy = bspline_w(s.f[1])
    s.wz = bspline_w(s.f[2])
    return s


@wp.func
def stencil_weight(s: Stencil, i: int, j: int, k: int) -> float:
    """Weight of node base + (i, j, k): the product of the three axis weights."""
    return s.wx[i] * s.wy[j] * s.wz[k]


@wp.func
def point_stencil(xp: wp.vec3, gi: GridInfo, flags: wp.array(dtype=wp.int32), substep: int, idx: int) -> Stencil:
    """Stencil of a boundary or force point at xp (m); a point outside the safe band raises POINT_OUT."""
    return stencil_at(checked_grid_coord(xp, gi, flags, POINT_OUT, substep, idx))


@wp.func
def gather_apic(grid: wp.array3d(dtype=wp.vec4), s: Stencil, inv_dx: float) -> G2PResult:
    """Interpolate velocity and the APIC/MLS affine matrix C = 4/dx^2 sum_i w_i v_i (x_i - x_p)^T.

    Separable form: with offsets o = (i, j, k) and f = g - base, x_i - x_p = dx (o - f), so
    C = 4/dx (S - v f^T) with S[:, c] = sum_i w_i v_i o_c.  Sums run in vec4 (the 4th lane is unused).
    """
    b = s.base
    f = s.f
    wx = s.wx
    wy = s.wy
    wz = s.wz
    v = wp.vec4(0.0)
    s0 = wp.vec4(0.0)  # sum w v i
    s1 = wp.vec4(0.0)  # sum w v j
    s2 = wp.vec4(0.0)  # sum w v k
    for i in range(3):
        for j in range(3):
            n0 = grid[b[0] + i, b[1] + j, b[2]]
            n1 = grid[b[0] + i, b[1] + j, b[2] + 1]
            n2 = grid[b[0] + i, b[1] + j, b[2] + 2]
            wij = wx[i] * wy[j]
            acc = wij * (wz[0] * n0 + wz[1] * n1 + wz[2] * n2)
            v = v + acc
            s2 = s2 + wij * (wz[1] * n1 + (2.0 * wz[2]) * n2)
            if i == 1:
                s0 = s0 + acc
            if i == 2:
                s0 = s0 + 2.0 * acc
            if j == 1:
                s1 = s1 + acc
            if j == 2:
                s1 = s1 + 2.0 * acc
    r = G2PResult()
    r.v = wp.vec3(v[0], v[1], v[2])
    c = 4.0 * inv_dx
    # C[row, col] = 4/dx (s_col[row] - v[row] f[col]), built element by element (row-major scalars)
    r.C = wp.mat33(
        c * (s0[0] - v[0] * f[0]), c * (s1[0] - v[0] * f[1]), c * (s2[0] - v[0] * f[2]),
        c * (s0[1] - v[1] * f[0]), c * (s1[1] - v[1] * f[1]), c * (s2[1] - v[1] * f[2]),
        c * (s0[2] - v[2] * f[0]), c * (s1[2] - v[2] * f[1]), c * (s2[2] - v[2] * f[2]),
    )
    return r


@wp.func
def scatter_apic(grid: wp.array3d(dtype=wp.vec4), s: Stencil, dx: float, mass: float, mv: wp.vec3, A: wp.mat33,
                 bbox: wp.array(dtype=wp.int32)):
    """P2G: node i receives w_i (mv + A (x_i - x_p)) momentum (mv: the particle's momentum, kg m/s, plus any body
    impulse) and w_i m mass; records the stencil bounding box.

    A (x_i - x_p) = dx A (o - f) = p0 + i a0 + j a1 + k a2, evaluated in vec4 with the mass in the 4th lane.
    """
    b = s.base
    f = s.f
    a0 = dx * wp.vec4(A[0, 0], A[1, 0], A[2, 0], 0.0)
    a1 = dx * wp.vec4(A[0, 1], A[1, 1], A[2, 1], 0.0)
    a2 = dx * wp.vec4(A[0, 2], A[1, 2], A[2, 2], 0.0)
    p0 = wp.vec4(mv[0], mv[1], mv[2], mass) - (f[0] * a0 + f[1] * a1 + f[2] * a2)
    for i in range(3):
        for j in range(3):
            wij = s.wx[i] * s.wy[j]
            pij = p0 + float(i) * a0 + float(j) * a1
            for k in range(3):
                wp.atomic_add(grid, b[0] + i, b[1] + j, b[2] + k, (wij * s.wz[k]) * (pij + float(k) * a2))
    wp.atomic_min(bbox, 0, b[0])
    wp.atomic_min(bbox, 1, b[1])
    wp.atomic_min(bbox, 2, b[2])
    wp.atomic_max(bbox, 3, b[0])
    wp.atomic_max(bbox, 4, b[1])
    wp.atomic_max(bbox, 5, b[2])
