"""The Warp backend's frame: NVIDIA Warp kernels (LLVM on CPU, CUDA on a GPU) from the Gaussians to finished pixels
and back, as one ``torch.autograd.Function`` (``_Frame``) with no torch autograd inside: the projection
(``splat_warp_projection``), the front-to-back forward pass and the hand-written back-to-front backward pass of
3DGS (Kerbl et al. 2023, sec. 4 and its released rasteriser); it follows the compositing rule of ``splat_torch``
exactly.

Design (chosen by measurement, ``tasks.render.benchmark``): one thread per image row.  (0) The drawn (camera,
Gaussian) pairs, the instances, are sorted by depth and gathered once into packed records (geometry, features,
exp(-a)), so no later kernel indexes the projection, the opacities or the colours.  (1) Every instance walks the rows
of its box and solves the quadratic sigma(x) <= ln(opacity / ALPHA_MIN) for its x span on that row, so only pairs
that can reach alpha >= 1/255 are ever visited; the spans are bucketed by row (a counting sort: count from a
difference array, scan, fill) and each row's bucket is insertion-sorted by instance, i.e. front to back (instances
arrive sorted by depth; on the CPU a launch runs in order, so the buckets are sorted already and the sort is skipped,
on CUDA the atomics scramble them).  (2) Forward: a row's thread composites its spans front to back into the row's
pixels (transmittance, channels, stop marker) - no per-pixel lists and no sort of pairs.  sigma is quadratic in x, so
along a span exp(-sigma) is evaluated by a recurrence instead of an exp per pair (two float64 multiplies per pixel,
drift < 1e-12); a span's start value and first ratio are two exps per span, taken vectorised by torch on the bucketed
exponents.  (3) Backward: the same thread walks its spans back to front, recovers T_i = T_final / prod (1 - alpha_j)
and the sum behind each Gaussian per pixel, and accumulates each span's gradient in registers - the geometry's as
three moments of dL/dsigma along the span (dy is constant on a row) - before one add per (instance, row) into the
instance's gradient record; one thread per instance then scatters the records' gradients to the projection, the
opacities and the colours, and the projection's adjoint takes them to the Gaussians.  Computation is float32 (the
recurrence float64) whatever the input dtype, with multiply-adds fused in the compositing kernels (-ffp-contract=fast
on the CPU); the instance kernels are compiled per channel layout.

On the CPU, steps (2) and (3) run in the lanes compositor (``splat_warp_lanes``, ``COMPOSITOR``): the same pairs in
the same order, a span's pixels 16 at a time in SIMD registers with one vectorised exp per pixel instead of the
recurrence (Warp's CPU code generation leaves these scalar kernels scalar); CUDA runs the kernels below.
"""

import functools
from typing import NamedTuple

import torch
import warp as wp

from .splat_projection import Projection
from .splat_torch import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN
from .splat_warp_finish import finished_pixel, finished_pixel_adjoint
from .splat_warp_lanes import LANES, MAX_CHANNELS, lane_kernels, plane_stride
from .splat_warp_projection import project_adjoint, project_warp
from .warp_interop import launch, scratch, warp_view

wp.set_module_options({"enable_backward": False})   # the backward pass is hand-written

_ALPHA_MIN = wp.constant(ALPHA_MIN)
_ALPHA_MAX = wp.constant(ALPHA_MAX)
_T_MIN = wp.constant(TRANSMITTANCE_MIN)
_NO_STOP = wp.constant(2**31 - 1)   # stop marker of a pixel that never stops
_GAUSS_MAX = wp.constant(wp.float64(1.0 + 1e-6))   # exp(-sigma) above it: sigma < 0 beyond the recurrence's rounding
_SPAN_MARGIN = wp.constant(1e-3)   # added to the exponent threshold so the spans hold every pair the rule keeps
_ROW_SLACK = wp.constant(1e-2)   # px added to an instance's row reach against rounding (a whole row: 9 % empty spans)
_vec6 = wp.types.vector(length=6, dtype=float)   # an instance's geometry: mean x, y px; conic a, b, c; opacity
# the compositing kernels' CPU flags: Warp's plus -ffp-contract=fast (Warp emits one statement per operation, so
# without it the compiler never fuses a multiply and an add)
_FMA = {"cpu_compiler_flags": f"{wp.config.cpu_compiler_flags or '-march=native'} -ffp-contract=fast"}


