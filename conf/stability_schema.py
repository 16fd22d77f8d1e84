"""Structured schema of ``python -m flows.stability`` (the numerical stability suite, :mod:`tasks.verification.stability`).

The suite reads the production config groups (``mpm``, ``sampling``, ``control``, ``signal``, ``simulation``,
``oracle`` and the object ``catalog``) from the same YAML files as the main flows, so every case runs with the
production settings; ``cases`` / ``quick`` select what runs.  A typo in an override is an error naming the key.
"""
from __future__ import annotations

from dataclasses import dataclass, field

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
