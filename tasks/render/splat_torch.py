"""Reference compositor in pure torch (the "pairs" design): the exact (Gaussian, pixel) pairs, alpha-composited
front to back per pixel with torch autograd for the backward pass.  It is the test oracle of the compiled backend
(as gsplat's ``_torch_impl`` is for its CUDA kernels) and runs on any torch device.

The compositing rule (3DGS, Kerbl et al. 2023, sec. 4 and its released rasteriser), defined here for both backends:
for the depth-sorted Gaussians i covering a pixel, alpha_i = min(ALPHA_MAX, o_i exp(-sigma_i)) with
sigma_i = 0.5 (a dx^2 + c dy^2) + b dx dy; a pair with sigma_i < 0 or alpha_i < ALPHA_MIN is skipped; the pixel stops
at the first Gaussian that would bring the transmittance T_i (1 - alpha_i) below TRANSMITTANCE_MIN (that Gaussian is
left out); weights w_i = alpha_i T_i with T_i = prod_{j<i} (1 - alpha_j); feature image = sum_i w_i f_i and
alpha image = sum_i w_i = 1 - T_final.
"""

import torch

from .splat_projection import pixel_boxes

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
TRANSMITTANCE_MIN = 1e-4
ALPHA_FLOOR = 1e-10   # expected depth divides by max(alpha, ALPHA_FLOOR)


