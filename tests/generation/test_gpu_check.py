"""``python -m flows.gpu_check``: on this CPU-only machine it skips cleanly without CUDA, and its CPU self-check runs
every part (renderer, MPM, diffusion pipeline, MUSIQ, AMT-S, VideoPhy-2) through the same code, each part's result
non-trivial and reproduced within its tolerance (exactly, CPU against CPU)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from flows.gpu_check import _BUILDERS, PARTS, cuda_missing, run_checks


def test_every_part_runs_on_the_cpu_and_reproduces_its_result():
    torch.set_num_threads(1)
    checks = run_checks("cpu")
    assert [c.part for c in checks] == list(PARTS)
    assert all(c.ok and c.difference == 0.0 and c.seconds > 0 for c in checks)
    assert "max |cpu - cpu| = 0.00e+00" in checks[0].line("cpu")


@pytest.mark.parametrize("part", PARTS)
def test_each_part_computes_something(part):
    torch.set_num_threads(1)
    run, _, _ = _BUILDERS[part]("cpu")
    out = np.asarray(run("cpu"), float)
    assert np.isfinite(out).all() and out.std() > 1e-3


def test_unknown_part_is_named():
    with pytest.raises(ValueError, match="unknown \\['shader'\\]"):
        run_checks("cpu", ["shader"])


@pytest.mark.skipif(cuda_missing() is None, reason="CUDA present: the skip path is not taken")
def test_without_cuda_the_check_skips_cleanly():
    done = subprocess.run([sys.executable, "-m", "flows.gpu_check", "parts=[musiq]"], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0 and "gpu_check skipped:" in done.stdout and "device=cpu" in done.stdout
