"""Compiled compositor: NVIDIA Warp kernels (LLVM on CPU, CUDA on a GPU) for the front-to-back forward pass and the
hand-written back-to-front backward pass of 3DGS (Kerbl et al. 2023, sec. 4 and its released rasteriser), wrapped in
a ``torch.autograd.Function``; it follows the compositing rule of ``splat_torch`` exactly.

Design (chosen by measurement, ``tasks.render.benchmark``): one thread per image row.  (1) Every instance (a drawn
(camera, Gaussian) pair) walks the rows of its box and solves the quadratic sigma(x) <= ln(opacity / ALPHA_MIN) for
its x span on that row, so only pairs that can reach alpha >= 1/255 are ever visited; the spans are bucketed by row
(a counting sort: count from a difference array, scan, fill) and each row's bucket is insertion-sorted by instance,
i.e. front to back (instances arrive sorted by depth; on the CPU a launch runs in order, so the buckets are sorted
already and the sort is skipped, on CUDA the atomics scramble them).  (2) Forward: a row's thread composites its
spans front to back into the row's pixels (transmittance, channels, stop marker) - no per-pixel lists and no sort of
pairs.  sigma is quadratic in x and y, so the Gaussian exp(-sigma) is evaluated by recurrences instead of an exp
per pair: along a span two multiplies per pixel, in float64 so that it drifts < 1e-12; each span's start value and
first ratio are carried from the instance's previous span by the same recurrences in x and y while the spans are
bucketed (five exps per instance, none per span: an exp per span cost ~25 % of the forward).  (3) Backward: the same thread walks its spans back to front, recovers
T_i = T_final / prod (1 - alpha_j) and the sum behind each Gaussian per pixel, and accumulates each span's gradient
in registers - the geometry's as three moments of dL/dsigma along the span (dy is constant on a row) - before one
atomic add per (instance, row).  Computation is float32 (the recurrence float64) whatever the input dtype; one pair
of kernels is compiled per channel count.
"""

import functools

import torch
import warp as wp

from .splat_torch import ALPHA_FLOOR, ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN
from .warp_interop import launch, scratch, warp_view

wp.set_module_options({"enable_backward": False})   # the backward pass is hand-written

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_ALPHA_MAX = wp.constant(ALPHA_MAX)
_T_MIN = wp.constant(TRANSMITTANCE_MIN)
_ALPHA_FLOOR = wp.constant(ALPHA_FLOOR)
_NO_STOP = wp.constant(2**31 - 1)   # stop marker of a pixel that never stops
_GAUSS_MAX = wp.constant(wp.float64(1.0 + 1e-6))   # exp(-sigma) above it: sigma < 0 beyond the recurrence's rounding
_SPAN_MARGIN = wp.constant(1e-3)   # added to the exponent threshold so the spans hold every pair the rule keeps
_vec6 = wp.types.vector(length=6, dtype=float)   # an instance's geometry: mean x, y px; conic a, b, c; opacity


@wp.func
def _geometry(means2d: wp.array(dtype=wp.vec2), conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float),
              k: int, n: int):
    """The geometry of the instance of camera-Gaussian k (flat camera * N + Gaussian) and Gaussian n."""
    m, q = means2d[k], conics[k]
    return _vec6(m[0], m[1], q[0], q[1], q[2], opacities[n])


@wp.func
def _pixel_gauss(geometry: _vec6, x: int, y: int):
    """exp(-sigma) at pixel (x, y) and its step ratios to pixels (x + 1, y) and (x, y + 1), float64.

    sigma = 0.5 (a dx^2 + c dy^2) + b dx dy at the pixel centre (x + 0.5, y + 0.5) with d = centre - mean; it is
    quadratic in x and y, so exp(-sigma(x + 1, y)) = exp(-sigma) ratio_x with ratio_x = exp(-(a (dx + 1/2) + b dy)),
    which itself steps by exp(-a) along x and exp(-b) along y (ratio_y likewise by exp(-c) and exp(-b))."""
    a, b, c = wp.float64(geometry[2]), wp.float64(geometry[3]), wp.float64(geometry[4])
    half = wp.float64(0.5)
    dx = wp.float64(x) + half - wp.float64(geometry[0])
    dy = wp.float64(y) + half - wp.float64(geometry[1])
    sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy
    return wp.exp(-sigma), wp.exp(-(a * (dx + half) + b * dy)), wp.exp(-(c * (dy + half) + b * dx))


