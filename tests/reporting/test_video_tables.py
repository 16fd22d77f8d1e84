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


def test_table1_averages_only_over_objects_where_every_method_has_a_value():
    """Known answers: flicker is defined for both methods on both objects (full 0.85, w/o Dirichlet 0.90: bold);
    placement IoU only where both have an effect (the can: 0.6 against 0.5, full bold; the full tomato's 0.8 has no
    counterpart and is not averaged in); the outside-mask PSNR has no counterpart at all (n/a, not a win)."""
    rows_in = _rows()
    rows_in.loc[2, "effect_placement_iou"] = 0.5  # w/o Dirichlet: an effect on the can only
    header, rows, best = table1(rows_in, LABELS, {"diffusers": "weights not present"})
    assert header[0] == "Method" and header[-len(PAPER_ONLY):] == list(PAPER_ONLY)
    col = {name: i for i, name in enumerate(header)}
    full, ablation, counted, missing = rows[:4]
    assert full[0] == "Full VirSqueezer, physics-rendered effect"
    assert full[col["Temporal flicker"]] == "0.850" and ablation[col["Temporal flicker"]] == "0.900"
    assert best[1][col["Temporal flicker"]] and not best[0][col["Temporal flicker"]]
    iou = col["Effect placement IoU"]
    assert (full[iou], ablation[iou], counted[iou]) == ("0.600", "0.500", "1")
    assert best[0][iou] and not best[1][iou]
    psnr = next(i for h, i in col.items() if h.startswith("Fidelity outside mask PSNR"))
    assert full[psnr] == ablation[psnr] == "n/a" and counted[psnr] == "0" and not best[0][psnr]
    assert missing[0].startswith("(not run) diffusion effect: weights not present")
    assert set(missing[1:]) == {"n/a"}


def test_by_construction_columns_say_so_in_their_header_and_are_never_bold():
    """The composited render gives PSNR inf / SSIM 1 outside the mask; a text-only generator that paints outside it
    scores 30 dB: the higher value is not bolded, and both headers say why."""
    base = {k: math.nan for k, _, _ in VIDEO_COLUMNS}
    df = pd.DataFrame([
        {"object": "can", "variant": "full", "backend": "physics", **base, "outside_mask_psnr_db": math.inf,
         "outside_mask_ssim": 1.0},
        {"object": "can", "variant": "full", "backend": "text_only", **base, "outside_mask_psnr_db": 30.0,
         "outside_mask_ssim": 0.9}])
    for header, _, best in (table1(df, LABELS, {}), table3(df, ["can"], LABELS)):
        names = [h for h in header if "Fidelity outside mask" in h] or None
        if names:
            assert all(h.endswith("= render by construction") for h in names) and len(names) == 2
    header, rows, best = table1(df, LABELS, {})
    for i, h in enumerate(header):
        if h.startswith("Fidelity outside mask"):
            assert rows[0][i] in ("inf", "1.000") and not best[0][i] and not best[1][i]
    header, rows, best = table3(df, ["can"], LABELS)
    for r, b in zip(rows, best):
        if r[1].startswith("Fidelity outside mask"):
            assert r[1].endswith("= render by construction") and not any(b)


def test_table3_has_a_row_per_method_and_metric_the_common_average_and_the_papers_block():
    header, rows, best = table3(_rows(), ["can", "tomato"], LABELS)
    assert header == ["Method", "Metric", "can", "tomato", "Avg."]
    ours = [r for r in rows if not r[0].startswith("paper")]
    assert len(ours) == 2 * len(VIDEO_COLUMNS)
    flicker_full = next(r for r in rows if r[0].startswith("Full") and r[1] == "Temporal flicker")
    assert flicker_full[2:] == ["0.900", "0.800", "0.850"]
    i = rows.index(flicker_full)
    assert best[i][2:] == [False, False, False]  # w/o Dirichlet is steadier on both objects
    iou_full = next(r for r in rows if r[0].startswith("Full") and r[1] == "Effect placement IoU")
    assert iou_full[2:] == ["0.600", "0.800", "n/a"]  # no counterpart in w/o Dirichlet: no average, no bold
    assert not any(best[rows.index(iou_full)])
    paper = [(r, b) for r, b in zip(rows, best) if r[0].startswith("paper (their metric definitions are not published)")]
    assert len(paper) == 8 and not any(any(b) for _, b in paper)
    pc = next(r for r, _ in paper if r[0].endswith("Full VirSqueezer") and r[1] == "Physical Commonsense")
    assert pc[2:] == ["0.368", "0.372", "0.366"]  # the paper's can, tomato and its own eight-object average


def test_table3_of_several_seeds_is_the_mean_over_the_seeds():
    second = _rows().assign(seed=1)
    second["temporal_flicker"] = second["temporal_flicker"] - 0.1  # seed 1: 0.1 steadier everywhere
    both = pd.concat([_rows().assign(seed=0), second], ignore_index=True)
    _, rows, _ = table3(both, ["can", "tomato"], LABELS)
    flicker_full = next(r for r in rows if r[0].startswith("Full") and r[1] == "Temporal flicker")
    assert flicker_full[2:] == ["0.850", "0.750", "0.800"]
    psnr_full = next(r for r in rows if r[0].startswith("Full") and r[1].startswith("Fidelity outside mask PSNR"))
    assert psnr_full[2:] == ["inf", "inf", "n/a"]  # w/o Dirichlet has no effect: no common object to average


def test_study_items_are_the_final_videos_of_the_chosen_variants(tmp_path):
    from flows.human_study import study_items

    for name in ("can_full_final.mp4", "can_no_dirichlet_final.mp4", "paper_cup_full_final.mp4",
                 "can_full_stages.mp4"):
        (tmp_path / name).write_bytes(b"")
    items = study_items(tmp_path, ["full", "no_dirichlet"])
    assert [(o, m) for o, m, _ in items] == [("can", "full"), ("can", "no_dirichlet"), ("paper_cup", "full")]
