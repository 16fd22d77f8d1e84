"""The diffusers backend of the effect generation (paper sec. 3.3) with tiny random components on CPU.

The real pipeline classes run end to end; random weights give no temporal coherence, so the tests pin what the
method guarantees regardless of weights: confinement (every pixel outside the mask equals the render), the depth
condition reaching the model, determinism, window bookkeeping, offline loading and the weights' identity.
"""

import dataclasses
import inspect
import os
from pathlib import Path

import huggingface_hub.constants
import numpy as np
import pytest
import torch
from diffusers.models.attention import FreeNoiseTransformerBlock

from tasks.generation.components import (
    DiffusionWeights,
    MissingWeightsError,
    ModelWeights,
    auto_device_dtype,
    check_weights,
    diffusion_weights,
    load_components,
    load_components_cached,
    missing_weights_message,
    weights_identity,
)
from tasks.generation.masked_diffusion import (
    DiffusionSettings,
    generate_effect,
    generate_text_only,
    temporal_windows,
)
from tasks.generation.prompts import NEGATIVE_PROMPT, effect_prompt
from tests.generation.tiny_diffusion import moving_disc_scene, save_diffusers_folders, tiny_components

SETTINGS = DiffusionSettings(num_inference_steps=4, strength=0.75, window=8, overlap=4, seed=0)
PROMPT = "a hand squeezing a ripe red tomato, pulp bursting out"


@pytest.fixture(scope="module")
def scene():
    return moving_disc_scene(num_frames=8, size=32)


@pytest.fixture(scope="module")
def effect(pipelines, scene):
    rgb, mask, depth = scene
    return generate_effect(pipelines, rgb, mask, depth, PROMPT, NEGATIVE_PROMPT, SETTINGS)


def _to_uint8(frames: np.ndarray) -> np.ndarray:
    return np.round(frames * 255).astype(np.uint8)


def test_video_pass_shape_and_every_pixel_outside_the_mask_is_the_render(scene, effect):
    rgb, mask, _ = scene
    frames, info = effect
    assert frames.shape == rgb.shape and frames.dtype == np.float32
    assert np.array_equal(frames[~mask], rgb[~mask])
    assert np.array_equal(_to_uint8(frames)[~mask], _to_uint8(rgb)[~mask])
    assert np.abs(frames[mask] - rgb[mask]).mean() > 0.05  # inside, the effect was generated
    assert 0 <= frames.min() and frames.max() <= 1
    assert info["steps_run"] == int(4 * 0.75) and info["windows"] == [[0, 8]] and info["refine_steps_run"] == 0


def test_refine_pass_changes_only_the_inside(pipelines, scene, effect):
    rgb, mask, depth = scene
    refined, info = generate_effect(
        pipelines, rgb, mask, depth, PROMPT, NEGATIVE_PROMPT, dataclasses.replace(SETTINGS, refine_pass=True)
    )
    assert info["refine_steps_run"] == int(4 * SETTINGS.refine_strength)  # one batch of 8 frames
    assert np.array_equal(refined[~mask], rgb[~mask])
    assert np.abs(refined[mask] - effect[0][mask]).mean() > 1e-3


def test_depth_condition_reaches_the_model_inside_the_mask(pipelines, scene, effect):
    rgb, mask, depth = scene
    shallower, _ = generate_effect(pipelines, rgb, mask, depth * 0.5, PROMPT, NEGATIVE_PROMPT, SETTINGS)
    assert np.abs(shallower[mask] - effect[0][mask]).mean() > 1e-3
    assert np.array_equal(shallower[~mask], effect[0][~mask])


def test_same_seed_same_frames_other_seed_other_frames(pipelines, scene, effect):
    rgb, mask, depth = scene
    again, _ = generate_effect(pipelines, rgb, mask, depth, PROMPT, NEGATIVE_PROMPT, SETTINGS)
    other, _ = generate_effect(
        pipelines, rgb, mask, depth, PROMPT, NEGATIVE_PROMPT, dataclasses.replace(SETTINGS, seed=1)
    )
    assert np.array_equal(again, effect[0])
    assert np.abs(other[mask] - effect[0][mask]).mean() > 0.01