def composite_instances(means2d: torch.Tensor, conics: torch.Tensor, radii: torch.Tensor, opacities: torch.Tensor,
                        features: torch.Tensor, drawn: torch.Tensor, width: int, height: int, n_images: int,
                        backgrounds: torch.Tensor | None = None,
                        expected_depth: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite the drawn (camera, Gaussian) instances of a projection into finished flat pixel buffers.

    means2d (C, N, 2) px, conics (C, N, 3) 1/px^2, radii (C, N) px of the projection; opacities (N,); features
    (N, K) or per camera (C, N, K); drawn (G,) int, the instances' flat index camera * N + Gaussian, sorted front
    to back; n_images = C; backgrounds (C, B) and expected_depth as in ``finish_pixels``.  Returns features
    (C * height * width, K) and alphas (C * height * width,), differentiable w.r.t. means2d, conics, opacities
    and features.
    """
    n = len(opacities)
    gaussian_ids = drawn % n
    means = means2d.reshape(-1, 2).index_select(0, drawn)
    boxes = pixel_boxes(means.detach(), radii.reshape(-1)[drawn], width, height)
    inst_features = features.reshape(-1, features.shape[-1]).index_select(0, drawn if features.dim() == 3
                                                                           else gaussian_ids)
    sums, alphas = composite_pairs(means, conics.reshape(-1, 3).index_select(0, drawn),
                                   opacities.index_select(0, gaussian_ids), inst_features, boxes,
                                   (drawn // n) * (height * width), width, height, n_images)
    return finish_pixels(sums, alphas, backgrounds, expected_depth), alphas


def finish_pixels(sums: torch.Tensor, alphas: torch.Tensor, backgrounds: torch.Tensor | None,
                  expected_depth: bool) -> torch.Tensor:
    """The finished pixels of composited sums (C * P, K) with alphas (C * P,): with expected_depth the last
    channel becomes sum_i w_i z_i / max(alpha, ALPHA_FLOOR) (m), then backgrounds (C, B) add (1 - alpha) times
    the camera's background to the first B channels."""
    if expected_depth:
        sums = torch.cat([sums[:, :-1], sums[:, -1:] / alphas[:, None].clamp_min(ALPHA_FLOOR)], dim=-1)
    if backgrounds is None:
        return sums
    n_back = backgrounds.shape[1]
    shown = sums[:, :n_back] + (1.0 - alphas[:, None]) * backgrounds.repeat_interleave(len(sums) // len(backgrounds), 0)
    return torch.cat([shown, sums[:, n_back:]], dim=-1)


def composite_pairs(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
                    boxes: torch.Tensor, pixel_offsets: torch.Tensor, width: int, height: int,
                    n_images: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite screen-space Gaussians ("instances", already sorted front to back) into flat pixel buffers.

    means2d: (G, 2) px; conics: (G, 3) 1/px^2; opacities: (G,) in [0, 1]; features: (G, K) any channels;
    boxes: (G, 4) int x0, x1, y0, y1 from ``pixel_boxes``; pixel_offsets: (G,) int, index of the instance's image
    in the flat buffer times width * height; width, height px; n_images: images in the buffer.
    Returns features (n_images * height * width, K) = sum_i w_i f_i and alphas (n_images * height * width,)
    = sum_i w_i, differentiable w.r.t. means2d, conics, opacities and features.
    """
    pixel, inst, weight = pair_weights(means2d, conics, opacities, boxes, pixel_offsets, width)
    n_pixels = n_images * height * width
    out_features = features.new_zeros(n_pixels, features.shape[1]).index_add(0, pixel,
                                                                             weight[:, None] * features[inst])
    return out_features, weight.new_zeros(n_pixels).index_add(0, pixel, weight)


def pair_weights(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, boxes: torch.Tensor,
                 pixel_offsets: torch.Tensor, width: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The compositing weights w_i = alpha_i T_i of every kept (instance, pixel) pair (arguments as in
    ``composite_pairs``). Returns pixel (pairs,) flat pixel index, inst (pairs,) instance index and weight (pairs,),
    grouped by pixel, front to back inside a pixel; weight is 0 behind a pixel's stop and differentiable.
    """
    device = means2d.device
    # 1. enumerate the pixels of every instance's box (index bookkeeping, no gradient)
    with torch.no_grad():
        box_w = (boxes[:, 1] - boxes[:, 0]).clamp_min(0).long()
        box_h = (boxes[:, 3] - boxes[:, 2]).clamp_min(0).long()
        count = box_w * box_h
        inst = torch.repeat_interleave(torch.arange(len(count), device=device), count)
        local = torch.arange(len(inst), device=device) - (torch.cumsum(count, 0) - count)[inst]
        px = boxes[inst, 0].long() + local % box_w[inst]
        py = boxes[inst, 2].long() + local // box_w[inst]

        # 2. prefilter: drop the pairs the compositing rule skips
        sigma = _exponent(means2d[inst], conics[inst], px, py)
        keep = (sigma >= 0) & (opacities[inst] * torch.exp(-sigma) >= ALPHA_MIN)
        inst, px, py = inst[keep], px[keep], py[keep]

        # 3. group by pixel; the stable sort keeps the front-to-back order inside a pixel
        pixel, perm = torch.sort(pixel_offsets[inst].long() + py * width + px, stable=True)
        inst, px, py = inst[perm], px[perm], py[perm]
        first = torch.ones_like(pixel, dtype=torch.bool)
        first[1:] = pixel[1:] != pixel[:-1]
        segment = torch.cumsum(first.long(), 0) - 1
        segment_start = torch.nonzero(first).squeeze(1)

    # 4. alpha of every kept pair, with gradient
    sigma = _exponent(means2d[inst], conics[inst], px, py)
    alpha = torch.clamp_max(opacities[inst] * torch.exp(-sigma), ALPHA_MAX)

    # 5. transmittance: one global float64 scan of log(1 - alpha), segmented by subtracting each pixel's start
    log_keep = torch.log1p(-alpha).double()
    inclusive = torch.cumsum(log_keep, 0)
    exclusive = inclusive - log_keep
    start = exclusive[segment_start][segment]
    transmittance = torch.exp(exclusive - start).to(alpha.dtype)
    with torch.no_grad():
        alive = torch.exp(inclusive - start) >= TRANSMITTANCE_MIN     # the early stop of 3DGS
    return pixel, inst, torch.where(alive, transmittance * alpha, torch.zeros_like(alpha))


def _exponent(means2d: torch.Tensor, conics: torch.Tensor, px: torch.Tensor, py: torch.Tensor) -> torch.Tensor:
    """sigma = 0.5 (a dx^2 + c dy^2) + b dx dy at pixel centres (px + 0.5, py + 0.5); (pairs,)."""
    dx = px.to(means2d.dtype) + 0.5 - means2d[:, 0]
    dy = py.to(means2d.dtype) + 0.5 - means2d[:, 1]
    return 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
