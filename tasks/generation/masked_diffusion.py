"""Mask-confined, depth-conditioned effect generation with AnimateDiff, ControlNet and SD img2img (paper sec. 3.3).

Per view, the simulated render I (RGB frames), the refined particle mask M~ and the normalised, mask-gated depth
D~ (eq. 6) condition the diffusion pipelines built from injected components:

- `AnimateDiffVideoToVideoControlNetPipeline`: video-to-video from the render, depth through ControlNet, the
  motion module's temporal attention for coherence across frames;
- optionally `StableDiffusionControlNetImg2ImgPipeline`: a low-strength per-frame pass (image = frame,
  control_image = depth), the paper's Stable Diffusion image-to-image module;
- `AnimateDiffPipeline` for the ablation "VirSqueezer w/o Physics-guided Conditions" (prompt only).

No pipeline takes a mask, so confinement is done in two places: after every denoising step the latents outside
the mask (max-pooled to the latent grid, i.e. dilated) are replaced by the input's latents re-noised to the
timestep the sampler has reached (`callback_on_step_end`), and the decoded frames are composited by the refined
mask in pixel space ("the refined foreground is blended with the background according to the particle mask"),
so every pixel outside the mask equals the render exactly (the VAE alone cannot reproduce it).

Long sequences (90 frames against the motion module's 16-32) use diffusers' FreeNoise (Qiu et al., ICLR 2024):
the motion module attends within sliding windows of `window` frames, stride `window - overlap`, and averages the
overlapping windows' outputs with pyramid (linear ramp) weights in every motion block at every step, so one
denoising trajectory covers all frames and no window boundary exists in the output. This beats blending
independently denoised windows (pixel cross-fades of different samples ghost, and overlapped frames are denoised
twice). The sequence is padded with copies of its last frame to a whole number of windows because diffusers
0.42.1 mis-normalises the frames of an incomplete last window under pyramid weights (FreeNoiseTransformerBlock
divides by one weight `weights[:, -n]` instead of per-frame weights); the padding is cropped afterwards.
"""

import math
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from diffusers import (
    AnimateDiffPipeline,
    AnimateDiffVideoToVideoControlNetPipeline,
    StableDiffusionControlNetImg2ImgPipeline,
    UNetMotionModel,
)

from tasks.generation.components import DiffusionComponents
from tasks.generation.memory_options import MemoryOptions, set_attention, set_split_inference

VAE_CHUNK_FRAMES = 16
PIPELINE_SIZE_MULTIPLE = 8


@dataclass(frozen=True)
class DiffusionSettings:
    """Sampler settings of the effect generation.

    num_inference_steps: DDIM steps of a full denoise; a pass of strength s runs int(steps * s) of them.
    strength: how far the video pass re-noises the render (0 keeps it, 1 starts from pure noise).
    guidance_scale: classifier-free guidance weight (1 disables the unconditional branch).
    controlnet_conditioning_scale: weight of the depth ControlNet residuals.
    window, overlap: frames per motion-module window and frames shared by neighbouring windows.
    seed: seeds every random draw (latent noise); equal seeds give identical frames.
    refine_pass, refine_strength: the per-frame SD ControlNet img2img pass and its strength (batches of `window`).
    resolution: px, the longer side of the frames the pipelines run on (the conditions are resized to it and the
    generated frames back to the render's size before the exact composite); None runs at the render's size.
    SD-1.5 was trained at 512 px (a 64 x 64 latent); far smaller latents give it little room.
    memory: attention processors and FreeNoise split inference applied per call (`memory_options`).
    """

    num_inference_steps: int = 20
    strength: float = 0.75
    guidance_scale: float = 7.5
    controlnet_conditioning_scale: float = 1.0
    window: int = 16
    overlap: int = 4
    seed: int = 0
    refine_pass: bool = False
    refine_strength: float = 0.3
    resolution: int | None = None
    memory: MemoryOptions = MemoryOptions()


@dataclass
class EffectPipelines:
    """The three real diffusers pipelines, sharing one set of injected components (one motion UNet)."""

    video: AnimateDiffVideoToVideoControlNetPipeline
    refine: StableDiffusionControlNetImg2ImgPipeline
    text_to_video: AnimateDiffPipeline