def test_text_only_ablation_gets_no_gbuffer_and_is_deterministic(pipelines):
    parameters = set(inspect.signature(generate_text_only).parameters)
    assert parameters == {"pipelines", "num_frames", "height", "width", "prompt", "negative_prompt", "settings"}
    assert "controlnet" not in pipelines.text_to_video.components
    frames, info = generate_text_only(pipelines, 6, 30, 28, PROMPT, NEGATIVE_PROMPT, SETTINGS)
    again, _ = generate_text_only(pipelines, 6, 30, 28, PROMPT, NEGATIVE_PROMPT, SETTINGS)
    assert frames.shape == (6, 30, 28, 3) and frames.dtype == np.float32
    assert info["steps_run"] == 4 and info["padded_shape"] == [6, 32, 32]
    assert np.array_equal(frames, again)


def test_windowed_long_sequence_has_its_length_and_no_seam(pipelines):
    """Criterion: with d_t = mean |frame_t - frame_{t-1}| over all pixels and channels, the largest d_t across a
    window boundary (t = a window's first frame, or the frame after a window's last) is not larger than the
    largest d_t inside windows. Random weights give no temporal coherence, so this pins the bookkeeping
    (order, padding, crop), not the smoothness a trained motion module adds."""
    rgb, mask, depth = moving_disc_scene(num_frames=20, size=32)
    frames, info = generate_effect(pipelines, rgb, mask, depth, PROMPT, NEGATIVE_PROMPT, SETTINGS)
    assert frames.shape == rgb.shape and np.array_equal(frames[~mask], rgb[~mask])
    assert info["windows"] == [[0, 8], [4, 12], [8, 16], [12, 20]]
    change = np.abs(np.diff(frames, axis=0)).mean(axis=(1, 2, 3))  # change[t - 1] = d_t
    boundaries = {start for start, _ in info["windows"][1:]} | {end for _, end in info["windows"][:-1]}
    across = [change[t - 1] for t in sorted(boundaries)]
    within = [change[t - 1] for t in range(1, 20) if t not in boundaries]
    assert max(across) <= max(within)


def test_sequence_not_tiling_the_windows_is_padded_and_cropped(pipelines):
    rgb, mask, depth = moving_disc_scene(num_frames=10, size=32)
    frames, info = generate_effect(pipelines, rgb, mask, depth, PROMPT, NEGATIVE_PROMPT, SETTINGS)
    assert frames.shape == rgb.shape and info["padded_shape"] == [12, 32, 32]
    assert info["windows"] == [[0, 8], [4, 12]]
    assert np.array_equal(frames[~mask], rgb[~mask])


def test_frame_size_not_a_multiple_of_8_is_padded_and_cropped(pipelines):
    rgb, mask, depth = moving_disc_scene(num_frames=4, size=32)
    rgb, mask, depth = rgb[:, :30, :26], mask[:, :30, :26], depth[:, :30, :26]
    frames, info = generate_effect(pipelines, rgb, mask, depth, PROMPT, NEGATIVE_PROMPT, SETTINGS)
    assert frames.shape == (4, 30, 26, 3) and info["padded_shape"] == [4, 32, 32]
    assert np.array_equal(frames[~mask], rgb[~mask])


def test_temporal_windows_tile_the_padded_sequence():
    for window, overlap in [(8, 4), (16, 4), (16, 0), (16, 15), (32, 8)]:
        for num_frames in range(1, 100):
            windows = temporal_windows(num_frames, window, overlap)
            assert windows[0][0] == 0 and windows[-1][1] >= num_frames
            if num_frames <= window:
                assert windows == [(0, num_frames)]
                continue
            assert all(end - start == window for start, end in windows)
            assert all(b[0] - a[0] == window - overlap for a, b in zip(windows, windows[1:]))
            assert windows[-1][1] - num_frames < window - overlap  # fewer padded frames than one stride
    assert temporal_windows(90, 16, 4) == [(start, start + 16) for start in range(0, 85, 12)]


