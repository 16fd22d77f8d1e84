"""The documented range of every metric the evaluation writes (paper sec. 4: Table 1 and Table 3's video metrics,
Table 2's deformation metrics), and the check that a value written lies in it.

One table, :data:`METRIC_RANGES`, keyed by the metric's name in the artifacts' ``metrics`` attrs; each range is
the one its definition states (``DEFINITIONS`` of :mod:`tasks.evaluation.video_quality`,
:mod:`tasks.evaluation.paper_metrics` and :mod:`tasks.evaluation.deformation_metrics`, printed in the report;
``tests/evaluation/test_metric_ranges.py`` holds the table to every "in [a, b]" those texts state).  A value outside
its range cannot be a result: it is an error in our code, and :func:`check_metrics` raises
:class:`MetricRangeError` (one line naming the metric, the scene, the value and the range) before the artifact is
written, so it never reaches a table.  NaN is "not applicable" (the artifact gives the reason) and always passes;
an infinity passes only where the definition gives one (a PSNR of identical pixels, ``inf``).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

__all__ = ["METRIC_RANGES", "MetricRange", "MetricRangeError", "check_metrics"]

_INF = math.inf


@dataclass(frozen=True)
class MetricRange:
    """Closed range [lo, hi] of a metric (units as its definition); ``infinite``: the infinite bound(s) are values
    the metric can take (else an infinite bound means "unbounded", the value itself must be finite)."""

    lo: float
    hi: float
    infinite: bool = False

    def text(self) -> str:
        def bound(v: float) -> str:
            return "inf" if v == _INF else "-inf" if v == -_INF else f"{v:g}"

        left = "[" if self.lo > -_INF or self.infinite else "("
        right = "]" if self.hi < _INF or self.infinite else ")"
        return f"{left}{bound(self.lo)}, {bound(self.hi)}{right}"

    def holds(self, value: float) -> bool:
        """``value`` in the range (NaN always; a rounding slack of 1e-9 relative at finite bounds)."""
        if math.isnan(value):
            return True
        if math.isinf(value):
            return self.infinite and value in (self.lo, self.hi)
        slack = 1e-9 * max(1.0, abs(self.lo) if math.isfinite(self.lo) else 1.0, abs(self.hi) if math.isfinite(self.hi)
                           else 1.0)
        return self.lo - slack <= value <= self.hi + slack


_UNIT = MetricRange(0.0, 1.0)
_CORRELATION = MetricRange(-1.0, 1.0)
_NONNEGATIVE = MetricRange(0.0, _INF)
_REAL = MetricRange(-_INF, _INF)
_PSNR = MetricRange(0.0, _INF, infinite=True)  # 10 log10(1 / MSE) of values in [0, 1]: MSE <= 1; inf when equal

METRIC_RANGES: dict[str, MetricRange] = {
    # Table 1 / Table 3, weight-free (tasks.evaluation.video_quality.DEFINITIONS)
    "temporal_flicker": _UNIT,
    "motion_smoothness": _UNIT,
    "imaging_quality_brisque": _UNIT,
    "outside_mask_psnr_db": _PSNR,
    "outside_mask_ssim": _CORRELATION,  # SSIM of two signals lies in [-1, 1]
    "effect_placement_iou": _UNIT,
    "multiview_psnr_db": _PSNR,
    "multiview_psnr_db_initial": _PSNR,
    "multiview_psnr_gain_db": MetricRange(-_INF, _INF, infinite=True),  # a difference of two PSNRs
    "multiview_mae": _UNIT,
    "control_coupling_pearson": _CORRELATION,
    "control_coupling_spearman": _CORRELATION,
    "control_coupling_lag_frames": _NONNEGATIVE,
    # Table 1, the paper's own metrics (tasks.evaluation.paper_metrics.DEFINITIONS)
    "imaging_quality_musiq": _UNIT,
    "motion_smoothness_amt": _UNIT,
    "physical_commonsense": _UNIT,
    "physical_commonsense_rating": MetricRange(0.0, 5.0),  # ratings 1-5, 0 for an answer without one
    "physical_commonsense_videocon": _UNIT,
    # Table 2 and Supplementary Part 6 (tasks.evaluation.deformation_metrics.DEFINITIONS)
    "bdc_t": _UNIT,
    "bdc_s": _UNIT,
    "sdc": _UNIT,
    "miou": _UNIT,
    "ate": _NONNEGATIVE,
    "mte": _NONNEGATIVE,
    "tce": _NONNEGATIVE,
    "cosine_similarity": _CORRELATION,
    "max_volume_change": _NONNEGATIVE,
    "max_squeeze_strain": _REAL,
    "rebound_ratio": _NONNEGATIVE,  # 1 - m(T-1) / max m with m(T-1) <= max m
    "max_ke_ie_in_contact": _NONNEGATIVE,
    "quasi_static_warned": _UNIT,
    "threshold_time": _REAL,
    "peak_reaction_force": _NONNEGATIVE,
    "peak_applied_force": _NONNEGATIVE,
    "peak_feedback_force": _REAL,
    # per-frame series written beside the scores
    "bdc_s_iou": _UNIT,
    "miou_iou": _UNIT,
}


class MetricRangeError(RuntimeError):
    """A metric outside its documented range: an error in VirSqueezer's code, never a result."""


def check_metrics(values: Mapping[str, float | None | str | Iterable[float | None]], scene: str) -> None:
    """Raise :class:`MetricRangeError` for the first value of ``values`` (metric name -> a number, None = NaN, the
    JSON string ``"inf"``, or a sequence of them: per finger, per frame) outside its :data:`METRIC_RANGES` entry;
    ``scene`` names the object (and variant, backend) in the message.  A name without an entry is an error too (a
    metric added without its range)."""
    for name, value in values.items():
        if name not in METRIC_RANGES:
            raise MetricRangeError(f"bug in VirSqueezer: metric {name} of {scene} has no documented range in "
                                   f"tasks/evaluation/metric_ranges.py; add it there with its definition")
        rng = METRIC_RANGES[name]
        items = [value] if value is None or isinstance(value, (str, int, float)) else list(value)
        for i, v in enumerate(items):
            x = math.nan if v is None else float(v)
            if not rng.holds(x):
                at = f"[{i}]" if len(items) > 1 else ""
                raise MetricRangeError(f"bug in VirSqueezer: metric {name}{at} of {scene} is {x:g}, outside its "
                                       f"documented range {rng.text()}; this is an error in our code, not a result "
                                       f"(nothing was written): please report it with this line")
