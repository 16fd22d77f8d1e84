"""Warp twin of ``splat_projection`` (same maths, arguments and outputs): the world covariance R S S^T R^T and the EWA
projection as Warp kernels (3DGS, Kerbl et al. 2023, eqs. 5-6; gsplat's ``fully_fused_projection``), differentiated
by Warp's generated adjoint kernels inside ``torch.autograd.Function``s.  float32 whatever the input dtype; the
projected means and conics are 0 where a Gaussian is culled (radius 0).
"""

import torch
import warp as wp

from .splat_projection import FOV_CLAMP, RADIUS_SIGMAS, Projection
from .warp_interop import launch, scratch, warp_view

_mat23 = wp.types.matrix(shape=(2, 3), dtype=float)
_sym6 = wp.types.vector(length=6, dtype=float)   # xx, xy, xz, yy, yz, zz
_FOV_SLACK = wp.constant(0.5 * (FOV_CLAMP - 1.0))   # times width / fx: how far t/z may reach beyond the image edge
_RADIUS_SIGMAS = wp.constant(RADIUS_SIGMAS)


@wp.kernel(enable_backward=True)
def _quat_scale_to_covar(quats: wp.array(dtype=wp.vec4), scales: wp.array(dtype=wp.vec3),
                         covars: wp.array(dtype=_sym6)):
    n = wp.tid()
    q = wp.normalize(quats[n])
    w, x, y, z = q[0], q[1], q[2], q[3]
    rot = wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                   2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                   2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))
    m = rot * wp.diag(scales[n])
    c = m * wp.transpose(m)
    covars[n] = _sym6(c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2])


@wp.kernel(enable_backward=True)
def _project(means: wp.array(dtype=wp.vec3), covars: wp.array(dtype=_sym6), viewmats: wp.array(dtype=wp.mat44),
             Ks: wp.array(dtype=wp.mat33), width: int, height: int, eps2d: float, near_plane: float,
             far_plane: float, means2d: wp.array2d(dtype=wp.vec2), depths: wp.array2d(dtype=float),
             conics: wp.array2d(dtype=wp.vec3), radii: wp.array2d(dtype=int)):
    c, n = wp.tid()
    # 1. world -> camera
    v, k = viewmats[c], Ks[c]
    rot = wp.mat33(v[0, 0], v[0, 1], v[0, 2], v[1, 0], v[1, 1], v[1, 2], v[2, 0], v[2, 1], v[2, 2])
    p = rot * means[n] + wp.vec3(v[0, 3], v[1, 3], v[2, 3])
    z = p[2]
    depths[c, n] = z
    radii[c, n] = 0
    if z <= near_plane or z >= far_plane:
        return
    s = covars[n]
    cov_c = rot * wp.mat33(s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5]) * wp.transpose(rot)
    # 2. Jacobian at t/z clamped to FOV_CLAMP x the half field of view, projected mean
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    w, h = float(width), float(height)
    tx = z * wp.clamp(p[0] / z, -(cx / fx + _FOV_SLACK * w / fx), (w - cx) / fx + _FOV_SLACK * w / fx)
    ty = z * wp.clamp(p[1] / z, -(cy / fy + _FOV_SLACK * h / fy), (h - cy) / fy + _FOV_SLACK * h / fy)
    jac = _mat23(fx / z, 0.0, -fx * tx / (z * z), 0.0, fy / z, -fy * ty / (z * z))
    mean2d = wp.vec2(k[0, 0] * p[0] + k[0, 1] * p[1] + k[0, 2] * z, k[1, 0] * p[0] + k[1, 1] * p[1] + k[1, 2] * z) / z
    # 3. 2D covariance with the low-pass filter, conic, radius
    cov2d = jac * cov_c * wp.transpose(jac)
    a, b, cc = cov2d[0, 0] + eps2d, cov2d[0, 1], cov2d[1, 1] + eps2d
    det = wp.max(a * cc - b * b, 1e-10)
    mid = 0.5 * (a + cc)
    radius = wp.ceil(_RADIUS_SIGMAS * wp.sqrt(mid + wp.sqrt(wp.max(mid * mid - det, 0.0))))
    if mean2d[0] + radius <= 0.0 or mean2d[0] - radius >= w or mean2d[1] + radius <= 0.0 or mean2d[1] - radius >= h:
        return
    means2d[c, n] = mean2d
    conics[c, n] = wp.vec3(cc / det, -b / det, a / det)
    radii[c, n] = int(radius)


