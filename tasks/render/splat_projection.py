"""EWA projection of 3D Gaussians onto image planes (Zwicker et al. 2002, "EWA splatting"; 3DGS, Kerbl et al. 2023,
sec. 4), with the same maths as gsplat's ``fully_fused_projection`` (pinhole camera, OpenCV axes: x right, y down,
z forward).

Conventions shared by the whole renderer:

* ``covars`` (N, 6) m^2: upper triangle xx, xy, xz, yy, yz, zz of the world-space covariance (gsplat's layout and the
  layout the MPM rollout writes as ``gaussian_covariances``);
* ``conics`` (camera, N, 3) 1/px^2: upper triangle a, b, c of the inverse 2D covariance, so that a Gaussian's
  exponent at a pixel offset d = (dx, dy) from its projected mean is ``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy``;
* pixel (x, y) has its centre at (x + 0.5, y + 0.5) px, as in gsplat.

Everything is torch and differentiable w.r.t. means, quats, scales and covars; ``radii`` and the pixel boxes are
integer bookkeeping.
"""

from typing import NamedTuple

import torch

# 3DGS's frustum clamp: the Jacobian is evaluated at t/z clamped to 1.3x the half field of view
FOV_CLAMP = 1.3
# a Gaussian covers the pixels within this many standard deviations of its largest 2D axis (3DGS)
RADIUS_SIGMAS = 3.0


class Projection(NamedTuple):
    """Screen-space Gaussians for every (camera, Gaussian) pair.

    radii: (camera, N) int32 px, ceil(3 sqrt(lambda_max(cov2d))); 0 = culled (behind the near plane, beyond the
    far plane or off screen). means2d: (camera, N, 2) px. depths: (camera, N) m, camera-space z.
    conics: (camera, N, 3) 1/px^2, upper triangle of cov2d^-1.
    """

    radii: torch.Tensor
    means2d: torch.Tensor
    depths: torch.Tensor
    conics: torch.Tensor


def quat_scale_to_covar(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """World covariance R S S^T R^T of each Gaussian (3DGS eq. 6) as the upper triangle.

    quats: (N, 4) w, x, y, z, normalised here (any non-zero length); scales: (N, 3) m, standard deviations along the
    local axes. Returns (N, 6) m^2 as xx, xy, xz, yy, yz, zz.
    """
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    rot = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)
    m = rot * scales[:, None, :]
    return covar_upper(m @ m.transpose(-1, -2))


def covar_upper(matrices: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) symmetric -> (..., 6) upper triangle xx, xy, xz, yy, yz, zz."""
    rows, cols = (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)
    return matrices[..., rows, cols]


def covar_matrix(covars: torch.Tensor) -> torch.Tensor:
    """(..., 6) upper triangle xx, xy, xz, yy, yz, zz -> (..., 3, 3) symmetric."""
    xx, xy, xz, yy, yz, zz = covars.unbind(-1)
    return torch.stack([xx, xy, xz, xy, yy, yz, xz, yz, zz], dim=-1).reshape(covars.shape[:-1] + (3, 3))


def project_gaussians(means: torch.Tensor, covars: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                      width: int, height: int, eps2d: float = 0.3, near_plane: float = 0.01,
                      far_plane: float = 1e10) -> Projection:
    """EWA projection (Zwicker et al. 2002, eq. 31; 3DGS eq. 5): cov2d = J W cov3 W^T J^T + eps2d I.

    means: (N, 3) m, world; covars: (N, 6) m^2, upper triangle; viewmats: (camera, 4, 4) world-to-camera;
    Ks: (camera, 3, 3) px intrinsics; width, height px; eps2d px^2 (the low-pass filter of 3DGS: a Gaussian covers
    at least ~1 px); near_plane, far_plane m (camera z). J is the perspective Jacobian at the camera-space mean with
    t/z clamped to 1.3x the half field of view (3DGS); a Gaussian is culled (radius 0) when its depth is outside
    (near_plane, far_plane) or its radius square misses the image.
    """
    # 1. world -> camera
    rot, trans = viewmats[:, :3, :3], viewmats[:, :3, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]                  # (camera, N, 3)
    cov_c = rot[:, None] @ covar_matrix(covars)[None] @ rot.transpose(-1, -2)[:, None]     # (camera, N, 3, 3)
    depths = means_c[..., 2]
    in_depth = (depths > near_plane) & (depths < far_plane)
    tz = torch.where(in_depth, depths, torch.ones_like(depths))   # culled ones: finite maths, no NaN gradients

    # 2. perspective Jacobian with the frustum clamp, projected mean
    fx, fy = Ks[:, 0, 0, None], Ks[:, 1, 1, None]
    cx, cy = Ks[:, 0, 2, None], Ks[:, 1, 2, None]
    slack_x, slack_y = (FOV_CLAMP - 1.0) * 0.5 * width / fx, (FOV_CLAMP - 1.0) * 0.5 * height / fy
    tx = tz * torch.clamp(means_c[..., 0] / tz, min=-(cx / fx + slack_x), max=(width - cx) / fx + slack_x)
    ty = tz * torch.clamp(means_c[..., 1] / tz, min=-(cy / fy + slack_y), max=(height - cy) / fy + slack_y)
    zero = torch.zeros_like(tz)
    jac = torch.stack([fx / tz, zero, -fx * tx / tz**2, zero, fy / tz, -fy * ty / tz**2], dim=-1)
    jac = jac.reshape(tz.shape + (2, 3))
    means2d = torch.einsum("cij,cnj->cni", Ks[:, :2, :3], means_c) / tz[..., None]

    # 3. 2D covariance with the low-pass filter, its inverse (conic) and radius
    cov2d = jac @ cov_c @ jac.transpose(-1, -2)
    a, b, c = cov2d[..., 0, 0] + eps2d, cov2d[..., 0, 1], cov2d[..., 1, 1] + eps2d
    det = (a * c - b * b).clamp_min(1e-10)
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    with torch.no_grad():
        mid = 0.5 * (a + c)
        lambda_max = mid + torch.sqrt((mid * mid - det).clamp_min(0.0))
        radii = torch.ceil(RADIUS_SIGMAS * torch.sqrt(lambda_max))
        on_screen = ((means2d[..., 0] + radii > 0) & (means2d[..., 0] - radii < width)
                     & (means2d[..., 1] + radii > 0) & (means2d[..., 1] - radii < height))
        radii = torch.where(in_depth & on_screen, radii, zero).to(torch.int32)
    return Projection(radii, means2d, depths, conics)


def pixel_boxes(means2d: torch.Tensor, radii: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """The pixels each projected Gaussian may touch: centres within its radius square, clipped to the image.

    means2d: (G, 2) px; radii: (G,) px. Returns (G, 4) int32 x0, x1, y0, y1 (end-exclusive; empty when x1 <= x0).
    """
    r = radii.to(means2d.dtype)
    x0 = torch.ceil(means2d[:, 0] - r - 0.5).clamp(0, width)
    x1 = (torch.floor(means2d[:, 0] + r - 0.5) + 1).clamp(0, width)
    y0 = torch.ceil(means2d[:, 1] - r - 0.5).clamp(0, height)
    y1 = (torch.floor(means2d[:, 1] + r - 0.5) + 1).clamp(0, height)
    return torch.stack([x0, x1, y0, y1], dim=-1).to(torch.int32)
