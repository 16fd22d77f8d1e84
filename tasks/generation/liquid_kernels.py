"""The per-pixel work of the screen-space liquid (:mod:`tasks.generation.fluid_render`) as Warp kernels on the CPU:
the normals from the smoothed depth (one-sided differences, cross product) and the shading's per-pixel geometry and
colour (refraction offsets, view and half vectors, Fresnel, sky, Beer-Lambert body, specular).

One thread per pixel row; the float64 arithmetic is that of the numpy formulation it replaced, operation for operation
and in its order (Warp's CPU code contracts no multiply-add; numpy sums a 3-vector's products left to right), and
numpy's clip is copied with its NaN and signed-zero rules.  What a Warp kernel cannot reproduce bit for bit stays
in numpy between the kernels: the exponentials (numpy's AVX-512 ``exp``), the powers (``np.power``, SVML on AVX-512)
and ``normal @ light`` (a BLAS product whose multiply-adds are fused), each on the same array as before, so the
outputs are bit-identical to the numpy code (``tests/generation/test_liquid_kernels.py``).
Units: metres, pixels; camera coordinates (x right, y down, z forward).
"""
from __future__ import annotations

import numpy as np
import warp as wp

from tasks.render.warp_numpy import numpy_view

wp.set_module_options({"enable_backward": False})

_f64 = wp.float64


@wp.func
def _clip(x: _f64, lo: _f64, hi: _f64) -> _f64:
    """numpy's ``clip`` of a float: NaN stays NaN, then max(x, lo) (lo on a tie), then min(., hi) (hi on a tie)."""
    if x != x:
        return x
    m = lo
    if x > lo:
        m = x
    if m < hi:
        return m
    return hi


@wp.func
def _position(depth: wp.array2d(dtype=_f64), y: int, x: int, fx: _f64, fy: _f64, cx: _f64, cy: _f64) -> wp.vec3d:
    """View-space position of pixel (y, x) at its depth, as ``normals_from_depth`` built it."""
    z = depth[y, x]
    return wp.vec3d((_f64(x) + _f64(0.5) - cx) / fx * z, (_f64(y) + _f64(0.5) - cy) / fy * z, z)


@wp.func
def _one_sided(p: wp.vec3d, fwd: wp.vec3d, ok_f: bool, bwd: wp.vec3d, ok_b: bool, step: wp.vec3d) -> wp.vec3d:
    """Of the forward (``fwd`` - p) and backward (p - ``bwd``) differences whose neighbour is covered, the one with
    the smaller depth change (forward on a tie); ``step`` where neither."""
    inf = _f64(wp.inf)
    forward = fwd - p
    backward = p - bwd
    cost_f = inf
    if ok_f:
        cost_f = wp.abs(forward[2])
    cost_b = inf
    if ok_b:
        cost_b = wp.abs(backward[2])
    if not (ok_f or ok_b):
        return step
    if cost_f <= cost_b:
        return forward
    return backward


@wp.func
def _normal_at(depth: wp.array2d(dtype=_f64), covered: wp.array2d(dtype=wp.uint8), y: int, x: int, fx: _f64,
               fy: _f64, cx: _f64, cy: _f64) -> wp.vec3d:
    """-unit(ddx x ddy) at covered pixel (y, x)."""
    height, width = depth.shape[0], depth.shape[1]
    zero = _f64(0.0)
    p = _position(depth, y, x, fx, fy, cx, cy)
    z = p[2]
    ok_r, ok_l, ok_d, ok_u = False, False, False, False
    right, left, down, up = p, p, p, p
    if x + 1 < width:
        ok_r = covered[y, x + 1] != wp.uint8(0)
        if ok_r:
            right = _position(depth, y, x + 1, fx, fy, cx, cy)
    if x > 0:
        ok_l = covered[y, x - 1] != wp.uint8(0)
        if ok_l:
            left = _position(depth, y, x - 1, fx, fy, cx, cy)
    if y + 1 < height:
        ok_d = covered[y + 1, x] != wp.uint8(0)
        if ok_d:
            down = _position(depth, y + 1, x, fx, fy, cx, cy)
    if y > 0:
        ok_u = covered[y - 1, x] != wp.uint8(0)
        if ok_u:
            up = _position(depth, y - 1, x, fx, fy, cx, cy)
    ddx = _one_sided(p, right, ok_r, left, ok_l, wp.vec3d(z / fx, zero, zero))
    ddy = _one_sided(p, down, ok_d, up, ok_u, wp.vec3d(zero, z / fy, zero))
    # numpy's cross product, component by component, then -v / |v| with |v|^2 summed left to right
    c0 = ddx[1] * ddy[2] - ddx[2] * ddy[1]
    c1 = ddx[2] * ddy[0] - ddx[0] * ddy[2]
    c2 = ddx[0] * ddy[1] - ddx[1] * ddy[0]
    norm = wp.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
    return wp.vec3d(-(c0 / norm), -(c1 / norm), -(c2 / norm))