def build_effect_pipelines(components: DiffusionComponents) -> EffectPipelines:
    """Assemble the pipelines from `components` (built once by `components.load_components` or by tests).

    The motion UNet (SD UNet + motion adapter, `UNetMotionModel.from_unet2d`) is built once here and shared by
    the video-to-video and the text-to-video pipeline; the img2img pipeline uses the 2D UNet. Each pipeline gets
    its own scheduler instance of the injected scheduler's class and config.
    """
    unet = components.unet
    motion_unet = UNetMotionModel.from_unet2d(unet, components.motion_adapter).to(unet.device).eval()
    shared = {"vae": components.vae, "text_encoder": components.text_encoder, "tokenizer": components.tokenizer}

    def scheduler():
        return type(components.scheduler).from_config(components.scheduler.config)

    pipelines = EffectPipelines(
        video=AnimateDiffVideoToVideoControlNetPipeline(
            **shared,
            unet=motion_unet,
            motion_adapter=components.motion_adapter,
            controlnet=components.controlnet,
            scheduler=scheduler(),
        ),
        refine=StableDiffusionControlNetImg2ImgPipeline(
            **shared,
            unet=unet,
            controlnet=components.controlnet,
            scheduler=scheduler(),
            safety_checker=None,
            feature_extractor=None,
            requires_safety_checker=False,
        ),
        text_to_video=AnimateDiffPipeline(
            **shared, unet=motion_unet, motion_adapter=components.motion_adapter, scheduler=scheduler()
        ),
    )
    for pipe in (pipelines.video, pipelines.refine, pipelines.text_to_video):
        pipe.set_progress_bar_config(disable=True)
    return pipelines


def frame_size_multiple(pipelines: EffectPipelines) -> int:
    """Pixels: frame height and width are padded to a multiple of this, lcm(8, vae_scale_factor).

    The pipelines refuse sizes that are not multiples of 8, and the latent grid is size / vae_scale_factor.
    Odd latent grids are fine: on an SD-1.5-layout model (vae_scale_factor 8, three UNet downsamplings) 64, 72,
    96, 104 and 128 pixels all ran through the video-to-video and img2img ControlNet pipelines (diffusers
    0.42.1; the UNets forward the upsample sizes). So 8 for SD-1.5 and for the tiny test models.
    """
    return math.lcm(PIPELINE_SIZE_MULTIPLE, pipelines.video.vae_scale_factor)


def temporal_windows(num_frames: int, window: int, overlap: int) -> list[tuple[int, int]]:
    """FreeNoise's windows [start, end) over a sequence padded to a whole number of them.

    One window when num_frames <= window; otherwise stride = window - overlap and ceil((num_frames - window) /
    stride) + 1 windows, the last ending at the padded length (>= num_frames).
    """
    if num_frames <= window:
        return [(0, num_frames)]
    stride = window - overlap
    count = math.ceil((num_frames - window) / stride) + 1
    return [(index * stride, index * stride + window) for index in range(count)]


def _check_settings(settings: DiffusionSettings, pipelines: EffectPipelines, strength: float) -> None:
    """ValueError naming the setting and the fix when the sampler cannot run as configured."""
    max_window = pipelines.video.motion_adapter.config.motion_max_seq_length
    if settings.num_inference_steps < 1 or not 0 < strength <= 1:
        raise ValueError(f"need num_inference_steps >= 1 and 0 < strength <= 1, got {settings}")
    if int(settings.num_inference_steps * strength) < 1:
        raise ValueError(f"num_inference_steps * strength < 1 runs no step; raise them ({settings})")
    if not 2 <= settings.window <= max_window or not 0 <= settings.overlap < settings.window:
        raise ValueError(
            f"need 2 <= window <= {max_window} (the motion module's length) and 0 <= overlap < window, "
            f"got window={settings.window}, overlap={settings.overlap}"
        )


