"""The per-pixel work of the hand's rasteriser (:func:`tasks.render.hand.render_hand`) as a Warp kernel on the CPU:
every pixel ray of a capsule's screen box against the capsule (Quilez's ray-capsule intersection, with the
anti-aliased silhouette of :mod:`tasks.render.hand`), z-buffered front depth and normal, largest coverage.

One thread per capsule walks its box row by row; Warp runs a CPU launch's threads one after another in index order,
so the z-buffer sees the capsules in list order (a tie keeps the first), and the float64 arithmetic is that of the
numpy formulation it replaced, operation for operation (Warp's CPU code contracts no multiply-add): depth, normals
and coverage were bit-identical to it on every view of the orange, tomato, can and clay videos (920 layers).
The skin's shading and the hand's depth compositing into the frame (:func:`tasks.render.hand.composite_hand`) are
kernels too, one thread per row of the rows and columns the hand covers, apart or fused in one pass.
Units: metres, pixels; camera coordinates (x right, y down, z forward).
"""
from __future__ import annotations

import numpy as np
import warp as wp

from tasks.render.warp_numpy import numpy_view

wp.set_module_options({"enable_backward": False})

_f64 = wp.float64
# per-capsule scalars, camera coordinates: a (3), b - a (3), |b - a|^2, -(b - a).a, the body's constant
# |b - a|^2 a.a - ((b - a).a)^2 - r^2 |b - a|^2, a.a - r^2, b (3), b.b - r^2, r, max(|b - a|^2, 1e-18)
CAPSULE_FIELDS = 16


@wp.kernel
def _draw_capsules(capsule: wp.array2d(dtype=_f64), box: wp.array2d(dtype=wp.int32), rays: wp.array3d(dtype=_f64),
                   focal: _f64, oy: int, ox: int, depth: wp.array2d(dtype=_f64), normal: wp.array3d(dtype=_f64),
                   coverage: wp.array2d(dtype=_f64)):
    """Capsule n: capsule[n] = the CAPSULE_FIELDS scalars; box[n] = (x0, x1, y0, y1) px, clipped (x1, y1 exclusive);
    rays (3, y, x): unit ray directions through the pixel centres; focal: fx px; depth, normal, coverage: buffers
    whose element [y - oy, x - ox] is pixel (y, x)."""
    n = wp.tid()
    a0, a1, a2 = capsule[n, 0], capsule[n, 1], capsule[n, 2]
    ba0, ba1, ba2 = capsule[n, 3], capsule[n, 4], capsule[n, 5]
    baba, baoa, body_c = capsule[n, 6], capsule[n, 7], capsule[n, 8]
    cap_a, b0, b1, b2, cap_b = capsule[n, 9], capsule[n, 10], capsule[n, 11], capsule[n, 12], capsule[n, 13]
    r, baba_safe = capsule[n, 14], capsule[n, 15]
    zero, one, tiny = _f64(0.0), _f64(1.0), _f64(1e-18)
    inf = _f64(wp.inf)
    for y in range(box[n, 2], box[n, 3]):
        for x in range(box[n, 0], box[n, 1]):
            rx, ry, rz = rays[0, y, x], rays[1, y, x], rays[2, y, x]
            bard = rx * ba0 + ry * ba1 + rz * ba2
            # anti-aliased silhouette: distance between the ray and the axis segment; a ray farther than r + half a
            # pixel from the axis neither hits nor covers (coverage 0, depth +inf): nothing to draw
            rda = rx * a0 + ry * a1 + rz * a2
            pax, pay, paz = a0 - rda * rx, a1 - rda * ry, a2 - rda * rz
            pbx, pby, pbz = ba0 - bard * rx, ba1 - bard * ry, ba2 - bard * rz
            denom = wp.max(pbx * pbx + pby * pby + pbz * pbz, tiny)
            s_near = wp.clamp(-(pax * pbx + pay * pby + paz * pbz) / denom, zero, one)
            gx, gy, gz = pax + s_near * pbx, pay + s_near * pby, paz + s_near * pbz
            gap = wp.sqrt(gx * gx + gy * gy + gz * gz)
            z_near = wp.max(a2 + s_near * ba2, _f64(1e-6))
            c = wp.clamp(_f64(0.5) + (r - gap) * focal / z_near, zero, one)
            if c > zero:
                # body of the cylinder
                rdoa = -(rx * a0 + ry * a1 + rz * a2)
                qa = baba - bard * bard
                qb = baba * rdoa - baoa * bard
                h = qb * qb - qa * body_c
                safe = wp.abs(qa) > tiny
                divisor = tiny
                if safe:
                    divisor = qa
                t_body = (-qb - wp.sqrt(wp.max(h, zero))) / divisor
                along = baoa + t_body * bard
                # end spheres
                bc = rx * a0 + ry * a1 + rz * a2
                h2 = bc * bc - cap_a
                t_caps = inf
                if h2 >= zero:
                    t_caps = bc - wp.sqrt(wp.max(h2, zero))
                bc = rx * b0 + ry * b1 + rz * b2
                h2 = bc * bc - cap_b
                t_b = inf
                if h2 >= zero:
                    t_b = bc - wp.sqrt(wp.max(h2, zero))
                t_caps = wp.min(t_caps, t_b)
                t = t_caps
                if h >= zero and along > zero and along < baba and safe:
                    t = wp.min(t_body, t_caps)
                d = z_near - r
                if t > zero and wp.isfinite(t):
                    px, py, pz = rx * t, ry * t, rz * t
                    s = wp.clamp(((px - a0) * ba0 + (py - a1) * ba1 + (pz - a2) * ba2) / baba_safe, zero, one)
                    nx, ny, nz = px - (a0 + s * ba0), py - (a1 + s * ba1), pz - (a2 + s * ba2)
                    norm = wp.max(wp.sqrt(nx * nx + ny * ny + nz * nz), _f64(1e-12))
                    nx, ny, nz = nx / norm, ny / norm, nz / norm
                    d = t * rz
                else:
                    nx, ny, nz = zero, zero, -one
                i, j = y - oy, x - ox
                if d < depth[i, j]:
                    depth[i, j] = d
                    normal[0, i, j] = nx
                    normal[1, i, j] = ny
                    normal[2, i, j] = nz
                coverage[i, j] = wp.max(coverage[i, j], c)