@wp.func
def _threshold(opacity: float):
    """The largest sigma at which the Gaussian reaches alpha >= ALPHA_MIN, ln(opacity / ALPHA_MIN), + _SPAN_MARGIN."""
    return wp.log(wp.max(opacity, 1e-12) / _ALPHA_MIN) + _SPAN_MARGIN


@wp.func
def _row_span(geometry: _vec6, threshold: float, box: wp.vec4i, y: int):
    """[x_begin, x_end) of row y inside the box where sigma <= threshold (may be empty)."""
    a, b, c = geometry[2], geometry[3], geometry[4]
    dy = float(y) + 0.5 - geometry[1]
    disc = (b * b - a * c) * dy * dy + 2.0 * a * threshold
    if threshold < 0.0 or disc < 0.0:
        return 0, 0
    inv_a = 1.0 / a
    middle = geometry[0] - 0.5 - b * dy * inv_a
    half = wp.sqrt(disc) * inv_a
    return wp.max(box[0], int(wp.ceil(middle - half))), wp.min(box[1], int(wp.floor(middle + half)) + 1)


@wp.kernel
def _bin(drawn: wp.array(dtype=int), n_gaussians: int, means2d: wp.array(dtype=wp.vec2),
         conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float), radii: wp.array(dtype=int), width: int,
         height: int, boxes: wp.array(dtype=wp.vec4i), decay: wp.array(dtype=wp.float64), marks: wp.array(dtype=int)):
    """Per instance i: its pixel box (``splat_projection.pixel_boxes``) with its rows cut to those its span ellipse
    sigma <= threshold reaches (|dy| <= sqrt(2 a threshold / det), plus a row of slack; no rows when empty),
    exp(-a) and +1 / -1 in the difference array of per-row span counts at its first / past-last row."""
    i = wp.tid()
    k = drawn[i]
    m, r, q = means2d[k], float(radii[k]), conics[k]
    x0 = int(wp.clamp(wp.ceil(m[0] - r - 0.5), 0.0, float(width)))
    x1 = int(wp.clamp(wp.floor(m[0] + r - 0.5) + 1.0, 0.0, float(width)))
    threshold, det = _threshold(opacities[k % n_gaussians]), q[0] * q[2] - q[1] * q[1]
    reach = r
    if det > 0.0:
        reach = wp.min(r, wp.sqrt(2.0 * q[0] * wp.max(threshold, 0.0) / det) + 1.0)
    y0 = int(wp.clamp(wp.ceil(m[1] - reach - 0.5), 0.0, float(height)))
    y1 = int(wp.clamp(wp.floor(m[1] + reach - 0.5) + 1.0, 0.0, float(height)))
    if x1 <= x0 or threshold < 0.0 or y1 < y0:
        y1 = y0
    boxes[i] = wp.vec4i(x0, x1, y0, y1)
    decay[i] = wp.exp(-wp.float64(conics[k][0]))
    if y1 > y0:
        first = (k // n_gaussians) * height
        wp.atomic_add(marks, first + y0, 1)
        wp.atomic_add(marks, first + y1, -1)


@wp.kernel
def _fill_rows(drawn: wp.array(dtype=int), n_gaussians: int, means2d: wp.array(dtype=wp.vec2),
               conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float), boxes: wp.array(dtype=wp.vec4i),
               height: int, decay: wp.array(dtype=wp.float64), row_offsets: wp.array(dtype=int),
               cursors: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), starts: wp.array(dtype=wp.vec2d)):
    """spans[row_offsets[r] + j] = (instance, x_begin, x_end) for every box row r of every instance: the part of
    the row where sigma <= ln(opacity / ALPHA_MIN) (+ _SPAN_MARGIN); starts[...] = exp(-sigma) and its step ratio
    along x at x_begin (``_pixel_gauss``), carried from span to span by the recurrences in x and y (float64: 5 exps
    per instance, not 2 per span; the values stay within ~exp(+-10) between spans inside the ellipse)."""
    i = wp.tid()
    k = drawn[i]
    geo = _geometry(means2d, conics, opacities, k, k % n_gaussians)
    threshold = _threshold(geo[5])
    box = boxes[i]
    first = (k // n_gaussians) * height
    decay_x, decay_xy, decay_y = decay[i], wp.exp(-wp.float64(geo[3])), wp.exp(-wp.float64(geo[4]))
    grow_x, grow_xy = wp.float64(1.0) / decay_x, wp.float64(1.0) / decay_xy
    gauss, ratio_x, ratio_y = wp.float64(0.0), wp.float64(0.0), wp.float64(0.0)
    xr, yr = int(0), int(-1)   # the pixel the recurrence stands at; yr < 0: not started
    for y in range(box[2], box[3]):
        x0, x1 = _row_span(geo, threshold, box, y)
        if x1 > x0:
            if yr < 0:
                gauss, ratio_x, ratio_y = _pixel_gauss(geo, x0, y)
            else:
                while yr < y:
                    gauss = gauss * ratio_y
                    ratio_y = ratio_y * decay_y
                    ratio_x = ratio_x * decay_xy
                    yr += 1
                while xr < x0:
                    gauss = gauss * ratio_x
                    ratio_x = ratio_x * decay_x
                    ratio_y = ratio_y * decay_xy
                    xr += 1
                while xr > x0:
                    ratio_x = ratio_x * grow_x
                    gauss = gauss / ratio_x
                    ratio_y = ratio_y * grow_xy
                    xr -= 1
            xr, yr = x0, y
        r = first + y
        j = row_offsets[r] + wp.atomic_add(cursors, r, 1)
        spans[j] = wp.vec3i(i, x0, x1)
        starts[j] = wp.vec2d(gauss, ratio_x)


@wp.kernel
def _sort_rows(row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), starts: wp.array(dtype=wp.vec2d)):
    """Insertion sort of each row's spans (and their starts) by instance, i.e. front to back (no-op for rows filled
    in order)."""
    r = wp.tid()
    begin, end = row_offsets[r], row_offsets[r + 1]
    for i in range(begin + 1, end):
        key, key_start = spans[i], starts[i]
        j = i - 1
        while j >= begin and spans[j][0] > key[0]:
            spans[j + 1] = spans[j]
            starts[j + 1] = starts[j]
            j -= 1
        spans[j + 1] = key
        starts[j + 1] = key_start


