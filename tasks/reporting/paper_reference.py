"""The paper's own numbers (Tables 1-3 of /work/shared/reference/virsqueezer-paper.tex), shown as a reference row
block under our tables so that a reader sees where we agree and differ.  The paper does not publish its metric
definitions (BDC-T/S, SDC, mIoU; which VideoPhy recipe; the LLM and human protocols), so the block is labelled
:data:`PAPER_LABEL` and never bolded; docs/results/paper-comparison.md explains each difference we understand.
"""
from __future__ import annotations

from typing import Mapping, Sequence

PAPER_LABEL = "paper (their metric definitions are not published)"
# the paper's object order in Tables 2 and 3
PAPER_OBJECTS = ("can", "plush_toy", "tomato", "rubber_duck", "clay", "orange", "rubber_ball", "paper_cup")

# Table 2: method -> metric -> (per object in PAPER_OBJECTS order, Avg.)
TABLE2: dict[str, dict[str, tuple[tuple[float, ...], float]]] = {
    "VirSqueezer w/o Dirichlet Boundary Constraint": {
        "BDC-T": ((0.85, 0.77, 0.73, 0.82, 0.73, 0.69, 0.72, 0.77), 0.764),
        "BDC-S": ((0.69, 0.67, 0.63, 0.75, 0.60, 0.55, 0.66, 0.68), 0.654),
        "SDC": ((0.82, 0.79, 0.70, 0.89, 0.77, 0.64, 0.77, 0.79), 0.771),
        "mIoU": ((0.72, 0.63, 0.70, 0.67, 0.65, 0.62, 0.64, 0.66), 0.661),
    },
    "Full VirSqueezer": {
        "BDC-T": ((0.86, 0.75, 0.77, 0.85, 0.72, 0.69, 0.77, 0.79), 0.775),
        "BDC-S": ((0.69, 0.65, 0.62, 0.72, 0.61, 0.57, 0.67, 0.65), 0.648),
        "SDC": ((0.87, 0.79, 0.72, 0.83, 0.79, 0.69, 0.78, 0.75), 0.778),
        "mIoU": ((0.70, 0.67, 0.69, 0.70, 0.65, 0.65, 0.67, 0.62), 0.669),
    },
}

# Table 3: method -> metric -> (per object, Avg.)
TABLE3: dict[str, dict[str, tuple[tuple[float, ...], float]]] = {
    "VirSqueezer w/o Physics-guided Conditions": {
        "Physical Commonsense": ((0.301, 0.284, 0.295, 0.310, 0.276, 0.291, 0.303, 0.287), 0.293),
        "Motion Smoothness": ((0.542, 0.531, 0.548, 0.556, 0.520, 0.535, 0.544, 0.526), 0.538),
        "Motion Realism": ((2.9, 2.8, 3.0, 3.1, 2.7, 2.9, 3.0, 2.8), 2.90),
        "Motion Consistency": ((2.7, 2.6, 2.8, 2.9, 2.5, 2.7, 2.8, 2.6), 2.70),
    },
    "Full VirSqueezer": {
        "Physical Commonsense": ((0.368, 0.361, 0.372, 0.375, 0.354, 0.369, 0.371, 0.358), 0.366),
        "Motion Smoothness": ((0.596, 0.588, 0.602, 0.607, 0.581, 0.594, 0.601, 0.587), 0.595),
        "Motion Realism": ((4.1, 4.0, 4.2, 4.3, 3.9, 4.1, 4.2, 4.0), 4.10),
        "Motion Consistency": ((4.3, 4.2, 4.4, 4.5, 4.1, 4.3, 4.4, 4.2), 4.30),
    },
}

# Table 1: method -> our Table 1 column key -> the paper's value (text).  Physical commonsense: the paper cites
# VideoPhy-2 without its recipe; VBench imaging quality / motion smoothness: MUSIQ / AMT-S; GPT-5 evaluation: the
# paper's LLM judge (ours is the configured judge); human evaluation: visual quality / motion realism / motion
# consistency.
TABLE1: dict[str, dict[str, str]] = {
    "PhysGaussian": {"physical_commonsense": "0.354", "imaging_quality_musiq": "0.522",
                     "motion_smoothness_amt": "0.994", "llm_visual_quality": "4.0", "llm_motion_realism": "3.8",
                     "llm_motion_consistency": "4.1", "human": "3.2 / 3.1 / 3.0"},
    "OmniPhysGS": {"physical_commonsense": "0.345", "imaging_quality_musiq": "0.516",
                   "motion_smoothness_amt": "0.994", "llm_visual_quality": "3.8", "llm_motion_realism": "3.9",
                   "llm_motion_consistency": "3.7", "human": "2.6 / 2.6 / 2.8"},
    "DreamGaussian4D": {"physical_commonsense": "0.071", "imaging_quality_musiq": "0.218",
                        "motion_smoothness_amt": "0.983", "llm_visual_quality": "3.1", "llm_motion_realism": "3.5",
                        "llm_motion_consistency": "3.1", "human": "2.0 / 2.3 / 2.1"},
    "Gaussians-to-Life": {"physical_commonsense": "0.234", "imaging_quality_musiq": "0.556",
                          "motion_smoothness_amt": "0.987", "llm_visual_quality": "3.7", "llm_motion_realism": "3.5",
                          "llm_motion_consistency": "3.2", "human": "2.2 / 2.3 / 2.7"},
    "VirSqueezer (Ours)": {"physical_commonsense": "0.368", "imaging_quality_musiq": "0.596",
                           "motion_smoothness_amt": "0.996", "llm_visual_quality": "3.9", "llm_motion_realism": "4.2",
                           "llm_motion_consistency": "4.3", "human": "3.9 / 4.1 / 4.2"},
}


def _per_object(values: tuple[float, ...], objects: Sequence[str]) -> list[str]:
    by_name = dict(zip(PAPER_OBJECTS, values))
    return [f"{by_name[o]:.3f}" if o in by_name else "-" for o in objects]


def object_rows(table: Mapping[str, Mapping[str, tuple[tuple[float, ...], float]]],
                objects: Sequence[str]) -> tuple[list[list[str]], list[list[bool]]]:
    """The paper's (method, metric) rows of Table 2 or 3 in our column order (``objects`` then Avg.; "-" for an
    object the paper does not have), labelled with :data:`PAPER_LABEL`, and their bold flags (all False).  The
    paper's Avg. is its own (over its eight objects)."""
    rows = [[f"{PAPER_LABEL}: {method}", metric, *_per_object(vals, objects), f"{avg:.3f}"]
            for method, metrics in table.items() for metric, (vals, avg) in metrics.items()]
    return rows, [[False] * len(r) for r in rows]


def table1_rows(keys: Sequence[str], human_columns: int) -> tuple[list[list[str]], list[list[bool]]]:
    """The paper's Table 1 methods as rows under ours: ``keys`` our Table 1 column keys (after "Method"), then
    ``human_columns`` columns for the human evaluation; "-" where the paper gives no number."""
    rows = []
    for method, values in TABLE1.items():
        rows.append([f"{PAPER_LABEL}: {method}", *(values.get(k, "-") for k in keys),
                     *([values["human"]] + ["-"] * (human_columns - 1) if human_columns else [])])
    return rows, [[False] * len(r) for r in rows]
