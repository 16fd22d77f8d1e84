"""The CPU compositor of the Warp backend: ``splat_warp``'s compositing forward and backward with each row span's
pixels taken LANES at a time in SIMD registers (clang vector extensions in Warp native functions; Warp's own CPU
code generation leaves the scalar kernels scalar, README "Renderer speed").  Same maths, same pairs, same order as
the pure-Warp kernels (which CUDA runs, and which ``splat_warp.COMPOSITOR = "scalar"`` selects on the CPU):

- a span's exp(-sigma) is one vectorised exp per pixel (float32, Cephes-style polynomial, max relative error
  1e-7 on [-87, 0.6]) instead of the scalar kernels' float64 recurrence; sigma is a quadratic in the lane's x;
- the per-pixel state lives in planes (one row of each channel after another), LANES-aligned and padded by one
  block, so a block of pixels is one load and one store per plane; lanes outside the span, pixels that stopped
  and pairs below 1/255 are masked out bitwise;
- the backward adds a span's gradients to its instance's records lane by lane (``partials``: instance, record =
  the 6 of the geometry then the channels, lane), summed over the lanes once per frame by the caller: summing 9-11
  vectors across their lanes after every span cost a quarter of the backward.

A CPU launch runs its threads one after the other, so the native code adds to the partials without atomics.
Planes: forward ``sums`` (row, channel + transmittance, stride) and ``stop`` (row, stride); backward ``state``
(row, 3 = T, behind, dL/dalpha, stride) and ``grad_sums`` (row, channel, stride); stride = ``plane_stride(width)``.
Measured (``python -m flows.bench.render``, README "Renderer speed"): on a 2-core AMD EPYC (AVX-512), the
compositing kernels of a 192 px frame of 3,400 Gaussians 1.37 -> 0.87 ms forward, 2.76 -> 1.54 ms backward.
"""

import functools
import platform
from typing import NamedTuple

import warp as wp

from .splat_torch import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN
from .splat_warp_finish import finished_pixel, finished_pixel_adjoint

LANES = 16   # fp32 lanes of a block (one AVX-512 register; two AVX2 ones)
MAX_CHANNELS = 16   # channels + 1 of a layout the lanes kernels take (the backward keeps one accumulator each)

_vec6 = wp.types.vector(length=6, dtype=float)
# Warp's CPU flags plus fused multiply-adds and, on x86, whole 512-bit registers where the CPU has them (clang
# otherwise splits a 16-lane vector into two 256-bit halves on AVX-512 CPUs; an x86-only option)
_CPU_FLAGS = {"cpu_compiler_flags": f"{wp.config.cpu_compiler_flags or '-march=native'} -ffp-contract=fast"
                                    + (" -mprefer-vector-width=512" if platform.machine().lower() in ("x86_64", "amd64")
                                       else "")}
_NO_STOP = 2**31 - 1

_HEADER = r"""
typedef float lanes_f __attribute__((ext_vector_type(LANES)));
typedef int lanes_i __attribute__((ext_vector_type(LANES)));
lanes_f lane;
for (int l = 0; l < LANES; ++l) lane[l] = (float)l;
// exp(x) for x <= 0.6 (clamped below at -87): 2^n p(r), r = x - n ln 2 (Cephes expf)
auto lanes_exp = [](lanes_f x) -> lanes_f {
    lanes_i low = x < -87.0f;
    x = (lanes_f)(((lanes_i)x & ~low) | ((lanes_i)(lanes_f)(-87.0f) & low));
    lanes_i n = __builtin_convertvector(x * 1.44269504088896341f - 0.5f, lanes_i);
    lanes_f fn = __builtin_convertvector(n, lanes_f);
    lanes_f r = x - fn * 0.693359375f + fn * 2.12194440e-4f;
    lanes_f p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    return (p * r * r + r + 1.0f) * (lanes_f)((n + 127) << 23);
};
auto load_f = [](const float* p) { lanes_f v; __builtin_memcpy(&v, p, sizeof(v)); return v; };
auto load_i = [](const int* p) { lanes_i v; __builtin_memcpy(&v, p, sizeof(v)); return v; };
auto store_f = [](float* p, lanes_f v) { __builtin_memcpy(p, &v, sizeof(v)); };
auto store_i = [](int* p, lanes_i v) { __builtin_memcpy(p, &v, sizeof(v)); };
auto add_f = [&](lanes_f* p, lanes_f v) { store_f((float*)p, load_f((const float*)p) + v); };
auto keep = [](lanes_i m, lanes_f v) { return (lanes_f)((lanes_i)v & m); };   // v where m, else +0
auto choose = [](lanes_i m, lanes_f a, lanes_f b) { return (lanes_f)(((lanes_i)a & m) | ((lanes_i)b & ~m)); };
const float* geometry_all = (const float*)geometry.data;
const float* features_all = (const float*)features.data;
const int* offsets = (const int*)row_offsets.data;
const int* span = (const int*)spans.data;
const float py = (float)(r % height) + 0.5f;
"""

