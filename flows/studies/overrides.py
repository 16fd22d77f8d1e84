"""The pipeline overrides a study passes to each of its runs: the user's own, in Hydra's syntax.

A study that runs the pipeline's steps (``flows.studies.ball``, ``flows.studies.fingers``) composes each run's
config from ``conf/evaluate.yaml`` with the run's overrides (object, mode, spacing) followed by the user's
command-line overrides of the pipeline's keys (``mpm.dx=0.008``, ``sampling.thin_wall_layers=3``,
``paths.artifacts=...``).  Hydra has already checked those keys against the study's config, whose pipeline
subtrees are the pipeline's own (conf/study/schema.py).
"""
from __future__ import annotations

from dataclasses import fields

from conf.schema import Config


def study_keys(schema: type) -> set[str]:
    """The study's own root keys: those of ``schema`` that the pipeline's :class:`conf.schema.Config` has not."""
    return {f.name for f in fields(schema)} - {f.name for f in fields(Config)}


def pipeline_overrides(schema: type) -> list[str]:
    """The running Hydra main's command-line overrides but the study's own keys (``schema``) and Hydra's, in the
    order given; none outside a Hydra main (a study's main called with a composed config)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return []
    own = study_keys(schema) | {"hydra"}
    out = []
    for override in HydraConfig.get().overrides.task:
        key = override.split("=", 1)[0].lstrip("+~")
        if key.split("@")[0].split(".")[0] not in own:
            out.append(override)
    return out
