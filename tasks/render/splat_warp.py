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
pairs.  Along a row sigma(x) is quadratic in x, so the Gaussian exp(-sigma) is evaluated by a recurrence (two
multiplies per pixel, in float64 so that it drifts < 1e-12 over a span; two exps per span and one per instance)
instead of an exp per pair.  (3) Backward: the same thread walks its spans back to front, recovers
T_i = T_final / prod (1 - alpha_j) and the sum behind each Gaussian per pixel, and accumulates each span's gradient
in registers - the geometry's as three moments of dL/dsigma along the span (dy is constant on a row) - before one
atomic add per (instance, row).  Computation is float32 (the recurrence float64) whatever the input dtype; one pair
of kernels is compiled per channel count.
"""

import functools

import torch
import warp as wp

from .splat_torch import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN
from .warp_interop import launch, warp_view

wp.set_module_options({"enable_backward": False})   # the backward pass is hand-written

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_ALPHA_MAX = wp.constant(ALPHA_MAX)
_T_MIN = wp.constant(TRANSMITTANCE_MIN)
_NO_STOP = wp.constant(2**31 - 1)   # stop marker of a pixel that never stops
_GAUSS_MAX = wp.constant(wp.float64(1.0 + 1e-6))   # exp(-sigma) above it: sigma < 0 beyond the recurrence's rounding
SPAN_MARGIN = 1e-3   # added to the exponent threshold so the spans hold every pair the rule keeps
_vec6 = wp.types.vector(length=6, dtype=float)   # an instance's geometry: mean x, y px; conic a, b, c; opacity


@wp.func
def _span_start(geometry: _vec6, x0: int, py: float):
    """exp(-sigma) at the first pixel x0 of a row span and its first step ratio, float64 (module docstring).

    sigma(x) = 0.5 (a dx^2 + c dy^2) + b dx dy at pixel centre (x + 0.5, py) with d = centre - mean; it is
    quadratic in x, so along the row exp(-sigma(x + 1)) = exp(-sigma(x)) ratio(x), ratio(x + 1) = ratio(x) exp(-a)."""
    a, b, c = wp.float64(geometry[2]), wp.float64(geometry[3]), wp.float64(geometry[4])
    dx = wp.float64(float(x0) + 0.5 - geometry[0])
    dy = wp.float64(py - geometry[1])
    sigma = wp.float64(0.5) * (a * dx * dx + c * dy * dy) + b * dx * dy
    return wp.exp(-sigma), wp.exp(-(a * (dx + wp.float64(0.5)) + b * dy))


@wp.func
def _row_span(geometry: _vec6, threshold: float, box: wp.vec4i, y: int):
    """[x_begin, x_end) of row y inside the box where sigma <= threshold (may be empty)."""
    a, b, c = geometry[2], geometry[3], geometry[4]
    dy = float(y) + 0.5 - geometry[1]
    disc = (b * b - a * c) * dy * dy + 2.0 * a * threshold
    if threshold < 0.0 or disc < 0.0:
        return 0, 0
    root = wp.sqrt(disc)
    lo = geometry[0] - 0.5 + (-b * dy - root) / a
    hi = geometry[0] - 0.5 + (-b * dy + root) / a
    return wp.max(box[0], int(wp.ceil(lo))), wp.min(box[1], int(wp.floor(hi)) + 1)


@wp.kernel
def _fill_rows(geometry: wp.array(dtype=_vec6), thresholds: wp.array(dtype=float), boxes: wp.array(dtype=wp.vec4i),
               image_rows: wp.array(dtype=int), row_offsets: wp.array(dtype=int), cursors: wp.array(dtype=int),
               spans: wp.array(dtype=wp.vec3i)):
    """spans[row_offsets[r] + k] = (instance, x_begin, x_end) for every box row r of every instance."""
    g = wp.tid()
    box = boxes[g]
    for y in range(box[2], box[3]):
        x0, x1 = _row_span(geometry[g], thresholds[g], box, y)
        r = image_rows[g] + y
        spans[row_offsets[r] + wp.atomic_add(cursors, r, 1)] = wp.vec3i(g, x0, x1)


@wp.kernel
def _sort_rows(row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i)):
    """Insertion sort of each row's spans by instance, i.e. front to back (no-op for rows filled in order)."""
    r = wp.tid()
    begin, end = row_offsets[r], row_offsets[r + 1]
    for i in range(begin + 1, end):
        key = spans[i]
        j = i - 1
        while j >= begin and spans[j][0] > key[0]:
            spans[j + 1] = spans[j]
            j -= 1
        spans[j + 1] = key


