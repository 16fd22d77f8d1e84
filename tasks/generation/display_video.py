"""The videos a viewer watches (paper sec. 3.3, the final video; issue "videos that show the squeeze"): every orbit
view of the G-buffer rig plus one close-up of the contact region, at ``render.video_width`` x ``video_height``, with
the glove's hand drawn from the recorded signals (:mod:`tasks.render.hand`) and the released material drawn by the
effect backend - never the raw released Gaussians.

This is a presentation step: it reads the artifacts of the method and writes frames nobody scores.  The G-buffer of
eq. 6, the conditions, the effect step's frames and every metric stay computed without the hand and at the G-buffer
resolution; ``render.hand`` and the video settings are read here only (and by the G-buffer's key through ``render``,
which changes no array of it).

Per view and frame:

1. the object's surface Gaussians (deformed by the MPM, as :mod:`tasks.render.gbuffer` draws them) at the video
   resolution: colour over ``render.background``, alpha and expected depth;
2. the released material: with the ``physics`` backend rendered by the same weight-free renderer as the effect
   step (screen-space liquid with anisotropic kernels, or stuffing strands) over the object, hidden by the object's
   depth and *not* clipped by a mask; with a diffusion backend the generated frames, resized, inside the resized
   refined mask (the close-up has no generated frame: it shows the released Gaussians); with ``none`` the released
   Gaussians;
3. the hand (``render.hand``), depth-composited: a finger in front occludes, behind is hidden.

Outputs ``frames`` (view, frame, y, x, 3) 8-bit sRGB, the close-up last; ``effect_coverage`` (view, frame, y, x) in
[0, 1]: where the released material is drawn (for the note's connected-component figures).
"""
from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import cv2
import numpy as np
import torch

from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.generation.physics_effect import (
    PARTICLE_RADIUS_FACTOR,
    appearance_for_effect,
    liquid_kernels,
    render_effect,
)
from tasks.render.cameras import distance_for_object, look_at, orbit_rig
from tasks.render.colour import srgb_uint8_to_linear, to_srgb_uint8
from tasks.render.device import torch_device
from tasks.render.hand import draw_hand, hand_sequence
from tasks.render.scene import drawn_covariances, frame_scene, released_appearance, rollout_particle_volumes
from tasks.render.splat import rasterization

CLOSEUP_AZIMUTH_DEG = 65.0  # the close-up looks at the fingers' contact from this far round, away from the palm