@wp.func
def _skin(normal: wp.vec3d, view: wp.vec3d, colour: wp.vec3d, light: wp.vec3d) -> wp.vec3f:
    """clip(colour (0.38 + 0.62 max(n.l, 0)) + 0.12 max(n.h, 0)^24, 0, 1), h = unit(l - v), as float32; normal n,
    view v unit, camera coordinates."""
    zero, one = _f64(0.0), _f64(1.0)
    n0, n1, n2 = normal[0], normal[1], normal[2]
    n_l = wp.max(n0 * light[0] + n1 * light[1] + n2 * light[2], zero)
    h0, h1, h2 = light[0] - view[0], light[1] - view[1], light[2] - view[2]
    norm = wp.max(wp.sqrt(h0 * h0 + h1 * h1 + h2 * h2), _f64(1e-12))
    n_h = wp.max(n0 * (h0 / norm) + n1 * (h1 / norm) + n2 * (h2 / norm), zero)
    spec = _f64(0.12) * wp.pow(n_h, _f64(24.0))
    base = _f64(0.38) + _f64(0.62) * n_l
    return wp.vec3f(wp.float32(wp.clamp(colour[0] * base + spec, zero, one)),
                    wp.float32(wp.clamp(colour[1] * base + spec, zero, one)),
                    wp.float32(wp.clamp(colour[2] * base + spec, zero, one)))


@wp.func
def _composite(rgb: wp.array3d(dtype=wp.float32), y: int, x: int, c: wp.float32, hand_depth: wp.float32,
               scene_depth: wp.float32, scene_alpha: wp.float32, hand: wp.vec3f, background: wp.vec3f):
    """The hand (colour ``hand``, coverage c > 0, depth) put into rgb[y, x] by depth: the scene depth s (+inf unless
    finite and > 0); the hand in front (hand_depth <= s): rgb = c hand + (1 - c) rgb; behind: rgb = rgb + ((1 - alpha)
    c) (hand - background); float32, the numpy expression's operations in its order."""
    zero, one = wp.float32(0.0), wp.float32(1.0)
    seen = scene_depth
    if not (seen > zero and wp.isfinite(seen)):
        seen = wp.float32(wp.inf)
    if hand_depth <= seen:
        rest = one - c
        for k in range(3):
            rgb[y, x, k] = c * hand[k] + rest * rgb[y, x, k]
    else:
        share = (one - scene_alpha) * c
        for k in range(3):
            rgb[y, x, k] = rgb[y, x, k] + share * (hand[k] - background[k])


@wp.kernel
def _shade_skin(normal: wp.array3d(dtype=_f64), view: wp.array3d(dtype=_f64), coverage: wp.array2d(dtype=_f64),
                colour: wp.vec3d, light: wp.vec3d, y0: int, x0: int, x1: int, rgb: wp.array3d(dtype=wp.float32)):
    """Row y = y0 + thread, columns [x0, x1): rgb[y, x] = the skin's shade (``_skin``) where coverage[y, x] > 0 (else
    left as it is)."""
    y = y0 + wp.tid()
    for x in range(x0, x1):
        if coverage[y, x] > _f64(0.0):
            shade = _skin(wp.vec3d(normal[0, y, x], normal[1, y, x], normal[2, y, x]),
                          wp.vec3d(view[0, y, x], view[1, y, x], view[2, y, x]), colour, light)
            for c in range(3):
                rgb[y, x, c] = shade[c]


