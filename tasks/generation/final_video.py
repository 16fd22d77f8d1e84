"""The scene's final video (paper sec. 3.3): what a viewer of the squeeze sees and what Tables 1 and 3 score.

A scene whose effect stage generated frames (released material: the composite of eq. 6's mask over the render) shows
those; a scene without released material skips the effect stages, and its final video is the G-buffer's render.
Prefect-free, so the report reads it as the metric steps do.
"""
from __future__ import annotations

from typing import Any, Mapping, Optional

import numpy as np


def final_video(effect: Optional[Mapping[str, Any]], gbuffer: Mapping[str, Any]) -> np.ndarray:
    """(view, frame, y, x, 3) RGB in [0, 1]: ``effect["frames"]`` when the effect artifact has frames, else
    ``gbuffer["rgb"]`` (``effect`` may be None: not read or not made)."""
    return effect["frames"] if effect is not None and "frames" in effect else gbuffer["rgb"]
