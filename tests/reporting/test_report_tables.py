"""The report's metric tables: the paper's Table 2 layout, averages, best-variant marking, CSV/parquet."""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from tasks.core.tables import markdown_table
from tasks.reporting.report_tables import TABLE2, TRAJECTORY, paper_layout, write_metric_files

LABELS = {"full": "Full VirSqueezer", "no_dirichlet": "w/o Dirichlet"}


def _rows() -> pd.DataFrame:
    return pd.DataFrame([
        {"object": "can", "variant": "full", "bdc_t": 0.8, "bdc_s": 0.6, "sdc": 0.9, "miou": 0.5, "ate": 0.001},
        {"object": "clay", "variant": "full", "bdc_t": 0.6, "bdc_s": math.nan, "sdc": 0.7, "miou": 0.4, "ate": 0.003},
        {"object": "can", "variant": "no_dirichlet", "bdc_t": 0.7, "bdc_s": 0.65, "sdc": 0.9, "miou": 0.2,
         "ate": 0.002},
        {"object": "clay", "variant": "no_dirichlet", "bdc_t": 0.5, "bdc_s": 0.3, "sdc": 0.6, "miou": 0.45,
         "ate": 0.001},
    ])


def test_table2_layout_averages_over_defined_objects_and_marks_the_best_variant_per_column():
    header, rows, best = paper_layout(_rows(), TABLE2, ["can", "clay"], LABELS)
    assert header == ["Method", "Metric", "can", "clay", "Avg."]
    assert [r[:2] for r in rows] == [[LABELS[v], m] for v in ("full", "no_dirichlet")
                                     for m in ("BDC-T", "BDC-S", "SDC", "mIoU")]
    by = {(r[0], r[1]): r[2:] for r in rows}
    assert by[(LABELS["full"], "BDC-T")] == ["0.800", "0.600", "0.700"]
    assert by[(LABELS["full"], "BDC-S")] == ["0.600", "-", "0.600"]  # NaN shown as '-', Avg over can only
    assert by[(LABELS["no_dirichlet"], "BDC-S")] == ["0.650", "0.300", "0.475"]
    flags = {(r[0], r[1]): f[2:] for r, f in zip(rows, best)}
    assert flags[(LABELS["full"], "BDC-T")] == [True, True, True]
    assert flags[(LABELS["no_dirichlet"], "BDC-S")] == [True, False, False]  # clay: only one variant defined
    assert flags[(LABELS["full"], "BDC-S")] == [False, False, True]  # 0.600 > 0.475
    assert flags[(LABELS["full"], "SDC")] == [True, True, True] and flags[(LABELS["no_dirichlet"], "SDC")][0]  # tie
    assert flags[(LABELS["no_dirichlet"], "mIoU")] == [False, True, False]


def test_lower_is_better_for_trajectory_errors_and_millimetres_are_shown():
    _, rows, best = paper_layout(_rows(), TRAJECTORY[:1], ["can", "clay"], LABELS)
    assert rows[0][2:] == ["1.000", "3.000", "2.000"] and rows[1][2:] == ["2.000", "1.000", "1.500"]
    assert best[0][2:] == [True, False, False] and best[1][2:] == [False, True, True]


def test_markdown_bold_and_metric_files_round_trip(tmp_path):
    text = markdown_table(["a", "b"], [["1", "2"]], [[False, True]])
    assert text.splitlines() == ["| a | b |", "|---|---|", "| 1 | **2** |"]
    df = _rows()
    paths = write_metric_files(df, tmp_path)
    assert [p.name for p in paths] == ["metrics.csv", "metrics.parquet"]
    pd.testing.assert_frame_equal(pd.read_parquet(paths[1]), df)
    assert list(pd.read_csv(paths[0]).columns[:2]) == ["object", "variant"]


