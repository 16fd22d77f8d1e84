"""NumPy arrays handed to Warp CPU kernels: outputs land in the array itself, converted inputs stay alive."""
from __future__ import annotations

import gc

import numpy as np
import pytest
import warp as wp

from tasks.render.warp_numpy import numpy_view


@wp.kernel
def _twice(src: wp.array(dtype=wp.float64), dst: wp.array(dtype=wp.float32)):
    i = wp.tid()
    dst[i] = wp.float32(src[i] * wp.float64(2.0))


def test_a_kernel_writes_into_the_output_array_and_reads_a_converted_input_that_outlives_its_caller():
    wp.init()
    src = numpy_view(np.arange(6, dtype=np.int64)[::-1])  # reversed int64: converted to a C-contiguous float64 copy
    gc.collect()  # only the Warp array holds the copy now
    out = np.full(6, -1.0, np.float32)
    wp.launch(_twice, dim=6, inputs=[src, numpy_view(out, wp.float32, output=True)], device="cpu")
    assert out.tolist() == [10.0, 8.0, 6.0, 4.0, 2.0, 0.0]


@pytest.mark.parametrize("bad", [np.zeros(6, np.float64), np.zeros(12, np.float32)[::2]])
def test_an_output_that_would_need_a_copy_is_refused(bad):
    with pytest.raises(ValueError, match="kernel output must be a C-contiguous float32 array"):
        numpy_view(bad, wp.float32, output=True)
