"""Structured schema of the render and effect knob study (``python -m flows.studies.render_convergence``,
conf/study/render_convergence.yaml): the pipeline's :class:`conf.schema.Config` plus a ``render_study`` section.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from conf.schema import Config


@dataclass
class RenderStudyConfig:
    """The render and effect knob study (tasks/verification/render_convergence.py): the settings swept per knob;
    each knob's reference is its finest setting (the largest resolution, the smallest stride, the most iterations),
    the other knobs stay at the base config's values.

    resolutions: render.width = render.height, px.  frame_strides: render.frame_stride.  refinement_iterations:
    refinement.iterations (eq. 7).
    """

    resolutions: list[int] = field(default_factory=lambda: [96, 128, 192, 256, 384])
    frame_strides: list[int] = field(default_factory=lambda: [1, 2, 3, 4, 6])
    refinement_iterations: list[int] = field(default_factory=lambda: [0, 15, 30, 60, 120, 240])


@dataclass
class RenderStudyRoot(Config):
    render_study: RenderStudyConfig = field(default_factory=RenderStudyConfig)


def register_render_study_config() -> None:
    from hydra.core.config_store import ConfigStore

    from conf.schema import register_configs

    register_configs()
    ConfigStore.instance().store(name="render_study_schema", node=RenderStudyRoot)


def validate_render_study(cfg) -> None:
    """Range checks of ``render_study``; raises ConfigError naming the key."""
    from conf.schema import ConfigError

    r = cfg.render_study
    for key, values, low in (("resolutions", r.resolutions, 16), ("frame_strides", r.frame_strides, 1),
                             ("refinement_iterations", r.refinement_iterations, 0)):
        if len(values) < 2 or min(values) < low or len(set(values)) != len(values):
            raise ConfigError(f"render_study.{key} must list at least two distinct values >= {low}, got "
                              f"{list(values)}")
    if cfg.object is None:
        raise ConfigError("object is not set: object=NAME (e.g. object=tomato, an object that releases material)")
