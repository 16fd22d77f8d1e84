"""Where torch work runs: CUDA when present (``device: auto``), else the CPU with a fixed thread count.

On this project's 2-core machines several steps run at once (one per worker process); torch's default of one
thread per core then oversubscribes the cores and small elementwise ops become 5-10x slower and erratic
(generation-notes.md, "Threads").  Steps therefore call :func:`torch_device`, which sets torch's thread count
from ``VIRSQUEEZER_TORCH_THREADS`` (default 1).
"""
from __future__ import annotations

import os

import torch


def torch_device(setting: str = "auto") -> torch.device:
    """The torch device for ``setting`` (auto | cpu | cuda), after fixing the CPU thread count."""
    torch.set_num_threads(max(1, int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1"))))
    if setting == "cuda" or (setting == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise RuntimeError("render.device=cuda but no CUDA device is present: use device=auto or cpu")
        return torch.device("cuda")
    return torch.device("cpu")