@wp.kernel
def _composite_hand(hand_rgb: wp.array3d(dtype=wp.float32), hand_depth: wp.array2d(dtype=wp.float32),
                    hand_coverage: wp.array2d(dtype=wp.float32), scene_alpha: wp.array2d(dtype=wp.float32),
                    scene_depth: wp.array2d(dtype=wp.float32), background: wp.vec3f, y0: int, x0: int, x1: int,
                    rgb: wp.array3d(dtype=wp.float32)):
    """Row y = y0 + thread, columns [x0, x1): the hand layer put into rgb by depth (``_composite``) where
    hand_coverage[y, x] > 0 (else rgb is left as it is)."""
    y = y0 + wp.tid()
    for x in range(x0, x1):
        c = hand_coverage[y, x]
        if c > wp.float32(0.0):
            hand = wp.vec3f(hand_rgb[y, x, 0], hand_rgb[y, x, 1], hand_rgb[y, x, 2])
            _composite(rgb, y, x, c, hand_depth[y, x], scene_depth[y, x], scene_alpha[y, x], hand, background)


@wp.kernel
def _shade_and_composite(normal: wp.array3d(dtype=_f64), view: wp.array3d(dtype=_f64),
                         coverage: wp.array2d(dtype=_f64), depth: wp.array2d(dtype=_f64), colour: wp.vec3d,
                         light: wp.vec3d, scene_alpha: wp.array2d(dtype=wp.float32),
                         scene_depth: wp.array2d(dtype=wp.float32), background: wp.vec3f, oy: int, ox: int, y0: int,
                         x0: int, x1: int, rgb: wp.array3d(dtype=wp.float32)):
    """``_shade_skin`` and ``_composite_hand`` in one pass, straight from ``_draw_capsules``' float64 buffers (normal,
    coverage, depth: element [y - oy, x - ox] is pixel (y, x)): where the coverage as float32 is > 0, the skin's shade
    put into rgb by the depth as float32 (what the hand layer holds).  Row y = y0 + thread, columns [x0, x1)."""
    y = y0 + wp.tid()
    i = y - oy
    for x in range(x0, x1):
        j = x - ox
        c = wp.float32(coverage[i, j])
        if c > wp.float32(0.0):
            shade = _skin(wp.vec3d(normal[0, i, j], normal[1, i, j], normal[2, i, j]),
                          wp.vec3d(view[0, y, x], view[1, y, x], view[2, y, x]), colour, light)
            _composite(rgb, y, x, c, wp.float32(depth[i, j]), scene_depth[y, x], scene_alpha[y, x], shade,
                       background)


def capsule_scalars(a: np.ndarray, b: np.ndarray, r: float) -> list[float]:
    """The kernel's CAPSULE_FIELDS scalars of capsule a-b (3,) m, radius r m, camera coordinates (numpy's dot
    products, so the kernel starts from the numbers the numpy formulation used)."""
    ba = b - a
    baba, baoa, oaoa = float(ba @ ba), -float(ba @ a), float(a @ a)
    return [*a, *ba, baba, baoa, baba * oaoa - baoa * baoa - r * r * baba, oaoa - r * r, *b, float(b @ b) - r * r, r,
            max(baba, 1e-18)]


