"""What one denoising step of the paper's video generator costs (sec. 3.3), measured with random weights of the real
sizes: no download, the architectures of the released models built from their published configs.

* ``sd15_video_models``: SD-1.5's UNet (``stable-diffusion-v1-5`` ``unet/config.json``: blocks 320/640/1280/1280,
  cross-attention width 768, 8 heads, 860 M parameters), the AnimateDiff v1-5-2 motion adapter (``MotionAdapter()``'s
  defaults are that release's config: 453 M) merged into a ``UNetMotionModel``, and the depth ControlNet made from the
  UNet (``ControlNetModel.from_unet``, the layout of ``control_v11f1p_sd15_depth``: 361 M), plus SD-1.5's VAE
  (83.7 M) for the encode/decode cost.
* ``step_flops``: the floating-point operations of one step (ControlNet + motion UNet on the classifier-free guidance
  batch, 2 x frames images), counted by ``torch.utils.flop_counter`` (2 per multiply-add) on fake tensors, so a
  16-frame window at 512 px is counted without being computed.
* ``time_step``: wall seconds and peak resident memory of one step run by the real
  ``AnimateDiffVideoToVideoControlNetPipeline`` (1 step at strength 1, ``output_type="latent"``: no VAE).
"""
from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass

import numpy as np
import torch

TEXT_TOKENS = 77
TEXT_WIDTH = 768  # CLIP ViT-L/14's width: SD-1.5's cross-attention dimension
VAE_SCALE = 8


@dataclass
class VideoModels:
    """The real-size models of one step and of the VAE, in one dtype on the CPU, evaluation mode."""

    unet: torch.nn.Module  # UNetMotionModel: SD-1.5 UNet + motion adapter
    motion_adapter: torch.nn.Module
    controlnet: torch.nn.Module
    vae: torch.nn.Module

    def parameters_m(self) -> dict[str, float]:
        """Millions of parameters per model (the motion UNet includes the adapter's)."""
        return {name: sum(p.numel() for p in getattr(self, name).parameters()) / 1e6
                for name in ("unet", "motion_adapter", "controlnet", "vae")}


def sd15_video_models(dtype: torch.dtype = torch.float32, seed: int = 0) -> VideoModels:
    """SD-1.5 UNet + AnimateDiff v1-5-2 motion adapter + depth ControlNet + SD VAE, random weights, real sizes."""
    from diffusers import AutoencoderKL, ControlNetModel, MotionAdapter, UNet2DConditionModel, UNetMotionModel

    torch.manual_seed(seed)
    unet2d = UNet2DConditionModel(sample_size=64, cross_attention_dim=TEXT_WIDTH, attention_head_dim=8)
    controlnet = ControlNetModel.from_unet(unet2d)
    adapter = MotionAdapter()
    unet = UNetMotionModel.from_unet2d(unet2d, adapter)
    del unet2d
    vae = AutoencoderKL(block_out_channels=(128, 256, 512, 512), layers_per_block=2, latent_channels=4,
                        down_block_types=("DownEncoderBlock2D",) * 4, up_block_types=("UpDecoderBlock2D",) * 4,
                        sample_size=512)
    return VideoModels(*(m.to(dtype).eval() for m in (unet, adapter, controlnet, vae)))


def step_flops(models: VideoModels, frames: int, size: int) -> tuple[int, int]:
    """FLOPs (2 per multiply-add) of one guided step on ``frames`` frames of ``size`` x ``size`` px: (ControlNet,
    motion UNet) on 2 x frames latents (unconditional + conditional), counted on fake tensors."""
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.utils.flop_counter import FlopCounterMode

    dtype, side = models.unet.dtype, size // VAE_SCALE
    with FakeTensorMode(allow_non_fake_inputs=True), torch.no_grad():
        latents = torch.zeros(2 * frames, 4, side, side, dtype=dtype)
        text = torch.zeros(2 * frames, TEXT_TOKENS, TEXT_WIDTH, dtype=dtype)
        depth = torch.zeros(2 * frames, 3, size, size, dtype=dtype)
        t = torch.tensor(500)
        with FlopCounterMode(display=False) as control:
            down, mid = models.controlnet(latents, t, encoder_hidden_states=text, controlnet_cond=depth,
                                          return_dict=False)
        with FlopCounterMode(display=False) as unet:
            models.unet(latents.reshape(2, frames, 4, side, side).transpose(1, 2), t, encoder_hidden_states=text,
                        down_block_additional_residuals=down, mid_block_additional_residual=mid)
    return int(control.get_total_flops()), int(unet.get_total_flops())


