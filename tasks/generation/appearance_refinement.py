"""4D appearance refinement of the released particles, eq. 7 (paper sec. 3.3):

    Theta_p* = argmin_Theta_p  sum_{v,t} L_rec(R(Theta_p; v, t), I_t^{v,*})

Theta_p are the released particles' appearance parameters - colour (linear RGB), opacity and a per-axis scale
(world axes) - one set per particle for the whole clip (the particles' positions come from the MPM and stay as
simulated); R renders the frame's Gaussians with our differentiable rasteriser (:mod:`tasks.render.splat`); I* are
the generated frames of the effect step.  The solid object's Gaussians and the background stay frozen (no
gradient, bit-identical), as the paper prescribes "to avoid instabilities".

L_rec is the mean absolute error in linear RGB over the refined mask dilated by ``mask_dilation_px`` (where the
released material is and may appear; elsewhere the generated frame is the simulated render by construction).
Each Adam iteration renders ``samples_per_iteration`` (view, frame) pairs drawn at random from the training views
and the frames that show released material, instead of all of them.  ``held_out_views`` are never trained on:
the video metrics measure the multi-view consistency of the refined 4D Gaussians there.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
import torch

from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.render.colour import srgb_uint8_to_linear, to_srgb_uint8
from tasks.render.device import torch_device
from tasks.render.scene import RELEASED_SCALE_FACTOR, drawn_covariances, released_appearance, rollout_particle_volumes
from tasks.render.splat import rasterization


@dataclass
class FrozenFrames:
    """What does not change during refinement, per rendered frame: the surface Gaussians (means (frame, point, 3)
    m, covars (frame, point, 6) m^2, colors (point, 3), opacities (point,)) and the released particles' positions
    (frame, particle, 3) m with their visibility (frame, particle) bool."""

    surface_means: torch.Tensor
    surface_covars: torch.Tensor
    surface_colors: torch.Tensor
    surface_opacities: torch.Tensor
    particle_means: torch.Tensor
    visible: torch.Tensor


class ReleasedAppearance(torch.nn.Module):
    """Theta_p: per released particle colour (sigmoid of a logit), opacity (sigmoid) and per-axis scale (exp of a
    log, m)."""

    def __init__(self, colors: np.ndarray, opacities: np.ndarray, scales: np.ndarray):
        super().__init__()
        eps = 1e-4
        c = np.clip(colors, eps, 1 - eps)
        o = np.clip(opacities, eps, 1 - eps)
        self.color_logit = torch.nn.Parameter(torch.as_tensor(np.log(c / (1 - c)), dtype=torch.float32))
        self.opacity_logit = torch.nn.Parameter(torch.as_tensor(np.log(o / (1 - o)), dtype=torch.float32))
        self.log_scale = torch.nn.Parameter(torch.as_tensor(np.log(scales), dtype=torch.float32))

    def values(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """colors (particle, 3) linear RGB, opacities (particle,), scales (particle, 3) m."""
        return torch.sigmoid(self.color_logit), torch.sigmoid(self.opacity_logit), torch.exp(self.log_scale)


def render_frame(frozen: FrozenFrames, theta: ReleasedAppearance, frame: int, viewmats: torch.Tensor,
                 Ks: torch.Tensor, width: int, height: int, background: torch.Tensor) -> torch.Tensor:
    """R(Theta_p; v, t): linear RGB (view, y, x, 3) of frame ``frame`` in the given cameras."""
    colors, opacities, scales = theta.values()
    shown = frozen.visible[frame]
    variances = scales[shown] ** 2
    zeros = torch.zeros_like(variances[:, 0])
    released_covars = torch.stack([variances[:, 0], zeros, zeros, variances[:, 1], zeros, variances[:, 2]], dim=1)
    means = torch.cat([frozen.surface_means[frame], frozen.particle_means[frame][shown]])
    covars = torch.cat([frozen.surface_covars[frame], released_covars])
    cols = torch.cat([frozen.surface_colors, colors[shown]])
    opac = torch.cat([frozen.surface_opacities, opacities[shown]])
    image, _, _ = rasterization(means, None, None, opac, cols, viewmats, Ks, width, height, render_mode="RGB",
                                backgrounds=background.expand(len(viewmats), 3), covars=covars)
    return image


def pair_loss(frozen: FrozenFrames, theta: ReleasedAppearance, targets: torch.Tensor, weights: torch.Tensor,
              viewmats: torch.Tensor, Ks: torch.Tensor, background: torch.Tensor,
              pairs: list[tuple[int, int]]) -> torch.Tensor:
    """L_rec over the (view, frame) ``pairs``: the mean absolute error in linear RGB over their loss regions."""
    height, width = targets.shape[2:4]
    total, count = 0.0, 0.0
    for v, f in pairs:
        image = render_frame(frozen, theta, f, viewmats[v:v + 1], Ks[v:v + 1], width, height, background)[0]
        w = weights[v, f][..., None]
        total = total + (w * (image - targets[v, f]).abs()).sum()
        count += float(w.sum()) * 3
    return total / max(count, 1.0)


def refine(frozen: FrozenFrames, theta: ReleasedAppearance, targets: torch.Tensor, weights: torch.Tensor,
           viewmats: torch.Tensor, Ks: torch.Tensor, background: torch.Tensor, train_views: list[int],
           frames: list[int], iterations: int, lr: float, samples: int, seed: int) -> list[float]:
    """Adam on Theta_p; each iteration renders ``samples`` (training view, frame) pairs drawn at random among those
    whose loss region is not empty.

    targets (view, frame, y, x, 3) linear RGB I*; weights (view, frame, y, x) 0/1 loss region.  Returns the loss
    of the sampled pairs per iteration (a stochastic estimate of L_rec; see :func:`pair_loss` for the whole)."""
    rng = np.random.default_rng(seed)
    opt = torch.optim.Adam(theta.parameters(), lr=lr)
    pairs = [(v, f) for v in train_views for f in frames if bool(weights[v, f].any())]
    curve = []
    for it in range(iterations if pairs else 0):
        opt.zero_grad()
        chosen = [pairs[i] for i in rng.integers(len(pairs), size=samples)]
        loss = pair_loss(frozen, theta, targets, weights, viewmats, Ks, background, chosen)
        loss.backward()
        opt.step()
        curve.append(float(loss.detach()))
        report_progress(it + 1, iterations, unit="iteration")
    return curve


def _dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    if radius <= 0:
        return mask
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    flat = mask.reshape(-1, *mask.shape[-2:]).astype(np.uint8)
    return np.stack([cv2.dilate(m, kernel) for m in flat]).reshape(mask.shape).astype(bool)


@artifact_step("appearance_refinement",
               inputs=("gbuffer", "conditions", "effect", "mpm_rollout", "object_model", "mpm_particles"),
               reads=("refinement", "render.background", "render.released", "render.released_default",
                      "render.device"),
               outputs=("rgb?", "released_index?", "released_color?", "released_opacity?", "released_scale?",
                        "loss?"))
def appearance_refinement_step(inputs, params):
    """Eq. 7: fit the released particles' colour, opacity and per-axis scale to the generated frames."""
    g, cond, effect = inputs["gbuffer"], inputs["conditions"], inputs["effect"]
    if "frames" not in effect:
        return {}, {"skipped": effect.attrs.get("skipped") or "no generated frames"}
    r = params["refinement"]
    device = torch_device(params["render.device"])
    # 1. the frozen scene and the initial Theta_p (the G-buffer's look of the released material)
    rollout, obj = inputs["mpm_rollout"], inputs["object_model"]
    frames_sim = g["frame_index"]
    visible_all = g["released_visible"]
    index = np.flatnonzero(visible_all.any(axis=0))
    volumes = rollout_particle_volumes(inputs["mpm_particles"].arrays, len(rollout["particle_material"]))[index]
    look = released_appearance({"released": params["render.released"],
                                "released_default": params["render.released_default"]}, g.attrs["released_material"])

    def tensor(a: Any) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)

    frozen = FrozenFrames(tensor(rollout["gaussian_positions"][frames_sim]),
                          tensor(drawn_covariances(rollout["gaussian_covariances"][frames_sim], obj["gaussian_scales"])),
                          tensor(obj["gaussian_colors"]),
                          tensor(obj["gaussian_opacities"]), tensor(rollout["particle_positions"][frames_sim][:, index]),
                          torch.as_tensor(visible_all[:, index], device=device))
    theta = ReleasedAppearance(np.tile(np.asarray(look["color"], float), (len(index), 1)),
                               np.full(len(index), float(look["opacity"])),
                               np.tile((RELEASED_SCALE_FACTOR * np.cbrt(volumes))[:, None], (1, 3))).to(device)
    # 2. targets, loss region, views
    n_views = g["rgb"].shape[0]
    held_out = sorted({v % n_views for v in r["held_out_views"]}) if n_views > 1 else []
    train_views = [v for v in range(n_views) if v not in held_out]
    frames = [int(f) for f in np.flatnonzero(visible_all.any(axis=1))]
    targets = tensor(srgb_uint8_to_linear(effect["frames"]))
    weights = tensor(_dilate(cond["refined_mask"], r["mask_dilation_px"]))
    viewmats, Ks, background = tensor(g["viewmats"]), tensor(g["Ks"]), tensor(params["render.background"])
    # 3. optimise; L_rec over every training pair and over the held-out views, before and after
    train_pairs = [(v, f) for v in train_views for f in frames if bool(weights[v, f].any())]
    held_pairs = [(v, f) for v in held_out for f in frames if bool(weights[v, f].any())]

    def objective(pairs: list[tuple[int, int]]) -> float | None:
        if not pairs:
            return None
        with torch.no_grad():
            return float(pair_loss(frozen, theta, targets, weights, viewmats, Ks, background, pairs))

    before = {"train": objective(train_pairs), "held_out": objective(held_pairs)}
    curve = refine(frozen, theta, targets, weights, viewmats, Ks, background, train_views, frames, r["iterations"],
                   r["lr"], r["samples_per_iteration"], r["seed"])
    after = {"train": objective(train_pairs), "held_out": objective(held_pairs)}
    # 4. the refined 4D Gaussians rendered in every view and frame
    height, width = g["rgb"].shape[2:4]
    with torch.no_grad():
        rgb = np.stack([render_frame(frozen, theta, f, viewmats, Ks, width, height, background).cpu().numpy()
                        for f in range(len(frames_sim))], axis=1)
        colors, opacities, scales = (t.cpu().numpy() for t in theta.values())
    arrays = {
        "rgb": Array(to_srgb_uint8(rgb), ("view", "frame", "y", "x", "channel"), "1",
                     "renders of the refined 4D Gaussians, 8-bit sRGB"),
        "released_index": Array(index.astype(np.int32), ("released",), "1", "rollout particle index"),
        "released_color": Array(colors, ("released", "channel"), "1", "refined colour, linear RGB"),
        "released_opacity": Array(opacities, ("released",), "1", "refined opacity"),
        "released_scale": Array(scales, ("released", "xyz"), "m", "refined standard deviation per world axis"),
        "loss": Array(np.asarray(curve, np.float32), ("iteration",), "1",
                      "L_rec of the sampled pairs: mean |R - I*| in the region"),
    }
    attrs: dict[str, Any] = {"skipped": None, "train_views": train_views, "held_out_views": held_out,
                             "loss_before": before, "loss_after": after,
                             "renders": len(curve) * r["samples_per_iteration"]}
    return arrays, attrs

