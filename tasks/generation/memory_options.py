"""Memory options of the diffusion pipelines (paper sec. 3.3 generator), chosen by device and exposed in the config.

At 512 px a 45-frame view is padded to 52 frames; with classifier-free guidance the spatial layers see 104 images at
once, and the VAE decodes every frame.  diffusers offers five ways to bound the peak memory, applied here to the real
pipeline objects:

* VAE slicing (``AutoencoderKL.enable_slicing``): encode / decode one image of a batch at a time; same result.
* VAE tiling (``enable_tiling``): encode / decode overlapping tiles (512 px tiles, blended seams); changes pixels
  slightly, so only when memory demands it.
* attention: ``sdpa`` (torch's fused scaled-dot-product attention, ``AttnProcessor2_0``: memory-efficient kernels on
  CUDA, the flash-attention CPU kernel) or ``sliced`` (``SlicedAttnProcessor``: the batch x heads dimension in slices
  of ``ATTENTION_SLICE``; the lowest peak, slower).
* model CPU offload (``enable_model_cpu_offload``, needs ``accelerate`` and CUDA): each model moves to the GPU only
  while it runs.
* FreeNoise split inference (``enable_free_noise_split_inference``): when the sequence spans several motion windows,
  the spatial layers run ``window`` frames at a time and the motion modules ``SPATIAL_SPLIT`` positions at a time.

Automatic choice (``None`` / ``auto`` in the config) by device, thresholds chosen from the sizes above, not measured
on a GPU here: on the CPU, VAE slicing, SDPA and split inference (memory is plentiful, tiling and slicing only cost
time); on CUDA the same, plus VAE tiling above 512 px and model CPU offload and sliced attention on GPUs under
``SMALL_GPU_GB``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

ATTENTION_SLICE = 8
SPATIAL_SPLIT = 256
SMALL_GPU_GB = 12.0
ATTENTION_CHOICES = ("auto", "sdpa", "sliced", "default")


@dataclass(frozen=True)
class MemoryOptions:
    """What is applied to the pipelines.  attention: ``sdpa`` | ``sliced`` | ``default`` (leave diffusers' choice)."""

    vae_slicing: bool = False
    vae_tiling: bool = False
    attention: str = "default"
    cpu_offload: bool = False
    split_inference: bool = False


def choose_memory_options(device: torch.device | str, resolution: int | None, vae_slicing: bool | None = None,
                          vae_tiling: bool | None = None, attention: str = "auto", cpu_offload: bool | None = None,
                          split_inference: bool | None = None, gpu_memory_gb: float | None = None) -> MemoryOptions:
    """The options for ``device`` and the pipeline's frame size (longer side, px); explicit values win over the
    automatic choice.  ``gpu_memory_gb``: the CUDA device's total memory (read from torch when None)."""
    device = torch.device(device)
    if attention not in ATTENTION_CHOICES:
        raise ValueError(f"generation.attention must be one of {', '.join(ATTENTION_CHOICES)}, got {attention!r}")
    cuda = device.type == "cuda"
    if cuda and gpu_memory_gb is None:
        gpu_memory_gb = torch.cuda.get_device_properties(device).total_memory / 2**30
    small = cuda and gpu_memory_gb < SMALL_GPU_GB
    if cpu_offload and not cuda:
        raise ValueError("generation.cpu_offload=true needs a CUDA device (it moves models between the CPU and the "
                         "GPU); leave it null on the CPU")
    return MemoryOptions(
        vae_slicing=True if vae_slicing is None else vae_slicing,
        vae_tiling=(cuda and (resolution or 0) > 512) if vae_tiling is None else vae_tiling,
        attention=("sliced" if small else "sdpa") if attention == "auto" else attention,
        cpu_offload=small if cpu_offload is None else cpu_offload,
        split_inference=True if split_inference is None else split_inference,
    )


def _attention_processor(options: MemoryOptions):
    from diffusers.models.attention_processor import AttnProcessor2_0, SlicedAttnProcessor

    return {"sdpa": AttnProcessor2_0, "sliced": lambda: SlicedAttnProcessor(ATTENTION_SLICE)}.get(options.attention)


def set_attention(models, options: MemoryOptions) -> None:
    """Install the attention processor of ``options`` in every attention layer of ``models`` (None entries are
    skipped); ``default`` leaves them."""
    make = _attention_processor(options)
    if make is None:
        return
    for model in models:
        if model is not None and hasattr(model, "set_attn_processor"):
            model.set_attn_processor(make())


def apply_memory_options(pipelines, options: MemoryOptions, device: torch.device | str) -> None:
    """Apply the static options to the pipelines (``EffectPipelines``): VAE slicing / tiling (one shared VAE),
    attention processors and model CPU offload.  Split inference is applied per call, after FreeNoise is set for
    the sequence (:func:`set_split_inference`)."""
    vae = pipelines.video.vae
    vae.enable_slicing() if options.vae_slicing else vae.disable_slicing()
    vae.enable_tiling() if options.vae_tiling else vae.disable_tiling()
    set_attention((pipelines.video.unet, pipelines.refine.unet, pipelines.video.controlnet, vae), options)
    if options.cpu_offload:
        try:
            import accelerate  # noqa: F401
        except ImportError:
            raise ValueError("generation.cpu_offload needs the accelerate package: pip install -e '.[weights]'") from None
        for pipe in (pipelines.video, pipelines.refine, pipelines.text_to_video):
            pipe.enable_model_cpu_offload(device=device)


_SPLIT_LISTS = ("attentions", "resnets", "downsamplers", "upsamplers")


def set_split_inference(pipe, window: int, enabled: bool) -> None:
    """FreeNoise split inference on the pipeline's motion UNet: removed first (diffusers cannot undo it, and FreeNoise
    cannot be switched while it is in place), then applied when ``enabled`` (call after ``enable_free_noise``)."""
    from diffusers.pipelines.free_noise_utils import SplitInferenceModule

    def unwrap(module):
        return module.module if isinstance(module, SplitInferenceModule) else module

    for block in [*pipe.unet.down_blocks, pipe.unet.mid_block, *pipe.unet.up_blocks]:
        for motion_module in getattr(block, "motion_modules", None) or []:
            motion_module.proj_in = unwrap(motion_module.proj_in)
            motion_module.proj_out = unwrap(motion_module.proj_out)
            for i, item in enumerate(motion_module.transformer_blocks):
                motion_module.transformer_blocks[i] = unwrap(item)
        for name in _SPLIT_LISTS:
            for i, item in enumerate(getattr(block, name, None) or []):
                getattr(block, name)[i] = unwrap(item)
    if enabled:
        pipe.enable_free_noise_split_inference(spatial_split_size=SPATIAL_SPLIT, temporal_split_size=window)


def uses_split_inference(unet) -> bool:
    """Whether any block of the motion UNet is wrapped for split inference."""
    from diffusers.pipelines.free_noise_utils import SplitInferenceModule

    return any(isinstance(m, SplitInferenceModule) for m in unet.modules())