def _seed_rows() -> pd.DataFrame:
    """Three seeds, two objects.  BDC-T of can: full 0.80/0.70/0.60 (mean 0.700, std 0.100), no_dirichlet
    0.50/0.55/0.60 (mean 0.550, std 0.050): |0.150| > hypot(0.1, 0.05) = 0.112, resolved.  clay: full
    0.40/0.50/0.60 (0.500 +- 0.100), no_dirichlet 0.45/0.45/0.45 (0.450 +- 0): |0.05| <= 0.1, within the spread.
    Avg. per seed: full 0.60/0.60/0.60 (0.600 +- 0), no_dirichlet 0.475/0.50/0.525 (0.500 +- 0.025): resolved."""
    full = {"can": (0.8, 0.7, 0.6), "clay": (0.4, 0.5, 0.6)}
    ablation = {"can": (0.5, 0.55, 0.6), "clay": (0.45, 0.45, 0.45)}
    return pd.DataFrame([{"object": obj, "seed": seed, "variant": variant, "bdc_t": vals[i]}
                         for variant, table in (("full", full), ("no_dirichlet", ablation))
                         for obj, vals in table.items() for i, seed in enumerate((0, 1, 2))])


def test_several_seeds_give_mean_and_std_and_mark_differences_within_the_spread():
    from tasks.reporting.report_tables import seed_note

    df = _seed_rows()
    header, rows, best = paper_layout(df, TABLE2[:1], ["can", "clay"], LABELS)
    assert rows[0] == [LABELS["full"], "BDC-T", "0.700 ± 0.100", "0.500 ± 0.100 ≈", "0.600 ± 0.000"]
    assert rows[1] == [LABELS["no_dirichlet"], "BDC-T", "0.550 ± 0.050", "0.450 ± 0.000 ≈", "0.500 ± 0.025"]
    assert best[0][2:] == [True, True, True] and best[1][2:] == [False, False, False]  # bold on the means
    note = seed_note(df)
    assert note.startswith("Mean ± sample standard deviation over 3 sampling seeds [0, 1, 2]")
    assert "≈: the difference to the best variant in that column is within the seed spread" in note
    assert seed_note(df[df["seed"] == 0]) is None


def test_one_seed_keeps_the_single_run_cells():
    header, rows, _ = paper_layout(_seed_rows().query("seed == 1"), TABLE2[:1], ["can", "clay"], LABELS)
    assert rows[0][2:] == ["0.700", "0.500", "0.600"] and rows[1][2:] == ["0.550", "0.450", "0.500"]


def test_metric_rows_keep_one_row_per_seed(tmp_path):
    from tasks.core.artifacts import Array, write_artifact
    from tasks.core.scope import seed_scope, split_seed_scope
    from tasks.reporting.report_tables import metric_rows

    assert seed_scope("can", 0) == "can" and seed_scope("can", 2) == "can@seed2"
    assert split_seed_scope("can@seed2") == ("can", 2) and split_seed_scope("can") == ("can", 0)
    refs = {}
    for seed, value in ((0, 0.8), (2, 0.6)):
        ref = write_artifact(tmp_path / f"{seed}.zarr", {"x": Array(np.zeros(1), ("i",), "1")},
                             step="deformation_metrics", scope=seed_scope("can", seed), config_digest="-",
                             attrs={"metrics": {"bdc_t": value}})
        refs[seed_scope("can", seed)] = {"variants": {"full": {"deformation_metrics": ref}}}
    df = metric_rows(refs)
    assert df[["object", "seed", "variant", "bdc_t"]].values.tolist() == [["can", 0, "full", 0.8], ["can", 2, "full", 0.6]]


