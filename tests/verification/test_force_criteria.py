"""The force-matched ablation's criterion study (``python -m flows.studies.force_match``): the reaction-matched
constant and the indentation read off calibration runs, against hand-computed answers."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tasks.verification.force_criteria import interpolated_indentation, reaction_matched_constant


def test_reaction_matched_constant_is_peak_normal_reaction_over_peak_total_coefficient():
    """Two fingers pressing along -z and +z over three frames.  Normal reactions |R . n| per frame: (1, 1), (3, 5),
    (2, 2) N -> peak total 8 N at frame 1; active coefficients' totals 0.2, 0.5 (+ an inactive finger's 9 left
    out), 0.4 -> peak 0.5; K_R = 16 N per unit coefficient.  Tangential reaction does not count."""
    n = np.tile(np.array([[0, 0, -1.0], [0, 0, 1.0], [1.0, 0, 0]]), (3, 1, 1))
    reaction = np.array([[[0.3, 0, 1], [0, 0, -1], [0, 0, 0]],
                         [[7.0, 0, 3], [0, 2, -5], [0, 0, 0]],
                         [[0, 0, -2], [0, 0, 2], [0, 0, 0]]])
    c = np.array([[0.1, 0.1, 0.0], [0.25, 0.25, 9.0], [0.2, 0.2, 0.0]])
    active = np.array([[True, True, False]] * 3)
    assert reaction_matched_constant(reaction, n, c, active) == pytest.approx((16.0, 8.0, 0.5))


def test_indentation_is_read_off_the_runs_log_log_and_nan_outside_them():
    """Runs on delta = 0.01 K^0.5: between K = 4 and 100 the log-log interpolation is exact (K = 25 -> 0.05); a
    failed run (inf) is left out; outside the runs' constants there is no answer."""
    ks = np.array([100.0, 4.0, 400.0])
    ds = np.array([0.1, 0.02, math.inf])
    assert interpolated_indentation(ks, ds, 25.0) == pytest.approx(0.05)
    assert math.isnan(interpolated_indentation(ks, ds, 200.0))  # above the last finite run
    assert math.isnan(interpolated_indentation(ks, ds, 1.0))
