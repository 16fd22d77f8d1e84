"""Single-file checkpoints given as config fields (generation.<model>_single_file and _single_file_config): tiny
checkpoints written in the original layouts users hold (an LDM SD-1.5 ``.safetensors``, AnimateDiff's motion-module
layout, lllyasviel's ControlNet layout; tests/generation/single_file_export.py) load offline through diffusers' real
``from_single_file`` conversion with only a local config folder, every tensor equal to the components written."""
from __future__ import annotations

import shutil

import pytest
import torch

from conf.generation_schema import GenerationConfig, RefinementConfig, VideoMetricsConfig, validate_generation
from tasks.generation.components import DiffusionWeights, check_weights, diffusion_weights, load_components
from tests.generation.single_file_export import (
    save_ldm_stable_diffusion,
    save_original_controlnet,
    save_original_motion_module,
)
from tests.generation.tiny_diffusion import save_diffusers_folders, tiny_components


@pytest.fixture(scope="module")
def components():
    return tiny_components(seed=0)


def _single_files(components, root):
    """The three checkpoints as single files in root/, their configs (no weights) in root/configs/."""
    save_diffusers_folders(components, DiffusionWeights(folder=str(root / "configs")))
    for weights in (root / "configs").rglob("*.safetensors"):
        weights.unlink()  # the config folders hold configs and tokenizer files only
    save_ldm_stable_diffusion(components, root / "sd15-finetune.safetensors")
    save_original_motion_module(components, root / "mm_sd_v15_v2.safetensors")
    save_original_controlnet(components, root / "control_sd15_depth.safetensors")


def _generation(root, **changes) -> GenerationConfig:
    fields = dict(backend="diffusers", weights=str(root),
                  stable_diffusion_single_file="sd15-finetune.safetensors",
                  stable_diffusion_single_file_config="configs/stable-diffusion",
                  motion_adapter_single_file="mm_sd_v15_v2.safetensors",
                  motion_adapter_single_file_config="configs/motion-adapter",
                  controlnet_depth_single_file=str(root / "control_sd15_depth.safetensors"),  # absolute works too
                  controlnet_depth_single_file_config="configs/controlnet-depth")
    return GenerationConfig(**(fields | changes))


def test_single_file_checkpoints_from_the_config_load_every_tensor(tmp_path, components):
    _single_files(components, tmp_path)
    generation = _generation(tmp_path)
    validate_generation(generation, RefinementConfig(), VideoMetricsConfig())
    weights = diffusion_weights(vars(generation))
    assert weights.motion_adapter.single_file == "mm_sd_v15_v2.safetensors"
    assert check_weights(weights) == []
    loaded = load_components(weights, "cpu", torch.float32)
    for name in ("vae", "text_encoder", "unet", "motion_adapter", "controlnet"):
        original, restored = getattr(components, name).state_dict(), getattr(loaded, name).state_dict()
        assert original.keys() == restored.keys(), name
        assert all(torch.equal(original[k], restored[k]) for k in original), name
    assert loaded.tokenizer("a tomato").input_ids == components.tokenizer("a tomato").input_ids
    assert loaded.scheduler.config.timestep_spacing == "linspace"


def test_a_single_file_without_its_config_folder_is_refused_naming_the_key(tmp_path, components):
    generation = _generation(tmp_path, motion_adapter_single_file_config=None)
    with pytest.raises(ValueError, match="generation.motion_adapter_single_file_config is required"):
        validate_generation(generation, RefinementConfig(), VideoMetricsConfig())
    _single_files(components, tmp_path)
    shutil.rmtree(tmp_path / "configs" / "controlnet-depth")
    missing = check_weights(diffusion_weights(vars(_generation(tmp_path))))
    assert [(m.model, m.problem) for m in missing] == [("a depth ControlNet", "folder absent")]


def test_the_fields_are_in_the_composed_config(compose_cfg):
    cfg = compose_cfg("squeeze", ["generation=diffusers", "generation.weights=/models",
                                  "generation.stable_diffusion_single_file=x.safetensors",
                                  "generation.stable_diffusion_single_file_config=cfg"])
    weights = diffusion_weights(cfg.generation)
    assert weights.stable_diffusion.single_file == "x.safetensors" and weights.stable_diffusion.single_file_config \
        == "cfg" and weights.controlnet_depth.single_file is None
