"""Warp twin of ``splat_projection`` (same maths and outputs): the world covariance R S S^T R^T and the EWA projection
in one Warp kernel (3DGS, Kerbl et al. 2023, eqs. 5-6; gsplat's ``fully_fused_projection``) and its hand-written
adjoint (1.6x faster than Warp's generated one), the first and last stage of the renderer's frame (``splat_warp``).
float32 whatever the input dtype; the projected means and conics are 0 where a Gaussian is culled (radius 0).
"""

import torch
import warp as wp

from .splat_projection import FOV_CLAMP, RADIUS_SIGMAS, Projection
from .warp_interop import launch, warp_view

wp.set_module_options({"enable_backward": False})   # the adjoint is hand-written (``_project_backward``)

_mat23 = wp.types.matrix(shape=(2, 3), dtype=float)
_sym6 = wp.types.vector(length=6, dtype=float)   # xx, xy, xz, yy, yz, zz
_FOV_SLACK = wp.constant(0.5 * (FOV_CLAMP - 1.0))   # times width / fx: how far t/z may reach beyond the image edge
_RADIUS_SIGMAS = wp.constant(RADIUS_SIGMAS)


@wp.func
def _quat_rotation(q: wp.vec4):
    """The rotation matrix of a unit quaternion w, x, y, z."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    return wp.mat33(1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
                    2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
                    2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y))


@wp.func
def _world_covariance(quats: wp.array(dtype=wp.vec4), scales: wp.array(dtype=wp.vec3), covars: wp.array(dtype=_sym6),
                      use_quats: int, n: int):
    """Gaussian n's world covariance as a symmetric 3x3 m^2: R S S^T R^T of its quaternion (w, x, y, z, normalised
    here) and scales (3DGS eq. 6) when use_quats, else its given upper triangle."""
    if use_quats != 0:
        m = _quat_rotation(wp.normalize(quats[n])) * wp.diag(scales[n])
        return m * wp.transpose(m)
    s = covars[n]
    return wp.mat33(s[0], s[1], s[2], s[1], s[3], s[4], s[2], s[4], s[5])


@wp.kernel
def _project(means: wp.array(dtype=wp.vec3), quats: wp.array(dtype=wp.vec4), scales: wp.array(dtype=wp.vec3),
             covars: wp.array(dtype=_sym6), use_quats: int, viewmats: wp.array(dtype=wp.mat44),
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
    cov_c = rot * _world_covariance(quats, scales, covars, use_quats, n) * wp.transpose(rot)
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


@wp.kernel
def _project_backward(means: wp.array(dtype=wp.vec3), quats: wp.array(dtype=wp.vec4), scales: wp.array(dtype=wp.vec3),
                      covars: wp.array(dtype=_sym6), use_quats: int, viewmats: wp.array(dtype=wp.mat44),
                      Ks: wp.array(dtype=wp.mat33), width: int, height: int, eps2d: float, near_plane: float,
                      far_plane: float, grad_means2d: wp.array2d(dtype=wp.vec2), grad_depths: wp.array2d(dtype=float),
                      grad_conics: wp.array2d(dtype=wp.vec3), grad_means: wp.array(dtype=wp.vec3),
                      grad_quats: wp.array(dtype=wp.vec4), grad_scales: wp.array(dtype=wp.vec3),
                      grad_covars: wp.array(dtype=_sym6)):
    """The adjoint of ``_project`` (its forward recomputed, then each step's chain rule in reverse order): the
    gradients of means2d, depths and conics -> those of means, quats and scales (use_quats) or covars."""
    c, n = wp.tid()
    v, k = viewmats[c], Ks[c]
    rot = wp.mat33(v[0, 0], v[0, 1], v[0, 2], v[1, 0], v[1, 1], v[1, 2], v[2, 0], v[2, 1], v[2, 2])
    p = rot * means[n] + wp.vec3(v[0, 3], v[1, 3], v[2, 3])
    z = p[2]
    grad_p = wp.vec3(0.0, 0.0, grad_depths[c, n])
    if z > near_plane and z < far_plane:
        # 1. the forward again: camera covariance, clamped Jacobian rows j0, j1, projected mean, 2D covariance
        cov = _world_covariance(quats, scales, covars, use_quats, n)
        cov_c = rot * cov * wp.transpose(rot)
        fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
        w, h = float(width), float(height)
        low_x, high_x = -(cx / fx + _FOV_SLACK * w / fx), (w - cx) / fx + _FOV_SLACK * w / fx
        low_y, high_y = -(cy / fy + _FOV_SLACK * h / fy), (h - cy) / fy + _FOV_SLACK * h / fy
        ux, uy = p[0] / z, p[1] / z
        tx, ty = z * wp.clamp(ux, low_x, high_x), z * wp.clamp(uy, low_y, high_y)
        z2 = z * z
        j0, j1 = wp.vec3(fx / z, 0.0, -fx * tx / z2), wp.vec3(0.0, fy / z, -fy * ty / z2)
        mean2d = wp.vec2(k[0, 0] * p[0] + k[0, 1] * p[1] + k[0, 2] * z,
                         k[1, 0] * p[0] + k[1, 1] * p[1] + k[1, 2] * z) / z
        s0, s1 = cov_c * j0, cov_c * j1
        a, b, cc = wp.dot(j0, s0) + eps2d, wp.dot(j0, s1), wp.dot(j1, s1) + eps2d
        # 2. conic (cc, -b, a) / det with det = max(a cc - b^2, 1e-10) -> a, b, cc
        det = wp.max(a * cc - b * b, 1e-10)
        g = grad_conics[c, n]
        grad_det = float(0.0)
        if a * cc - b * b > 1e-10:
            grad_det = -(g[0] * cc - g[1] * b + g[2] * a) / (det * det)
        grad_a, grad_cc = g[2] / det + grad_det * cc, g[0] / det + grad_det * a
        grad_b = -g[1] / det - 2.0 * grad_det * b
        # 3. a = j0 . S j0, b = j0 . S j1, cc = j1 . S j1 (S = cov_c, symmetric) -> S, j0, j1
        grad_cov_c = grad_a * wp.outer(j0, j0) + grad_b * wp.outer(j0, j1) + grad_cc * wp.outer(j1, j1)
        grad_j0, grad_j1 = 2.0 * grad_a * s0 + grad_b * s1, 2.0 * grad_cc * s1 + grad_b * s0
        # 4. j0, j1 -> z and t; t = z clamp(p / z): p inside the clamp, z times the bound outside it
        grad_z = (-fx * grad_j0[0] - fy * grad_j1[1] + 2.0 * (fx * tx * grad_j0[2] + fy * ty * grad_j1[2]) / z) / z2
        grad_tx, grad_ty = -fx / z2 * grad_j0[2], -fy / z2 * grad_j1[2]
        grad_px, grad_py = float(0.0), float(0.0)
        if ux < low_x or ux > high_x:
            grad_z += grad_tx * wp.clamp(ux, low_x, high_x)
        else:
            grad_px = grad_tx
        if uy < low_y or uy > high_y:
            grad_z += grad_ty * wp.clamp(uy, low_y, high_y)
        else:
            grad_py = grad_ty
        # 5. mean2d = (K p)_xy / z -> p
        gm = grad_means2d[c, n]
        grad_px += (k[0, 0] * gm[0] + k[1, 0] * gm[1]) / z
        grad_py += (k[0, 1] * gm[0] + k[1, 1] * gm[1]) / z
        grad_z += ((k[0, 2] - mean2d[0]) * gm[0] + (k[1, 2] - mean2d[1]) * gm[1]) / z
        grad_p += wp.vec3(grad_px, grad_py, grad_z)
        # 6. cov_c = R cov R^T -> cov -> covars, or (cov = M M^T, M = rotation(q / |q|) diag(scales)) quats, scales
        grad_cov = wp.transpose(rot) * grad_cov_c * rot
        if use_quats != 0:
            q_raw, scale = quats[n], scales[n]
            q = wp.normalize(q_raw)
            r = _quat_rotation(q)
            grad_m = (grad_cov + wp.transpose(grad_cov)) * (r * wp.diag(scale))
            rt_grad_m = wp.transpose(r) * grad_m   # its diagonal: d scale_j = sum_i grad_m_ij r_ij
            wp.atomic_add(grad_scales, n, wp.vec3(rt_grad_m[0, 0], rt_grad_m[1, 1], rt_grad_m[2, 2]))
            gr = grad_m * wp.diag(scale)   # of the rotation's entries
            qw, qx, qy, qz = q[0], q[1], q[2], q[3]
            grad_q = 2.0 * wp.vec4(
                -qz * gr[0, 1] + qy * gr[0, 2] + qz * gr[1, 0] - qx * gr[1, 2] - qy * gr[2, 0] + qx * gr[2, 1],
                qy * gr[0, 1] + qz * gr[0, 2] + qy * gr[1, 0] - 2.0 * qx * gr[1, 1] - qw * gr[1, 2] + qz * gr[2, 0]
                + qw * gr[2, 1] - 2.0 * qx * gr[2, 2],
                -2.0 * qy * gr[0, 0] + qx * gr[0, 1] + qw * gr[0, 2] + qx * gr[1, 0] + qz * gr[1, 2] - qw * gr[2, 0]
                + qz * gr[2, 1] - 2.0 * qy * gr[2, 2],
                -2.0 * qz * gr[0, 0] - qw * gr[0, 1] + qx * gr[0, 2] + qw * gr[1, 0] - 2.0 * qz * gr[1, 1]
                + qy * gr[1, 2] + qx * gr[2, 0] + qy * gr[2, 1])
            wp.atomic_add(grad_quats, n, (grad_q - q * wp.dot(q, grad_q)) / wp.length(q_raw))   # of q / |q|
        else:
            wp.atomic_add(grad_covars, n, _sym6(grad_cov[0, 0], grad_cov[0, 1] + grad_cov[1, 0],
                                                grad_cov[0, 2] + grad_cov[2, 0], grad_cov[1, 1],
                                                grad_cov[1, 2] + grad_cov[2, 1], grad_cov[2, 2]))
    # 7. p = R mean + t -> mean
    wp.atomic_add(grad_means, n, wp.transpose(rot) * grad_p)


def project_warp(means: torch.Tensor, quats: torch.Tensor | None, scales: torch.Tensor | None,
                 covars: torch.Tensor | None, viewmats: torch.Tensor, Ks: torch.Tensor, settings: tuple) -> Projection:
    """The projection of float32 contiguous Gaussians (quats and scales, or covars; the others None) into every
    camera, without gradient (``project_adjoint`` is its backward).  settings: (width, height, eps2d, near_plane,
    far_plane).  Outputs are fresh tensors (culled pairs: radius 0, mean and conic 0)."""
    shape, f32, device = (len(viewmats), len(means)), torch.float32, means.device
    proj = Projection(torch.empty(shape, dtype=torch.int32, device=device),
                      torch.zeros(shape + (2,), dtype=f32, device=device), torch.empty(shape, dtype=f32, device=device),
                      torch.zeros(shape + (3,), dtype=f32, device=device))
    launch(_project, shape, _inputs(means, quats, scales, covars, viewmats, Ks) + list(settings) + _outputs(proj),
           device)
    return proj


def project_adjoint(means: torch.Tensor, quats: torch.Tensor | None, scales: torch.Tensor | None,
                    covars: torch.Tensor | None, viewmats: torch.Tensor, Ks: torch.Tensor, settings: tuple,
                    grad_means2d: torch.Tensor, grad_depths: torch.Tensor,
                    grad_conics: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None,
                                                         torch.Tensor | None]:
    """The adjoint of ``project_warp`` (same inputs; ``_project_backward``): the gradients (camera, N, ...) of
    means2d, depths and conics -> those of means, quats, scales, covars (None for the inputs that were None)."""
    grads = [None if t is None else torch.zeros_like(t) for t in (means, quats, scales, covars)]
    launch(_project_backward, (len(viewmats), len(means)),
           _inputs(means, quats, scales, covars, viewmats, Ks) + list(settings) + [
               warp_view(grad_means2d.contiguous(), wp.vec2), warp_view(grad_depths.contiguous()),
               warp_view(grad_conics.contiguous(), wp.vec3), warp_view(grads[0], wp.vec3),
               _view_or_null(grads[1], wp.vec4), _view_or_null(grads[2], wp.vec3), _view_or_null(grads[3], _sym6)],
           means.device)
    return tuple(grads)


def _inputs(means, quats, scales, covars, viewmats, Ks) -> list:
    return [warp_view(means, wp.vec3), _view_or_null(quats, wp.vec4), _view_or_null(scales, wp.vec3),
            _view_or_null(covars, _sym6), int(quats is not None), _view_or_null(viewmats, wp.mat44),
            _view_or_null(Ks, wp.mat33)]


def _view_or_null(tensor, dtype):
    return None if tensor is None else warp_view(tensor, dtype)


def _outputs(proj: Projection) -> list:
    return [warp_view(proj.means2d, wp.vec2), warp_view(proj.depths), warp_view(proj.conics, wp.vec3),
            warp_view(proj.radii)]


def project_gaussians_warp(means: torch.Tensor, covars: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                           width: int, height: int, eps2d: float = 0.3, near_plane: float = 0.01,
                           far_plane: float = 1e10) -> Projection:
    """``splat_projection.project_gaussians`` in Warp (same arguments and outputs, float32), without gradient (the
    renderer differentiates it inside ``splat_warp``)."""
    f32 = [t.detach().float().contiguous() for t in (means, covars, viewmats, Ks)]
    return project_warp(f32[0], None, None, f32[1], f32[2], f32[3],
                        (int(width), int(height), float(eps2d), float(near_plane), float(far_plane)))
