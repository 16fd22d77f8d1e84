"""The G-buffer of a simulated squeeze, G_t^v = {I_t^v, D_t^v, M_t^v} (paper sec. 3.2, last paragraph; sec. 3.3).

Every rendered frame t of the MPM rollout is one set of 3D Gaussians (:mod:`tasks.render.scene`): the surface
Gaussians of the object model, deformed by the MPM (means and F Sigma F^T covariances of the rollout, each axis
capped at ``MAX_SURFACE_STRETCH`` x its rest scale: :func:`tasks.render.scene.drawn_covariances`), and the
released interior material (juice, cola, stuffing) as isotropic Gaussians from the frame of its release on, with
the look of ``render.released``.  They are rendered from the orbit rig (:mod:`tasks.render.cameras`) with our
differentiable rasteriser (:func:`tasks.render.splat.rasterization`):

* ``rgb`` I: the composited colour over ``render.background``, stored as 8-bit sRGB;
* ``depth`` D: the expected depth sum_i w_i z_i / sum_i w_i (m, camera z; 0 where nothing is drawn);
* ``alpha``: the composited opacity;
* ``mask`` M: the composited weight of released Gaussians (an indicator colour channel), in [0, alpha];
* ``surface_depth``: the expected depth of the object alone (without released material; +inf where empty),
  which the weight-free effect renderer needs to hide particles behind the object.

Frames are every ``render.frame_stride``-th simulated frame; ``frame_index`` names them.  A scene without
released material renders its surface only (its mask is 0 everywhere) and says so in ``notes``.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.physics.labels import INTERIOR
from tasks.render.cameras import distance_for_object, orbit_cameras
from tasks.render.colour import to_srgb_uint8
from tasks.render.device import torch_device
from tasks.render.scene import (
    drawn_covariances,
    frame_scene,
    released_appearance,
    released_visibility,
    rollout_particle_volumes,
)
from tasks.render.splat import rasterization


def orbit_rig(render: Mapping[str, Any], bbox_min: np.ndarray, bbox_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """viewmats (view, 4, 4) and Ks (view, 3, 3) of ``render.views`` cameras around the object's rest box, at the
    distance where its bounding sphere spans ``render.fill`` of the image width."""
    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    radius = distance_for_object(0.5 * (hi - lo), render["fov_deg"], render["fill"])
    return orbit_cameras(0.5 * (lo + hi), radius, render["views"], render["elevation_deg"], render["fov_deg"],
                         render["width"], render["height"], render["azimuth0_deg"])


def render_gbuffer(surface_positions: np.ndarray, surface_covariances: np.ndarray, surface_colors: np.ndarray,
                   surface_opacities: np.ndarray, particle_positions: np.ndarray, particle_volumes: np.ndarray,
                   visible: np.ndarray, released_color: np.ndarray, released_opacity: float, viewmats: np.ndarray,
                   Ks: np.ndarray, width: int, height: int, background: np.ndarray, near_plane: float,
                   device: torch.device) -> dict[str, np.ndarray]:
    """Render the frames given (leading axis) from every camera.

    surface_positions (frame, point, 3) m, surface_covariances (frame, point, 6) m^2, surface_colors (point, 3)
    linear RGB, surface_opacities (point,); particle_positions (frame, particle, 3) m, particle_volumes
    (particle,) m^3, visible (frame, particle) bool: released material drawn in that frame.
    Returns float arrays (view, frame, y, x[, channel]): ``rgb`` linear, ``depth`` m, ``alpha``, ``mask``,
    ``surface_depth`` m (+inf where the object is not seen).
    """
    n_frames, n_views = len(surface_positions), len(viewmats)
    out = {name: np.zeros((n_views, n_frames, height, width) + ((3,) if name == "rgb" else ()), np.float32)
           for name in ("rgb", "depth", "alpha", "mask", "surface_depth")}
    cams = dict(viewmats=torch.as_tensor(viewmats, dtype=torch.float32, device=device),
                Ks=torch.as_tensor(Ks, dtype=torch.float32, device=device), width=width, height=height,
                near_plane=near_plane, render_mode="RGB+ED")
    backgrounds = torch.as_tensor(np.append(background, 0.0), dtype=torch.float32, device=device).repeat(n_views, 1)
    for f in range(n_frames):
        scene = frame_scene(surface_positions[f], surface_covariances[f], surface_colors, surface_opacities,
                            particle_positions[f], particle_volumes, visible[f], released_color, released_opacity)
        t = {k: torch.as_tensor(v, device=device) for k, v in scene._asdict().items()}
        with torch.no_grad():
            colors, alphas, _ = rasterization(t["means"], None, None, t["opacities"], t["colors"],
                                              backgrounds=backgrounds, covars=t["covars"], **cams)
            out["rgb"][:, f] = colors[..., :3].cpu().numpy()
            out["mask"][:, f] = colors[..., 3].cpu().numpy()
            out["depth"][:, f] = colors[..., 4].cpu().numpy()
            out["alpha"][:, f] = alphas[..., 0].cpu().numpy()
            n_surface = len(surface_colors)
            if visible[f].any():  # the object alone, for occlusion of the effect
                s_colors, s_alphas, _ = rasterization(t["means"][:n_surface], None, None, t["opacities"][:n_surface],
                                                      t["colors"][:n_surface, :3], covars=t["covars"][:n_surface],
                                                      **cams)
                surface, seen = s_colors[..., 3].cpu().numpy(), s_alphas[..., 0].cpu().numpy()
            else:
                surface, seen = out["depth"][:, f], out["alpha"][:, f]
            out["surface_depth"][:, f] = np.where(seen > 1e-3, surface, np.inf)
        report_progress(f + 1, n_frames)
    return out


@artifact_step("gbuffer", inputs=("object_model", "mpm_particles", "mpm_rollout", "material_oracle"), reads=("render",),
               outputs=("rgb", "depth", "alpha", "mask", "surface_depth", "frame_index", "time", "viewmats", "Ks",
                        "released_visible"))
def gbuffer_step(inputs, params):
    """Multi-view G-buffer of the simulated squeeze (sec. 3.2-3.3): RGB, depth, alpha, released-material mask."""
    render = params["render"]
    obj, rollout = inputs["object_model"], inputs["mpm_rollout"]
    materials = inputs["material_oracle"].attrs["materials"]
    # 1. the frames, the rig, and what is released when
    n_sim = len(rollout["time"])
    frames = np.arange(0, n_sim, render["frame_stride"])
    viewmats, Ks = orbit_rig(render, obj.attrs["bbox_min"], obj.attrs["bbox_max"])
    n_particles = len(rollout["particle_material"])
    event = rollout.attrs.get("threshold_event") or {}
    released = rollout["released"] if "released" in rollout else np.zeros(n_particles, bool)
    released = released & (rollout["particle_material"] == INTERIOR)
    visible = released_visibility(released, event.get("frame") if event.get("crossed") else None, n_sim)[frames]
    interior = (materials.get("interior") or {}).get("name")
    look = released_appearance(render, interior)
    # 2. render
    covariances = drawn_covariances(rollout["gaussian_covariances"][frames], obj["gaussian_scales"])
    g = render_gbuffer(rollout["gaussian_positions"][frames], covariances,
                       obj["gaussian_colors"], obj["gaussian_opacities"], rollout["particle_positions"][frames],
                       rollout_particle_volumes(inputs["mpm_particles"].arrays, n_particles), visible, np.asarray(look["color"]),
                       float(look["opacity"]), viewmats, Ks, render["width"], render["height"],
                       np.asarray(render["background"], float), render["near_plane"], torch_device(render["device"]))
    # 3. arrays
    dims = ("view", "frame", "y", "x")
    arrays = {
        "rgb": Array(to_srgb_uint8(g["rgb"]), dims + ("channel",), "1", "I: composited colour, 8-bit sRGB"),
        "depth": Array(g["depth"], dims, "m", "D: expected depth (camera z); 0 where nothing is drawn"),
        "alpha": Array(g["alpha"], dims, "1", "composited opacity"),
        "mask": Array(g["mask"], dims, "1", "M: composited weight of the released interior material"),
        "surface_depth": Array(g["surface_depth"], dims, "m", "expected depth of the object alone; inf: empty"),
        "frame_index": Array(frames.astype(np.int32), ("frame",), "1", "index of the simulated frame"),
        "time": Array(rollout["time"][frames], ("frame",), "s"),
        "viewmats": Array(viewmats.astype(np.float32), ("view", "row", "col"), "m", "world-to-camera (OpenCV)"),
        "Ks": Array(Ks.astype(np.float32), ("view", "row", "col"), "px", "pinhole intrinsics"),
        "released_visible": Array(visible, ("frame", "particle"), "1", "released material drawn in the frame"),
    }
    has_release = bool(visible.any())
    attrs = {"released_material": interior if has_release else None,
             "release_fingers": list(event.get("fingers") or []) if has_release else [], "released_look": look if has_release else None,
             "effect": materials.get("effect") if has_release else None, "has_released_material": has_release,
             "mask_peak_px": int((g["mask"] > 0.5).sum(axis=(2, 3)).max(initial=0)),
             "notes": [] if has_release else ["no released material in view: the squeeze never crossed the "
                                              "material's threshold, or the object has no interior"]}
    return arrays, attrs