def test_report_of_a_seed_grid_shows_mean_std_the_spread_note_and_per_seed_rows(tmp_path):
    """What the user reads: Table 2 cells ``mean ± std``, the ≈ mark and its caption; metrics.csv one row per seed."""
    from flows.runtime import RunTable
    from tasks.core.artifacts import Array, write_artifact
    from tasks.core.scope import seed_scope
    from tasks.reporting.report import write_run_report

    refs: dict = {}
    for i, r in enumerate(_seed_rows().itertuples(index=False)):
        ref = write_artifact(tmp_path / "a" / f"{i}.zarr", {"x": Array(np.zeros(1), ("i",), "1")},
                             step="deformation_metrics", scope=seed_scope(r.object, r.seed), config_digest="-",
                             attrs={"metrics": {"bdc_t": r.bdc_t}})
        refs.setdefault(seed_scope(r.object, r.seed), {"variants": {}})["variants"][r.variant] = {
            "deformation_metrics": ref}
    md = write_run_report(tmp_path / "report", cfg={}, table=RunTable(), refs=refs, wall_seconds=1.0,
                          variants=LABELS).read_text()
    assert "| Full VirSqueezer | BDC-T | **0.700 ± 0.100** | **0.500 ± 0.100 ≈** | **0.600 ± 0.000** |" in md
    assert "| w/o Dirichlet | BDC-T | 0.550 ± 0.050 | 0.450 ± 0.000 ≈ | 0.500 ± 0.025 |" in md
    assert "Mean ± sample standard deviation over 3 sampling seeds [0, 1, 2]" in md
    rows = pd.read_csv(tmp_path / "report" / "metrics.csv")
    assert len(rows) == 12 and sorted(set(rows["seed"])) == [0, 1, 2]


def test_report_shows_the_quasi_static_check_as_the_solver_applied_it(tmp_path):
    """The rollout table gives the check's measure over the contacts it judged, its limit and whether it warned;
    the physical figures table and the definitions give the same measure (not the per-frame KE/IE of old)."""
    from flows.runtime import RunTable
    from tasks.core.artifacts import Array, write_artifact
    from tasks.evaluation.deformation_metrics import DEFINITIONS
    from tasks.reporting.report import quasi_static_cell, rollout_summary, write_run_report

    T = 6
    frame_arrays = {"squeeze_strain": Array(np.full((T, 5), 0.1), ("frame", "finger"), "1"),
                    "feedback_force": Array(np.full((T, 5), 2.0), ("frame", "finger"), "N"),
                    **{k: Array(np.zeros(T), ("frame",), "1") for k in ("dirichlet_tracking_error", "ke_ie_ratio")}}
    qs = {"mass_scale": 4.0, "limit": 0.1, "max_ke_ie_in_contact": 0.3, "contacts_over_limit": 1,
          "contacts_checked": 2, "frames_checked": 5, "frames_in_contact": 6}
    rollout = write_artifact(tmp_path / "r.zarr", frame_arrays, step="mpm_rollout", scope="can", config_digest="-",
                             attrs={"threshold_event": {"threshold": 0.3, "crossed": False}, "boundary": "force",
                                    "n_particles": 10, "substeps_total": 60, "mass_scale": 4.0, "quasi_static": qs})
    summary = rollout_summary({"can": {"variants": {"no_dirichlet": {"mpm_rollout": rollout}}}})
    assert "| quasi-static check: max KE/IE / limit |" in summary.splitlines()[0]
    assert "| x4 | 0.3 / 0.1: WARNED in 1 of 2 contact(s) (5 frames checked) |" in summary
    assert quasi_static_cell({**qs, "contacts_over_limit": 0, "max_ke_ie_in_contact": 0.02}) == \
        "0.02 / 0.1: ok in 2 contact(s) (5 frames checked)"
    assert quasi_static_cell({**qs, "contacts_checked": 0, "max_ke_ie_in_contact": None}) == \
        "not checked (no mass scaling or no loaded frame)"
    metrics = write_artifact(tmp_path / "m.zarr", {"x": Array(np.zeros(1), ("i",), "1")}, step="deformation_metrics",
                             scope="can", config_digest="-",
                             attrs={"metrics": {"bdc_t": 0.5, "max_ke_ie_in_contact": 0.3, "quasi_static_warned": 1.0},
                                    "definitions": DEFINITIONS})
    md = write_run_report(tmp_path / "report", cfg={}, table=RunTable(), refs={"can": {"variants": {
        "no_dirichlet": {"deformation_metrics": metrics}}}}, wall_seconds=1.0, variants=LABELS).read_text()
    physical = md.split("## Physical figures per object and variant")[1].split("##")[0]
    assert "| object | seed | variant | max_ke_ie_in_contact | quasi_static_warned |" in physical
    assert "| can | 0 | no_dirichlet | 0.3 | 1 |" in physical
    assert f"- **max_ke_ie_in_contact**: {DEFINITIONS['max_ke_ie_in_contact']}" in md
    assert "over the contacts it judges" in DEFINITIONS["max_ke_ie_in_contact"]
    assert f"- **quasi_static_warned**: {DEFINITIONS['quasi_static_warned']}" in md