def test_diffusers_freenoise_misweights_an_incomplete_last_window():
    """Why sequences are padded to whole windows: in diffusers 0.42.1 the frames covered only by an incomplete
    last window come out of a pyramid-weighted FreeNoise block different from that window's own output; when the
    windows tile the sequence they match. If this starts failing, diffusers fixed it and the padding can go."""
    torch.manual_seed(0)
    block = FreeNoiseTransformerBlock(
        dim=8, num_attention_heads=2, attention_head_dim=4, double_self_attention=True,
        context_length=8, context_stride=4, weighting_scheme="pyramid",
    ).eval()
    hidden = torch.randn(3, 24, 8)
    with torch.no_grad():
        incomplete = block(hidden[:, :22])[:, 20:] - block(hidden[:, 14:22])[:, 6:]
        tiled = block(hidden)[:, 20:] - block(hidden[:, 16:24])[:, 4:]
    assert incomplete.abs().max() > 0.1
    assert tiled.abs().max() < 1e-5


@pytest.mark.parametrize(
    ("change", "names"),
    [
        ({"mask": lambda m: m.astype(np.float32)}, "mask"),
        ({"rgb": lambda r: r * 2}, "rgb"),
        ({"depth": lambda d: d[:, :-1]}, "depth"),
        ({"settings": lambda s: dataclasses.replace(s, window=40)}, "window"),
        ({"settings": lambda s: dataclasses.replace(s, overlap=8)}, "overlap"),
        ({"settings": lambda s: dataclasses.replace(s, num_inference_steps=1, strength=0.5)}, "strength"),
    ],
)
def test_bad_inputs_raise_a_value_error_naming_them(pipelines, scene, change, names):
    arguments = dict(zip(("rgb", "mask", "depth"), scene)) | {"settings": SETTINGS}
    for key, alter in change.items():
        arguments[key] = alter(arguments[key])
    with pytest.raises(ValueError, match=names):
        generate_effect(pipelines, prompt=PROMPT, negative_prompt="", **arguments)


def test_empty_weights_folder_names_all_three_models_and_where_they_go(tmp_path):
    weights = DiffusionWeights(folder=str(tmp_path))
    missing = check_weights(weights)
    assert [model.repo for model in missing] == [
        "stable-diffusion-v1-5/stable-diffusion-v1-5",
        "guoyww/animatediff-motion-adapter-v1-5-2",
        "lllyasviel/control_v11f1p_sd15_depth",
    ]
    message = missing_weights_message(missing)
    for name, subfolder in [
        ("an SD-1.5 base", "stable-diffusion"),
        ("an AnimateDiff motion adapter", "motion-adapter"),
        ("a depth ControlNet", "controlnet-depth"),
    ]:
        assert name in message and f"--local-dir {tmp_path / subfolder}" in message
    assert message.count("hf download ") == 3 and "huggingface-cli" not in message
    with pytest.raises(MissingWeightsError, match="stable-diffusion-v1-5"):
        load_components(weights)


def test_incomplete_folder_and_single_file_without_config_are_named(tmp_path):
    weights = DiffusionWeights(folder=str(tmp_path))
    save_diffusers_folders(tiny_components(seed=0), weights)
    (tmp_path / "stable-diffusion" / "unet" / "diffusion_pytorch_model.safetensors").unlink()
    (tmp_path / "depth.safetensors").write_bytes(b"\0")
    weights = dataclasses.replace(weights, controlnet_depth=ModelWeights("controlnet-depth", "depth.safetensors"))
    missing = check_weights(weights)
    assert [(model.model, model.expected) for model in missing] == [
        ("an SD-1.5 base", tmp_path / "stable-diffusion"),
        ("a depth ControlNet", tmp_path / "depth.safetensors"),
    ]
    assert "unet/" in missing[0].problem and "single_file_config" in missing[1].problem