def closeup_camera(fingertips: np.ndarray, palm: np.ndarray, object_centre: np.ndarray, frame: int,
                   render: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """viewmat (4, 4) and K (3, 3) of the close-up: aimed at the centroid of the four fingers' tips (index .. pinky)
    at ``frame`` (the peak squeeze), from outside the object along the direction centre -> centroid turned
    ``CLOSEUP_AZIMUTH_DEG`` about world z away from the palm and raised by ``render.elevation_deg`` + 15 degrees, at the distance
    where a sphere around the four tips (their spread + 2 cm) spans ``render.closeup_fill`` of the image width."""
    tips = np.asarray(fingertips, np.float64)[frame, 1:]
    target = tips.mean(axis=0)
    out = target - np.asarray(object_centre, np.float64)
    out[2] = 0.0
    out = out / max(np.linalg.norm(out), 1e-9)
    best = None
    for sign in (1.0, -1.0):  # the turn that moves the camera away from the palm
        a = np.radians(sign * CLOSEUP_AZIMUTH_DEG)
        d = np.array([np.cos(a) * out[0] - np.sin(a) * out[1], np.sin(a) * out[0] + np.cos(a) * out[1], 0.0])
        gap = np.linalg.norm(target + 0.1 * d - np.asarray(palm, np.float64)[frame])
        best = (gap, d) if best is None or gap > best[0] else best
    elevation = np.radians(render["elevation_deg"] + 15.0)
    direction = np.cos(elevation) * best[1] + np.array([0.0, 0.0, np.sin(elevation)])
    radius = float(np.linalg.norm(tips - target, axis=1).max()) + 0.02
    distance = distance_for_object(np.array([radius, 0.0, 0.0]), render["fov_deg"], render["closeup_fill"])
    width, height = render["video_width"], render["video_height"]
    focal = 0.5 * width / np.tan(0.5 * np.radians(render["fov_deg"]))
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return look_at(target + distance * direction, target), K


def display_cameras(render: Mapping[str, Any], bbox_min: np.ndarray, bbox_max: np.ndarray,
                    signals: Mapping[str, np.ndarray], peak_frame: int) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """The orbit rig of the G-buffer at the video resolution, plus the close-up (``render.closeup``): viewmats
    (view, 4, 4), Ks (view, 3, 3), names."""
    video = {**render, "width": render["video_width"], "height": render["video_height"]}
    viewmats, Ks = orbit_rig(video, bbox_min, bbox_max)
    names = [f"view {v}" for v in range(len(viewmats))]
    if render["closeup"]:
        centre = 0.5 * (np.asarray(bbox_min, float) + np.asarray(bbox_max, float))
        vm, K = closeup_camera(signals["fingertip_positions"], signals["palm_position"], centre, peak_frame, render)
        viewmats, Ks = np.concatenate([viewmats, vm[None]]), np.concatenate([Ks, K[None]])
        names.append("close-up")
    return viewmats, Ks, names


def _resize(images: np.ndarray, width: int, height: int, interpolation: int) -> np.ndarray:
    return cv2.resize(images, (width, height), interpolation=interpolation)


def render_display_frame(scene_arrays: dict[str, np.ndarray], cams: dict[str, Any], background: np.ndarray,
                         device: torch.device) -> dict[str, np.ndarray]:
    """One frame's Gaussians (``frame_scene`` fields, numpy) in every camera: linear ``rgb`` (view, y, x, 3),
    ``alpha`` and expected ``depth`` (m; +inf where alpha <= 0.5)."""
    t = {k: torch.as_tensor(v, device=device) for k, v in scene_arrays.items()}
    n = len(cams["viewmats"])
    backgrounds = torch.as_tensor(background, dtype=torch.float32, device=device).repeat(n, 1)
    with torch.no_grad():
        colors, alphas, _ = rasterization(t["means"], None, None, t["opacities"], t["colors"][:, :3],
                                          backgrounds=backgrounds, covars=t["covars"], render_mode="RGB+ED", **cams)
    alpha = alphas[..., 0].cpu().numpy()
    depth = colors[..., 3].cpu().numpy()
    return {"rgb": colors[..., :3].cpu().numpy(), "alpha": alpha, "depth": np.where(alpha > 0.5, depth, np.inf)}


class StageClock:
    """CPU seconds (``time.process_time``) per stage of the display step, for the cost benchmark
    (``flows/bench/video.py``); ``None`` in the step: nothing is timed."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self._t = time.process_time()

    def lap(self, stage: str) -> None:
        """Charge the CPU time since the last lap to ``stage``."""
        now = time.process_time()
        self.seconds[stage] = self.seconds.get(stage, 0.0) + now - self._t
        self._t = now


def _lap(clock: StageClock | None, stage: str) -> None:
    if clock is not None:
        clock.lap(stage)


@artifact_step("display_video",
               inputs=("object_model", "signal_smoothing", "mpm_particles", "mpm_rollout", "gbuffer", "conditions",
                       "effect"),
               reads=("render", "generation.backend", "generation.seed"),
               outputs=("frames", "effect_coverage", "viewmats", "Ks"))
def display_video_step(inputs, params):
    """The watched videos: every orbit view and the close-up at the video resolution, with the hand (module doc)."""
    return display_video(inputs, params)


def display_video(inputs: Mapping[str, Any], params: Mapping[str, Any], clock: StageClock | None = None
                  ) -> tuple[dict[str, Array], dict[str, Any]]:
    """The display step's arrays and attrs from its input artifacts and parameters (:func:`display_video_step`);
    ``clock``: CPU seconds per stage (surface, liquid kernels, released material, hand, encode; the close-up's
    apart), for the benchmark."""
    render, backend = params["render"], params["generation.backend"]
    obj, rollout, g, cond, effect = (inputs[k] for k in ("object_model", "mpm_rollout", "gbuffer", "conditions",
                                                         "effect"))
    signals = inputs["signal_smoothing"]
    device = torch_device(render["device"])
    frames = g["frame_index"]
    strain = rollout["squeeze_strain"]
    peak = int(np.clip(np.argmax(strain.max(axis=1)) if strain.size else 0, 0, len(signals["time"]) - 1))
    viewmats, Ks, names = display_cameras(render, obj.attrs["bbox_min"], obj.attrs["bbox_max"], signals, peak)
    width, height = render["video_width"], render["video_height"]
    n_views, n_orbit = len(viewmats), len(g["viewmats"])
    cams = dict(viewmats=torch.as_tensor(viewmats, dtype=torch.float32, device=device),
                Ks=torch.as_tensor(Ks, dtype=torch.float32, device=device), width=width, height=height,
                near_plane=render["near_plane"])
    background = np.asarray(render["background"], np.float32)
    # the released material and how it is drawn
    visible = g["released_visible"]
    volumes = rollout_particle_volumes(inputs["mpm_particles"].arrays, len(rollout["particle_material"]))
    radii = PARTICLE_RADIUS_FACTOR * np.cbrt(volumes)
    has_release = bool(g.attrs["has_released_material"]) and backend != "none"
    physics = has_release and backend == "physics" and "frames" in effect
    generated = has_release and not physics and "frames" in effect
    kind, appearance = appearance_for_effect(g.attrs["effect"]) if physics else (None, None)
    look = released_appearance(render, g.attrs.get("released_material"))
    hands = hand_sequence(signals, frames) if render["hand"] else None
    skin = np.asarray(render["hand_colour"], np.float64)
    covariances = drawn_covariances(rollout["gaussian_covariances"][frames], obj["gaussian_scales"])
    out = np.zeros((n_views, len(frames), height, width, 3), np.uint8)
    coverage = np.zeros((n_views, len(frames), height, width), np.float32)
    _lap(clock, "set-up")
    for f in range(len(frames)):
        # 1. the object's surface (with the released Gaussians only where nothing else draws them)
        blobs = visible[f] & (not physics) & (g.attrs["has_released_material"])
        scene = frame_scene(rollout["gaussian_positions"][frames[f]], covariances[f], obj["gaussian_colors"],
                            obj["gaussian_opacities"], rollout["particle_positions"][frames[f]], volumes, blobs,
                            np.asarray(look["color"]), float(look["opacity"]))
        base = render_display_frame(scene._asdict(), cams, background, device)
        rgb, alpha, depth = base["rgb"], base["alpha"], base["depth"]
        _lap(clock, "surface Gaussians")
        shown = rollout["particle_positions"][frames[f]][visible[f]]
        kernels = liquid_kernels(kind, shown, radii[visible[f]]) if physics and len(shown) else None
        _lap(clock, "liquid kernels")
        for v in range(n_views):
            where = " (close-up)" if v >= n_orbit else ""
            image, a, z = rgb[v], alpha[v], depth[v]
            # 2. the released material
            if physics and len(shown):
                drawn = render_effect(kind, shown, radii[visible[f]], viewmats[v], Ks[v], image, z, appearance,
                                      params["generation.seed"], kernels)
                image = drawn.rgb
                coverage[v, f] = drawn.coverage
                a = np.maximum(a, drawn.coverage)
                z = np.where(drawn.coverage > 0.5, np.minimum(z, drawn.depth), z)
            elif generated and v < n_orbit:
                mask = _resize(cond["refined_mask"][v, f].astype(np.float32), width, height, cv2.INTER_LINEAR)
                frame = srgb_uint8_to_linear(_resize(effect["frames"][v, f], width, height, cv2.INTER_CUBIC))
                image = image + mask[..., None] * (frame - image)
                coverage[v, f] = mask
            _lap(clock, "released material" + where)
            # 3. the hand
            if hands is not None:
                image = draw_hand(hands[f], viewmats[v], Ks[v], skin, image, a, z, background)
            _lap(clock, "hand" + where)
            out[v, f] = to_srgb_uint8(image)
            _lap(clock, "encode")
        report_progress(f + 1, len(frames))
    dims = ("view", "frame", "y", "x")
    arrays = {"frames": Array(out, dims + ("channel",), "1", "the watched video, 8-bit sRGB (close-up last)"),
              "effect_coverage": Array(coverage, dims, "1", "where the released material is drawn"),
              "viewmats": Array(viewmats.astype(np.float32), ("view", "row", "col"), "m", "world-to-camera"),
              "Ks": Array(Ks.astype(np.float32), ("view", "row", "col"), "px", "pinhole intrinsics")}
    how = ("physics-rendered (weight-free), unclipped" if physics else
           "generated frames resized into the refined mask" if generated else
           "released Gaussians" if g.attrs["has_released_material"] else "no released material")
    return arrays, {"views": names, "hand": bool(render["hand"]), "released": how, "peak_frame": peak,
                    "size": [width, height]}