# one row's spans front to back into its planes (sums: channels then transmittance; stop)
_FORWARD = _HEADER + r"""
float* plane = (float*)sums.data + (size_t)r * (n_channels + 1) * stride;
float* t_plane = plane + (size_t)n_channels * stride;
int* stops = (int*)stop.data + (size_t)r * stride;
for (int x = 0; x < stride; x += LANES) {
    for (int c = 0; c < n_channels; ++c) store_f(plane + c * stride + x, (lanes_f)0.0f);
    store_f(t_plane + x, (lanes_f)1.0f);
    store_i(stops + x, (lanes_i)NO_STOP);
}
for (int j = offsets[r]; j < offsets[r + 1]; ++j) {
    const int g = span[3 * j], x0 = span[3 * j + 1], x1 = span[3 * j + 2];
    if (x1 <= x0) continue;   // an empty span (a box row the Gaussian cannot reach with alpha >= 1/255)
    const float* geo = geometry_all + 6 * g;
    const float* f = features_all + (size_t)n_channels * g;
    const float dy = py - geo[1], half_a = 0.5f * geo[2], b_dy = geo[3] * dy, c_dy2 = 0.5f * geo[4] * dy * dy;
    const float opacity = geo[5], dx0 = (float)x0 + 0.5f - geo[0];
    for (int x = x0; x < x1; x += LANES) {
        lanes_f t = load_f(t_plane + x);
        lanes_i open = (lane < (float)(x1 - x)) & (t >= 0.0f);   // t < 0: a stopped pixel
        if (!__builtin_reduce_or(open)) continue;
        lanes_f dx = lane + (dx0 + (float)(x - x0));
        lanes_f gauss = lanes_exp(-((half_a * dx + b_dy) * dx + c_dy2));
        lanes_f alpha = opacity * gauss;
        alpha = choose(alpha > ALPHA_MAX, (lanes_f)ALPHA_MAX, alpha);
        // gauss > GAUSS_MAX: sigma < 0; alpha < ALPHA_MIN: too faint
        lanes_i on = open & (gauss <= GAUSS_MAX) & (alpha >= ALPHA_MIN);
        lanes_f next_t = t * (1.0f - alpha);
        lanes_i stopping = on & (next_t < T_MIN);   // the pixel stops at g, which is left out
        lanes_i adding = on & ~stopping;
        lanes_f weight = keep(adding, alpha * t);
        for (int c = 0; c < n_channels; ++c) {
            float* p = plane + c * stride + x;
            store_f(p, load_f(p) + weight * f[c]);
        }
        store_f(t_plane + x, choose(stopping, -t, choose(adding, next_t, t)));   // the sign marks a stop
        if (__builtin_reduce_or(stopping))
            store_i(stops + x, (load_i(stops + x) & ~stopping) | ((lanes_i)g & stopping));
    }
}
""".replace("NO_STOP", str(_NO_STOP))

