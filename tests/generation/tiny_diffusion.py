"""Tiny randomly initialised diffusion components for tests, built in memory offline (no hub, no files read).

Sizes follow diffusers' own AnimateDiff/ControlNet fast tests (block_out_channels=(8, 8), cross_attention_dim=8,
norm groups of 2): a 2-block VAE (vae_scale_factor 2), a 2-block UNet, a MotionAdapter with tiny motion blocks,
a ControlNet made by `ControlNetModel.from_unet`, a 5-layer CLIP text encoder of width 8 and a CLIPTokenizer built
in memory from a character vocabulary with `model_max_length=77`. The scheduler is DDIM with `steps_offset=1`
and `timestep_spacing="linspace"`.

The ControlNet's zero convolutions, and any other weight tensor a fresh model initialises to exactly zero (so that
it would contribute nothing), are re-drawn from a seeded normal distribution: with the published zero
initialisation the depth condition could not reach the output and the tests of conditioning would be vacuous.

Also here: writing the components as diffusers-format folders, a synthetic G-buffer scene, and the CPU-time
benchmark (`python -m tests.tiny_diffusion`).
"""

import os
import string
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from diffusers import (
    AutoencoderKL,
    ControlNetModel,
    DDIMScheduler,
    MotionAdapter,
    StableDiffusionPipeline,
    UNet2DConditionModel,
)
from transformers import CLIPTextConfig, CLIPTextModel, CLIPTokenizer

from tasks.generation.components import DiffusionComponents, DiffusionWeights
from tasks.generation.masked_diffusion import (
    DiffusionSettings,
    build_effect_pipelines,
    generate_effect,
    generate_text_only,
)

CROSS_ATTENTION_DIM = 8
BLOCK_OUT_CHANNELS = (8, 8)
ZERO_INIT_STD = 1.0


def tiny_tokenizer() -> CLIPTokenizer:
    """CLIP BPE tokenizer over single characters (no merges), built in memory; ids 0 and 1 are the specials."""
    vocab = {"<|startoftext|>": 0, "<|endoftext|>": 1}
    for character in string.ascii_lowercase + string.digits + string.punctuation:
        vocab.setdefault(character, len(vocab))
        vocab.setdefault(character + "</w>", len(vocab))
    return CLIPTokenizer(vocab=vocab, merges=[], model_max_length=77)


def _redraw_zero_weights(model: torch.nn.Module, generator: torch.Generator) -> None:
    """Replace every all-zero weight tensor (zero convolutions, zero-initialised projections) by seeded noise."""
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            if name.endswith("weight") and not parameter.any():
                parameter.copy_(torch.randn(parameter.shape, generator=generator) * ZERO_INIT_STD)


def tiny_components(seed: int = 0) -> DiffusionComponents:
    """All seven components, float32 on CPU, deterministic for a given seed."""
    torch.manual_seed(seed)
    unet = UNet2DConditionModel(
        block_out_channels=BLOCK_OUT_CHANNELS,
        layers_per_block=2,
        sample_size=8,
        in_channels=4,
        out_channels=4,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=CROSS_ATTENTION_DIM,
        norm_num_groups=2,
    )
    vae = AutoencoderKL(
        block_out_channels=BLOCK_OUT_CHANNELS,
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D", "DownEncoderBlock2D"),
        up_block_types=("UpDecoderBlock2D", "UpDecoderBlock2D"),
        latent_channels=4,
        norm_num_groups=2,
    )
    motion_adapter = MotionAdapter(
        block_out_channels=BLOCK_OUT_CHANNELS,
        motion_layers_per_block=2,
        motion_norm_num_groups=2,
        motion_num_attention_heads=4,
        motion_max_seq_length=32,
    )
    controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(8, 8))
    text_encoder = CLIPTextModel(
        CLIPTextConfig(
            bos_token_id=0,
            eos_token_id=1,
            pad_token_id=1,
            hidden_size=CROSS_ATTENTION_DIM,
            intermediate_size=37,
            layer_norm_eps=1e-05,
            num_attention_heads=4,
            num_hidden_layers=5,
            vocab_size=1000,
        )
    )
    generator = torch.Generator().manual_seed(seed)
    for model in (unet, vae, motion_adapter, controlnet):
        _redraw_zero_weights(model, generator)
    scheduler = DDIMScheduler(
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="linear",
        clip_sample=False,
        set_alpha_to_one=False,
        steps_offset=1,
        timestep_spacing="linspace",
    )
    return DiffusionComponents(
        vae=vae.eval(),
        text_encoder=text_encoder.eval(),
        tokenizer=tiny_tokenizer(),
        unet=unet.eval(),
        motion_adapter=motion_adapter.eval(),
        controlnet=controlnet.eval(),
        scheduler=scheduler,
    )


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
    `python -m tests.tiny_diffusion`): the video pass (4 DDIM steps at strength 0.75, so 3 run, with CFG), the
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
