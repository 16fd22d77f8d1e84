"""Error against run time (issue 5): the error measures, the Pareto front and the observed order on known
answers, and one tiny real sweep through the flow that writes the table."""
from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tasks.verification.convergence import (
    TABLE_COLUMNS,
    ConvergenceError,
    bbox_diagonal,
    distances_from,
    observed_order,
    pareto_front,
    peak_strain_error,
    position_error,
    reaction_force_error,
    rollout_errors,
    timing_spread,
    tracer_drift,
)


def _rollout(rng, T=6, S=40):
    return {
        "gaussian_positions": rng.normal(size=(T, S, 3)) * 0.01,
        "reaction_force": rng.normal(size=(T, 5, 3)),
        "applied_force": np.zeros((T, 5, 3)),
        "squeeze_strain": np.abs(rng.normal(size=(T, 5))) * 0.1,
    }


def test_identical_rollouts_have_zero_error():
    ref = _rollout(np.random.default_rng(0))
    assert rollout_errors(ref, ref, size=0.1) == {k: 0.0 for k in (
        "position_error", "final_position_error", "reaction_force_error", "peak_strain_error")}


def test_known_offset_gives_the_known_normalised_rms():
    ref = np.zeros((4, 10, 3))
    run = ref.copy()
    run[..., 0] += 0.003  # every point 3 mm off along x in every frame
    run[..., 2] -= 0.004  # and 4 mm along z: |dx| = 5 mm
    size = bbox_diagonal([0, 0, 0], [0.03, 0.04, 0.0])  # 50 mm
    assert size == pytest.approx(0.05)
    assert position_error(run, ref, size) == pytest.approx(0.1)
    # half of the frames off: RMS = sqrt(0.5) x 5 mm
    run[:2] = 0.0
    assert position_error(run, ref, size) == pytest.approx(math.sqrt(0.5) * 0.1)


def test_distances_from_each_reference_use_the_first_runs_diagonal():
    box = np.array([[0.0, 0.0, 0.0], [0.03, 0.04, 0.0]])  # diagonal 50 mm
    coarse = np.repeat(box[None], 3, axis=0)
    fine = coarse.copy()
    fine[..., 0] += 0.005  # every point 5 mm off along x: 0.1 of the diagonal
    other = coarse.copy()
    other[1:, :, 2] += 0.005  # 2 of 3 frames 5 mm off along z: sqrt(2/3) x 0.1
    d = distances_from({("grid", "4"): coarse, ("grid", "2"): fine, ("pins", "2"): other},
                       {"grid": ("grid", "2"), "pins": ("pins", "2")})
    assert d[("grid", "2")] == {"grid": 0.0, "pins": pytest.approx(math.sqrt(0.01 + 0.01 * 2 / 3))}
    assert d[("grid", "4")]["grid"] == pytest.approx(0.1)
    assert d[("grid", "4")]["pins"] == pytest.approx(math.sqrt(2 / 3) * 0.1)
    with pytest.raises(ConvergenceError, match="every case failed"):
        distances_from({}, {})


def test_reaction_force_error_is_relative_l2_of_the_magnitudes():
    ref = np.zeros((3, 5, 3))
    ref[:, 1, 2] = [1.0, 2.0, 2.0]  # |R_index| over frames, norm 3
    run = ref.copy()
    run[:, 1, 2] *= -1.0  # same magnitudes, opposite direction: no magnitude error
    assert reaction_force_error(run, ref) == 0.0
    run[:, 1, 2] = [1.0, 2.0, 3.5]  # magnitude off by 1.5 in one frame
    assert reaction_force_error(run, ref) == pytest.approx(0.5)
    assert reaction_force_error(np.zeros((3, 5)), np.zeros((3, 5))) == 0.0
    assert reaction_force_error(np.ones((3, 5)), np.zeros((3, 5))) == math.inf


def test_peak_strain_error_compares_per_finger_peaks():
    ref = np.zeros((10, 5))
    ref[4, 0], ref[6, 1] = 0.3, 0.4  # peaks (0.3, 0.4): norm 0.5
    run = np.roll(ref, 2, axis=0)  # same peaks, later: no error
    assert peak_strain_error(run, ref) == 0.0
    run[6, 0] = 0.2  # thumb peak 0.2 instead of 0.3 -> 0.1 / 0.5
    assert peak_strain_error(run, ref) == pytest.approx(0.2)


def test_mismatched_tracers_are_refused():
    with pytest.raises(ConvergenceError, match="surface sampling"):
        position_error(np.zeros((3, 10, 3)), np.zeros((3, 12, 3)), 0.1)


def test_tracer_drift_is_the_growth_of_the_distance_to_the_material():
    particles = np.zeros((2, 3, 3))
    particles[:, :, 0] = [0.0, 0.01, 0.02]  # three particles on the x axis, at rest
    tracers = np.zeros((2, 2, 3))
    tracers[:, :, 1] = 0.001  # two tracers 1 mm off the body
    assert tracer_drift(tracers, particles) == 0.0
    tracers[1, 1, 1] = 0.005  # one leaves it: 5 mm away at the end
    assert tracer_drift(tracers, particles) == pytest.approx(0.004)


def test_pareto_front_of_a_hand_example():
    cost = [10, 20, 30, 15, 40, 25, np.nan]
    err = [0.5, 0.2, 0.1, 0.6, 0.1, 0.2, 0.0]
    # 15 s/0.6 is dominated by 10 s/0.5; 40 s/0.1 by 30 s/0.1; 25 s/0.2 by 20 s/0.2; NaN cost never on it
    assert pareto_front(cost, err).tolist() == [True, True, True, False, False, False, False]


