"""Differentiable 3D Gaussian splatting (3DGS, Kerbl et al. 2023) behind gsplat's ``rasterization`` interface: the
G-buffer renderer of paper sec. 3.2 (RGB, depth and released-particle mask maps per view and frame) and the
differentiable renderer R(Theta_p; v, t) of eq. 7.

Two backends implement the same maths: ``"torch"``, the pure-torch reference (``splat_projection``, ``splat_torch``:
the test oracle), and ``"warp"``, a whole frame of Warp kernels with hand-written backward passes (``splat_warp``,
``splat_warp_projection``), the default because it is 30-50x faster on the CPU (``tasks.render.benchmark``).  Both
run on the device of the inputs (CPU or CUDA).
"""

from typing import Literal

import torch

from .splat_projection import Projection, project_gaussians, quat_scale_to_covar
from .splat_torch import composite_instances
from .splat_warp import FrameSettings, render_warp

Backend = Literal["torch", "warp"]
RenderMode = Literal["RGB", "D", "ED", "RGB+D", "RGB+ED"]
BACKENDS = ("torch", "warp")
DEFAULT_BACKEND: Backend = "warp"


def rasterization(means: torch.Tensor, quats: torch.Tensor | None, scales: torch.Tensor | None,
                  opacities: torch.Tensor, colors: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor,
                  width: int, height: int, near_plane: float = 0.01, far_plane: float = 1e10, eps2d: float = 0.3,
                  backgrounds: torch.Tensor | None = None, render_mode: RenderMode = "RGB+ED",
                  covars: torch.Tensor | None = None,
                  backend: Backend = DEFAULT_BACKEND) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render N 3D Gaussians into C pinhole cameras (gsplat's ``rasterization``: same names, shapes, semantics).

    Gaussians: means (N, 3) m, world (z up by our rig's convention, any frame works); quats (N, 4) w, x, y, z (not
    necessarily normalised) and scales (N, 3) m standard deviations, or instead covars (N, 6) m^2, the upper
    triangle xx, xy, xz, yy, yz, zz (the MPM's F Sigma F^T; also (N, 3, 3)); opacities (N,) in [0, 1]; colors
    (N, D) or per camera (C, N, D): any D channels, composited linearly (linear RGB in [0, 1] for images).
    Cameras: viewmats (C, 4, 4) world-to-camera, OpenCV axes (x right, y down, z forward); Ks (C, 3, 3) px;
    width, height px; near_plane, far_plane m (camera z); eps2d px^2, added to every 2D covariance (3DGS's
    low-pass filter); backgrounds (C, D) colour behind the Gaussians, added as (1 - alpha) * background.

    Maths: EWA projection (``splat_projection``), then per pixel the depth-sorted front-to-back compositing of 3DGS
    with alpha_i = min(0.99, o_i exp(-0.5 d^T conic d)), pairs with alpha_i < 1/255 skipped, stop when the
    transmittance would fall below 1e-4 (``splat_torch``); each pixel value is sum_i w_i f_i with
    w_i = alpha_i prod_{j<i} (1 - alpha_j).

    render_mode: "RGB" (the D channels), "D" (accumulated depth sum_i w_i z_i, m), "ED" (expected depth
    sum_i w_i z_i / sum_i w_i, m; 0 where nothing is drawn), "RGB+D" / "RGB+ED" (D channels plus depth last).

    Masks as channels: a 0/1 indicator in a colour channel renders to the composited weight of the flagged
    Gaussians, sum over flagged i of w_i, in [0, alpha]; e.g. D = 4 (RGB + is_released) gives the released
    interior material's mask M of paper sec. 3.3 (1 where only opaque released material is seen, 0 where the
    surface covers it or nothing is drawn); give it background 0.

    Differentiable (torch autograd) w.r.t. means, quats, scales, covars, opacities and colors; not w.r.t.
    viewmats, Ks.  backend: "warp" (default, compiled, float32 inside) or "torch" (reference; float64 capable).

    Returns render_colors (C, height, width, D or D + 1 or 1), render_alphas (C, height, width, 1) and meta:
    radii (C, N) int32 px (0 = culled), means2d (C, N, 2) px, depths (C, N) m, conics (C, N, 3) 1/px^2 (means2d
    and conics are meaningful where radii > 0),
    camera_ids / gaussian_ids (instances,) of the drawn (camera, Gaussian) pairs front to back, width, height,
    n_cameras, backend.
    """
    covars = _check_arguments(means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds,
                              render_mode, covars, backend)
    n_cameras = len(viewmats)
    expected = render_mode in ("ED", "RGB+ED")
    shown_backgrounds = backgrounds if render_mode not in ("D", "ED") else None
    if backend == "warp":
        settings = FrameSettings(int(width), int(height), float(eps2d), float(near_plane), float(far_plane),
                                 0 if render_mode in ("D", "ED") else colors.shape[-1], render_mode != "RGB",
                                 expected)
        flat_features, flat_alphas, proj, drawn = render_warp(
            means, quats if covars is None else None, scales if covars is None else None, covars, opacities,
            None if render_mode in ("D", "ED") else colors, viewmats, Ks, shown_backgrounds, settings)
    else:
        flat_features, flat_alphas, proj, drawn = _render_torch(means, quats, scales, opacities, colors, viewmats,
                                                                Ks, width, height, near_plane, far_plane, eps2d,
                                                                shown_backgrounds, render_mode, covars, expected)
    render_colors = flat_features.reshape(n_cameras, height, width, -1)
    render_alphas = flat_alphas.reshape(n_cameras, height, width, 1)
    meta = {"radii": proj.radii, "means2d": proj.means2d, "depths": proj.depths, "conics": proj.conics,
            "camera_ids": drawn // len(means), "gaussian_ids": drawn % len(means), "width": width, "height": height,
            "n_cameras": n_cameras, "backend": backend}
    return render_colors, render_alphas, meta


def _check_arguments(means, quats, scales, opacities, colors, viewmats, Ks, width, height, backgrounds, render_mode,
                     covars, backend) -> torch.Tensor | None:
    """Shapes and options as documented in ``rasterization``; returns covars as (N, 6) or None."""
    n = means.shape[0] if means.dim() == 2 else -1
    if means.dim() != 2 or means.shape[1] != 3:
        raise ValueError(f"means must be (N, 3), got {tuple(means.shape)}")
    if covars is not None:
        if covars.shape == (n, 3, 3):
            covars = covars[:, (0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2)]
        if covars.shape != (n, 6):
            raise ValueError(f"covars must be (N, 6) xx xy xz yy yz zz or (N, 3, 3), got {tuple(covars.shape)}")
    elif quats is None or scales is None or quats.shape != (n, 4) or scales.shape != (n, 3):
        raise ValueError("give quats (N, 4) and scales (N, 3), or covars (N, 6)")
    if opacities.shape != (n,):
        raise ValueError(f"opacities must be (N,) = ({n},), got {tuple(opacities.shape)}")
    if viewmats.dim() != 3 or viewmats.shape[1:] != (4, 4) or Ks.shape != (len(viewmats), 3, 3):
        raise ValueError(f"viewmats must be (C, 4, 4) and Ks (C, 3, 3), got {tuple(viewmats.shape)}, "
                         f"{tuple(Ks.shape)}")
    if colors.shape[-2] != n or colors.dim() not in (2, 3) or (colors.dim() == 3 and len(colors) != len(viewmats)):
        raise ValueError(f"colors must be (N, D) or (C, N, D), got {tuple(colors.shape)}")
    if int(width) != width or int(height) != height or width < 1 or height < 1:
        raise ValueError(f"width and height must be positive integers, got {width} x {height}")
    if backgrounds is not None and backgrounds.shape != (len(viewmats), colors.shape[-1]):
        raise ValueError(f"backgrounds must be (C, D) = ({len(viewmats)}, {colors.shape[-1]}), "
                         f"got {tuple(backgrounds.shape)}")
    if render_mode not in ("RGB", "D", "ED", "RGB+D", "RGB+ED"):
        raise ValueError(f"render_mode must be RGB, D, ED, RGB+D or RGB+ED, got {render_mode!r}")
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {sorted(BACKENDS)}, got {backend!r}")
    return covars


def _render_torch(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, far_plane, eps2d,
                  backgrounds, render_mode, covars, expected) -> tuple[torch.Tensor, torch.Tensor, Projection,
                                                                        torch.Tensor]:
    """The reference backend in torch stages: covariances, projection, the instances front to back, compositing
    (``render_warp``'s outputs: flat features and alphas, the projection, the drawn instances)."""
    if covars is None:
        covars = quat_scale_to_covar(quats, scales)
    n_cameras = len(viewmats)
    proj = project_gaussians(means, covars, viewmats, Ks, width, height, eps2d, near_plane, far_plane)
    # the instances: the drawn (camera, Gaussian) pairs, front to back (flat index camera * N + Gaussian)
    with torch.no_grad():
        drawn = torch.nonzero(proj.radii.flatten() > 0).squeeze(1)
        drawn = drawn[torch.sort(proj.depths.flatten()[drawn], stable=True).indices]
    # features per Gaussian (N, D) or per camera and Gaussian (C, N, D): colour channels, then depth
    depths = proj.depths[..., None]
    features = {"RGB": colors, "D": depths, "ED": depths}.get(render_mode)
    if features is None:
        features = torch.cat([colors.expand(n_cameras, *colors.shape[-2:]), depths.to(colors.dtype)], dim=-1)
    flat_features, flat_alphas = composite_instances(proj.means2d, proj.conics, proj.radii, opacities, features,
                                                     drawn, width, height, n_cameras, backgrounds, expected)
    return flat_features, flat_alphas, proj, drawn