def _check_conditions(rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray) -> None:
    """ValueError naming the G-buffer input and the fix when shapes, dtypes or ranges are wrong."""
    if rgb.ndim != 4 or rgb.shape[-1] != 3 or rgb.shape[0] < 1 or not np.issubdtype(rgb.dtype, np.floating):
        raise ValueError(f"rgb must be (frame, y, x, 3) float in [0, 1], got {rgb.shape} {rgb.dtype}")
    if mask.shape != rgb.shape[:3] or mask.dtype != np.bool_:
        raise ValueError(f"mask must be (frame, y, x) bool matching rgb {rgb.shape[:3]}, got {mask.shape} {mask.dtype}")
    if depth.shape != rgb.shape[:3]:
        raise ValueError(f"depth must be (frame, y, x) matching rgb {rgb.shape[:3]}, got {depth.shape}")
    for name, values in (("rgb", rgb), ("depth", depth)):
        if not np.all(np.isfinite(values)) or values.min() < 0 or values.max() > 1:
            raise ValueError(f"{name} must be finite and within [0, 1]; normalise it first (eq. 6 for depth)")


def _pad(values: np.ndarray, frames: int, height: int, width: int, fill: str | bool) -> np.ndarray:
    """Pad axes (frame, y, x) at the end to the given sizes: frames repeat the last one; pixels by `fill`
    ('edge' replicates the border, False pads a mask with 'outside')."""
    values = np.pad(values, [(0, frames - values.shape[0])] + [(0, 0)] * (values.ndim - 1), mode="edge")
    spatial = [(0, 0), (0, height - values.shape[1]), (0, width - values.shape[2])] + [(0, 0)] * (values.ndim - 3)
    if fill == "edge":
        return np.pad(values, spatial, mode="edge")
    return np.pad(values, spatial, mode="constant", constant_values=fill)