@wp.kernel
def _normals(depth: wp.array2d(dtype=_f64), covered: wp.array2d(dtype=wp.uint8), fx: _f64, fy: _f64, cx: _f64,
             cy: _f64, normal: wp.array3d(dtype=_f64)):
    """Row y: normal[y, x] = -unit(ddx x ddy) where covered, else (0, 0, -1); depth read where covered only."""
    y = wp.tid()
    for x in range(depth.shape[1]):
        n = wp.vec3d(_f64(0.0), _f64(0.0), _f64(-1.0))
        if covered[y, x] != wp.uint8(0):
            n = _normal_at(depth, covered, y, x, fx, fy, cx, cy)
        normal[y, x, 0] = n[0]
        normal[y, x, 1] = n[1]
        normal[y, x, 2] = n[2]


@wp.func
def _view(y: int, x: int, fx: _f64, fy: _f64, cx: _f64, cy: _f64) -> wp.vec3d:
    """Unit direction from pixel (y, x)'s centre towards the camera, -unit(((x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy,
    1))."""
    one = _f64(1.0)
    d0 = (_f64(x) + _f64(0.5) - cx) / fx * one
    d1 = (_f64(y) + _f64(0.5) - cy) / fy * one
    norm = wp.sqrt(d0 * d0 + d1 * d1 + one * one)
    return wp.vec3d(-(d0 / norm), -(d1 / norm), -(one / norm))


@wp.kernel
def _shading_geometry(normal: wp.array3d(dtype=_f64), shift_m: wp.array2d(dtype=_f64), z: wp.array2d(dtype=_f64),
                      light: wp.vec3d, fx: _f64, fy: _f64, cx: _f64, cy: _f64,
                      map_x: wp.array2d(dtype=wp.float32), map_y: wp.array2d(dtype=wp.float32),
                      n_dot_v: wp.array2d(dtype=_f64), grazing: wp.array2d(dtype=_f64),
                      n_dot_h: wp.array2d(dtype=_f64)):
    """Row y, per pixel: the refraction's remap coordinates, clip(n.v, 0, 1), 1 - that (Schlick's base) and
    clip(n.h, 0, inf) (Blinn-Phong's base), h = unit(v + l)."""
    y = wp.tid()
    zero, one = _f64(0.0), _f64(1.0)
    for x in range(n_dot_v.shape[1]):
        n0, n1, n2 = normal[y, x, 0], normal[y, x, 1], normal[y, x, 2]
        map_x[y, x] = wp.float32(_f64(x) - fx * n0 * shift_m[y, x] / z[y, x])
        map_y[y, x] = wp.float32(_f64(y) - fy * n1 * shift_m[y, x] / z[y, x])
        v = _view(y, x, fx, fy, cx, cy)
        ndv = _clip(n0 * v[0] + n1 * v[1] + n2 * v[2], zero, one)
        n_dot_v[y, x] = ndv
        grazing[y, x] = one - ndv
        h0, h1, h2 = v[0] + light[0], v[1] + light[1], v[2] + light[2]
        norm = wp.sqrt(h0 * h0 + h1 * h1 + h2 * h2)
        n_dot_h[y, x] = _clip(n0 * (h0 / norm) + n1 * (h1 / norm) + n2 * (h2 / norm), zero, _f64(wp.inf))


@wp.kernel
def _liquid_colour(normal: wp.array3d(dtype=_f64), refracted: wp.array3d(dtype=wp.float32),
                   transmittance: wp.array3d(dtype=_f64), turbid: wp.array2d(dtype=_f64),
                   n_dot_l: wp.array2d(dtype=_f64), n_dot_v: wp.array2d(dtype=_f64),
                   fresnel_power: wp.array2d(dtype=_f64), fade: wp.array2d(dtype=_f64),
                   specular_power: wp.array2d(dtype=_f64), optics: wp.array(dtype=_f64),
                   fx: _f64, fy: _f64, cx: _f64, cy: _f64, rgb: wp.array3d(dtype=wp.float32)):
    """Row y, per pixel and channel: (1 - F) body + F sky + specular, clipped to [0, 1].  optics = (ambient, 1 - ambient,
    f0, 1 - f0, specular, body colour (3), sky horizon (3), sky zenith - horizon (3))."""
    y = wp.tid()
    zero, one = _f64(0.0), _f64(1.0)
    ambient, diffuse, f0, schlick, specular = optics[0], optics[1], optics[2], optics[3], optics[4]
    for x in range(n_dot_v.shape[1]):
        ndl = _clip(n_dot_l[y, x], zero, _f64(wp.inf))
        beta = turbid[y, x]
        fresnel = fade[y, x] * (f0 + schlick * fresnel_power[y, x])
        reflected_y = _f64(2.0) * n_dot_v[y, x] * normal[y, x, 1] - _view(y, x, fx, fy, cx, cy)[1]
        up = _clip(-reflected_y, zero, one)
        shine = fade[y, x] * specular * specular_power[y, x]
        for c in range(3):
            lit_body = optics[5 + c] * (ambient + diffuse * ndl)
            body = (one - beta) * transmittance[y, x, c] * _f64(refracted[y, x, c]) + beta * lit_body
            sky = optics[8 + c] + optics[11 + c] * up
            rgb[y, x, c] = wp.float32(_clip((one - fresnel) * body + fresnel * sky + shine, zero, one))