@wp.func
def _pixel_exponents(geometry: _vec6, x: int, y: int):
    """-sigma at pixel (x, y) and the exponent of its step ratio to pixel (x + 1, y), float64 (their exps are a
    span's start: exp(-sigma) and ratio_x = exp(-sigma(x + 1, y)) / exp(-sigma(x, y))).

    sigma = 0.5 (a dx^2 + c dy^2) + b dx dy at the pixel centre (x + 0.5, y + 0.5) with d = centre - mean; it is
    quadratic in x, so exp(-sigma(x + 1, y)) = exp(-sigma) ratio_x with ratio_x = exp(-(a (dx + 1/2) + b dy)),
    which itself steps by exp(-a) along x (``decay``)."""
    a, b, c = wp.float64(geometry[2]), wp.float64(geometry[3]), wp.float64(geometry[4])
    half = wp.float64(0.5)
    dx = wp.float64(x) + half - wp.float64(geometry[0])
    dy = wp.float64(y) + half - wp.float64(geometry[1])
    return -(half * (a * dx * dx + c * dy * dy) + b * dx * dy), -(a * (dx + half) + b * dy)


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
def _fill_rows(drawn: wp.array(dtype=int), n_gaussians: int, geometry: wp.array(dtype=_vec6),
               boxes: wp.array(dtype=wp.vec4i), height: int, row_offsets: wp.array(dtype=int),
               cursors: wp.array(dtype=int),
               spans: wp.array(dtype=wp.vec3i), with_starts: int, starts: wp.array(dtype=wp.vec2d)):
    """spans[row_offsets[r] + j] = (instance, x_begin, x_end) for every box row r of every instance: the part of
    the row where sigma <= ln(opacity / ALPHA_MIN) (+ _SPAN_MARGIN); with_starts, starts[...] = the exponents of
    exp(-sigma) and of its step ratio along x at x_begin (``_pixel_exponents``; the caller takes their exps,
    vectorised)."""
    i = wp.tid()
    geo = geometry[i]
    threshold = _threshold(geo[5])
    box = boxes[i]
    first = (drawn[i] // n_gaussians) * height
    for y in range(box[2], box[3]):
        x0, x1 = _row_span(geo, threshold, box, y)
        r = first + y
        j = row_offsets[r] + wp.atomic_add(cursors, r, 1)
        spans[j] = wp.vec3i(i, x0, x1)
        if with_starts == 0:
            continue
        starts[j] = wp.vec2d(wp.float64(0.0), wp.float64(0.0))   # an empty span's: never read
        if x1 > x0:
            log_gauss, log_ratio = _pixel_exponents(geo, x0, y)
            starts[j] = wp.vec2d(log_gauss, log_ratio)


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


class FrameKernels(NamedTuple):
    """A channel layout's kernels (``_composite_kernels``) and its vector types: the channels, the colours alone,
    the channels and the transmittance."""

    instances: wp.Kernel
    forward: wp.Kernel
    backward: wp.Kernel
    scatter: wp.Kernel
    vec: type
    vec_c: type
    vec_t: type


@functools.cache
def _composite_kernels(n_colors: int, with_depth: bool):
    """The kernels of a frame's instances for n_colors colour channels and, with_depth, the camera-space depth as the
    last channel (compiled once per pair): their records and boxes, the compositing forward and backward, and the
    scatter of the instances' gradients.  Instance i is camera-Gaussian k = drawn[i] (flat camera * N + Gaussian),
    Gaussian n = k % N; its colours are row k of ``colors`` when per_camera, else row n, its depth depths[k]."""
    n_channels = n_colors + int(with_depth)
    vec = wp.types.vector(length=n_channels, dtype=float)
    vec_c = wp.types.vector(length=max(n_colors, 1), dtype=float)   # the colours (a dummy channel when none)
    vec_t = wp.types.vector(length=n_channels + 1, dtype=float)   # the channels and the transmittance

    @wp.kernel(module="unique", enable_backward=False)
    def instances(drawn: wp.array(dtype=int), n_gaussians: int, means2d: wp.array(dtype=wp.vec2),
                  conics: wp.array(dtype=wp.vec3), opacities: wp.array(dtype=float), colors: wp.array(dtype=vec_c),
                  depths: wp.array(dtype=float), per_camera: int, radii: wp.array(dtype=int), width: int, height: int,
                  geometry: wp.array(dtype=_vec6), features: wp.array(dtype=vec), decay: wp.array(dtype=wp.float64),
                  boxes: wp.array(dtype=wp.vec4i), marks: wp.array(dtype=int)):
        """Per instance i, its packed records - geometry (mean x, y px, conic a, b, c 1/px^2, opacity), features,
        exp(-a) - gathered once for all its spans; its pixel box (``splat_projection.pixel_boxes``) with its rows cut
        to those its span ellipse sigma <= threshold reaches (|dy| <= sqrt(2 a threshold / det) + _ROW_SLACK; no
        rows when empty); +1 / -1 in the difference array of per-row span counts at its first / past-last
        row."""
        i = wp.tid()
        k = drawn[i]
        n = k % n_gaussians
        m, r, q = means2d[k], float(radii[k]), conics[k]
        geometry[i] = _vec6(m[0], m[1], q[0], q[1], q[2], opacities[n])
        f = vec()
        c = vec_c(colors[wp.where(per_camera != 0, k, n)])
        for ch in range(n_colors):
            f[ch] = c[ch]
        if wp.static(with_depth):
            f[n_channels - 1] = depths[k]
        features[i] = f
        decay[i] = wp.exp(-wp.float64(q[0]))
        x0 = int(wp.clamp(wp.ceil(m[0] - r - 0.5), 0.0, float(width)))
        x1 = int(wp.clamp(wp.floor(m[0] + r - 0.5) + 1.0, 0.0, float(width)))
        threshold, det = _threshold(opacities[n]), q[0] * q[2] - q[1] * q[1]
        reach = r
        if det > 0.0:
            reach = wp.min(r, wp.sqrt(2.0 * q[0] * wp.max(threshold, 0.0) / det) + _ROW_SLACK)
        y0 = int(wp.clamp(wp.ceil(m[1] - reach - 0.5), 0.0, float(height)))
        y1 = int(wp.clamp(wp.floor(m[1] + reach - 0.5) + 1.0, 0.0, float(height)))
        if x1 <= x0 or threshold < 0.0 or y1 < y0:
            y1 = y0
        boxes[i] = wp.vec4i(x0, x1, y0, y1)
        if y1 > y0:
            first = (k // n_gaussians) * height
            wp.atomic_add(marks, first + y0, 1)
            wp.atomic_add(marks, first + y1, -1)

    @wp.kernel(module="unique", enable_backward=False, module_options=_FMA)
    def forward(geometry: wp.array(dtype=_vec6), features: wp.array(dtype=vec), decay: wp.array(dtype=wp.float64),
                row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), starts: wp.array(dtype=wp.vec2d),
                width: int, height: int,
                backgrounds: wp.array(dtype=float), n_background: int, expected_depth: int,
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
            geo = geometry[g]
            f = features[g]
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
            out_features[row + x] = finished_pixel(v, t, expected_depth, backgrounds, n_background, camera)

    @wp.kernel(module="unique", enable_backward=False, module_options=_FMA)
    def backward(geometry: wp.array(dtype=_vec6), features: wp.array(dtype=vec), decay: wp.array(dtype=wp.float64),
                 row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), starts: wp.array(dtype=wp.vec2d),
                 width: int, height: int, backgrounds: wp.array(dtype=float), n_background: int, expected_depth: int,
                 out_features: wp.array(dtype=vec),
                 stop: wp.array(dtype=int), transmittance: wp.array(dtype=float), grad_finished: wp.array(dtype=vec),
                 grad_finished_alphas: wp.array(dtype=float), grad_out_features: wp.array(dtype=vec),
                 state: wp.array(dtype=wp.vec3), grad_geometry: wp.array(dtype=_vec6),
                 grad_features: wp.array(dtype=vec)):
        # per pixel, state = (T, behind, dL/dalpha of the composited alpha): T starts as the final transmittance and
        # is divided back to T_i; behind (starts 0) holds what the Gaussians behind the current one add to
        # grad . features + grad_alpha_image * alpha, per unit T in front (one array: one address per pixel)
        r = wp.tid()
        py = float(r % height) + 0.5
        row = r * width
        # gradients of the finished pixels -> of the composited sums and alpha (grad_out_*: written here)
        camera = r // height
        for x in range(width):
            grad_v, grad_a = finished_pixel_adjoint(grad_finished[row + x], grad_finished_alphas[row + x],
                                                    transmittance[row + x], out_features[row + x][n_channels - 1],
                                                    expected_depth, backgrounds, n_background, camera)
            grad_out_features[row + x] = grad_v
            state[row + x] = wp.vec3(transmittance[row + x], 0.0, grad_a)
        j = row_offsets[r + 1] - 1
        while j >= row_offsets[r]:
            g, x0, x1 = spans[j][0], spans[j][1], spans[j][2]
            j -= 1
            if x1 <= x0:
                continue
            geo = geometry[g]
            f = features[g]
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
            wp.atomic_add(grad_geometry, g, _vec6(-(geo[2] * m1 + geo[3] * dy * m0), -(geo[3] * m1 + geo[4] * dy * m0),
                                                  0.5 * m2, dy * m1, 0.5 * dy * dy * m0, grad_opacity))
            wp.atomic_add(grad_features, g, grad_f)

    @wp.kernel(module="unique", enable_backward=False)
    def scatter(drawn: wp.array(dtype=int), n_gaussians: int, per_camera: int, grad_geometry: wp.array(dtype=_vec6),
                grad_features: wp.array(dtype=vec), grad_means2d: wp.array(dtype=wp.vec2),
                grad_conics: wp.array(dtype=wp.vec3), grad_opacities: wp.array(dtype=float),
                grad_colors: wp.array(dtype=vec_c), grad_depths: wp.array(dtype=float)):
        """Instance i's gradients (of its records) to those of the projection, opacities and colours it came from."""
        i = wp.tid()
        k = drawn[i]
        n = k % n_gaussians
        g, f = grad_geometry[i], grad_features[i]
        wp.atomic_add(grad_means2d, k, wp.vec2(g[0], g[1]))
        wp.atomic_add(grad_conics, k, wp.vec3(g[2], g[3], g[4]))
        wp.atomic_add(grad_opacities, n, g[5])
        c = vec_c()
        for ch in range(n_colors):
            c[ch] = f[ch]
        wp.atomic_add(grad_colors, wp.where(per_camera != 0, k, n), c)
        if wp.static(with_depth):
            wp.atomic_add(grad_depths, k, f[n_channels - 1])

    return FrameKernels(instances, forward, backward, scatter, vec, vec_c, vec_t)


def instance_spans(kernels: FrameKernels, drawn: torch.Tensor, proj: Projection, opacities: torch.Tensor,
                   colors: torch.Tensor, width: int, height: int, with_starts: bool = True) -> tuple[torch.Tensor, ...]:
    """The instances' records and every image row's spans (instance, x_begin, x_end), front to back, with where
    their recurrences start.  No gradient.

    kernels: those of the frame's channels; drawn: (G,) int32 flat camera * N + Gaussian of the instances, front to
    back; proj: the Warp projection of the C cameras; opacities (N,), colors (N, D) or (C, N, D) float32 contiguous.
    Returns the records geometry (G, 6)
    (mean x, y px, conic a, b, c 1/px^2, opacity), features (G, D [+ 1 depth]) and decay (G,) float64 exp(-a);
    offsets (C * height + 1,) int32, spans (sum of box heights, 3) int32 - row r owns
    ``spans[offsets[r]:offsets[r + 1]]``; a span is the part of the box row where the instance can reach
    alpha >= 1/255 (empty when x_end <= x_begin) -, starts (spans, 2) float64 exp(-sigma) and its step ratio at
    each span's first pixel (with_starts; else (0, 2): the lanes compositor takes an exp per pixel).
    """
    device, n_rows, n_gaussians = drawn.device, len(proj.radii) * height, len(opacities)
    # 1. records, boxes and the difference array of per-row counts, 2. its scan
    geometry = torch.empty(len(drawn), 6, dtype=torch.float32, device=device)
    features = torch.empty(len(drawn), kernels.vec._length_, dtype=torch.float32, device=device)
    decay = torch.empty(len(drawn), dtype=torch.float64, device=device)
    boxes = scratch("boxes", (len(drawn), 4), torch.int32, device)
    marks = scratch("marks", (n_rows + 1,), torch.int32, device).zero_()
    launch(kernels.instances, len(drawn), [
        warp_view(drawn), n_gaussians, warp_view(proj.means2d.view(-1, 2), wp.vec2),
        warp_view(proj.conics.view(-1, 3), wp.vec3), warp_view(opacities),
        warp_view(colors.view(-1, colors.shape[-1]), kernels.vec_c), warp_view(proj.depths.view(-1)),
        int(colors.dim() == 3), warp_view(proj.radii.view(-1)), width, height, warp_view(geometry, _vec6),
        warp_view(features, kernels.vec), warp_view(decay, wp.float64), warp_view(boxes, wp.vec4i),
        warp_view(marks)], device)
    offsets = torch.zeros(n_rows + 1, dtype=torch.int32, device=device)
    torch.cumsum(torch.cumsum(marks[:-1], 0), 0, out=offsets[1:])
    # 3. the spans, 4. each row sorted front to back
    spans = torch.empty(int(offsets[-1]), 3, dtype=torch.int32, device=device)
    starts = torch.empty(len(spans) if with_starts else 0, 2, dtype=torch.float64, device=device)
    cursors = scratch("cursors", (n_rows + 1,), torch.int32, device).zero_()
    launch(_fill_rows, len(drawn), [warp_view(drawn), n_gaussians, warp_view(geometry, _vec6),
                                    warp_view(boxes, wp.vec4i), height, warp_view(offsets), warp_view(cursors),
                                    warp_view(spans, wp.vec3i), int(with_starts), warp_view(starts, wp.vec2d)],
           device)
    torch.exp(starts, out=starts)   # two exps per span, vectorised
    if device.type != "cpu":   # a CPU launch runs its threads in order: the buckets are filled sorted
        launch(_sort_rows, n_rows, [warp_view(offsets), warp_view(spans, wp.vec3i), warp_view(starts, wp.vec2d)],
               device)
    return geometry, features, decay, offsets, spans, starts


COMPOSITOR = "auto"   # "auto": the lanes compositor on the CPU (``splat_warp_lanes``), these kernels on CUDA; "scalar"


def uses_lanes(device: torch.device, n_channels: int) -> bool:
    """Whether a frame of ``n_channels`` composited channels on ``device`` takes the lanes compositor
    (``COMPOSITOR``; a layout of more than MAX_CHANNELS - 1 channels takes the scalar kernels)."""
    if COMPOSITOR not in ("auto", "scalar"):
        raise ValueError(f"splat_warp.COMPOSITOR must be auto or scalar, got {COMPOSITOR!r}")
    return COMPOSITOR == "auto" and device.type == "cpu" and n_channels + 1 <= MAX_CHANNELS


class FrameSettings(NamedTuple):
    """What a frame renders besides its tensors: image size px, the projection's eps2d px^2, near_plane and far_plane
    m, the colour channels (n_colors, 0 for depth alone), the depth as a last channel (with_depth), the expected
    depth instead of the accumulated one (expected_depth)."""

    width: int
    height: int
    eps2d: float
    near_plane: float
    far_plane: float
    n_colors: int
    with_depth: bool
    expected_depth: bool


class _Frame(torch.autograd.Function):
    """A whole frame of float32 Gaussians as one differentiable step, with no torch autograd inside: projection
    (``project_warp``), the instances front to back, their records and row spans (``instance_spans``) and the
    compositing forward; backward, the compositing backward, the scatter of the instances' gradients and the
    projection's adjoint (``project_adjoint``)."""

    @staticmethod
    def forward(ctx, means, quats, scales, covars, opacities, colors, viewmats, Ks, backgrounds,
                settings: FrameSettings):
        device, n_images = means.device, len(viewmats)
        proj = project_warp(means, quats, scales, covars, viewmats, Ks, tuple(settings[:5]))
        # the drawn (camera, Gaussian) instances front to back (flat index camera * N + Gaussian)
        drawn = torch.nonzero(proj.radii.flatten() > 0).squeeze(1)
        drawn = drawn[torch.sort(proj.depths.flatten()[drawn], stable=True).indices].int()
        kernels = _composite_kernels(settings.n_colors, settings.with_depth)
        n_channels, n_rows = kernels.vec._length_, n_images * settings.height
        lanes = uses_lanes(device, n_channels)
        records = instance_spans(kernels, drawn, proj, opacities, colors, settings.width, settings.height,
                                 with_starts=not lanes)
        n_pixels = n_rows * settings.width
        out_features = torch.empty(n_pixels, n_channels, dtype=torch.float32, device=device)
        out_alphas, final_t = (torch.empty(n_pixels, dtype=torch.float32, device=device) for _ in range(2))
        finishing = [warp_view(backgrounds.view(-1)), backgrounds.shape[1] * int(backgrounds.shape[0] > 0),
                     int(settings.expected_depth)]
        geometry, features, decay, offsets, spans, starts = records
        if lanes:   # 16 pixels of a span at a time, in planes (``splat_warp_lanes``)
            stride = plane_stride(settings.width)
            stop = torch.empty(n_rows, stride, dtype=torch.int32, device=device)
            sums = scratch("sums_planes", (n_rows * (n_channels + 1) * stride,), torch.float32, device)
            ctx.span_arrays = [warp_view(geometry, _vec6), warp_view(features.view(-1)), warp_view(offsets),
                               warp_view(spans, wp.vec3i), settings.width, settings.height, stride] + finishing
            forward = lane_kernels(n_channels, kernels.vec).forward
        else:
            stop = torch.empty(n_pixels, dtype=torch.int32, device=device)
            sums = scratch("sums", (n_pixels, n_channels + 1), torch.float32, device)
            ctx.span_arrays = [warp_view(geometry, _vec6), warp_view(features, kernels.vec),
                               warp_view(decay, wp.float64), warp_view(offsets), warp_view(spans, wp.vec3i),
                               warp_view(starts, wp.vec2d), settings.width, settings.height] + finishing
            forward = kernels.forward
        launch(forward, n_rows, ctx.span_arrays + [
            warp_view(out_features, kernels.vec), warp_view(out_alphas), warp_view(final_t), warp_view(stop.view(-1)),
            warp_view(sums) if lanes else warp_view(sums, kernels.vec_t)], device)
        ctx.lanes = lanes
        ctx.save_for_backward(means, quats, scales, covars, viewmats, Ks, colors, drawn, *records, final_t, stop,
                              out_features, backgrounds)
        ctx.settings = settings
        ctx.mark_non_differentiable(proj.radii, proj.means2d, proj.depths, proj.conics, drawn)
        return out_features, out_alphas, proj.radii, proj.means2d, proj.depths, proj.conics, drawn

    @staticmethod
    def backward(ctx, grad_image, grad_alphas, *_):
        means, quats, scales, covars, viewmats, Ks, colors, drawn, *records = ctx.saved_tensors
        final_t, stop, out_features, _ = records[6:]
        settings, device, shape = ctx.settings, means.device, (len(viewmats), len(means))
        kernels = _composite_kernels(settings.n_colors, settings.with_depth)
        # 1. the compositing backward into the instances' records, 2. to the projection, opacities and colours
        grad_image, grad_alphas = grad_image.contiguous(), grad_alphas.contiguous()
        n_rows, n_channels = shape[0] * settings.height, kernels.vec._length_
        if ctx.lanes:
            stride = plane_stride(settings.width)
            grad_sums = scratch("grad_sums_planes", (n_rows * n_channels * stride,), torch.float32, device)
            state = scratch("state_planes", (n_rows * 3 * stride,), torch.float32, device)   # T, behind, grad alpha
            # the gradients of the records (geometry, features) per instance and lane
            partials = scratch("partials", (len(drawn), 6 + n_channels, LANES), torch.float32, device).zero_()
            backward, views = lane_kernels(n_channels, kernels.vec).backward, (
                warp_view(grad_sums), warp_view(state), warp_view(partials.view(-1)))
        else:
            grad_sums = scratch("grad_sums", tuple(out_features.shape), torch.float32, device)   # of the sums
            state = scratch("state", (len(final_t), 3), torch.float32, device)   # T, behind, grad alpha
            grad_geometry, grad_features = torch.zeros_like(records[0]), torch.zeros_like(records[1])
            backward, views = kernels.backward, (warp_view(grad_sums, kernels.vec), warp_view(state, wp.vec3),
                                                 warp_view(grad_geometry, _vec6),
                                                 warp_view(grad_features, kernels.vec))
        launch(backward, n_rows, ctx.span_arrays + [
            warp_view(out_features, kernels.vec), warp_view(stop.view(-1)), warp_view(final_t),
            warp_view(grad_image, kernels.vec), warp_view(grad_alphas), *views], device)
        if ctx.lanes:   # the instances' records: their lanes summed
            records_grad = partials.sum(dim=2)
            grad_geometry, grad_features = records_grad[:, :6].contiguous(), records_grad[:, 6:].contiguous()
        grad_means2d, grad_depths, grad_conics = (torch.zeros(shape[0] * shape[1], size, dtype=torch.float32,
                                                              device=device) for size in (2, 1, 3))
        grad_opacities = torch.zeros(len(means), dtype=torch.float32, device=device)
        grad_colors = torch.zeros_like(colors)
        launch(kernels.scatter, len(drawn), [
            warp_view(drawn), len(means), int(colors.dim() == 3), warp_view(grad_geometry, _vec6),
            warp_view(grad_features, kernels.vec), warp_view(grad_means2d, wp.vec2), warp_view(grad_conics, wp.vec3),
            warp_view(grad_opacities), warp_view(grad_colors.view(-1, colors.shape[-1]), kernels.vec_c),
            warp_view(grad_depths.view(-1))], device)
        # 3. the projection's adjoint
        grad_means, grad_quats, grad_scales, grad_covars = project_adjoint(
            means, quats, scales, covars, viewmats, Ks, tuple(settings[:5]), grad_means2d.view(shape + (2,)),
            grad_depths.view(shape), grad_conics.view(shape + (3,)))
        return grad_means, grad_quats, grad_scales, grad_covars, grad_opacities, grad_colors, None, None, None, None


def render_warp(means: torch.Tensor, quats: torch.Tensor | None, scales: torch.Tensor | None,
                covars: torch.Tensor | None, opacities: torch.Tensor, colors: torch.Tensor | None,
                viewmats: torch.Tensor, Ks: torch.Tensor, backgrounds: torch.Tensor | None,
                settings: FrameSettings) -> tuple[torch.Tensor, torch.Tensor, Projection, torch.Tensor]:
    """A frame of ``splat.rasterization`` on the Warp backend: Gaussians (quats and scales, or covars) into the
    cameras, composited into finished pixels (colours, then the depth with settings.with_depth; expected depth,
    backgrounds), differentiable w.r.t. means, quats, scales, covars, opacities and colors (None with n_colors 0).
    Returns features (C * height * width, channels) and alphas (C * height * width,) in the colours' dtype, the
    projection and the drawn instances (flat camera * N + Gaussian, front to back)."""
    dtype = means.dtype if colors is None else colors.dtype
    f32 = [None if t is None else t.float().contiguous() for t in (means, quats, scales, covars, opacities)]
    if colors is None:   # depth alone: a dummy colour channel the kernels never read
        colors = torch.zeros(len(means), 1, dtype=torch.float32, device=means.device)
    backgrounds = (torch.zeros(0, 1, device=means.device) if backgrounds is None
                   else backgrounds.detach().float().contiguous())
    features, alphas, radii, means2d, depths, conics, drawn = _Frame.apply(
        *f32, colors.float().contiguous(), viewmats.detach().float().contiguous(), Ks.detach().float().contiguous(),
        backgrounds, settings)
    return features.to(dtype), alphas.to(dtype), Projection(radii, means2d, depths, conics), drawn
