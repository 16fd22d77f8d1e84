"""Config access of the material oracle (paper sec. 3.2): the object's material overrides and the oracle
settings, read from dataclasses, DictConfigs or dicts and checked with one-line errors."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Optional

from tasks.physics.oracle.schema import MaterialOracleError

OVERRIDE_KEYS: tuple[str, ...] = (
    "model", "youngs_modulus", "poisson_ratio", "density", "yield_stress", "squeeze_threshold")
SHELL_OVERRIDE_KEYS: tuple[str, ...] = OVERRIDE_KEYS[:-1]


def config_field(obj: Any, key: str, default: Any = None) -> Any:
    """``obj[key]`` of a mapping or ``obj.key`` of a dataclass / DictConfig (``default`` when absent)."""
    if obj is None:
        return default
    if isinstance(obj, Mapping):
        return obj.get(key, default)
    return getattr(obj, key, default)


def read_overrides(overrides: Any, name: str) -> dict[str, Any]:
    """The non-None override values (dataclass, DictConfig, dict or None), type-checked."""
    if overrides is None:
        return {}
    if isinstance(overrides, Mapping):
        unknown = sorted(str(k) for k in overrides.keys() if k not in OVERRIDE_KEYS)
        if unknown:
            raise MaterialOracleError(
                f"object {name!r}: unknown material override(s) {', '.join(unknown)}: allowed keys are "
                f"{', '.join(OVERRIDE_KEYS)}")
    out: dict[str, Any] = {}
    for key in OVERRIDE_KEYS:
        value = config_field(overrides, key)
        if value is None:
            continue
        if key == "model":
            out[key] = str(value)
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise MaterialOracleError(f"object {name!r}: material.{key} {value!r} is not a number: give it in SI "
                                      "units (e.g. 1.0e6)")
        try:
            out[key] = float(value)
        except ValueError:
            raise MaterialOracleError(f"object {name!r}: material.{key} {value!r} is not a number: give it in SI "
                                      "units (e.g. 1.0e6)") from None
    return out


@dataclass(frozen=True)
class OracleSettings:
    """The oracle's settings (``OracleConfig``): backend, LLM endpoint and model, key variable, timeout (s), cache."""

    backend: str
    llm_url: Optional[str]
    llm_model: str
    api_key_env: str
    timeout_s: float
    cache_dir: Optional[str]


def read_settings(cfg: Any) -> OracleSettings:
    """:class:`OracleSettings` from an ``OracleConfig``-like object (``None`` = offline table), checked."""
    backend = str(config_field(cfg, "backend", "table"))
    if backend not in ("table", "llm"):
        raise MaterialOracleError(f"oracle.backend {backend!r} must be 'table' or 'llm'")
    timeout_s = config_field(cfg, "timeout_s", 20.0)
    try:
        timeout_s = float(timeout_s)
    except (TypeError, ValueError):
        raise MaterialOracleError(f"oracle.timeout_s {timeout_s!r} is not a number of seconds") from None
    if not (math.isfinite(timeout_s) and timeout_s > 0):
        raise MaterialOracleError(f"oracle.timeout_s {timeout_s:g} must be > 0 s")
    url = config_field(cfg, "llm_url")
    cache_dir = config_field(cfg, "cache_dir")
    return OracleSettings(backend=backend, llm_url=None if url is None else str(url),
                          llm_model=str(config_field(cfg, "llm_model", "gpt-5")),
                          api_key_env=str(config_field(cfg, "api_key_env", "VIRSQUEEZER_LLM_API_KEY")),
                          timeout_s=timeout_s, cache_dir=None if cache_dir is None else str(cache_dir))

