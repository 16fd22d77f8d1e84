"""Table 1 and Table 3 layouts of the video metrics, and the human-study items of a report folder."""
from __future__ import annotations

import math

import pandas as pd

from tasks.reporting.video_tables import PAPER_ONLY, VIDEO_COLUMNS, table1, table3

LABELS = {"full": "Full VirSqueezer", "no_dirichlet": "w/o Dirichlet"}


def _rows():
    base = {k: math.nan for k, _, _ in VIDEO_COLUMNS}
    return pd.DataFrame([
        {"object": "can", "variant": "full", "backend": "physics", **base, "temporal_flicker": 0.9,
         "outside_mask_psnr_db": math.inf, "effect_placement_iou": 0.6},
        {"object": "tomato", "variant": "full", "backend": "physics", **base, "temporal_flicker": 0.8,
         "outside_mask_psnr_db": math.inf, "effect_placement_iou": 0.8},
        {"object": "can", "variant": "no_dirichlet", "backend": "physics", **base, "temporal_flicker": 0.95},
        {"object": "tomato", "variant": "no_dirichlet", "backend": "physics", **base, "temporal_flicker": 0.85},
    ])


def test_table1_averages_over_the_objects_where_a_metric_applies_and_marks_the_best():
    header, rows, best = table1(_rows(), LABELS, {"diffusers": "weights not present"})
    assert header[0] == "Method" and header[-len(PAPER_ONLY):] == list(PAPER_ONLY)
    col = {name: i for i, name in enumerate(header)}
    full, ablation, missing = rows
    assert full[0] == "Full VirSqueezer, physics-rendered effect"
    assert full[col["Temporal flicker"]] == "0.850" and ablation[col["Temporal flicker"]] == "0.900"
    assert full[col["Effect placement IoU"]] == "0.700"  # mean over the two objects
    assert full[col["Fidelity outside mask PSNR (dB)"]] == "inf"  # identical pixels outside the mask
    assert ablation[col["Effect placement IoU"]] == "n/a"  # no effect in that variant
    assert best[1][col["Temporal flicker"]] and not best[0][col["Temporal flicker"]]
    assert missing[0].startswith("(not run) diffusion effect: weights not present")
    assert set(missing[1:]) == {"n/a"}


def test_table3_has_a_row_per_method_and_metric_and_the_average_column():
    header, rows, best = table3(_rows(), ["can", "tomato"], LABELS)
    assert header == ["Method", "Metric", "can", "tomato", "Avg."]
    assert len(rows) == 2 * len(VIDEO_COLUMNS)
    flicker_full = next(r for r in rows if r[0].startswith("Full") and r[1] == "Temporal flicker")
    assert flicker_full[2:] == ["0.900", "0.800", "0.850"]
    i = rows.index(flicker_full)
    assert best[i][2:] == [False, False, False]  # w/o Dirichlet is steadier on both objects


def test_table3_of_several_seeds_is_the_mean_over_the_seeds():
    second = _rows().assign(seed=1)
    second["temporal_flicker"] = second["temporal_flicker"] - 0.1  # seed 1: 0.1 steadier everywhere
    both = pd.concat([_rows().assign(seed=0), second], ignore_index=True)
    _, rows, _ = table3(both, ["can", "tomato"], LABELS)
    flicker_full = next(r for r in rows if r[0].startswith("Full") and r[1] == "Temporal flicker")
    assert flicker_full[2:] == ["0.850", "0.750", "0.800"]
    psnr_full = next(r for r in rows if r[0].startswith("Full") and r[1].startswith("Fidelity outside mask PSNR"))
    assert psnr_full[2:] == ["inf", "inf", "inf"]


def test_study_items_are_the_final_videos_of_the_chosen_variants(tmp_path):
    from flows.human_study import study_items

    for name in ("can_full_final.mp4", "can_no_dirichlet_final.mp4", "paper_cup_full_final.mp4",
                 "can_full_stages.mp4"):
        (tmp_path / name).write_bytes(b"")
    items = study_items(tmp_path, ["full", "no_dirichlet"])
    assert [(o, m) for o, m, _ in items] == [("can", "full"), ("can", "no_dirichlet"), ("paper_cup", "full")]