def draw_capsules(capsules: np.ndarray, boxes: np.ndarray, rays: np.ndarray, focal: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """Front depth (h, w) m (+inf where nothing; on the anti-aliased fringe outside the silhouette the depth of the
    axis point nearest the ray, less r), unit normal (3, h, w) (camera coordinates; (0, 0, -1) where nothing and on
    the fringe) and coverage (h, w) in [0, 1] of capsules (n, CAPSULE_FIELDS) (:func:`capsule_scalars`) over their
    screen boxes (n, 4) int (x0, x1, y0, y1) px, and the origin (y, x) px of these buffers: they span the union of
    the boxes only (pixel (y, x) is element [y - origin y, x - origin x]; (0, 0) buffers at (0, 0) for no capsule);
    rays (3, y, x) unit pixel-centre directions of the whole image; focal: fx px."""
    boxes = np.ascontiguousarray(boxes, np.int32).reshape(-1, 4)
    if len(capsules) == 0:
        return np.zeros((0, 0)), np.zeros((3, 0, 0)), np.zeros((0, 0)), (0, 0)
    ox, oy = int(boxes[:, 0].min()), int(boxes[:, 2].min())
    height, width = int(boxes[:, 3].max()) - oy, int(boxes[:, 1].max()) - ox
    depth = np.full((height, width), np.inf)
    coverage = np.zeros((height, width))
    normal = np.zeros((3, height, width))
    normal[2] = -1.0
    wp.init()   # no-op once Warp is up
    inputs = [numpy_view(capsules), numpy_view(boxes, wp.int32), numpy_view(rays), focal, oy, ox]
    outputs = [numpy_view(x, output=True) for x in (depth, normal, coverage)]
    wp.launch(_draw_capsules, dim=len(capsules), inputs=inputs + outputs, device="cpu")
    return depth, normal, coverage, (oy, ox)


def _covered(coverage: np.ndarray) -> tuple[int, int, int, int] | None:
    """The launch of a per-row kernel over the rows and columns where ``coverage`` (y, x) > 0: (rows, y0, x0, x1),
    or None where there is none."""
    drawn = coverage > 0
    rows, cols = np.flatnonzero(drawn.any(axis=1)), np.flatnonzero(drawn.any(axis=0))
    if len(rows) == 0:
        return None
    return int(rows[-1]) + 1 - int(rows[0]), int(rows[0]), int(cols[0]), int(cols[-1]) + 1


def shade_skin_pixels(normal: np.ndarray, view: np.ndarray, coverage: np.ndarray, colour: np.ndarray,
                      light: np.ndarray) -> np.ndarray:
    """(y, x, 3) float32 linear RGB of the skin where ``coverage`` (y, x) > 0, zero elsewhere (``_shade_skin``):
    normal, view (3, y, x) unit, camera coordinates; colour (3,) linear RGB; light (3,) unit, towards the light."""
    rgb = np.zeros((*coverage.shape, 3), np.float32)
    launch = _covered(coverage)
    if launch is None:
        return rgb
    wp.init()
    wp.launch(_shade_skin, dim=launch[0],
              inputs=[*(numpy_view(a, _f64) for a in (normal, view, coverage)), wp.vec3d(*map(float, colour)),
                      wp.vec3d(*map(float, light)), *launch[1:], numpy_view(rgb, wp.float32, output=True)],
              device="cpu")
    return rgb


def composite_hand_pixels(scene_rgb: np.ndarray, scene_alpha: np.ndarray, scene_depth: np.ndarray,
                          background: np.ndarray, hand_rgb: np.ndarray, hand_depth: np.ndarray,
                          hand_coverage: np.ndarray) -> np.ndarray:
    """(y, x, 3) float32: ``scene_rgb`` with the hand layer (rgb (y, x, 3), depth (y, x) m, coverage (y, x)) put in by
    depth (``_composite_hand``) over the rows and columns with coverage; every input as float32, as the display
    step's are (bit-identical to the numpy expression on float32 inputs)."""
    out = np.array(scene_rgb, dtype=np.float32, order="C")
    launch = _covered(hand_coverage)
    if launch is None:
        return out
    wp.init()
    wp.launch(_composite_hand, dim=launch[0],
              inputs=[*(numpy_view(a, wp.float32) for a in (hand_rgb, hand_depth, hand_coverage, scene_alpha,
                                                             scene_depth)),
                      wp.vec3f(*map(float, np.asarray(background, np.float32))), *launch[1:],
                      numpy_view(out, wp.float32, output=True)],
              device="cpu")
    return out


def shade_and_composite_pixels(normal: np.ndarray, view: np.ndarray, coverage: np.ndarray, depth: np.ndarray,
                               origin: tuple[int, int], colour: np.ndarray, light: np.ndarray, scene_rgb: np.ndarray,
                               scene_alpha: np.ndarray, scene_depth: np.ndarray, background: np.ndarray) -> np.ndarray:
    """(y, x, 3) float32: ``scene_rgb`` with the skin (:func:`shade_skin_pixels` of normal, view, coverage) put in by
    depth (:func:`composite_hand_pixels` with the coverage and depth as float32), in one pass
    (``_shade_and_composite``): the same numbers as the two functions one after the other, without the hand layer.
    normal (3, h, w), coverage, depth (h, w): :func:`draw_capsules`' buffers at ``origin`` (y, x) px; view (3, y, x)
    and the scene's arrays: the whole image."""
    out = np.array(scene_rgb, dtype=np.float32, order="C")
    launch = _covered(coverage)
    if launch is None:
        return out
    wp.init()
    rows, y0, x0, x1 = launch
    oy, ox = origin
    wp.launch(_shade_and_composite, dim=rows,
              inputs=[*(numpy_view(a, _f64) for a in (normal, view, coverage, depth)), wp.vec3d(*map(float, colour)),
                      wp.vec3d(*map(float, light)), *(numpy_view(a, wp.float32) for a in (scene_alpha, scene_depth)),
                      wp.vec3f(*map(float, np.asarray(background, np.float32))), oy, ox, oy + y0, ox + x0, ox + x1,
                      numpy_view(out, wp.float32, output=True)], device="cpu")
    return out