def test_diffusers_folders_round_trip_offline_and_identity_tracks_weight_files(tmp_path):
    components = tiny_components(seed=0)
    weights = DiffusionWeights(folder=str(tmp_path))
    save_diffusers_folders(components, weights)
    assert check_weights(weights) == []
    loaded = load_components(weights, "cpu", torch.float32)
    assert huggingface_hub.constants.is_offline_mode() and os.environ["HF_HUB_OFFLINE"] == "1"
    for name in ("vae", "text_encoder", "unet", "motion_adapter", "controlnet"):
        original, restored = getattr(components, name).state_dict(), getattr(loaded, name).state_dict()
        assert original.keys() == restored.keys()
        assert all(torch.equal(original[key], restored[key]) for key in original), name
    assert loaded.tokenizer(PROMPT).input_ids == components.tokenizer(PROMPT).input_ids
    assert loaded.scheduler.config.timestep_spacing == "linspace" and loaded.scheduler.config.steps_offset == 1

    assert load_components_cached(weights) is load_components_cached(weights)
    identity = weights_identity(weights)
    assert identity == weights_identity(weights)
    assert set(identity["stable_diffusion"]["sha256"]) >= {
        "unet/diffusion_pytorch_model.safetensors",
        "vae/diffusion_pytorch_model.safetensors",
        "text_encoder/model.safetensors",
        "tokenizer/tokenizer.json",
    }
    assert identity["controlnet_depth"]["configs"]["config.json"]["conditioning_embedding_out_channels"] == [8, 8]
    with torch.no_grad():
        components.controlnet.controlnet_mid_block.weight.mul_(2)
    components.controlnet.save_pretrained(Path(weights.folder) / "controlnet-depth")
    changed = weights_identity(weights)
    assert changed["controlnet_depth"]["sha256"] != identity["controlnet_depth"]["sha256"]
    assert changed["stable_diffusion"] == identity["stable_diffusion"]


def test_weights_and_device_from_config():
    weights = diffusion_weights(
        {"weights": "/models", "stable_diffusion": "sd15", "controlnet_depth_single_file": "depth.safetensors"}
    )
    assert weights == DiffusionWeights(
        "/models",
        ModelWeights("sd15"),
        ModelWeights("motion-adapter"),
        ModelWeights("controlnet-depth", "depth.safetensors"),
    )
    with pytest.raises(ValueError, match="generation.weights"):
        diffusion_weights({"weights": None})
    expected = ("cuda", torch.float16) if torch.cuda.is_available() else ("cpu", torch.float32)
    device, dtype = auto_device_dtype()
    assert (device.type, dtype) == expected
    assert auto_device_dtype(True, "cpu", "bfloat16") == (torch.device("cpu"), torch.bfloat16)
    with pytest.raises(ValueError, match="dtype"):
        auto_device_dtype(False, "auto", "float8")


def test_effect_prompt_names_object_and_effect():
    tomato = effect_prompt(
        "Tomato", "A ripe red tomato with a thin 1 mm waxy skin around soft, juicy pulp", "pulp", "liquid"
    )
    assert tomato.prompt == (
        "a hand squeezing a ripe red tomato, pulp bursting and spraying out of the tomato, splashing droplets, "
        "photorealistic, high detail"
    )
    assert tomato.negative_prompt == NEGATIVE_PROMPT
    plush = effect_prompt("Plush teddy bear", "", "stuffing", "stuffing")
    assert plush.prompt.startswith("a hand squeezing a plush teddy bear, fluffy stuffing spilling out of the torn")
    assert effect_prompt("Can", "", "cola", "liquid", prompt_override="x", negative_override="y") == (
        type(tomato)("x", "y")
    )
    with pytest.raises(ValueError, match="effect"):
        effect_prompt("Can", "", "cola", "smoke")
