"""Structured schemas of the ``metrics`` config group (the deformation metrics, :mod:`tasks.evaluation.deformation_metrics`)
and of the ``paper_metrics`` group (the paper's video metrics that need downloaded weights).

The paper (sec. "Evaluation for Squeezing Controlled Deformation", Table 2) names BDC-T, BDC-S, SDC and mIoU
but does not define them; the definitions used here are in ``tasks.evaluation.deformation_metrics.DEFINITIONS``.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any, Optional


@dataclass
class MetricsConfig:
    """Settings of the deformation metrics.

    region_fraction: mIoU threshold as a fraction of the frame's peak prescribed displacement: a point belongs
        to the prescribed (observed) deformed region of frame t when its prescribed (observed non-rigid)
        displacement is at least ``region_fraction * max_i |prescribed_i|`` (1, in (0, 1)).
    ate_with_scale: the ATE alignment of the reconstructed onto the sensed trajectory also fits a scale
        (similarity instead of rigid Umeyama fit).
    min_motion: frame-to-frame increments (m) of the sensed or reconstructed trajectory shorter than this are
        not used by the cosine similarity (their direction is noise); >= 0.
    """

    region_fraction: float = 0.1
    ate_with_scale: bool = False
    min_motion: float = 1e-5


def validate_metrics(cfg: Any = None) -> MetricsConfig:
    """Check ``cfg`` (None, a MetricsConfig, a mapping or an OmegaConf node) and return it as a MetricsConfig.

    Raises ValueError naming the key (``metrics.<key>: ...``) for unknown keys and out-of-range values.
    """
    if cfg is None:
        return MetricsConfig()
    known = [f.name for f in fields(MetricsConfig)]
    if isinstance(cfg, MetricsConfig):
        data = {k: getattr(cfg, k) for k in known}
    elif isinstance(cfg, Mapping):  # plain dicts and OmegaConf DictConfig
        data = {k: cfg[k] for k in cfg}
    else:
        raise TypeError(f"metrics: expected a mapping or MetricsConfig, got {type(cfg).__name__}")
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"metrics: unknown keys {unknown}; known keys are {known}")
    c = MetricsConfig(**data)
    if not (isinstance(c.region_fraction, (int, float)) and 0.0 < c.region_fraction < 1.0):
        raise ValueError(f"metrics.region_fraction: must be in (0, 1) (fraction of the peak displacement), "
                         f"got {c.region_fraction}")
    if c.ate_with_scale not in (True, False):
        raise ValueError(f"metrics.ate_with_scale: must be true or false, got {c.ate_with_scale!r}")
    if not (isinstance(c.min_motion, (int, float)) and math.isfinite(c.min_motion) and c.min_motion >= 0.0):
        raise ValueError(f"metrics.min_motion: must be a finite length >= 0 m, got {c.min_motion}")
    return MetricsConfig(region_fraction=float(c.region_fraction), ate_with_scale=bool(c.ate_with_scale),
                         min_motion=float(c.min_motion))


PAPER_METRIC_VIEWS = ("all", "view0")


@dataclass
class PaperMetricsConfig:
    """The paper's own video metrics (sec. 4.1, Table 1), computed only where their weights are present; nothing is
    downloaded (:mod:`tasks.evaluation.paper_metrics`).

    musiq_weights: path of MUSIQ's SPAQ checkpoint ``musiq_spaq_ckpt-358bb6af.pth`` (VBench imaging quality);
    amt_weights: path of AMT-S's checkpoint ``amt-s.pth`` (VBench motion smoothness);
    videophy_weights: folder of VideoPhy-2's rater ``videophy_2_auto`` (config.json, weights, tokenizer files;
    physical commonsense as the share of videos rated >= 4, and the mean 1-5 rating); videocon_weights: folder of
    VideoCon-Physics ``videocon_physics`` (the same architecture; physical commonsense as P(Yes) / (P(Yes) +
    P(No))); unset (the default) = not computed, at no cost.  views: the views scored, ``all`` (their mean) or ``view0``.
    device: where the metric networks run, ``auto`` (CUDA when present, as the renderer) | ``cpu`` | ``cuda``.
    weights_digest: set by the pre-flight check: content digest of the present weight files (cache key).
    """

    musiq_weights: Optional[str] = None
    amt_weights: Optional[str] = None
    videophy_weights: Optional[str] = None
    videocon_weights: Optional[str] = None
    views: str = "all"
    device: str = "auto"
    weights_digest: Optional[str] = None


def validate_paper_metrics(cfg: Any) -> None:
    """Range checks of the ``paper_metrics`` group; raises ValueError naming the key."""
    if cfg.device not in ("auto", "cpu", "cuda"):
        raise ValueError(f"paper_metrics.device: must be auto, cpu or cuda, got {cfg.device!r}")
    if cfg.views not in PAPER_METRIC_VIEWS:
        raise ValueError(f"paper_metrics.views: must be all or view0, got {cfg.views!r}")
