"""Known rotations for tests that check objectivity or recover a rigid motion."""
from __future__ import annotations

import numpy as np


def rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues' formula: the proper rotation (3, 3) by ``angle`` (rad) about ``axis`` (any length)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