# one row's spans back to front: T_i, the sums behind, the gradients of each span's record
_BACKWARD = _HEADER + r"""
float* t_plane = (float*)state.data + (size_t)r * 3 * stride;
float* behind_plane = t_plane + stride;
const float* grad_alpha_plane = t_plane + 2 * stride;
const float* grad_plane = (const float*)grad_sums.data + (size_t)r * n_channels * stride;
const int* stops = (const int*)stop.data + (size_t)r * stride;
lanes_f grad_f[MAX_CHANNELS];
for (int j = offsets[r + 1] - 1; j >= offsets[r]; --j) {
    const int g = span[3 * j], x0 = span[3 * j + 1], x1 = span[3 * j + 2];
    if (x1 <= x0) continue;
    const float* geo = geometry_all + 6 * g;
    const float* f = features_all + (size_t)n_channels * g;
    const float dy = py - geo[1], half_a = 0.5f * geo[2], b_dy = geo[3] * dy, c_dy2 = 0.5f * geo[4] * dy * dy;
    const float opacity = geo[5], dx0 = (float)x0 + 0.5f - geo[0];
    // dL/dsigma moments over the span (dy is the row's): sum g_s, sum g_s dx, sum g_s dx^2; sum G dL/dalpha
    lanes_f m0 = 0.0f, m1 = 0.0f, m2 = 0.0f, grad_opacity = 0.0f;
    for (int c = 0; c < n_channels; ++c) grad_f[c] = 0.0f;
    for (int x = x0; x < x1; x += LANES) {
        lanes_i open = (lane < (float)(x1 - x)) & ((lanes_i)g < load_i(stops + x));   // in front of the stop
        if (!__builtin_reduce_or(open)) continue;
        lanes_f dx = lane + (dx0 + (float)(x - x0));
        lanes_f gauss = lanes_exp(-((half_a * dx + b_dy) * dx + c_dy2));
        lanes_f raw_alpha = opacity * gauss;
        lanes_f alpha = choose(raw_alpha > ALPHA_MAX, (lanes_f)ALPHA_MAX, raw_alpha);
        lanes_i on = open & (gauss <= GAUSS_MAX) & (alpha >= ALPHA_MIN);   // skipped: sigma < 0, too faint
        lanes_f t_after = load_f(t_plane + x), behind = load_f(behind_plane + x);
        lanes_f t = t_after / (1.0f - alpha);   // T_i, in front of Gaussian i
        lanes_f grad_here = load_f(grad_alpha_plane + x);
        lanes_f weight = keep(on, alpha * t);
        for (int c = 0; c < n_channels; ++c) {
            lanes_f grad_pixel = load_f(grad_plane + c * stride + x);
            grad_here += grad_pixel * f[c];
            grad_f[c] += weight * grad_pixel;
        }
        lanes_f grad_alpha = t * (grad_here - behind);
        store_f(t_plane + x, choose(on, t, t_after));
        store_f(behind_plane + x, choose(on, alpha * grad_here + (1.0f - alpha) * behind, behind));
        lanes_i unclamped = on & (raw_alpha <= ALPHA_MAX);   // a clamped alpha passes no gradient to geometry, opacity
        lanes_f grad_sigma = keep(unclamped, -alpha * grad_alpha);
        m0 += grad_sigma;
        m1 += grad_sigma * dx;
        m2 += grad_sigma * dx * dx;
        grad_opacity += keep(unclamped, gauss * grad_alpha);
    }
    // the span's share of its instance's gradient records, still per lane (summed over the lanes once per instance)
    lanes_f* part = (lanes_f*)((float*)partials.data + (size_t)g * (6 + n_channels) * LANES);
    add_f(part + 0, -(geo[2] * m1 + (geo[3] * dy) * m0));
    add_f(part + 1, -(geo[3] * m1 + (geo[4] * dy) * m0));
    add_f(part + 2, 0.5f * m2);
    add_f(part + 3, dy * m1);
    add_f(part + 4, (0.5f * dy * dy) * m0);
    add_f(part + 5, grad_opacity);
    for (int c = 0; c < n_channels; ++c) add_f(part + 6 + c, grad_f[c]);
}
""".replace("MAX_CHANNELS", str(MAX_CHANNELS))


def _constants(snippet: str) -> str:
    """The snippet with its named constants written in: LANES, the compositing rule's ALPHA_MAX, ALPHA_MIN and
    T_MIN (``splat_torch``) and GAUSS_MAX, the exp(-sigma) above which sigma < 0 beyond rounding (1 + 1e-6, as in
    ``splat_warp``)."""
    return (snippet.replace("LANES", str(LANES))
            .replace("ALPHA_MAX", f"{ALPHA_MAX!r}f").replace("ALPHA_MIN", f"{ALPHA_MIN!r}f")
            .replace("T_MIN", f"{TRANSMITTANCE_MIN!r}f").replace("GAUSS_MAX", "1.000001f"))


def plane_stride(width: int) -> int:
    """Floats per row of a plane: the width rounded up to LANES, plus one block (a span's last block may start at
    its last pixel)."""
    return -(-width // LANES) * LANES + LANES


@wp.func_native(_constants(_FORWARD))
def _composite_row(r: int, geometry: wp.array(dtype=_vec6), features: wp.array(dtype=float),
                   row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), n_channels: int, height: int,
                   stride: int, stop: wp.array(dtype=int), sums: wp.array(dtype=float)):
    """Row r's spans composited front to back into its planes (module doc)."""
    ...


