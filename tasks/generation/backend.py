"""From the ``generation`` config to the diffusion components: where the weights are, on which device and in which
precision, and one loaded set per process (the builder itself is :mod:`tasks.generation.components`)."""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from tasks.generation.components import (
    DiffusionComponents,
    DiffusionWeights,
    ModelWeights,
    auto_device_dtype,
    load_components,
)

_LOADED: dict[tuple[str, str, str], DiffusionComponents] = {}
DTYPES = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}


def diffusion_weights(generation: Mapping[str, Any]) -> DiffusionWeights:
    """The local weights named by ``generation.weights`` and its three subfolder names."""
    return DiffusionWeights(folder=str(generation["weights"]),
                            stable_diffusion=ModelWeights(generation["stable_diffusion"]),
                            motion_adapter=ModelWeights(generation["motion_adapter"]),
                            controlnet_depth=ModelWeights(generation["controlnet_depth"]))


def device_and_dtype(generation: Mapping[str, Any]) -> tuple[torch.device, torch.dtype]:
    """``generation.device`` / ``dtype``; ``auto`` = CUDA in float16 when present, else CPU in float32."""
    device, dtype = auto_device_dtype(prefer_bfloat16=generation["dtype"] == "bfloat16")
    if generation["device"] != "auto":
        device = torch.device(generation["device"])
    if generation["dtype"] != "auto":
        dtype = DTYPES[generation["dtype"]]
    return device, dtype


def components_for(generation: Mapping[str, Any]) -> DiffusionComponents:
    """The components of ``generation``, loaded once per process (the weights take seconds to minutes to load)."""
    weights = diffusion_weights(generation)
    device, dtype = device_and_dtype(generation)
    key = (repr(weights), str(device), str(dtype))
    if key not in _LOADED:
        _LOADED[key] = load_components(weights, device, dtype)
    return _LOADED[key]