def normals_pixels(depth: np.ndarray, covered: np.ndarray, fx: float, fy: float, cx: float, cy: float
                   ) -> np.ndarray:
    """Unit normals (y, x, 3) float64 of :func:`tasks.generation.fluid_render.normals_from_depth`: depth (y, x) m
    (read where ``covered`` only), covered (y, x) bool, intrinsics px."""
    height, width = depth.shape
    normal = np.empty((height, width, 3))
    if depth.size == 0:
        return normal
    wp.init()   # no-op once Warp is up
    inputs = [numpy_view(depth), numpy_view(np.ascontiguousarray(covered, bool).view(np.uint8), wp.uint8),
              *map(float, (fx, fy, cx, cy))]
    wp.launch(_normals, dim=height, inputs=[*inputs, numpy_view(normal, output=True)], device="cpu")
    return normal


def shading_geometry(normal: np.ndarray, shift_m: np.ndarray, z: np.ndarray, light: np.ndarray, fx: float,
                     fy: float, cx: float, cy: float) -> tuple[np.ndarray, ...]:
    """Per pixel of the shading (:func:`tasks.generation.fluid_render.shade_liquid`): remap coordinates map_x, map_y
    (y, x) float32 px of the refraction (x - f n_x shift / z), clip(n.v, 0, 1), 1 - that, clip(n.h, 0, inf) (y, x)
    float64.  normal (y, x, 3) unit; shift_m, z (y, x) m; light (3,) unit, towards the light."""
    height, width = z.shape
    map_x, map_y = np.empty((height, width), np.float32), np.empty((height, width), np.float32)
    n_dot_v, grazing, n_dot_h = (np.empty((height, width)) for _ in range(3))
    if z.size == 0:
        return map_x, map_y, n_dot_v, grazing, n_dot_h
    wp.init()
    inputs = [*map(numpy_view, (normal, shift_m, z)), wp.vec3d(*map(float, light)), *map(float, (fx, fy, cx, cy))]
    outputs = [*(numpy_view(m, wp.float32, output=True) for m in (map_x, map_y)),
               *(numpy_view(m, output=True) for m in (n_dot_v, grazing, n_dot_h))]
    wp.launch(_shading_geometry, dim=height, inputs=inputs + outputs, device="cpu")
    return map_x, map_y, n_dot_v, grazing, n_dot_h


def liquid_colour(normal: np.ndarray, refracted: np.ndarray, transmittance: np.ndarray, turbid: np.ndarray,
                  n_dot_l: np.ndarray, n_dot_v: np.ndarray, fresnel_power: np.ndarray, fade: np.ndarray,
                  specular_power: np.ndarray, optics: np.ndarray, fx: float, fy: float, cx: float, cy: float
                  ) -> np.ndarray:
    """(y, x, 3) float32 in [0, 1]: the liquid's colour from the shading's per-pixel terms (``_liquid_colour``).

    normal (y, x, 3); refracted (y, x, 3) float32, the remapped background; transmittance (y, x, 3) exp(-sigma_a t);
    turbid, n_dot_l (unclipped), n_dot_v, fresnel_power ((1 - n.v)^5), fade, specular_power (n.h^shininess) (y, x);
    optics (14,) as the kernel's docstring; intrinsics px."""
    height, width = n_dot_v.shape
    rgb = np.empty((height, width, 3), np.float32)
    if n_dot_v.size == 0:
        return rgb
    wp.init()
    inputs = [numpy_view(normal), numpy_view(refracted, wp.float32),
              *map(numpy_view, (transmittance, turbid, n_dot_l, n_dot_v, fresnel_power, fade, specular_power, optics)),
              *map(float, (fx, fy, cx, cy))]
    wp.launch(_liquid_colour, dim=height, inputs=[*inputs, numpy_view(rgb, wp.float32, output=True)], device="cpu")
    return rgb
