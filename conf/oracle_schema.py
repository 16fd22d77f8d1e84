"""Structured (dataclass) schema of the material oracle's config (``material.oracle`` group).

The material oracle turns an object's free-text description into physical properties for the MPM
simulation (paper sec. 3.2, "Squeezing-Driven Deformation"; the paper uses GPT-5).  Two backends exist:

* ``table`` (default, offline): a curated table of real material properties with their sources
  (:mod:`tasks.physics.material_oracle`); no network.
* ``llm``: any OpenAI-compatible chat-completions endpoint at ``llm_url`` (``POST {llm_url}/chat/completions``).
  The API key is read at call time from the environment variable named by ``api_key_env`` - it is never part
  of the config, of results, of cache files or of error messages.  Answers are cached on disk as JSON under
  ``cache_dir`` (``None``: no cache).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

ORACLE_BACKENDS: tuple[str, ...] = ("table", "llm")


@dataclass
class OracleConfig:
    """How the material oracle answers (see module docstring)."""

    backend: str = "table"  # table | llm
    llm_url: Optional[str] = None  # base URL of an OpenAI-compatible API, e.g. http://127.0.0.1:8000/v1
    llm_model: str = "gpt-5"  # model name sent to the endpoint (the paper uses GPT-5)
    api_key_env: str = "VIRSQUEEZER_LLM_API_KEY"  # name of the environment variable holding the API key
    timeout_s: float = 20.0  # s, total time allowed for one LLM request
    cache_dir: Optional[str] = None  # directory of cached LLM answers (JSON); None: no cache