def vae_flops(models: VideoModels, size: int) -> tuple[int, int]:
    """FLOPs of encoding and of decoding one ``size`` x ``size`` frame with the VAE, on fake tensors."""
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.utils.flop_counter import FlopCounterMode

    dtype = models.vae.dtype
    out = []
    for run in ("encode", "decode"):
        with FakeTensorMode(allow_non_fake_inputs=True), FlopCounterMode(display=False) as counter, torch.no_grad():
            if run == "encode":
                models.vae.encode(torch.zeros(1, 3, size, size, dtype=dtype))
            else:
                models.vae.decode(torch.zeros(1, 4, size // VAE_SCALE, size // VAE_SCALE, dtype=dtype))
        out.append(int(counter.get_total_flops()))
    return out[0], out[1]


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


@contextlib.contextmanager
def peak_rss(interval_s: float = 0.02):
    """Samples the process's resident memory every ``interval_s`` while the block runs; yields a dict whose
    ``before`` and ``peak`` (bytes) are filled on exit."""
    record = {"before": _rss_bytes(), "peak": 0}
    stop = threading.Event()

    def sample():
        while not stop.is_set():
            record["peak"] = max(record["peak"], _rss_bytes())
            stop.wait(interval_s)

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        yield record
    finally:
        stop.set()
        thread.join()
        record["peak"] = max(record["peak"], _rss_bytes())


def video_pipeline(models: VideoModels):
    """The real ``AnimateDiffVideoToVideoControlNetPipeline`` around the models (no text encoder or tokenizer: the
    step is timed from prompt embeddings)."""
    from diffusers import AnimateDiffVideoToVideoControlNetPipeline, DDIMScheduler

    scheduler = DDIMScheduler(beta_start=0.00085, beta_end=0.012, beta_schedule="linear", clip_sample=False,
                              steps_offset=1, timestep_spacing="linspace")
    pipe = AnimateDiffVideoToVideoControlNetPipeline(
        vae=models.vae, text_encoder=None, tokenizer=None, unet=models.unet, motion_adapter=models.motion_adapter,
        controlnet=models.controlnet, scheduler=scheduler)
    pipe.set_progress_bar_config(disable=True)
    return pipe


def time_step(pipe, frames: int, size: int, guidance_scale: float = 7.5) -> dict[str, float]:
    """One denoising step of the pipeline on ``frames`` random latents of a ``size`` px video with random depth
    frames and prompt embeddings: {"seconds", "rss_before_gb", "rss_peak_gb"} (the peak includes the weights)."""
    dtype, side = pipe.unet.dtype, size // VAE_SCALE
    generator = torch.Generator().manual_seed(0)
    latents = torch.randn(1, 4, frames, side, side, generator=generator).to(dtype)
    text = torch.randn(1, TEXT_TOKENS, TEXT_WIDTH, generator=generator).to(dtype)
    depth = [np.random.default_rng(i).random((size, size, 3), dtype=np.float32) for i in range(frames)]
    with peak_rss() as memory, torch.inference_mode():
        started = time.perf_counter()
        pipe(latents=latents, conditioning_frames=depth, prompt_embeds=text, negative_prompt_embeds=text,
             num_inference_steps=1, strength=1.0, guidance_scale=guidance_scale, height=size, width=size,
             output_type="latent")
        seconds = time.perf_counter() - started
    return {"seconds": seconds, "rss_before_gb": memory["before"] / 1e9, "rss_peak_gb": memory["peak"] / 1e9}


def time_vae(models: VideoModels, size: int) -> tuple[float, float]:
    """Wall seconds to encode and to decode one random ``size`` x ``size`` frame."""
    dtype = models.vae.dtype
    with torch.inference_mode():
        started = time.perf_counter()
        models.vae.encode(torch.rand(1, 3, size, size).to(dtype) * 2 - 1)
        encode = time.perf_counter() - started
        started = time.perf_counter()
        models.vae.decode(torch.randn(1, 4, size // VAE_SCALE, size // VAE_SCALE).to(dtype))
        return encode, time.perf_counter() - started
