"""Checks of the config and of every input file, run before the flow starts (no Prefect server, no step).

A bad input stops the run with one line naming the input (its config key) and the fix, and no traceback:
:func:`preflight` raises ``SystemExit(line)``.  What is checked:

1. the config's ranges (:func:`conf.schema.validate`);
2. the SenseGlove recording (``signal=csv``): it exists, is at most ``MAX_RECORDING_BYTES``, and parses
   completely (columns, numbers, ranges, truncation), with the reader the step uses;
3. every selected object's geometry file (``kind: mesh`` or ``ply``): it exists and is a closed,
   self-intersection-free mesh or a 3DGS PLY in the Inria layout, with the loader the step uses;
4. the diffusion weights when a diffusion backend runs: every model present in ``generation.weights`` (a message
   naming each missing model, the folder expected and how to fetch it); their identity (configs + file digests)
   is recorded in ``generation.weights_digest``, which is part of the effect step's cache key.
"""
from __future__ import annotations

from typing import Any

from omegaconf import DictConfig

from conf.schema import ConfigError, validate
from tasks.control.gaussian_ply import GaussianPlyError
from tasks.control.object_model import ObjectModelError, check_geometry_file
from tasks.control.recording import SignalError, read_recording


def _objects(cfg: DictConfig) -> list[tuple[str, Any]]:
    if cfg.object is not None:
        return [("object", cfg.object)]
    return [(f"catalog.{name}", cfg.catalog[name]) for name in cfg.grid.objects if name in cfg.catalog]


def preflight(cfg: DictConfig) -> None:
    """Refuse a bad config or input file with one line (``SystemExit``) before anything heavy starts; record the
    diffusion weights' identity in the config."""
    # 1. config ranges
    try:
        validate(cfg)
    except ConfigError as exc:
        raise SystemExit(f"config error: {exc}") from None
    # 2. the recording, read exactly as the squeeze_signals step reads it
    if cfg.signal.source == "csv":
        try:
            read_recording(cfg.signal.path, frame_rate=cfg.control.smoothing.frame_rate)
        except SignalError as exc:
            raise SystemExit(f"input error: signal.path: {exc}") from None
    # 3. geometry files of the selected objects
    for key, obj in _objects(cfg):
        if obj.geometry.kind in ("mesh", "ply"):
            try:
                check_geometry_file(obj.geometry.kind, obj.geometry.path)
            except (ObjectModelError, GaussianPlyError) as exc:
                raise SystemExit(f"input error: {key}.geometry.path: {exc}") from None
    # 4. diffusion weights
    backends = list(cfg.grid.backends) if cfg.grid.backends else [cfg.generation.backend]
    if {"diffusers", "text_only"} & set(backends):
        from tasks.core.artifacts import digest_of
        from tasks.generation.components import (
            check_weights,
            diffusion_weights,
            missing_weights_message,
            weights_identity,
        )

        weights = diffusion_weights(cfg.generation)
        missing = check_weights(weights)
        if missing:
            raise SystemExit(f"input error: generation.weights: {missing_weights_message(missing)}")
        cfg.generation.weights_digest = digest_of(weights_identity(weights))
