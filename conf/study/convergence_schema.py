"""Structured schema of the error-against-run-time sweep (``python -m flows.studies.convergence``,
conf/study/convergence.yaml).

The root is the pipeline's :class:`conf.schema.Config` plus a ``convergence`` section, so every pipeline key
keeps its type checks and a typo in a sweep key is an error naming it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from omegaconf import MISSING

from conf.schema import Config

REFINEMENT_PARAMETERS = ("dx", "dt", "none")
# errors of a setting against the reference (tasks/verification/convergence.py defines each)
ERROR_COLUMNS = ("position_error", "final_position_error", "reaction_force_error", "peak_strain_error")


@dataclass
class SettingConfig:
    """One point of the sweep: a name, the family it belongs to, and what it changes.

    preset: name of a ``conf/preset/<name>.yaml`` applied first (None: none).
    overrides: ``key=value`` strings applied on top of the base config (and the preset), e.g.
        ``sampling.particle_spacing=0.003`` or ``mpm.target_substeps_per_frame=200``.
    """

    name: str = MISSING
    family: str = MISSING
    overrides: list[str] = field(default_factory=list)
    preset: str | None = None


@dataclass
class ConvergenceConfig:
    """The sweep: settings, which one is the reference, and what each family refines.

    reference: name of the setting every error is measured against (the finest affordable one).
    families: family -> refinement parameter for the observed order: ``dx`` (grid spacing), ``dt`` (mean
        substep) or ``none`` (a modelling knob such as stiffness scaling: no order).
    pareto_error: the error column the Pareto front is taken on.
    """

    reference: str = "reference"
    settings: list[SettingConfig] = field(default_factory=list)
    families: dict[str, str] = field(default_factory=dict)
    pareto_error: str = "position_error"


@dataclass
class ConvergenceRoot(Config):
    convergence: ConvergenceConfig = field(default_factory=ConvergenceConfig)


def register_convergence_config() -> None:
    from hydra.core.config_store import ConfigStore

    from conf.schema import register_configs

    register_configs()
    ConfigStore.instance().store(name="convergence_schema", node=ConvergenceRoot)


def validate_convergence(cfg) -> None:
    """Range checks of the ``convergence`` section; raises ConfigError naming the key."""
    from conf.schema import ConfigError

    c = cfg.convergence
    names = [s.name for s in c.settings]
    if not names:
        raise ConfigError("convergence.settings is empty: list at least the reference and one other setting")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"convergence.settings names {dup} more than once")
    if c.reference not in names:
        raise ConfigError(f"convergence.reference {c.reference!r} is not a setting name: {names}")
    for fam, param in c.families.items():
        if param not in REFINEMENT_PARAMETERS:
            raise ConfigError(f"convergence.families.{fam} must be one of {list(REFINEMENT_PARAMETERS)}, got {param!r}")
    if c.pareto_error not in ERROR_COLUMNS:
        raise ConfigError(f"convergence.pareto_error must be one of {list(ERROR_COLUMNS)}, got {c.pareto_error!r}")
    if cfg.object is None:
        raise ConfigError("object is not set: object=NAME (e.g. object=rubber_ball)")