@functools.cache
def _composite_kernels(n_channels: int):
    """Forward and backward compositing kernels for n_channels feature channels (compiled once per count)."""
    vec = wp.types.vector(length=n_channels, dtype=float)

    @wp.kernel(module="unique", enable_backward=False)
    def forward(geometry: wp.array(dtype=_vec6), decay: wp.array(dtype=wp.float64), features: wp.array(dtype=vec),
                row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), width: int, height: int,
                out_features: wp.array(dtype=vec),
                transmittance: wp.array(dtype=float), stop: wp.array(dtype=int)):
        r = wp.tid()
        py = float(r % height) + 0.5
        row = r * width
        for x in range(width):
            out_features[row + x] = vec()
            transmittance[row + x] = 1.0
            stop[row + x] = _NO_STOP
        for i in range(row_offsets[r], row_offsets[r + 1]):
            g, x0, x1 = spans[i][0], spans[i][1], spans[i][2]
            geo = _vec6(geometry[g])
            f = vec(features[g])
            gauss, ratio = _span_start(geo, x0, py)
            for x in range(x0, x1):
                gauss_x = wp.float64(gauss)
                gauss = gauss * ratio
                ratio = ratio * decay[g]
                t = transmittance[row + x]
                if t < 0.0:
                    continue   # a stopped pixel
                alpha = wp.min(_ALPHA_MAX, geo[5] * float(gauss_x))
                if gauss_x > _GAUSS_MAX or alpha < _ALPHA_MIN:   # sigma < 0 or too faint
                    continue
                next_t = t * (1.0 - alpha)
                if next_t < _T_MIN:
                    transmittance[row + x] = -t   # the pixel stops at g, which is left out; the sign marks it
                    stop[row + x] = g
                    continue
                out_features[row + x] = out_features[row + x] + (alpha * t) * f
                transmittance[row + x] = next_t
        for x in range(width):
            transmittance[row + x] = wp.abs(transmittance[row + x])

    @wp.kernel(module="unique", enable_backward=False)
    def backward(geometry: wp.array(dtype=_vec6), decay: wp.array(dtype=wp.float64), features: wp.array(dtype=vec),
                 row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), width: int, height: int,
                 stop: wp.array(dtype=int), grad_out_features: wp.array(dtype=vec),
                 grad_out_alphas: wp.array(dtype=float), transmittance: wp.array(dtype=float),
                 behind: wp.array(dtype=float), grad_geometry: wp.array(dtype=_vec6),
                 grad_features: wp.array(dtype=vec)):
        # transmittance starts as the final one and is divided back to T_i; behind (starts 0) holds what the
        # Gaussians behind the current one add to grad . features + grad_alpha_image * alpha, per unit T in front
        r = wp.tid()
        py = float(r % height) + 0.5
        row = r * width
        i = row_offsets[r + 1] - 1
        while i >= row_offsets[r]:
            g, x0, x1 = spans[i][0], spans[i][1], spans[i][2]
            i -= 1
            geo = _vec6(geometry[g])
            f = vec(features[g])
            dy = py - geo[1]
            grad_f = vec()
            # dL/dsigma moments over the span (dy is the row's): sum g_s, sum g_s dx, sum g_s dx^2; sum G dL/dalpha
            m0, m1, m2, grad_opacity = float(0.0), float(0.0), float(0.0), float(0.0)
            gauss64, ratio = _span_start(geo, x0, py)
            for x in range(x0, x1):
                gauss_x = wp.float64(gauss64)
                gauss64 = gauss64 * ratio
                ratio = ratio * decay[g]
                p = row + x
                if g >= stop[p]:
                    continue   # at or behind the pixel's stop
                gauss = float(gauss_x)
                alpha = wp.min(_ALPHA_MAX, geo[5] * gauss)
                if gauss_x > _GAUSS_MAX or alpha < _ALPHA_MIN:
                    continue
                t = transmittance[p] / (1.0 - alpha)   # T_i, in front of Gaussian i
                transmittance[p] = t
                grad_pixel = grad_out_features[p]
                grad_here = wp.dot(grad_pixel, f) + grad_out_alphas[p]
                grad_f += (alpha * t) * grad_pixel
                grad_alpha = t * (grad_here - behind[p])
                behind[p] = alpha * grad_here + (1.0 - alpha) * behind[p]
                if geo[5] * gauss <= _ALPHA_MAX:   # a clamped alpha passes no gradient to its geometry and opacity
                    grad_sigma = -alpha * grad_alpha
                    dx = float(x) + 0.5 - geo[0]
                    m0 += grad_sigma
                    m1 += grad_sigma * dx
                    m2 += grad_sigma * dx * dx
                    grad_opacity += gauss * grad_alpha
            if x1 > x0:
                wp.atomic_add(grad_geometry, g, _vec6(-(geo[2] * m1 + geo[3] * dy * m0),
                                                      -(geo[3] * m1 + geo[4] * dy * m0), 0.5 * m2, dy * m1,
                                                      0.5 * dy * dy * m0, grad_opacity))
                wp.atomic_add(grad_features, g, grad_f)

    return forward, backward, vec


