"""Particle sets shared by the MPM tests."""
from __future__ import annotations

import numpy as np


def lattice(lo, hi, h: float) -> np.ndarray:
    """Cell-centred particle lattice of spacing ~h (m) filling the box [lo, hi] (m): (N, 3)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    n = np.maximum(np.round((hi - lo) / h).astype(int), 1)
    axes = [lo[i] + (np.arange(n[i]) + 0.5) * (hi[i] - lo[i]) / n[i] for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