@wp.func_native(_constants(_BACKWARD))
def _composite_row_backward(r: int, geometry: wp.array(dtype=_vec6), features: wp.array(dtype=float),
                            row_offsets: wp.array(dtype=int), spans: wp.array(dtype=wp.vec3i), n_channels: int,
                            height: int, stride: int, stop: wp.array(dtype=int), state: wp.array(dtype=float),
                            grad_sums: wp.array(dtype=float), partials: wp.array(dtype=float)):
    """Row r's spans back to front: T_i and the sums behind each pixel's Gaussians, each span's gradients added to
    its instance's records (module doc)."""
    ...


class LaneKernels(NamedTuple):
    """A channel layout's lanes kernels: the forward and the backward of ``splat_warp``'s compositing."""

    forward: wp.Kernel
    backward: wp.Kernel


@functools.cache
def lane_kernels(n_channels: int, vec: type) -> LaneKernels:
    """The lanes kernels of ``n_channels`` composited channels (``vec`` their Warp vector type), with the same
    arguments as ``splat_warp``'s forward and backward except the planes (module doc) and their stride."""

    @wp.kernel(module="unique", enable_backward=False, module_options=_CPU_FLAGS)
    def forward(geometry: wp.array(dtype=_vec6), features: wp.array(dtype=float), row_offsets: wp.array(dtype=int),
                spans: wp.array(dtype=wp.vec3i), width: int, height: int, stride: int,
                backgrounds: wp.array(dtype=float), n_background: int, expected_depth: int,
                out_features: wp.array(dtype=vec), out_alphas: wp.array(dtype=float),
                transmittance: wp.array(dtype=float), stop: wp.array(dtype=int), sums: wp.array(dtype=float)):
        r = wp.tid()
        _composite_row(r, geometry, features, row_offsets, spans, n_channels, height, stride, stop, sums)
        # the finished pixels (``finish_pixels``): alpha, expected depth, background
        camera, row, plane = r // height, r * width, r * (n_channels + 1) * stride
        for x in range(width):
            t = wp.abs(sums[plane + n_channels * stride + x])
            transmittance[row + x] = t
            out_alphas[row + x] = 1.0 - t
            v = vec()
            for c in range(n_channels):
                v[c] = sums[plane + c * stride + x]
            out_features[row + x] = finished_pixel(v, t, expected_depth, backgrounds, n_background, camera)

    @wp.kernel(module="unique", enable_backward=False, module_options=_CPU_FLAGS)
    def backward(geometry: wp.array(dtype=_vec6), features: wp.array(dtype=float), row_offsets: wp.array(dtype=int),
                 spans: wp.array(dtype=wp.vec3i), width: int, height: int, stride: int,
                 backgrounds: wp.array(dtype=float), n_background: int, expected_depth: int,
                 out_features: wp.array(dtype=vec), stop: wp.array(dtype=int), transmittance: wp.array(dtype=float),
                 grad_finished: wp.array(dtype=vec), grad_finished_alphas: wp.array(dtype=float),
                 grad_sums: wp.array(dtype=float), state: wp.array(dtype=float),
                 partials: wp.array(dtype=float)):
        r = wp.tid()
        row, camera = r * width, r // height
        grads, states = r * n_channels * stride, r * 3 * stride
        # gradients of the finished pixels -> of the composited sums and alpha; the state planes (T, behind,
        # dL/dalpha) start as (final T, 0, that); the padding is zeroed (its lanes are masked, never NaN)
        for x in range(stride):
            grad_a, t = float(0.0), float(1.0)
            grad_v = vec()
            if x < width:
                t = transmittance[row + x]
                grad_v, grad_a = finished_pixel_adjoint(grad_finished[row + x], grad_finished_alphas[row + x], t,
                                                        out_features[row + x][n_channels - 1], expected_depth,
                                                        backgrounds, n_background, camera)
            for c in range(n_channels):
                grad_sums[grads + c * stride + x] = grad_v[c]
            state[states + x] = t
            state[states + stride + x] = 0.0
            state[states + 2 * stride + x] = grad_a
        _composite_row_backward(r, geometry, features, row_offsets, spans, n_channels, height, stride, stop, state,
                                grad_sums, partials)

    return LaneKernels(forward, backward)