class _QuatScaleToCovar(torch.autograd.Function):
    @staticmethod
    def forward(ctx, quats, scales):
        covars = torch.empty(len(quats), 6, dtype=torch.float32, device=quats.device)
        launch(_quat_scale_to_covar, len(quats),
               [warp_view(quats, wp.vec4), warp_view(scales, wp.vec3), warp_view(covars, _sym6)], quats.device)
        ctx.save_for_backward(quats, scales)
        return covars

    @staticmethod
    def backward(ctx, grad_covars):
        quats, scales = ctx.saved_tensors
        grad_quats, grad_scales = torch.zeros_like(quats), torch.zeros_like(scales)
        grad_covars = grad_covars.contiguous()
        launch(_quat_scale_to_covar, len(quats), [warp_view(quats, wp.vec4), warp_view(scales, wp.vec3)], quats.device,
               outputs=[warp_view(scratch("covars", (len(quats), 6), torch.float32, quats.device), _sym6)],
               adj_inputs=[warp_view(grad_quats, wp.vec4), warp_view(grad_scales, wp.vec3)],
               adj_outputs=[warp_view(grad_covars, _sym6)])
        return grad_quats, grad_scales


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane):
        shape, f32, device = (len(viewmats), len(means)), torch.float32, means.device
        outputs = [torch.zeros(shape + (2,), dtype=f32, device=device), torch.empty(shape, dtype=f32, device=device),
                   torch.zeros(shape + (3,), dtype=f32, device=device),
                   torch.empty(shape, dtype=torch.int32, device=device)]
        scalars = [width, height, eps2d, near_plane, far_plane]
        launch(_project, shape, _project_arrays(means, covars, viewmats, Ks) + scalars + _outputs(outputs),
               device)
        ctx.mark_non_differentiable(outputs[3])
        ctx.save_for_backward(means, covars, viewmats, Ks)
        ctx.scalars = scalars
        return tuple(outputs)

    @staticmethod
    def backward(ctx, grad_means2d, grad_depths, grad_conics, _):
        means, covars, viewmats, Ks = ctx.saved_tensors
        grad_means, grad_covars = torch.zeros_like(means), torch.zeros_like(covars)
        grad_means2d, grad_depths, grad_conics = (t.contiguous() for t in (grad_means2d, grad_depths, grad_conics))
        shape, f32, device = tuple(grad_depths.shape), torch.float32, means.device
        outputs = [scratch("means2d", shape + (2,), f32, device), scratch("depths", shape, f32, device),
                   scratch("conics", shape + (3,), f32, device), scratch("radii", shape, torch.int32, device)]
        launch(_project, (len(viewmats), len(means)), _project_arrays(means, covars, viewmats, Ks) + ctx.scalars,
               device, outputs=_outputs(outputs),
               adj_inputs=[warp_view(grad_means, wp.vec3), warp_view(grad_covars, _sym6), None, None, 0, 0, 0.0, 0.0,
                           0.0],
               adj_outputs=[warp_view(grad_means2d, wp.vec2), warp_view(grad_depths), warp_view(grad_conics, wp.vec3),
                            None])
        return grad_means, grad_covars, None, None, None, None, None, None, None


def _project_arrays(means, covars, viewmats, Ks) -> list:
    return [warp_view(means, wp.vec3), warp_view(covars, _sym6), warp_view(viewmats, wp.mat44), warp_view(Ks, wp.mat33)]


def _outputs(tensors) -> list:
    means2d, depths, conics, radii = tensors
    return [warp_view(means2d, wp.vec2), warp_view(depths), warp_view(conics, wp.vec3), warp_view(radii)]


def quat_scale_to_covar_warp(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """``splat_projection.quat_scale_to_covar`` in Warp: quats (N, 4) w, x, y, z, scales (N, 3) m -> covars (N, 6)
    m^2 xx, xy, xz, yy, yz, zz (float32)."""
    return _QuatScaleToCovar.apply(quats.float().contiguous(), scales.float().contiguous())


def project_gaussians_warp(means: torch.Tensor, covars: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                           width: int, height: int, eps2d: float = 0.3, near_plane: float = 0.01,
                           far_plane: float = 1e10) -> Projection:
    """``splat_projection.project_gaussians`` in Warp (same arguments and outputs, float32), differentiable w.r.t.
    means and covars."""
    f32 = [t.float().contiguous() for t in (means, covars, viewmats, Ks)]
    means2d, depths, conics, radii = _Project.apply(*f32, int(width), int(height), float(eps2d), float(near_plane),
                                                    float(far_plane))
    return Projection(radii, means2d, depths, conics)
