"""The finished pixel of the Warp backend's compositors (``splat_warp``'s kernels and ``splat_warp_lanes``) and its
adjoint: ``splat_torch.finish_pixels`` for one pixel, generic over the layout's channel vector."""

from typing import Any

import warp as wp

from .splat_torch import ALPHA_FLOOR

_ALPHA_FLOOR = wp.constant(ALPHA_FLOOR)


@wp.func
def finished_pixel(sums: Any, t: float, expected_depth: int, backgrounds: wp.array(dtype=float), n_background: int,
                   camera: int):
    """The composited channels ``sums`` of a pixel with final transmittance ``t`` finished: with expected_depth the
    last channel (sum_i w_i z_i, m) divided by max(1 - t, ALPHA_FLOOR), then t times the camera's background added
    to the first n_background channels."""
    v = sums
    last = len(v) - 1
    if expected_depth != 0:
        v[last] = v[last] / wp.max(1.0 - t, _ALPHA_FLOOR)
    for c in range(n_background):
        v[c] = v[c] + t * backgrounds[camera * n_background + c]
    return v


@wp.func
def finished_pixel_adjoint(grad_finished: Any, grad_alpha: float, t: float, finished_last: float,
                           expected_depth: int, backgrounds: wp.array(dtype=float), n_background: int, camera: int):
    """The gradients of a pixel's composited channels and of its alpha 1 - t from those of its finished channels
    (``grad_finished``) and of its alpha (``grad_alpha``); ``finished_last``: its finished last channel (the
    expected depth, m, with expected_depth)."""
    grad = grad_finished
    last = len(grad) - 1
    for c in range(n_background):
        grad_alpha -= grad[c] * backgrounds[camera * n_background + c]
    if expected_depth != 0:
        a = 1.0 - t
        if a > _ALPHA_FLOOR:
            grad_alpha -= grad[last] * finished_last / a
        grad[last] = grad[last] / wp.max(a, _ALPHA_FLOOR)
    return grad, grad_alpha