def test_flight_figure_draws_the_free_blobs_and_states_the_measured_acceleration(tmp_path):
    """A rollout with a flight record gets the flight figure (a PNG, its free blob recomputed from the record) and
    the caption states the measured acceleration and its deviation from the expected one; one with a record but no
    free blob still gets the figure; a rollout without a release gets none."""
    from tasks.core.artifacts import Array, write_artifact
    from tasks.physics.free_flight import blob_flights, flight_summary
    from tasks.reporting.report import flight_caption, flight_figure

    t = 1.0 + np.arange(40) / 600
    z = 0.03 - 0.5 * 9.81 * (t - 1.0) ** 2
    x = np.stack(np.broadcast_arrays(0.0, 0.0, z[:, None] + np.array([0.0, 0.002])), -1).astype(np.float32)
    grid = {"grid_origin": [-0.1, -0.1, -0.1], "dx": 0.008, "gravity": -9.81}
    held = np.zeros((40, 2), bool)
    fall = {**flight_summary(blob_flights(t, x, held, np.array(grid["grid_origin"]), 0.008, np.ones(2), np.ones(2))),
            **grid}
    assert fall["flights"] == 1 and fall["error"] == pytest.approx(0.0, abs=1e-4)
    arrays = {"time": Array(np.arange(45) / 30, ("frame",), "s"),
              "released_flight_time": Array(t, ("sample",), "s"),
              "released_flight_positions": Array(x, ("sample", "loose", "xyz"), "m"),
              "released_flight_held": Array(held, ("sample", "loose"), "1"),
              "released_flight_mass": Array(np.ones(2), ("loose",), "kg"),
              "released_flight_physical_mass": Array(np.ones(2), ("loose",), "kg")}
    for name, hold in [("r", held), ("h", ~held)]:
        ref = write_artifact(tmp_path / f"{name}.zarr", {**arrays, "released_flight_held": Array(
            hold, ("sample", "loose"), "1")}, step="mpm_rollout", scope="tomato", config_digest="-",
            attrs={"released_free_fall": fall})
        path = flight_figure("tomato", {"mpm_rollout": ref}, tmp_path / f"{name}.png")
        assert path is not None and path.read_bytes()[:4] == b"\x89PNG"
    # every released particle held throughout: the recorder keeps none of them, the figure still says so
    empty = write_artifact(tmp_path / "e.zarr", {**arrays, **{k: Array(np.asarray(arrays[k].data)[..., :0, :] if
                           k == "released_flight_positions" else np.asarray(arrays[k].data)[..., :0],
                           arrays[k].dims, arrays[k].units) for k in ("released_flight_positions",
                           "released_flight_held", "released_flight_mass", "released_flight_physical_mass")}},
                           step="mpm_rollout", scope="plush_toy", config_digest="-", attrs={"released_free_fall": {}})
    path = flight_figure("plush_toy", {"mpm_rollout": empty}, tmp_path / "e.png")
    assert path is not None and path.read_bytes()[:4] == b"\x89PNG"
    fall = {**fall, "acceleration": -9.5, "error": -9.5 / -9.81 - 1, "flights": 3, "particles": 12,
            "longest_flight": 0.04}
    assert flight_caption(fall) == ("released material: a = -9.50 m/s^2 (-3.2 % of the expected -9.81), median of "
                                    "3 free blobs'\nflights (12 particles), longest 40 ms")
    assert flight_caption(None) == "released material: no free blob flew for 4 recorder samples (a = none)"
    bare = write_artifact(tmp_path / "b.zarr", {"time": arrays["time"]}, step="mpm_rollout", scope="ball",
                          config_digest="-")
    assert flight_figure("ball", {"mpm_rollout": bare}, tmp_path / "none.png") is None