def test_timing_spread_compares_settings_doing_the_same_work():
    df = pd.DataFrame({"setting": ["a", "b", "c"], "status": "ok", "rollout_s": [20.0, 50.0, 90.0],
                       "n_particles": [800, 800, 800], "substeps_total": [9000, 9000, 18000], "dx_m": 0.008})
    assert "a, b do the same work" in timing_spread(df) and "(2.5 x)" in timing_spread(df)
    assert timing_spread(df.iloc[[0, 2]]) == ""


@pytest.mark.parametrize("p", [1.0, 2.0, 1.5])
def test_observed_order_recovers_a_known_order(p):
    h = np.array([0.016, 0.008, 0.004, 0.002, 0.001])
    e = 3.0 * h ** p
    fit = observed_order(np.append(h, 0.0005), np.append(e, 0.0))  # the reference (error 0) is left out
    assert fit.n == 5 and fit.p == pytest.approx(p) and fit.C == pytest.approx(3.0)
    assert fit.pairwise == pytest.approx([p] * 4)
    assert observed_order([0.01], [0.1]) is None


REPO = Path(__file__).resolve().parents[2]


# ------------------------------------------------------------------------------------------ the real flow, tiny
TINY = ["object=rubber_ball", "sampling.surface_points=300", "sampling.particle_spacing=0.006", "signal.duration=0.6",
        "control.smoothing.frame_rate=10"]


def _sweep(overrides: list[str], server: str, cwd: Path) -> dict[str, str]:
    """``python -m flows.studies.convergence`` with ``overrides`` on the shared Prefect server: its per-task status
    counts and its report path (the lines it prints)."""
    env = dict(os.environ, PYTHONPATH=str(REPO), PREFECT_API_URL=server)
    out = subprocess.run([sys.executable, "-m", "flows.studies.convergence", *overrides], cwd=cwd, env=env,
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    printed = out.stdout + out.stderr  # the flow's prints go through Prefect's log (log_prints)
    statuses, report = re.search(r"per-task table \(([^)]*)\)", printed), re.search(r"report: (\S+)", printed)
    assert statuses and report, printed[-3000:]
    return {"statuses": statuses.group(1), "report": report.group(1)}


def test_two_setting_sweep_writes_the_table(prefect_server, tmp_path):
    overrides = [
        f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}", "run_name=tiny", *TINY,
        "convergence.reference=fine",
        ("convergence.settings=[{name: fine, family: grid, overrides: []},"
         "{name: coarse, family: grid, overrides: ['mpm.particles_per_cell=27']}]"),
        "convergence.families={grid: dx}"]
    out = _sweep(overrides, prefect_server, tmp_path)
    df = pd.read_csv(tmp_path / "reports" / "convergence" / "tiny" / "convergence.csv")
    assert list(df.columns) == list(TABLE_COLUMNS)
    assert df["setting"].tolist() == ["fine", "coarse"] and (df["status"] == "ok").all()
    fine, coarse = df.iloc[0], df.iloc[1]
    assert fine["reference"] and fine["position_error"] == 0.0 and fine["reaction_force_error"] == 0.0
    assert fine["dx_m"] == pytest.approx(0.012) and coarse["dx_m"] == pytest.approx(0.018)  # 6 mm x cbrt(8 | 27)
    assert coarse["n_particles"] == fine["n_particles"]  # the same particles on a coarser grid
    assert 0 < coarse["position_error"] < 0.2 and coarse["rollout_s"] > 0
    assert (tmp_path / "reports" / "convergence" / "tiny" / "pareto.png").stat().st_size > 0
    # a rerun of the sweep is served from the cache and reports the same recorded times
    again = _sweep(overrides, prefect_server, tmp_path)
    assert re.fullmatch(r"cached: \d+", again["statuses"]), again["statuses"]
    df2 = pd.read_csv(tmp_path / "reports" / "convergence" / "tiny" / "convergence.csv")
    pd.testing.assert_series_equal(df["rollout_s"], df2["rollout_s"])
    assert out["report"] == again["report"]


def test_finger_study_row_writes_a_missing_quasi_static_measure():
    """The finger study's table row (tasks.verification.finger_modes.table_row): the numbers at their precision, a
    metric the run has not as '-', and a quasi-static measure stored as None (kinetic energy without internal energy in a
    contact) as 'inf / none' instead of stopping the study (it did, on the plush toy with surface contact)."""
    from tasks.verification.finger_modes import table_row

    r = dict(bdc_t=0.5, bdc_s=None, sdc=0.25, miou=0.125, seconds=61.2, substeps=9220, reaction_peak=10.109,
             reaction_mean_peak=5.655, feedback_peak=10.109, feedback_rule="|contact force| (no yield stress)",
             strain_peak=0.249, predicted_peak=0.155, ke_ie=None)
    assert table_row("plush_toy", "surface_dirichlet", "default", r) == (
        "| plush_toy | surface_dirichlet | default | 0.500 | - | 0.250 | 0.125 | 61 | 9220 | 10.11 / 5.66 | "
        "10.11 (contact force (no yield stress)) | 0.249 / 0.155 | inf / none |")
    assert table_row("clay", "grid_dirichlet", "3 mm", {**r, "ke_ie": 0.0123}).endswith("| 0.012 |")