def _padded_size(pipelines: EffectPipelines, num_frames: int, height: int, width: int, settings: DiffusionSettings):
    """(windows, padded frames, padded height, padded width) for a sequence of this size."""
    windows = temporal_windows(num_frames, settings.window, settings.overlap)
    multiple = frame_size_multiple(pipelines)
    return windows, windows[-1][1], -(-height // multiple) * multiple, -(-width // multiple) * multiple


def _use_windows(pipe: AnimateDiffVideoToVideoControlNetPipeline | AnimateDiffPipeline, frames: int, settings):
    """FreeNoise on the (shared) motion UNet when the sequence exceeds one window, off otherwise; then split
    inference (only with FreeNoise) and the attention processors of `settings.memory` (FreeNoise rebuilds the motion
    blocks with diffusers' default processors)."""
    set_split_inference(pipe, settings.window, False)
    if frames > settings.window:
        pipe.enable_free_noise(
            context_length=settings.window,
            context_stride=settings.window - settings.overlap,
            weighting_scheme="pyramid",
        )
    else:
        pipe.disable_free_noise()
    set_split_inference(pipe, settings.window, settings.memory.split_inference and frames > settings.window)
    set_attention((pipe.unet,), settings.memory)
    pipe.unet.eval()


def _resolution_size(height: int, width: int, resolution: int | None) -> tuple[int, int]:
    """(height, width) scaled so that the longer side is `resolution` px (aspect kept, rounded); unchanged for None."""
    if not resolution or max(height, width) == resolution:
        return height, width
    scale = resolution / max(height, width)
    return max(1, round(height * scale)), max(1, round(width * scale))


def _resize_frames(frames: np.ndarray, size: tuple[int, int], nearest: bool = False) -> np.ndarray:
    """(frame, y, x[, c]) resized to `size` (y, x): area averaging down, bilinear up, nearest for masks."""
    if frames.shape[1:3] == tuple(size):
        return frames
    import cv2

    down = size[0] * size[1] < frames.shape[1] * frames.shape[2]
    mode = cv2.INTER_NEAREST if nearest else cv2.INTER_AREA if down else cv2.INTER_LINEAR
    dtype = frames.dtype
    source = frames.astype(np.uint8) if dtype == np.bool_ else frames
    out = np.stack([cv2.resize(frame, (size[1], size[0]), interpolation=mode) for frame in source])
    return out.astype(dtype) if dtype == np.bool_ else np.clip(out, 0, 1) if not nearest else out


def _to_resolution(rgb: np.ndarray, mask: np.ndarray, depth: np.ndarray, resolution: int | None):
    """The G-buffer conditions at the pipeline's resolution (`_resolution_size`): rgb and depth resampled, the mask
    by nearest neighbour (its pixels stay whole)."""
    size = _resolution_size(*mask.shape[1:], resolution)
    return _resize_frames(rgb, size), _resize_frames(mask, size, nearest=True), _resize_frames(depth, size)


def _pass_timesteps(scheduler, num_inference_steps: int, strength: float) -> torch.Tensor:
    """The timesteps a pass of this strength runs, as the img2img / video2video pipelines truncate them."""
    scheduler.set_timesteps(num_inference_steps)
    kept = min(int(num_inference_steps * strength), num_inference_steps)
    return scheduler.timesteps[(num_inference_steps - kept) * scheduler.order :]


def _clean_latents(vae, frames: np.ndarray) -> torch.Tensor:
    """VAE posterior means of frames (frame, y, x, 3) in [0, 1], scaled: (frame, latent channel, y/s, x/s)."""
    pixels = torch.from_numpy(np.ascontiguousarray(frames, dtype=np.float32)).permute(0, 3, 1, 2) * 2 - 1
    with torch.no_grad():
        chunks = [
            vae.encode(chunk.to(vae.device, vae.dtype)).latent_dist.mean for chunk in pixels.split(VAE_CHUNK_FRAMES)
        ]
    return torch.cat(chunks) * vae.config.scaling_factor


def _latent_mask(mask: np.ndarray, scale: int, device: torch.device) -> torch.Tensor:
    """Mask (frame, y, x) max-pooled to the latent grid: (frame, 1, y/s, x/s) bool, true where any pixel is."""
    pooled = F.max_pool2d(torch.from_numpy(mask).float()[:, None], scale)
    return (pooled > 0.5).to(device)


class _LatentConfinement:
    """`callback_on_step_end` that confines denoising to the mask.

    After the sampler's step i the latents are at timestep t_{i+1}; outside the latent mask they are replaced by
    the input's clean latents re-noised to t_{i+1} with the pass's own noise (by the clean latents after the
    last step). Works for video (1, C, frame, h, w) and image-batch (frame, C, h, w) layouts alike.
    """

    def __init__(self, clean: torch.Tensor, noise: torch.Tensor, inside: torch.Tensor, timesteps: torch.Tensor):
        self.clean, self.noise, self.inside, self.timesteps = clean, noise, inside, timesteps
        self.steps_run = 0

    def __call__(self, pipe, step_index: int, timestep, callback_kwargs: dict) -> dict:
        if int(timestep) != int(self.timesteps[step_index]):
            raise RuntimeError(f"pipeline timestep {int(timestep)} differs from the confinement schedule")
        reached = self.timesteps[step_index + 1 : step_index + 2]
        reference = pipe.scheduler.add_noise(self.clean, self.noise, reached) if len(reached) else self.clean
        self.steps_run += 1
        return {"latents": torch.where(self.inside, callback_kwargs["latents"], reference)}


def _as_video(per_frame: torch.Tensor) -> torch.Tensor:
    """(frame, C, h, w) -> the video pipelines' latent layout (1, C, frame, h, w)."""
    return per_frame.permute(1, 0, 2, 3)[None]


def _depth_frames(depth: np.ndarray) -> np.ndarray:
    """Depth (frame, y, x) in [0, 1] -> the ControlNet's 3-channel image (frame, y, x, 3) float32."""
    return np.repeat(depth.astype(np.float32)[..., None], 3, axis=-1)


def _video_pass(pipelines, rgb, mask, control, prompt, negative_prompt, settings, generator) -> tuple[np.ndarray, int]:
    """AnimateDiff video-to-video + depth ControlNet over the whole (padded) sequence, latents confined."""
    pipe = pipelines.video
    _use_windows(pipe, rgb.shape[0], settings)
    timesteps = _pass_timesteps(pipe.scheduler, settings.num_inference_steps, settings.strength)
    clean = _clean_latents(pipe.vae, rgb)
    noise = torch.randn(clean.shape, generator=generator).to(clean)
    confinement = _LatentConfinement(
        _as_video(clean),
        _as_video(noise),
        _as_video(_latent_mask(mask, pipe.vae_scale_factor, clean.device)),
        timesteps,
    )
    output = pipe(
        latents=pipe.scheduler.add_noise(confinement.clean, confinement.noise, timesteps[:1]),
        conditioning_frames=list(control),
        prompt=prompt,
        negative_prompt=negative_prompt,
        height=rgb.shape[1],
        width=rgb.shape[2],
        decode_chunk_size=VAE_CHUNK_FRAMES,
        **_denoising_kwargs(settings, settings.strength, generator, confinement),
    )
    return output.frames[0], confinement.steps_run


def _denoising_kwargs(settings, strength: float, generator, confinement: "_LatentConfinement") -> dict:
    """The pipeline arguments both passes share: steps, strength, CFG and ControlNet scales, and the latent
    confinement called after every step."""
    return dict(num_inference_steps=settings.num_inference_steps, strength=strength,
                guidance_scale=settings.guidance_scale,
                controlnet_conditioning_scale=float(settings.controlnet_conditioning_scale), generator=generator,
                output_type="np", callback_on_step_end=confinement, callback_on_step_end_tensor_inputs=["latents"])


def _refine_pass(pipelines, frames, mask, control, prompt, negative_prompt, settings, generator):
    """SD ControlNet img2img per frame (batches of `window` frames) at `refine_strength`, latents confined."""
    pipe = pipelines.refine
    refined, steps_run = [], 0
    for start in range(0, frames.shape[0], settings.window):
        batch = slice(start, min(frames.shape[0], start + settings.window))
        count = batch.stop - batch.start
        timesteps = _pass_timesteps(pipe.scheduler, settings.num_inference_steps, settings.refine_strength)
        clean = _clean_latents(pipe.vae, frames[batch])
        noise = torch.randn(clean.shape, generator=generator).to(clean)
        inside = _latent_mask(mask[batch], pipe.vae_scale_factor, clean.device)
        confinement = _LatentConfinement(clean, noise, inside, timesteps)
        output = pipe(
            prompt=[prompt] * count,
            negative_prompt=[negative_prompt] * count,
            image=frames[batch],
            control_image=control[batch],
            latents=pipe.scheduler.add_noise(clean, noise, timesteps[:1]),
            height=frames.shape[1],
            width=frames.shape[2],
            **_denoising_kwargs(settings, settings.refine_strength, generator, confinement),
        )
        refined.append(output.images)
        steps_run += confinement.steps_run
    return np.concatenate(refined), steps_run


def generate_effect(
    pipelines: EffectPipelines,
    rgb: np.ndarray,
    mask: np.ndarray,
    depth: np.ndarray,
    prompt: str,
    negative_prompt: str,
    settings: DiffusionSettings,
) -> tuple[np.ndarray, dict]:
    """The paper's conditional effect generation for one view (sec. 3.3, conditions of eq. 6).

    rgb: (frame, y, x, 3) float in [0, 1], the simulated render I, sRGB-encoded (display values: Stable
    Diffusion's VAE was trained on sRGB images, so pass 8-bit sRGB / 255, not linear RGB); mask: (frame, y, x)
    bool, the refined particle mask M~; depth: (frame, y, x) float in [0, 1], the normalised mask-gated depth D~
    with near = 1 (relative inverse depth, the depth ControlNet's convention), 0 outside the mask. Returns frames
    (frame, y, x, 3) float32 in [0, 1], equal to `rgb` (as float32) at every pixel outside the mask, and
    info {"steps_run", "refine_steps_run", "windows" ([start, end) over the padded frames), "padded_shape"
    (frame, y, x), "seconds"}. Frames are padded to a whole number of windows and to `frame_size_multiple`
    pixels (edge copies, mask padded with 'outside') and cropped back. Deterministic for a given seed.
    """
    # 1. Check the inputs and the sampler settings.
    _check_conditions(rgb, mask, depth)
    _check_settings(settings, pipelines, settings.strength)
    if settings.refine_pass:
        _check_settings(settings, pipelines, settings.refine_strength)
    started = time.perf_counter()
    num_frames = mask.shape[0]
    # 2. Resize to the pipeline's resolution, pad to a whole number of motion windows and a valid frame size.
    work_rgb, work_mask, work_depth = _to_resolution(rgb.astype(np.float32), mask, depth, settings.resolution)
    height, width = work_mask.shape[1:]
    windows, frames, padded_height, padded_width = _padded_size(pipelines, num_frames, height, width, settings)
    rgb_in = _pad(work_rgb, frames, padded_height, padded_width, "edge")
    mask_in = _pad(work_mask, frames, padded_height, padded_width, False)
    control = _pad(_depth_frames(work_depth), frames, padded_height, padded_width, "edge")
    generator = torch.Generator("cpu").manual_seed(settings.seed)
    # 3. Video pass: AnimateDiff + ControlNet depth, latent confinement, pixel composite by the mask.
    video, steps_run = _video_pass(pipelines, rgb_in, mask_in, control, prompt, negative_prompt, settings, generator)
    result = np.where(mask_in[..., None], video, rgb_in)
    # 4. Optional per-frame SD img2img + ControlNet pass on the composited frames.
    refine_steps_run = 0
    if settings.refine_pass:
        refined, refine_steps_run = _refine_pass(
            pipelines, result, mask_in, control, prompt, negative_prompt, settings, generator
        )
        result = np.where(mask_in[..., None], refined, rgb_in)
    # 5. Crop the padding, back to the render's size; outside the mask every pixel is the render's own value.
    generated = _resize_frames(result[:num_frames, :height, :width], mask.shape[1:])
    frames_out = np.where(mask[..., None], generated, rgb.astype(np.float32))
    info = {
        "steps_run": steps_run,
        "refine_steps_run": refine_steps_run,
        "windows": [list(window) for window in windows],
        "padded_shape": [frames, padded_height, padded_width],
        "resolution": [height, width],
        "seconds": time.perf_counter() - started,
    }
    return frames_out.astype(np.float32), info


def generate_text_only(
    pipelines: EffectPipelines,
    num_frames: int,
    height: int,
    width: int,
    prompt: str,
    negative_prompt: str,
    settings: DiffusionSettings,
) -> tuple[np.ndarray, dict]:
    """The ablation "VirSqueezer w/o Physics-guided Conditions" (paper sec. 4, Effect of Physics-guided Conditions).

    The same generator (motion UNet, VAE, text encoder, scheduler) as `generate_effect`, run as AnimateDiff
    text-to-video from pure noise with all `num_inference_steps`: it gets the prompt, negative prompt, frame count,
    frame size, seed, guidance scale and window/overlap, and nothing of the G-buffer: no render (no
    video-to-video start), no depth (no ControlNet), no mask (no confinement, no composite), so every pixel is
    generated. Long sequences use FreeNoise with its "shuffle_context" noise. Returns frames
    (frame, y, x, 3) float32 in [0, 1] and info {"steps_run", "windows", "padded_shape", "seconds"}.
    """
    # 1. Check the request.
    if num_frames < 1 or height < 1 or width < 1:
        raise ValueError(f"need num_frames, height, width >= 1, got {num_frames}, {height}, {width}")
    _check_settings(settings, pipelines, 1.0)
    started = time.perf_counter()
    # 2. Generate at the pipeline's resolution and the padded size, then crop and resize to the requested size.
    out_size = (height, width)
    height, width = _resolution_size(height, width, settings.resolution)
    windows, frames, padded_height, padded_width = _padded_size(pipelines, num_frames, height, width, settings)
    pipe = pipelines.text_to_video
    _use_windows(pipe, frames, settings)
    output = pipe(
        prompt=prompt,
        negative_prompt=negative_prompt,
        num_frames=frames,
        height=padded_height,
        width=padded_width,
        num_inference_steps=settings.num_inference_steps,
        guidance_scale=settings.guidance_scale,
        generator=torch.Generator("cpu").manual_seed(settings.seed),
        output_type="np",
        decode_chunk_size=VAE_CHUNK_FRAMES,
    )
    info = {
        "steps_run": len(pipe.scheduler.timesteps),
        "windows": [list(window) for window in windows],
        "padded_shape": [frames, padded_height, padded_width],
        "resolution": [height, width],
        "seconds": time.perf_counter() - started,
    }
    return _resize_frames(output.frames[0][:num_frames, :height, :width].astype(np.float32), out_size), info