@functools.cache
def _composite_kernels(n_channels: int):
    """Forward and backward compositing kernels for n_channels feature channels (compiled once per count).
    Instance i is camera-Gaussian k = drawn[i] (flat camera * N + Gaussian), Gaussian n = k % N; its features are
    row k of ``features`` when per_camera, else row n."""
    vec = wp.types.vector(length=n_channels, dtype=float)
    vec_t = wp.types.vector(length=n_channels + 1, dtype=float)   # the channels and the transmittance

    @wp.kernel(module="unique", enable_backward=False)
    def forward(drawn: wp.array(dtype=int), n_gaussians: int, means2d: wp.array(dtype=wp.vec2),
                conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float), features: wp.array(dtype=vec),
                per_camera: int, decay: wp.array(dtype=wp.float64), row_offsets: wp.array(dtype=int),
                spans: wp.array(dtype=wp.vec3i), starts: wp.array(dtype=wp.vec2d), width: int, height: int,
                backgrounds: wp.array2d(dtype=float), n_background: int, expected_depth: int,
                out_features: wp.array(dtype=vec), out_alphas: wp.array(dtype=float),
                transmittance: wp.array(dtype=float), stop: wp.array(dtype=int), sums: wp.array(dtype=vec_t)):
        # sums: per pixel the composited channels and, last, the transmittance (one address per pair)
        r = wp.tid()
        row = r * width
        empty = vec_t()
        empty[n_channels] = 1.0
        for x in range(width):
            sums[row + x] = empty
            stop[row + x] = _NO_STOP
        for j in range(row_offsets[r], row_offsets[r + 1]):
            g, x0, x1 = spans[j][0], spans[j][1], spans[j][2]
            if x1 <= x0:
                continue   # an empty span (a box row the Gaussian cannot reach with alpha >= 1/255)
            k = drawn[g]
            n = k % n_gaussians
            geo = _geometry(means2d, conics, opacities, k, n)
            f = vec(features[wp.where(per_camera != 0, k, n)])
            f_t = vec_t()
            for c in range(n_channels):
                f_t[c] = f[c]
            step = decay[g]
            start = starts[j]
            gauss, ratio = start[0], start[1]
            p, end = row + x0, row + x1
            while p < end:   # a while loop: leaner machine code than range() in Warp's CPU kernels
                gauss_x = gauss
                gauss = gauss * ratio
                ratio = ratio * step
                s = sums[p]
                t = s[n_channels]
                alpha = wp.min(_ALPHA_MAX, geo[5] * float(gauss_x))
                # t < 0: a stopped pixel; gauss_x > _GAUSS_MAX: sigma < 0; alpha < _ALPHA_MIN: too faint
                if t >= 0.0 and gauss_x <= _GAUSS_MAX and alpha >= _ALPHA_MIN:
                    next_t = t * (1.0 - alpha)
                    if next_t < _T_MIN:
                        s[n_channels] = -t   # the pixel stops at g, which is left out; the sign marks it
                        stop[p] = g
                    else:
                        s = s + (alpha * t) * f_t
                        s[n_channels] = next_t
                    sums[p] = s
                p += 1
        # the finished pixels (``finish_pixels``): alpha, expected depth, background
        camera = r // height
        for x in range(width):
            s = sums[row + x]
            t = wp.abs(s[n_channels])
            transmittance[row + x] = t
            out_alphas[row + x] = 1.0 - t
            v = vec()
            for c in range(n_channels):
                v[c] = s[c]
            if expected_depth != 0:
                v[n_channels - 1] = v[n_channels - 1] / wp.max(1.0 - t, _ALPHA_FLOOR)
            for c in range(n_background):
                v[c] = v[c] + t * backgrounds[camera, c]
            out_features[row + x] = v

    @wp.kernel(module="unique", enable_backward=False)
    def backward(drawn: wp.array(dtype=int), n_gaussians: int, means2d: wp.array(dtype=wp.vec2),
                 conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float), features: wp.array(dtype=vec),
                 per_camera: int, decay: wp.array(dtype=wp.float64), row_offsets: wp.array(dtype=int),
                 spans: wp.array(dtype=wp.vec3i), starts: wp.array(dtype=wp.vec2d), width: int, height: int,
                 backgrounds: wp.array2d(dtype=float), n_background: int, expected_depth: int, out_features: wp.array(dtype=vec),
                 stop: wp.array(dtype=int), transmittance: wp.array(dtype=float), grad_finished: wp.array(dtype=vec),
                 grad_finished_alphas: wp.array(dtype=float), grad_out_features: wp.array(dtype=vec),
                 state: wp.array(dtype=wp.vec3), grad_means2d: wp.array(dtype=wp.vec2), grad_conics: wp.array(dtype=wp.vec3),
                 grad_opacities: wp.array(dtype=float), grad_features: wp.array(dtype=vec)):
        # per pixel, state = (T, behind, dL/dalpha of the composited alpha): T starts as the final transmittance and
        # is divided back to T_i; behind (starts 0) holds what the Gaussians behind the current one add to
        # grad . features + grad_alpha_image * alpha, per unit T in front (one array: one address per pixel)
        r = wp.tid()
        py = float(r % height) + 0.5
        row = r * width
        # gradients of the finished pixels -> of the composited sums and alpha (grad_out_*: written here)
        camera = r // height
        for x in range(width):
            grad_v = grad_finished[row + x]
            grad_a = grad_finished_alphas[row + x]
            for c in range(n_background):
                grad_a -= grad_v[c] * backgrounds[camera, c]
            if expected_depth != 0:
                a = 1.0 - transmittance[row + x]
                if a > _ALPHA_FLOOR:
                    grad_a -= grad_v[n_channels - 1] * out_features[row + x][n_channels - 1] / a
                grad_v[n_channels - 1] = grad_v[n_channels - 1] / wp.max(a, _ALPHA_FLOOR)
            grad_out_features[row + x] = grad_v
            state[row + x] = wp.vec3(transmittance[row + x], 0.0, grad_a)
        j = row_offsets[r + 1] - 1
        while j >= row_offsets[r]:
            g, x0, x1 = spans[j][0], spans[j][1], spans[j][2]
            j -= 1
            if x1 <= x0:
                continue
            k = drawn[g]
            n = k % n_gaussians
            geo = _geometry(means2d, conics, opacities, k, n)
            row_f = wp.where(per_camera != 0, k, n)
            f = vec(features[row_f])
            step = decay[g]
            dy = py - geo[1]
            grad_f = vec()
            # dL/dsigma moments over the span (dy is the row's): sum g_s, sum g_s dx, sum g_s dx^2; sum G dL/dalpha
            m0, m1, m2, grad_opacity = float(0.0), float(0.0), float(0.0), float(0.0)
            start = starts[j + 1]   # j already stepped to the next span
            gauss64, ratio = start[0], start[1]
            x = x0
            while x < x1:
                gauss_x = gauss64
                gauss64 = gauss64 * ratio
                ratio = ratio * step
                p = row + x
                gauss = float(gauss_x)
                alpha = wp.min(_ALPHA_MAX, geo[5] * gauss)
                # skipped: at or behind the pixel's stop, sigma < 0, too faint
                if g < stop[p] and gauss_x <= _GAUSS_MAX and alpha >= _ALPHA_MIN:
                    s = state[p]
                    t = s[0] / (1.0 - alpha)   # T_i, in front of Gaussian i
                    grad_pixel = grad_out_features[p]
                    grad_here = wp.dot(grad_pixel, f) + s[2]
                    grad_f += (alpha * t) * grad_pixel
                    grad_alpha = t * (grad_here - s[1])
                    state[p] = wp.vec3(t, alpha * grad_here + (1.0 - alpha) * s[1], s[2])
                    if geo[5] * gauss <= _ALPHA_MAX:   # a clamped alpha passes no gradient to geometry and opacity
                        grad_sigma = -alpha * grad_alpha
                        dx = float(x) + 0.5 - geo[0]
                        m0 += grad_sigma
                        m1 += grad_sigma * dx
                        m2 += grad_sigma * dx * dx
                        grad_opacity += gauss * grad_alpha
                x += 1
            wp.atomic_add(grad_means2d, k, wp.vec2(-(geo[2] * m1 + geo[3] * dy * m0), -(geo[3] * m1 + geo[4] * dy * m0)))
            wp.atomic_add(grad_conics, k, wp.vec3(0.5 * m2, dy * m1, 0.5 * dy * dy * m0))
            wp.atomic_add(grad_opacities, n, grad_opacity)
            wp.atomic_add(grad_features, row_f, grad_f)

    return forward, backward, vec, vec_t


