"""NumPy arrays handed to NVIDIA Warp CPU kernels without a copy (the display step's per-pixel kernels)."""
from __future__ import annotations

import numpy as np
import warp as wp

_NUMPY = {wp.float64: np.float64, wp.float32: np.float32, wp.int32: np.int32, wp.uint8: np.uint8}


def numpy_view(a: np.ndarray, dtype: type = wp.float64, output: bool = False) -> wp.array:
    """A Warp CPU array of ``dtype`` (float64, float32, int32 or uint8) over the memory of ``a``; the Warp array
    keeps that memory alive until it is gone.  An input that is not C-contiguous or not of ``dtype``'s NumPy type
    is converted first; an ``output`` never is (a kernel's writes must land in ``a`` itself, not in a copy)."""
    data = np.ascontiguousarray(a, _NUMPY[dtype])
    if output and data is not a:
        raise ValueError(f"a kernel output must be a C-contiguous {_NUMPY[dtype].__name__} array, got "
                         f"{a.dtype} with strides {a.strides}")
    return wp.array(data, dtype=dtype, device="cpu", copy=False)
