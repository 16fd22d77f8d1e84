"""Structured schema of the ``llm_judge`` config group: the vision-LLM evaluation of paper sec. 4.1.4 (Table 1's
LLM columns).  Without ``url`` nothing is asked and the report says "not computed: no endpoint configured"."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass
class LLMJudgeConfig:
    """url: base URL of an OpenAI-compatible API with a vision model (``/chat/completions`` is appended), None =
    off.  model: the model's name.  api_key_env: environment variable holding the key (read from the environment
    only, never logged or written).  timeout_s: seconds per request.  frames: video frames sent, evenly in time.
    max_image_px: longest side of every image sent.  cache_dir: answer cache (JSON; None: ask every time)."""

    url: Optional[str] = None
    model: str = "gpt-5"
    api_key_env: str = "VIRSQUEEZER_LLM_API_KEY"
    timeout_s: float = 120.0
    frames: int = 8
    max_image_px: int = 512
    cache_dir: Optional[str] = None