def row_spans(drawn: torch.Tensor, means2d: torch.Tensor, conics: torch.Tensor, radii: torch.Tensor,
              opacities: torch.Tensor, width: int, height: int,
              n_images: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Every image row's spans (instance, x_begin, x_end), front to back, and where their recurrences start. No
    gradient.

    drawn: (G,) int32 flat camera * N + Gaussian of the instances, front to back; means2d (C * N, 2) px, conics
    (C * N, 3) 1/px^2, radii (C * N,) int32 px, opacities (N,), all float32 contiguous; n_images = C.
    Returns offsets (C * height + 1,) int32, spans (sum of box heights, 3) int32 - row r owns
    ``spans[offsets[r]:offsets[r + 1]]``; a span is the part of the box row where the instance can reach
    alpha >= 1/255 (empty when x_end <= x_begin) -, starts (spans, 2) float64 exp(-sigma) and its step ratio at
    each span's first pixel, and each instance's exp(-a) (G,) float64.
    """
    device, n_rows, n_gaussians = drawn.device, n_images * height, len(opacities)
    # 1. boxes and the difference array of per-row counts, 2. its scan
    boxes = scratch("boxes", (len(drawn), 4), torch.int32, device)
    decay = torch.empty(len(drawn), dtype=torch.float64, device=device)
    marks = scratch("marks", (n_rows + 1,), torch.int32, device).zero_()
    views = [warp_view(drawn), n_gaussians, warp_view(means2d, wp.vec2), warp_view(conics, wp.vec3),
             warp_view(opacities)]
    launch(_bin, len(drawn), views + [warp_view(radii), width, height, warp_view(boxes, wp.vec4i),
                                      warp_view(decay, wp.float64), warp_view(marks)], device)
    offsets = torch.zeros(n_rows + 1, dtype=torch.int32, device=device)
    torch.cumsum(torch.cumsum(marks[:-1], 0), 0, out=offsets[1:])
    # 3. the spans, 4. each row sorted front to back
    spans = torch.empty(int(offsets[-1]), 3, dtype=torch.int32, device=device)
    starts = torch.empty(len(spans), 2, dtype=torch.float64, device=device)
    cursors = scratch("cursors", (n_rows + 1,), torch.int32, device).zero_()
    launch(_fill_rows, len(drawn), views + [warp_view(boxes, wp.vec4i), height,
                                            warp_view(decay, wp.float64), warp_view(offsets),
                                            warp_view(cursors), warp_view(spans, wp.vec3i),
                                            warp_view(starts, wp.vec2d)], device)
    if device.type != "cpu":   # a CPU launch runs its threads in order: the buckets are filled sorted
        launch(_sort_rows, n_rows, [warp_view(offsets), warp_view(spans, wp.vec3i), warp_view(starts, wp.vec2d)],
               device)
    return offsets, spans, starts, decay


class _Composite(torch.autograd.Function):
    """Differentiable compositing of float32 instances over precomputed row spans into finished pixels (expected
    depth, background), one Warp thread per image row."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, features, drawn, per_camera: int, decay, row_offsets, spans,
                starts, width: int, height: int, backgrounds, expected_depth: int):
        forward_kernel, _, vec, vec_t = _composite_kernels(features.shape[1])
        n_rows = len(row_offsets) - 1
        device, n_pixels = means2d.device, n_rows * width
        out_features = torch.empty(n_pixels, features.shape[1], dtype=torch.float32, device=device)
        out_alphas, final_t = (torch.empty(n_pixels, dtype=torch.float32, device=device) for _ in range(2))
        stop = torch.empty(n_pixels, dtype=torch.int32, device=device)
        sums = scratch("sums", (n_pixels, features.shape[1] + 1), torch.float32, device)
        ctx.finish = [width, height, warp_view(backgrounds), backgrounds.shape[1] * int(backgrounds.shape[0] > 0),
                      expected_depth]
        ctx.span_arrays = _span_arrays(means2d, conics, opacities, features, drawn, per_camera, decay, row_offsets,
                                       spans, starts, vec)   # the backward's too (its tensors are saved below)
        launch(forward_kernel, n_rows, ctx.span_arrays + ctx.finish + [
            warp_view(out_features, vec), warp_view(out_alphas), warp_view(final_t), warp_view(stop),
            warp_view(sums, vec_t)], device)
        ctx.save_for_backward(means2d, conics, opacities, features, drawn, decay, row_offsets, spans, starts,
                              final_t, stop, out_features, backgrounds)
        ctx.per_camera = per_camera
        return out_features, out_alphas

    @staticmethod
    def backward(ctx, grad_features_image, grad_alphas_image):
        (means2d, conics, opacities, features, drawn, decay, row_offsets, spans, starts, final_t, stop, out_features,
         _) = ctx.saved_tensors
        _, backward_kernel, vec, _ = _composite_kernels(features.shape[1])
        grads = [torch.zeros_like(t) for t in (means2d, conics, opacities, features)]
        grad_features_image, grad_alphas_image = grad_features_image.contiguous(), grad_alphas_image.contiguous()
        grad_sums = scratch("grad_sums", tuple(out_features.shape), torch.float32, final_t.device)   # of the sums
        state = scratch("state", (len(final_t), 3), torch.float32, final_t.device)   # T, behind, grad alpha
        launch(backward_kernel, len(row_offsets) - 1, ctx.span_arrays + ctx.finish
            + [warp_view(out_features, vec), warp_view(stop), warp_view(final_t),
               warp_view(grad_features_image, vec), warp_view(grad_alphas_image),
               warp_view(grad_sums, vec), warp_view(state, wp.vec3)] + [
            warp_view(grads[0], wp.vec2), warp_view(grads[1], wp.vec3), warp_view(grads[2]),
            warp_view(grads[3], vec)], means2d.device)
        return (*grads, None, None, None, None, None, None, None, None, None, None)


