"""What a run selects from its config: objects, variants, sampling seeds and effect backends.

Shared by :mod:`flows.preflight` (before anything heavy is imported) and :mod:`flows.pipeline`; imports neither
Prefect nor any step, so the checks that run before a flow stay fast.
"""
from __future__ import annotations

from typing import Any

from omegaconf import DictConfig


def _selected(single: Any, catalog: Any, names: Any, what: str) -> list[tuple[str, DictConfig]]:
    """``[(what, single)]`` when the user picked one (``object=NAME`` / ``variant=NAME``), else
    ``(f"{group}.{n}", catalog[n])`` for every name in ``names`` (``grid.objects`` / ``grid.variants``), each with
    the config key it is read from."""
    if single is not None:
        return [(what, single)]
    missing = [n for n in names if n not in catalog]
    if missing:
        raise SystemExit(f"grid.{what}s names unknown {what}s {missing}: known {sorted(catalog)}")
    group = "catalog" if what == "object" else "variants"
    return [(f"{group}.{n}", catalog[n]) for n in names]


def object_entries(cfg: DictConfig) -> list[tuple[str, DictConfig]]:
    """(config key, object) of every selected object: ``("object", cfg.object)`` for ``object=NAME``, otherwise
    ``("catalog.<name>", ...)`` for every name in ``grid.objects``; an unknown name stops the run (SystemExit)."""
    return _selected(cfg.object, cfg.catalog, cfg.grid.objects, "object")


def selected_objects(cfg: DictConfig) -> list[DictConfig]:
    """``object=NAME`` selects one object; otherwise every name in ``grid.objects`` from the catalog."""
    return [obj for _, obj in object_entries(cfg)]


def selected_variants(cfg: DictConfig) -> list[DictConfig]:
    """``variant=NAME`` selects one variant; otherwise every name in ``grid.variants`` from ``variants``."""
    return [v for _, v in _selected(cfg.variant, cfg.variants, cfg.grid.variants, "variant")]


def selected_seeds(cfg: DictConfig) -> list[int]:
    """``grid.seeds`` when given, else the one ``sampling.seed``."""
    return [int(s) for s in cfg.grid.seeds] if cfg.grid.seeds is not None else [int(cfg.sampling.seed)]


def selected_backends(cfg: DictConfig) -> list[str]:
    """``grid.backends`` when set, else the one ``generation.backend``."""
    return list(cfg.grid.backends) if cfg.grid.backends else [cfg.generation.backend]
