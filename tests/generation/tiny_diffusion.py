"""Tiny randomly initialised diffusion components for tests (built by tasks/generation/tiny_components.py, shared
with ``python -m flows.gpu_check``; see there for their sizes), written as diffusers-format folders, a synthetic
G-buffer scene, and the CPU-time benchmark (`python -m tests.generation.tiny_diffusion`).
"""

import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from diffusers import StableDiffusionPipeline

from tasks.generation.components import DiffusionComponents, DiffusionWeights
from tasks.generation.masked_diffusion import (
    DiffusionSettings,
    build_effect_pipelines,
    generate_effect,
    generate_text_only,
)
from tasks.generation.tiny_components import tiny_components, tiny_tokenizer  # noqa: F401  (the tests' import path)


def save_diffusers_folders(components: DiffusionComponents, weights: DiffusionWeights) -> None:
    """Write the components in diffusers format (`save_pretrained`) into the three folders `weights` names."""
    StableDiffusionPipeline(
        vae=components.vae,
        text_encoder=components.text_encoder,
        tokenizer=components.tokenizer,
        unet=components.unet,
        scheduler=components.scheduler,
        safety_checker=None,
        feature_extractor=None,
        requires_safety_checker=False,
    ).save_pretrained(Path(weights.folder) / weights.stable_diffusion.subfolder)
    components.motion_adapter.save_pretrained(Path(weights.folder) / weights.motion_adapter.subfolder)
    components.controlnet.save_pretrained(Path(weights.folder) / weights.controlnet_depth.subfolder)


def moving_disc_scene(num_frames: int, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A synthetic G-buffer: rgb (frame, y, x, 3) smooth gradients with a slowly varying blue channel, mask
    (frame, y, x) a disc of radius size/4 drifting right by size/80 per frame, depth (frame, y, x) a vertical
    ramp in [0.5, 1] gated by the mask (eq. 6 form)."""
    yy, xx = np.mgrid[:size, :size] / size
    frame = np.arange(num_frames)[:, None, None]
    blue = np.broadcast_to(0.5 + 0.2 * np.sin(frame / 5), (num_frames, size, size))
    rgb = np.stack(np.broadcast_arrays(0.3 + 0.4 * xx[None], 0.3 + 0.4 * yy[None], blue), axis=-1)
    mask = (xx[None] - 0.35 - frame / 80) ** 2 + (yy[None] - 0.5) ** 2 < 0.25**2
    depth = np.where(mask, 0.5 + 0.5 * yy[None], 0.0)
    return rgb.astype(np.float32), mask, depth.astype(np.float32)


def benchmark_cpu_time_per_frame(sizes: tuple[int, ...] = (64, 256), num_frames: int = 8) -> None:
    """Print process CPU seconds per frame with the tiny models, 1 torch thread by default (run
    `python -m tests.generation.tiny_diffusion`): the video pass (4 DDIM steps at strength 0.75, so 3 run, with CFG), the
    video pass plus the refine pass (1 more step at strength 0.3) and text-to-video (all 4 steps)."""
    torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))
    pipelines = build_effect_pipelines(tiny_components())
    settings = DiffusionSettings(num_inference_steps=4, strength=0.75, window=8, overlap=4)
    generate_effect(pipelines, *moving_disc_scene(2, 16), "warm-up", "", settings)
    for size in sizes:
        rgb, mask, depth = moving_disc_scene(num_frames, size)
        runs = {
            "video pass": lambda: generate_effect(pipelines, rgb, mask, depth, "a tomato", "", settings),
            "video + refine": lambda: generate_effect(
                pipelines, rgb, mask, depth, "a tomato", "", replace(settings, refine_pass=True)
            ),
            "text only": lambda: generate_text_only(pipelines, num_frames, size, size, "a tomato", "", settings),
        }
        for name, run in runs.items():
            started = time.process_time()
            run()
            print(f"{size}x{size} {name}: {(time.process_time() - started) / num_frames:.3f} s CPU per frame")


if __name__ == "__main__":
    benchmark_cpu_time_per_frame((64,), num_frames=8)
    benchmark_cpu_time_per_frame((256,), num_frames=2)