def _span_arrays(means2d, conics, opacities, features, drawn, per_camera, decay, row_offsets, spans, starts,
                 vec) -> list:
    return [warp_view(drawn), len(opacities), warp_view(means2d, wp.vec2), warp_view(conics, wp.vec3),
            warp_view(opacities), warp_view(features, vec), per_camera, warp_view(decay, wp.float64),
            warp_view(row_offsets), warp_view(spans, wp.vec3i), warp_view(starts, wp.vec2d)]


def composite_warp(means2d: torch.Tensor, conics: torch.Tensor, radii: torch.Tensor, opacities: torch.Tensor,
                   features: torch.Tensor, drawn: torch.Tensor, width: int, height: int, n_images: int,
                   backgrounds: torch.Tensor | None = None,
                   expected_depth: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp twin of ``splat_torch.composite_instances`` (same arguments, same rule, same outputs): the instances
    are gathered inside the kernels, their gradients scattered back there, and the pixels finished there."""
    f32 = [t.float().contiguous() for t in (means2d.reshape(-1, 2), conics.reshape(-1, 3), opacities,
                                             features.reshape(-1, features.shape[-1]))]
    drawn = drawn.int()
    row_offsets, spans, starts, decay = row_spans(drawn, *(t.detach() for t in f32[:2]), radii.reshape(-1).int(),
                                                  f32[2].detach(), width, height, n_images)
    backgrounds = (torch.zeros(0, 1, device=means2d.device) if backgrounds is None
                   else backgrounds.detach().float().contiguous())
    out_features, out_alphas = _Composite.apply(*f32, drawn, int(features.dim() == 3), decay, row_offsets, spans,
                                                starts, width, height, backgrounds, int(expected_depth))
    return out_features.to(features.dtype), out_alphas.to(features.dtype)
