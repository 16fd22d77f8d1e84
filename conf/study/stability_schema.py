"""Structured schema of ``python -m flows.studies.stability`` (the numerical stability suite,
:mod:`tasks.verification.stability`).

The suite reads the production config groups (``mpm``, ``sampling``, ``control``, ``signal``, ``simulation``,
``oracle`` and the object ``catalog``) from the same YAML files as the main flows, so every case runs with the
production settings; ``cases`` / ``quick`` select what runs.  A typo in an override is an error naming the key.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from conf.mpm_schema import MPMConfig
from conf.oracle_schema import OracleConfig
from conf.schema import (
    ControlConfig,
    ObjectConfig,
    PathsConfig,
    SamplingConfig,
    SignalConfig,
    SimulationConfig,
)


@dataclass
class StabilityConfig:
    """``cases``: case names or categories to run (empty = all; see ``tasks.verification.stability.default_cases``);
    ``quick``: only the quick subset of the selection (< 1 min on 2 cores); ``run_name``: report folder under
    ``<paths.reports>/stability/`` (default: a time stamp)."""

    cases: list[str] = field(default_factory=list)
    quick: bool = False
    run_name: str | None = None
    paths: PathsConfig = field(default_factory=PathsConfig)
    catalog: dict[str, ObjectConfig] = field(default_factory=dict)
    signal: SignalConfig = field(default_factory=SignalConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    mpm: MPMConfig = field(default_factory=MPMConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    oracle: OracleConfig = field(default_factory=OracleConfig)


def register_stability_config() -> None:
    """Register the schema with Hydra's ConfigStore as ``stability_schema``."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="stability_schema", node=StabilityConfig)


def validate_stability(cfg: Any) -> None:
    """The checks a pipeline run's simulation groups get (:func:`conf.schema.validate_simulation`), with every
    catalog object (a case may take its material from any): an unknown key (``+mpm.foo=1``) or a non-finite
    number (``mpm.dt=inf``) anywhere, or a value out of range, raises :class:`conf.schema.ConfigError` naming it."""
    from conf.schema import validate_simulation

    validate_simulation(cfg, [(f"catalog.{name}", obj) for name, obj in cfg.catalog.items()])
