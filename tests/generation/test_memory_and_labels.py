"""The diffusion backend's resolution, memory options and label, on the real pipeline objects with tiny components:
the conditions are resized to ``generation.resolution`` and the result back to the render exactly outside the mask;
VAE slicing / tiling, the attention processors and FreeNoise split inference are installed on the pipelines (and
split inference removed again for a short sequence) without changing the frames beyond float rounding; the label
says which passes ran."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from diffusers.models.attention_processor import AttnProcessor2_0, SlicedAttnProcessor

from tasks.generation.effect import diffusion_label
from tasks.generation.masked_diffusion import DiffusionSettings, generate_effect
from tasks.generation.memory_options import (
    MemoryOptions,
    apply_memory_options,
    choose_memory_options,
    uses_split_inference,
)
from tests.generation.tiny_diffusion import moving_disc_scene, tiny_components

SETTINGS = DiffusionSettings(num_inference_steps=2, strength=1.0, window=8, overlap=4, seed=0)
PROMPT = "juice bursting out"


def test_automatic_memory_options_by_device_and_explicit_values_win():
    assert choose_memory_options("cpu", 512) == MemoryOptions(vae_slicing=True, vae_tiling=False, attention="sdpa",
                                                              cpu_offload=False, split_inference=True)
    small = choose_memory_options("cuda", 768, gpu_memory_gb=8)
    assert small == MemoryOptions(vae_slicing=True, vae_tiling=True, attention="sliced", cpu_offload=True,
                                  split_inference=True)
    large = choose_memory_options("cuda", 512, gpu_memory_gb=80)
    assert not large.vae_tiling and not large.cpu_offload and large.attention == "sdpa"
    assert choose_memory_options("cpu", 512, vae_slicing=False, attention="sliced", split_inference=False) == \
        MemoryOptions(vae_slicing=False, attention="sliced", split_inference=False)
    with pytest.raises(ValueError, match="generation.cpu_offload=true needs a CUDA device"):
        choose_memory_options("cpu", 512, cpu_offload=True)
    with pytest.raises(ValueError, match="generation.attention"):
        choose_memory_options("cpu", 512, attention="flash")


def test_options_are_installed_on_the_real_pipelines_and_keep_the_frames(pipelines):
    rgb, mask, depth = moving_disc_scene(num_frames=12, size=32)  # 12 frames: two FreeNoise windows of 8
    plain, info = generate_effect(pipelines, rgb, mask, depth, PROMPT, "", SETTINGS)
    assert info["windows"] == [[0, 8], [4, 12]] and not uses_split_inference(pipelines.video.unet)
    options = MemoryOptions(vae_slicing=True, vae_tiling=True, attention="sliced", split_inference=True)
    apply_memory_options(pipelines, options, "cpu")
    try:
        vae = pipelines.video.vae
        assert vae.use_slicing and vae.use_tiling and pipelines.refine.vae is vae
        for model in (pipelines.refine.unet, pipelines.video.controlnet, vae):
            assert all(isinstance(p, SlicedAttnProcessor) for p in model.attn_processors.values())
        sliced, _ = generate_effect(pipelines, rgb, mask, depth, PROMPT, "",
                                    dataclasses.replace(SETTINGS, memory=options))
        # applied per call on the motion UNet, after FreeNoise rebuilt its motion blocks
        assert uses_split_inference(pipelines.video.unet)
        assert all(isinstance(p, SlicedAttnProcessor) for p in pipelines.video.unet.attn_processors.values())
        np.testing.assert_allclose(sliced, plain, atol=2e-5)  # same computation, other summation order
        # a one-window sequence: split inference removed again (diffusers cannot undo it itself)
        short = [a[:8] for a in (rgb, mask, depth)]
        generate_effect(pipelines, *short, PROMPT, "", dataclasses.replace(SETTINGS, memory=options))
        assert not uses_split_inference(pipelines.video.unet)
    finally:
        apply_memory_options(pipelines, MemoryOptions(attention="sdpa"), "cpu")
    assert not pipelines.video.vae.use_slicing
    assert all(isinstance(p, AttnProcessor2_0) for p in pipelines.video.controlnet.attn_processors.values())


def test_resolution_runs_the_pipeline_larger_and_composites_at_the_render_size(pipelines):
    rgb, mask, depth = moving_disc_scene(num_frames=4, size=32)
    frames, info = generate_effect(pipelines, rgb, mask, depth, PROMPT, "",
                                   dataclasses.replace(SETTINGS, resolution=48))
    assert info["resolution"] == [48, 48] and info["padded_shape"] == [4, 48, 48]
    assert frames.shape == rgb.shape and np.array_equal(frames[~mask], rgb[~mask])
    assert np.abs(frames[mask] - rgb[mask]).mean() > 0.05


def test_the_label_says_which_passes_ran(pipelines):
    rgb, mask, depth = moving_disc_scene(num_frames=4, size=32)
    _, off = generate_effect(pipelines, rgb, mask, depth, PROMPT, "", SETTINGS)
    _, on = generate_effect(pipelines, rgb, mask, depth, PROMPT, "",
                            dataclasses.replace(SETTINGS, refine_pass=True, refine_strength=0.5))
    assert off["refine_steps_run"] == 0 and on["refine_steps_run"] == 1
    assert diffusion_label("diffusers", {"views": [off, off]}) == \
        "diffusion (AnimateDiff + depth ControlNet, without img2img pass; 32 x 32 px)"
    assert diffusion_label("diffusers", {"views": [on]}) == \
        "diffusion (AnimateDiff + depth ControlNet + SD ControlNet img2img pass; 32 x 32 px)"
    assert diffusion_label("text_only", {"views": [dict(off, windows=[[0, 8], [4, 12]])]}) == \
        "text-only diffusion (AnimateDiff text-to-video, w/o physics-guided conditions; 32 x 32 px, FreeNoise over " \
        "2 windows)"


def test_the_configured_backend_runs_at_its_resolution_with_the_automatic_options(tmp_path):
    from dataclasses import asdict

    from conf.generation_schema import GenerationConfig
    from tasks.generation.components import DiffusionWeights
    from tasks.generation.effect import diffusion_effect
    from tests.generation.tiny_diffusion import save_diffusers_folders

    save_diffusers_folders(tiny_components(seed=0), DiffusionWeights(folder=str(tmp_path)))
    generation = vars(GenerationConfig(backend="diffusers", weights=str(tmp_path), steps=2, strength=1.0, window=8,
                                       overlap=4, resolution=48, device="cpu"))
    rgb, mask, depth = moving_disc_scene(num_frames=4, size=32)
    out, info = diffusion_effect(generation, rgb[None], mask[None], depth[None], PROMPT, "")
    assert out.shape == (1, 4, 32, 32, 3) and np.array_equal(out[0][~mask], rgb[~mask])
    assert info["memory"] == asdict(choose_memory_options("cpu", 48)) and info["views"][0]["resolution"] == [48, 48]
    assert diffusion_label("diffusers", info) == \
        "diffusion (AnimateDiff + depth ControlNet, without img2img pass; 48 x 48 px)"
