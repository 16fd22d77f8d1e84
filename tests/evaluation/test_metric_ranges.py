"""The table of documented metric ranges (tasks/evaluation/metric_ranges.py): it agrees with every range the
metrics' definitions state, it covers every metric the evaluation writes, and a value outside is a one-line bug
report, never a result."""
from __future__ import annotations

import math
import re

import pytest

from tasks.evaluation import deformation_metrics, paper_metrics, video_quality
from tasks.evaluation.metric_ranges import METRIC_RANGES, MetricRange, MetricRangeError, check_metrics
from tasks.evaluation.video_metrics import VIDEO_METRICS


def _stated(text: str) -> tuple[float, float] | None:
    """The range a definition states for its metric ("(1, in [a, b]", unit 1 then the range), or None."""
    m = re.search(r"\b1, in \[(-?\d+(?:\.\d+)?), (-?\d+(?:\.\d+)?)\]", text)
    return (float(m[1]), float(m[2])) if m else None


def test_the_table_agrees_with_every_range_the_definitions_state():
    checked = 0
    for definitions in (video_quality.DEFINITIONS, paper_metrics.DEFINITIONS, deformation_metrics.DEFINITIONS):
        for key, text in definitions.items():
            stated = _stated(text)
            name = key if key in METRIC_RANGES else key.rsplit("_", 1)[0]  # motion_smoothness_dis -> _smoothness
            if stated is None or name not in METRIC_RANGES:
                continue
            assert (METRIC_RANGES[name].lo, METRIC_RANGES[name].hi) == stated, key
            checked += 1
    assert checked == 16  # every "(1, in [a, b]" of the three definition tables has its entry


def test_every_metric_the_evaluation_writes_has_a_range():
    written = set(VIDEO_METRICS) | set(paper_metrics.DEFINITIONS) | {
        k for k in deformation_metrics.DEFINITIONS if k not in ("nonrigid_displacement", "volume_ratio")}
    assert written - set(METRIC_RANGES) == set()


def test_a_value_outside_its_range_is_a_bug_named_in_one_line():
    with pytest.raises(MetricRangeError) as exc:
        check_metrics({"temporal_flicker": 1.0, "imaging_quality_brisque": 5.21}, "tomato (physics effect)")
    assert str(exc.value) == (
        "bug in VirSqueezer: metric imaging_quality_brisque of tomato (physics effect) is 5.21, outside its "
        "documented range [0, 1]; this is an error in our code, not a result (nothing was written): please report "
        "it with this line")
    with pytest.raises(MetricRangeError, match=r"metric bdc_t\[3\] of can is -0.5, outside its documented range "
                                               r"\[0, 1\]"):
        check_metrics({"bdc_t": [0.2, None, 1.0, -0.5, 0.0]}, "can")  # per finger: the finger's index
    with pytest.raises(MetricRangeError, match=r"metric ate of can is inf, outside its documented range \[0, inf\)"):
        check_metrics({"ate": math.inf}, "can")
    with pytest.raises(MetricRangeError, match="metric sharpness of can has no documented range"):
        check_metrics({"sharpness": 0.5}, "can")


def test_nan_documented_infinities_and_rounding_pass():
    check_metrics({"outside_mask_psnr_db": "inf", "multiview_psnr_db": math.inf, "multiview_psnr_gain_db": -math.inf,
                   "control_coupling_pearson": 1.0 + 4e-16, "bdc_s": None, "miou": math.nan,
                   "physical_commonsense_rating": 0.0}, "can")
    assert METRIC_RANGES["outside_mask_psnr_db"].text() == "[0, inf]"
    assert METRIC_RANGES["max_squeeze_strain"].text() == "(-inf, inf)"
    assert not MetricRange(0.0, 1.0).holds(1.001) and not MetricRange(0.0, 1.0).holds(-1e-6)
    assert not MetricRange(-math.inf, math.inf).holds(math.inf)  # unbounded, yet infinite is not a value


def test_the_reference_page_lists_every_range():
    """docs/reference/preflight.md's table is generated from the same table (docs/hooks/reference.py)."""
    import importlib.util
    from pathlib import Path

    hook = Path(__file__).resolve().parents[2] / "docs" / "hooks" / "reference.py"
    spec = importlib.util.spec_from_file_location("docs_reference_hook", hook)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    rows = module.metric_ranges_markdown().splitlines()[2:]
    assert rows == [f"| `{name}` | {rng.text()} |" for name, rng in METRIC_RANGES.items()]
    assert "| `imaging_quality_brisque` | [0, 1] |" in rows and "| `ate` | [0, inf) |" in rows
