"""The report's metric tables: the paper's Table 2 layout, averages, best-variant marking, CSV/parquet."""
from __future__ import annotations

import math

import pandas as pd

from tasks.reporting.report_tables import TABLE2, TRAJECTORY, markdown_table, paper_layout, write_metric_files

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