def row_spans(geometry: torch.Tensor, boxes: torch.Tensor, image_rows: torch.Tensor,
              n_rows: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Every image row's spans (instance, x_begin, x_end), front to back. No gradient.

    geometry: (G, 6) float32 mean x, y px, conic a, b, c 1/px^2, opacity; boxes: (G, 4) int32 x0, x1, y0, y1;
    image_rows: (G,) int64, the instance's image index times the image height; n_rows: images x height.
    Returns offsets (n_rows + 1,) int32 and spans (sum of box heights, 3) int32: row r owns
    ``spans[offsets[r]:offsets[r + 1]]``; a span is the part of the box row where the instance can reach
    alpha >= 1/255 (empty when x_end <= x_begin).
    """
    device = geometry.device
    # 1. per-row counts of box rows from a difference array, 2. their scan
    marks = torch.zeros(n_rows + 1, dtype=torch.int64, device=device)
    ones = torch.ones(len(boxes), dtype=torch.int64, device=device)
    marks.index_add_(0, image_rows + boxes[:, 2], ones).index_add_(0, image_rows + boxes[:, 3], -ones)
    offsets = torch.zeros(n_rows + 1, dtype=torch.int32, device=device)
    torch.cumsum(torch.cumsum(marks[:-1], 0), 0, out=offsets[1:])
    # 3. spans where sigma <= ln(opacity / ALPHA_MIN) (+ margin), 4. each row sorted front to back
    thresholds = torch.log(geometry[:, 5].clamp_min(1e-12) / ALPHA_MIN) + SPAN_MARGIN
    spans = torch.empty(int(offsets[-1]), 3, dtype=torch.int32, device=device)
    launch(_fill_rows, len(geometry), [warp_view(geometry, _vec6), warp_view(thresholds), warp_view(boxes, wp.vec4i),
                                        warp_view(image_rows.int()), warp_view(offsets),
                                        warp_view(torch.zeros(n_rows, dtype=torch.int32, device=device)),
                                        warp_view(spans, wp.vec3i)], device)
    if device.type != "cpu":   # a CPU launch runs its threads in order: the buckets are filled sorted
        launch(_sort_rows, n_rows, [warp_view(offsets), warp_view(spans, wp.vec3i)], device)
    return offsets, spans


class _Composite(torch.autograd.Function):
    """Differentiable compositing of float32 instances over precomputed row spans, one Warp thread per image row."""

    @staticmethod
    def forward(ctx, geometry, features, row_offsets, spans, width: int, height: int):
        forward_kernel, _, vec = _composite_kernels(features.shape[1])
        n_rows = len(row_offsets) - 1
        device, n_pixels = geometry.device, n_rows * width
        out_features = torch.empty(n_pixels, features.shape[1], dtype=torch.float32, device=device)
        final_t = torch.empty(n_pixels, dtype=torch.float32, device=device)
        stop = torch.empty(n_pixels, dtype=torch.int32, device=device)
        decay = torch.exp(-geometry[:, 2].detach().double())   # exp(-a): the step of the ratio along a row
        launch(forward_kernel, n_rows, _span_arrays(geometry, decay, features, row_offsets, spans, vec) + [
            width, height, warp_view(out_features, vec), warp_view(final_t), warp_view(stop)], device)
        ctx.save_for_backward(geometry, decay, features, row_offsets, spans, final_t, stop)
        ctx.width, ctx.height = width, height
        return out_features, 1.0 - final_t

    @staticmethod
    def backward(ctx, grad_features_image, grad_alphas_image):
        geometry, decay, features, row_offsets, spans, final_t, stop = ctx.saved_tensors
        _, backward_kernel, vec = _composite_kernels(features.shape[1])
        grad_geometry, grad_features = torch.zeros_like(geometry), torch.zeros_like(features)
        scratch = [final_t.clone(), torch.zeros_like(final_t)]   # T, behind
        launch(backward_kernel, len(row_offsets) - 1, _span_arrays(geometry, decay, features, row_offsets, spans,
                                                                   vec) + [
            ctx.width, ctx.height, warp_view(stop), warp_view(grad_features_image.contiguous(), vec),
            warp_view(grad_alphas_image.contiguous())] + [warp_view(t) for t in scratch] + [
            warp_view(grad_geometry, _vec6), warp_view(grad_features, vec)], geometry.device)
        return grad_geometry, grad_features, None, None, None, None


def _span_arrays(geometry, decay, features, row_offsets, spans, vec) -> list:
    return [warp_view(geometry, _vec6), warp_view(decay, wp.float64), warp_view(features, vec), warp_view(row_offsets),
            warp_view(spans, wp.vec3i)]


def composite_warp(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
                   boxes: torch.Tensor, pixel_offsets: torch.Tensor, width: int, height: int,
                   n_images: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp twin of ``splat_torch.composite_pairs`` (same arguments, same rule, same outputs).

    means2d: (G, 2) px; conics: (G, 3) 1/px^2; opacities: (G,); features: (G, K); boxes: (G, 4) int; pixel_offsets:
    (G,) int (image index times width * height); instances sorted front to back. Returns features
    (n_images * height * width, K) and alphas (n_images * height * width,) in the dtype of ``features``,
    differentiable w.r.t. means2d, conics, opacities and features.
    """
    geometry = torch.cat([means2d, conics, opacities[:, None]], dim=1).float().contiguous()
    row_offsets, spans = row_spans(geometry.detach(), boxes.int().contiguous(), pixel_offsets.long() // width,
                                   n_images * height)
    out_features, out_alphas = _Composite.apply(geometry, features.float().contiguous(), row_offsets, spans, width,
                                                height)
    return out_features.to(features.dtype), out_alphas.to(features.dtype)
