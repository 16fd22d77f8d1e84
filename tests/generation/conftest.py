"""Fixtures of the generation tests."""
from __future__ import annotations

import os

import pytest
import torch

from tasks.generation.masked_diffusion import build_effect_pipelines
from tests.generation.tiny_diffusion import tiny_components


@pytest.fixture(scope="module")
def pipelines():
    """The effect pipelines (AnimateDiff video-to-video ControlNet, SD ControlNet img2img) on the tiny random
    components of seed 0, built once per test module, torch on VIRSQUEEZER_TORCH_THREADS threads (default 1)."""
    torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))
    return build_effect_pipelines(tiny_components(seed=0))
