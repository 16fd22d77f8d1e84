"""The secondary effect of a squeeze, generated under the physics (paper sec. 3.3), by the backend configured:

* ``physics`` (default, weight-free): the released material rendered as what it is - a liquid surface
  (screen-space fluid rendering) or fibrous stuffing - from the simulated particles, blended by the refined mask;
  labelled "physics-rendered" in every report;
* ``diffusers`` (the method): AnimateDiff video-to-video + depth ControlNet (+ optional SD img2img pass) on the
  simulated render, conditioned on the prompt and the mask-gated depth, confined by the refined mask;
* ``text_only`` (the ablation "w/o physics-guided conditions"): the same generator with the prompt only;
* ``none``: no effect.

Every backend's output is ``frames`` (view, frame, y, x, channel) 8-bit sRGB: outside the refined mask each pixel
equals the simulated render exactly (except ``text_only``, which generates every pixel).  A scene without
released material, or the ``none`` backend, writes no frames and says why (``skipped``).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.generation.physics_effect import appearance_for_effect, composite_effect, render_effect
from tasks.render.colour import srgb_uint8_to_linear, to_srgb_uint8
from tasks.render.scene import rollout_particle_volumes

PARTICLE_RADIUS_FACTOR = 0.75  # sphere radius of a released particle = this x cbrt(its volume): neighbours overlap


def physics_effect(sim_rgb: np.ndarray, surface_depth: np.ndarray, refined_mask: np.ndarray,
                   particle_positions: np.ndarray, radii: np.ndarray, visible: np.ndarray, viewmats: np.ndarray,
                   Ks: np.ndarray, effect: str, seed: int) -> np.ndarray:
    """The weight-free effect for every view and frame.

    sim_rgb (view, frame, y, x, 3) linear RGB; surface_depth (view, frame, y, x) m (+inf: no object);
    refined_mask (view, frame, y, x) bool; particle_positions (frame, particle, 3) m; radii (particle,) m;
    visible (frame, particle) bool; viewmats (view, 4, 4), Ks (view, 3, 3); effect: the oracle's effect name.
    Returns the composited frames (view, frame, y, x, 3) linear RGB.
    """
    kind, appearance = appearance_for_effect(effect)
    out = sim_rgb.copy()
    n_views, n_frames = sim_rgb.shape[:2]
    for f in range(n_frames):
        shown = visible[f]
        if not shown.any():
            continue
        for v in range(n_views):
            frame = render_effect(kind, particle_positions[f][shown], radii[shown], viewmats[v], Ks[v],
                                  sim_rgb[v, f], surface_depth[v, f], appearance, seed)
            out[v, f] = composite_effect(sim_rgb[v, f], frame.rgb, refined_mask[v, f])
        report_progress(f + 1, n_frames)
    return out


def diffusion_effect(generation: Mapping[str, Any], sim_srgb: np.ndarray, refined_mask: np.ndarray,
                     gated_depth: np.ndarray, prompt: str, negative_prompt: str) -> tuple[np.ndarray, dict]:
    """``diffusers`` / ``text_only`` for every view: frames (view, frame, y, x, 3) sRGB in [0, 1] (Stable
    Diffusion works on sRGB-encoded images) from the simulated render ``sim_srgb`` (same layout), and run info.

    diffusers is imported here, not at the top: the default (physics) backend never loads it."""
    from tasks.generation.components import auto_device_dtype, diffusion_weights, load_components_cached
    from tasks.generation.masked_diffusion import (
        DiffusionSettings,
        build_effect_pipelines,
        generate_effect,
        generate_text_only,
    )

    device, dtype = auto_device_dtype(generation["dtype"] == "bfloat16", generation["device"], generation["dtype"])
    pipelines = build_effect_pipelines(load_components_cached(diffusion_weights(generation), device, dtype))
    settings = DiffusionSettings(num_inference_steps=generation["steps"], strength=generation["strength"],
                                 guidance_scale=generation["guidance_scale"],
                                 controlnet_conditioning_scale=generation["controlnet_scale"],
                                 window=generation["window"], overlap=generation["overlap"], seed=generation["seed"],
                                 refine_pass=generation["refine_pass"], refine_strength=generation["refine_strength"])
    out, infos = np.empty_like(sim_srgb), []
    n_views, n_frames, height, width = refined_mask.shape
    for v in range(n_views):
        if generation["backend"] == "text_only":
            out[v], info = generate_text_only(pipelines, n_frames, height, width, prompt, negative_prompt, settings)
        else:
            out[v], info = generate_effect(pipelines, sim_srgb[v], refined_mask[v], gated_depth[v], prompt,
                                           negative_prompt, settings)
        infos.append(info)
        report_progress(v + 1, n_views, unit="view")
    return out, {"views": infos}


@artifact_step("effect", inputs=("gbuffer", "conditions", "mpm_rollout", "mpm_particles", "material_oracle"),
               reads=("generation", "object.display_name", "object.description"),
               outputs=("frames?",))
def effect_step(inputs, params):
    """The secondary effect under the physics (sec. 3.3) by ``generation.backend``; see the module docstring."""
    generation = params["generation"]
    g, cond = inputs["gbuffer"], inputs["conditions"]
    backend = generation["backend"]
    # 1. what this scene needs
    if backend == "none":
        return {}, {"backend": backend, "skipped": "generation=none: no effect generated"}
    if not g.attrs["has_released_material"] and backend != "text_only":
        return {}, {"backend": backend, "skipped": "no released material: " + "; ".join(g.attrs["notes"])}
    info: dict[str, Any] = {}
    # 2. generate
    if backend == "physics":
        sim_rgb = srgb_uint8_to_linear(g["rgb"])
        rollout, particles = inputs["mpm_rollout"], inputs["mpm_particles"]
        frames = g["frame_index"]
        volumes = rollout_particle_volumes(particles.arrays, len(rollout["particle_material"]))
        visible = g["released_visible"]
        out = physics_effect(sim_rgb, g["surface_depth"], cond["refined_mask"], rollout["particle_positions"][frames],
                             PARTICLE_RADIUS_FACTOR * np.cbrt(volumes), visible, g["viewmats"], g["Ks"],
                             g.attrs["effect"], generation["seed"])
        frames_out = to_srgb_uint8(out)
        label = "physics-rendered (screen-space fluid / strand rendering; no diffusion)"
    else:
        from tasks.generation.prompts import effect_prompt

        look = g.attrs["released_look"] or {"effect": "liquid"}
        text = effect_prompt(params["object.display_name"], params["object.description"],
                             g.attrs["released_material"] or "juice", look["effect"], generation["prompt"],
                             generation["negative_prompt"])
        out, info = diffusion_effect(generation, g["rgb"].astype(np.float32) / 255.0, cond["refined_mask"],
                                     cond["gated_depth"], text.prompt, text.negative_prompt)
        frames_out = np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)
        info.update(prompt=text.prompt, negative_prompt=text.negative_prompt)
        label = ("text-only diffusion (w/o physics-guided conditions)" if backend == "text_only"
                 else "diffusion (AnimateDiff + SD img2img + depth ControlNet)")
    if backend != "text_only":  # every pixel outside the refined mask is the simulated render, byte for byte
        frames_out = np.where(cond["refined_mask"][..., None], frames_out, g["rgb"])
    arrays = {"frames": Array(frames_out, ("view", "frame", "y", "x", "channel"), "1",
                              f"final frames, 8-bit sRGB: {label}")}
    # no wall time in the attrs: they are part of the content digest, which must not depend on the machine's load
    info = {k: v for k, v in info.items() if k != "views"} | (
        {"views": [{k: v for k, v in view.items() if k != "seconds"} for view in info["views"]]} if "views" in info
        else {})
    return arrays, {"backend": backend, "label": label, "skipped": None, "info": info}
