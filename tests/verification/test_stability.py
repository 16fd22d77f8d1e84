"""Numerical stability suite (tasks/verification/stability.py, flows/stability.py): every guard exercised through the suite's case
runner with real Warp kernels, the thin-wall detection on the real objects, a stable soft case with known answers,
and the CLI on the quick subset.

Known answers used:
  * the forced-Courant refusal quotes C = dt c_p / dx = 1.5 exactly (dt is chosen from it);
  * the shell buckle wavelength 2 pi sqrt(R t) / (12 (1 - nu^2))^(1/4) of the can (R 33 mm, t 0.1 mm, nu 0.33) is
    6.3 mm < 2 dx = 16 mm; the rubber ball's (R 32.5 mm, t 3 mm, nu 0.49) is 35.7 mm > 16 mm;
  * dimensional analysis: with the CFL-adaptive step, a fixed-corotated column of E = 1 kPa and its twin of E = 1 GPa
    (same nu, rho) are the same dimensionless problem: same substeps, same energy drift, same force error.
"""
from __future__ import annotations

import csv
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tasks.physics.wall_resolution import thin_wall_finding
from tasks.verification.stability import (
    Case,
    SuiteContext,
    crafted_session,
    default_cases,
    run_case,
    select_cases,
)

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ctx() -> SuiteContext:
    """The production config groups, composed exactly as ``python -m flows.studies.stability`` does."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from conf.study.stability_schema import register_stability_config

    register_stability_config()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose(config_name="study/stability", overrides=[])
    GlobalHydra.instance().clear()
    return SuiteContext.from_config(cfg)


def case(name: str) -> Case:
    return next(c for c in default_cases() if c.name == name)


# ============================================================================================ guards
def test_courant_forced_above_limit_is_refused_and_the_suite_goes_on(ctx):
    row = run_case(case("courant_forced_1.5"), ctx)
    assert row.outcome == "refused"
    assert "Courant number 1.5 > limit 0.8: lower dt or E" in row.reason
    assert "c_p=" in row.reason and "dx=0.008 m" in row.reason
    assert row.courant == pytest.approx(1.5, rel=1e-6) and row.substeps == 0
    # with the limit raised, the same kind of dt blows up within a few substeps: the advective check stops it
    row = run_case(case("courant_unguarded_2.5"), ctx)
    assert row.outcome == "unstable"
    assert "advective Courant number" in row.reason and "> limit 3.0" in row.reason
    assert 0 < row.substeps < 50


def test_particles_pushed_out_of_the_domain_name_the_padding(ctx):
    row = run_case(case("pushed_out"), ctx)
    assert row.outcome == "unstable", row.reason
    assert "particle left the simulation grid (entered the padding layer / domain boundary)" in row.reason
    assert "'clay_shell'" in row.reason and "enlarge the domain" in row.reason
    assert "substep" in row.reason and "t=" in row.reason
    assert row.substeps > 0 and np.isfinite(row.j_min)


def test_nonfinite_state_and_nan_input_are_named(ctx):
    row = run_case(case("nan_state"), ctx)
    assert row.outcome == "unstable", row.reason
    assert row.reason.startswith("non-finite particle state (NaN/inf position, velocity or F) at substep")
    assert "frame 2" in row.reason and "'clay_shell'" in row.reason and "Likely cause" in row.reason
    row = run_case(case("nan_boundary_input"), ctx)
    assert row.outcome == "refused", row.reason
    assert "Dirichlet boundary input contains NaN/inf" in row.reason and "1 of 64 points" in row.reason
    assert "frame 1" in row.reason


def test_instability_below_the_courant_limit_is_not_reported_stable(ctx):
    """Courant 0.95 (accepted only with courant_limit raised to 1) grows the energy of a nu = 0.45 column ~100x
    while J stays inside the guard band: the suite's free-phase energy check must report it (or a future guard
    refuse it).  The default limit 0.8 refuses it up front (tests/physics/test_mpm_guards.py), and 0.8 itself is stable."""
    row = run_case(case("courant_adaptive_0.95_nu0.45"), ctx)
    assert row.outcome in ("unstable", "refused"), row
    if row.outcome == "unstable" and row.reason.startswith("UNCAUGHT"):
        assert "free-phase energy grew" in row.reason
        assert row.energy_drift > 1.0  # energy at least doubled: an instability, not dissipation
    at_limit = run_case(case("courant_adaptive_0.8_nu0.49"), ctx)
    assert at_limit.outcome == "stable", at_limit.reason
    assert at_limit.energy_drift < 0.005 and 0.78 < at_limit.courant <= 0.8  # dt evenly splits each frame


def test_energy_guard_names_the_frame_and_material_of_the_courant_095_instability(ctx):
    """The same Courant 0.95 case: the solver's energy guard (kinetic + internal + gravitational energy against the
    plates' work) now stops it with one line, long before the x120 growth, while the stable cases of this file
    (Courant 0.3 gel, 0.8 at nu = 0.49) run through with their plates doing work on the column."""
    row = run_case(case("courant_adaptive_0.95_nu0.45"), ctx)
    assert row.outcome == "unstable", row
    assert row.reason.startswith("energy guard at frame "), row.reason
    assert "beyond the boundary work" in row.reason and "grew: 'material' +" in row.reason
    assert "Courant number 0.9" in row.reason and ", limit 1," in row.reason
    frame = int(row.reason.split("energy guard at frame ")[1].split()[0])
    assert 2 <= frame < 40


# ============================================================================================ thin walls
def test_thin_walls_of_the_real_objects(ctx):
    rows = {o: run_case(case(f"thin_wall_{o}"), ctx) for o in ("can", "paper_cup", "rubber_ball")}
    for o in ("can", "paper_cup"):
        assert rows[o].outcome == "flagged", rows[o].reason
        assert rows[o].reason.startswith(f"FLAGGED {o} wall")
        # sampled in the default sampling.thin_wall_layers = 2
        assert "< dx 8 mm: two particle layers at the thickness's Gauss points" in rows[o].reason
        assert "< 2 dx = 16 mm" in rows[o].reason
    assert rows["rubber_ball"].outcome == "resolved", rows["rubber_ball"].reason
    # thinner than the spacing, yet its buckles span 2+ cells
    assert "two particle layers" in rows["rubber_ball"].reason

    def wavelength(R, t, nu):
        return 2 * math.pi * math.sqrt(R * t) / (12 * (1 - nu ** 2)) ** 0.25

    base = {"particle_spacing": 0.004, "thin_wall": True}
    can = thin_wall_finding({**base, "wall_thickness": 1e-4, "bbox_min": [-0.033, -0.033, -0.0575],
                             "bbox_max": [0.033, 0.033, 0.0575]}, dx=0.008, poisson_ratio=0.33, name="can")
    assert can.buckle_wavelength == pytest.approx(wavelength(0.033, 1e-4, 0.33)) == pytest.approx(6.3e-3, rel=0.01)
    assert can.flagged and can.under_resolution == pytest.approx(0.016 / can.buckle_wavelength)
    assert can.particle_layers == 1 and "one particle layer (membrane-like" in can.message  # no layer count: one
    two = thin_wall_finding({**base, "thin_wall_layers": 2, "wall_thickness": 1e-4, "bbox_min": [-0.033] * 3,
                             "bbox_max": [0.033] * 3}, dx=0.008, poisson_ratio=0.33, name="can")
    assert two.particle_layers == 2 and "two particle layers at the thickness's Gauss points" in two.message
    assert not two.advice  # 0.0125 dx thick
    # the ball's 3 mm wall on a 4.5 mm grid (0.67 dx) in two Gauss layers, held in plane stress: advised to take
    # three; in three: not; at exactly half a cell (the orange's 4 mm peel on the 8 mm grid): not; at 3/4 of a cell
    # (mpm.membrane_max_thickness) it carries 3D stress: not, unless plane stress is asked for up to a cell
    thick = {**base, "thin_wall_layers": 2, "wall_thickness": 3e-3, "bbox_min": [-0.0325] * 3,
             "bbox_max": [0.0325] * 3}
    advised = thin_wall_finding(thick, dx=0.0045, poisson_ratio=0.49, name="ball")
    assert "(0.67 dx) in two Gauss layers" in advised.advice and "sampling.thin_wall_layers=3" in advised.advice
    assert advised.advice in advised.message and not advised.flagged  # listed in a report for its advice
    three = thin_wall_finding({**thick, "thin_wall_layers": 3}, dx=0.0045, poisson_ratio=0.49, name="ball")
    assert "three particle layers" in three.message and not three.advice
    assert not thin_wall_finding(thick, dx=0.004, poisson_ratio=0.49).advice
    assert "(0.75 dx)" in thin_wall_finding(thick, dx=0.004, poisson_ratio=0.49, membrane_max_thickness=1.0).advice
    half = thin_wall_finding({**thick, "wall_thickness": 4e-3}, dx=0.008, poisson_ratio=0.3, name="orange")
    assert not half.advice and "thin_wall_layers=3" not in half.message
    ball = thin_wall_finding({**base, "wall_thickness": 3e-3, "bbox_min": [-0.0325] * 3, "bbox_max": [0.0325] * 3},
                             dx=0.008, poisson_ratio=0.49, name="ball")
    assert not ball.flagged and ball.buckle_wavelength == pytest.approx(0.0357, rel=0.01)
    solid = thin_wall_finding({"particle_spacing": 0.004, "wall_thickness": 0.0, "bbox_min": [0] * 3,
                               "bbox_max": [0.05] * 3}, dx=0.008)
    assert not solid.flagged and "solid body" in solid.message
    with pytest.raises(ValueError, match="dx must be > 0"):
        thin_wall_finding(base, dx=0.0)


# ============================================================================================ a stable case
def test_soft_gel_is_stable_with_bounded_dissipation_and_scale_invariant(ctx):
    """E = 1 kPa gel column (production dx 8 mm, Courant 0.3): stable; J within 1 % of the 1 % compression; the
    free phase (no gravity, no boundary: a conservative system) must not GAIN energy (growth = instability), and
    loses what the MLS-MPM/APIC transfers dissipate: ~27 % over 3 periods of a mode spanning 8 cells (bound 40 %).
    The plate force matches E A eps within 10 % (the closed-form accuracy of tests/physics/test_mpm_closed_forms.py)."""
    soft = run_case(case("soft_gel_1kPa"), ctx)
    assert soft.outcome == "stable", soft.reason
    assert 0.98 < soft.j_min <= 1.0 <= soft.j_max < 1.01
    assert -0.40 < soft.energy_drift <= 0.005
    assert abs(soft.accuracy_error) < 0.10
    assert soft.courant == pytest.approx(0.3, abs=1e-3) and soft.ke_ie_max < 0.1
    gel = case("soft_gel_1kPa")
    stiff = Case("stiff_twin", "stiffness", "compression", "E x 1e6",
                 {"material": {**gel.params["material"], "youngs_modulus": 1.0e9}})
    twin = run_case(stiff, ctx)
    assert twin.outcome == "stable"
    assert twin.substeps == soft.substeps
    assert twin.energy_drift == pytest.approx(soft.energy_drift, abs=2e-3)
    assert twin.accuracy_error == pytest.approx(soft.accuracy_error, abs=2e-3)
    assert twin.substeps_per_simulated_second == pytest.approx(soft.substeps_per_simulated_second * 1e3, rel=1e-6)


# ============================================================================================ inputs and CLI
def test_crafted_sessions_and_case_selection():
    g = np.linspace(-1, 1, 12)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pts = 0.03 * pts / np.linalg.norm(pts, axis=1, keepdims=True)  # points on a 3 cm sphere
    nrm = pts / 0.03
    step = crafted_session("step", pts, nrm, duration=0.5, sensor_rate=200.0, onset=0.3)
    t, u = step["time"], step["flexion"]
    assert np.allclose(u[t < 0.3], 0.05) and np.allclose(u[t >= 0.3], 1.0)  # full flexion within one sensor sample
    tips = step["fingertip_positions"]
    half = 0.5 * (pts.max(axis=0) - pts.min(axis=0))
    travel = 0.25 * min(half[0], half[1])  # travel_fraction x the smaller horizontal half-width
    assert np.linalg.norm(tips[-1] - tips[0], axis=1) == pytest.approx(np.full(5, travel), rel=1e-6)
    osc = crafted_session("oscillation", pts, nrm, duration=0.5, sensor_rate=200.0, frequency="nyquist", onset=0.3)
    after = osc["flexion"][osc["time"] >= 0.3, 0]
    assert np.allclose(after[::2], 0.05) and np.allclose(after[1::2], 1.0)  # on/off every sensor sample
    with pytest.raises(ValueError, match="unknown stability case"):
        select_cases(["courant_forced_15"])
    quick = select_cases(quick=True)
    assert {c.category for c in quick} >= {"stiffness", "knobs", "courant", "boundary", "nonfinite", "thin_wall"}
    assert [c.name for c in select_cases(["courant"])] == [c.name for c in default_cases() if c.category == "courant"]


def test_cli_quick_subset_writes_table(tmp_path):
    env = dict(os.environ, PYTHONPATH=str(REPO))
    out = subprocess.run([sys.executable, "-m", "flows.studies.stability", "quick=true", f"paths.reports={tmp_path}",
                          "run_name=t"], cwd=REPO, env=env, capture_output=True, text=True, timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    csv_path = tmp_path / "stability" / "t" / "stability.csv"
    with open(csv_path) as fh:
        rows = {r["case"]: r for r in csv.DictReader(fh)}
    assert list(rows) == [c.name for c in select_cases(quick=True)]
    assert rows["courant_forced_1.5"]["outcome"] == "refused"
    assert rows["pushed_out"]["outcome"] == "unstable"
    assert rows["thin_wall_can"]["outcome"] == "flagged"
    assert rows["soft_gel_1kPa"]["outcome"] == "stable"
    assert float(rows["aluminium_69GPa"]["substeps_per_simulated_second"]) > 1e6  # real 69 GPa, adaptive step
    assert rows["aluminium_mass_auto"]["error_vs_unaccelerated"] != ""
    md = (tmp_path / "stability" / "t" / "stability.md").read_text()
    assert "| case | category | outcome |" in md and "## Failures the solver guards did not catch" in md
    assert "stability.csv" in out.stdout and "courant_forced_1.5" in out.stdout
