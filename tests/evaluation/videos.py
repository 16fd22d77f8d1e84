"""Synthetic videos shared by the evaluation tests."""
from __future__ import annotations

import numpy as np


def noise_video(frames: int, h: int, w: int, seed: int = 0) -> np.ndarray:
    """Uniform uint8 noise, (frames, h, w, 3): a video with no content, for shape and loader checks."""
    return np.random.default_rng(seed).integers(0, 256, (frames, h, w, 3), dtype=np.uint8)
