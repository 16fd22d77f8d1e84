"""Tracers (surface Gaussians) embedded in the material: placed from the particles they are bound to.
"""
from __future__ import annotations

import warp as wp

from .structs import KERNEL_OPTIONS

wp.set_module_options(KERNEL_OPTIONS)


@wp.kernel
def k_tracer_embed(x: wp.array(dtype=wp.vec3), F: wp.array(dtype=wp.mat33), anchor: wp.array2d(dtype=wp.int32),
                   weight: wp.array2d(dtype=float), offset: wp.array2d(dtype=wp.vec3), tx: wp.array(dtype=wp.vec3),
                   tF: wp.array(dtype=wp.mat33)):
    """Tracers (surface Gaussians) embedded in the material: tracer t, bound at rest to particles k with weights
    w_tk (sum 1) and rest offsets r_tk = X_t - X_k (m), sits at x_t = sum_k w_tk (x_k + F_k r_tk) with
    F_t = sum_k w_tk F_k.  Exact for any affine motion of its anchors (x = A X + b, F = A), and never farther from
    the material than its anchors' deformed offsets: no drift, unlike a massless point advected by the grid."""
    t = wp.tid()
    xt = wp.vec3(0.0)
    Ft = wp.mat33(0.0)
    for j in range(anchor.shape[1]):
        k = anchor[t, j]
        w = weight[t, j]
        xt = xt + w * (x[k] + F[k] @ offset[t, j])
        Ft = Ft + w * F[k]
    tx[t] = xt
    tF[t] = Ft
