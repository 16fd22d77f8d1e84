"""Video-metric tables in the paper's layouts: Table 1 (methods x metrics) and Table 3 (method x metric rows,
objects and the average as columns), from the ``video_metrics`` artifacts of a run.

Methods are what ran: variant (``full``, ``no_dirichlet``) x effect backend (``physics``, ``diffusers``,
``text_only``).  The paper's own rows that need weights we cannot ship, and its MUSIQ / AMT-S /
VideoCon-Physics / human / LLM columns, are listed as "n/a" with the reason, never filled in.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import pandas as pd

from tasks.core.artifacts import ArtifactError, read_group_attrs

# (column, heading, higher is better)
VIDEO_COLUMNS = (
    ("temporal_flicker", "Temporal flicker", True),
    ("motion_smoothness", "Motion smoothness (RIFE/DIS interp.)", True),
    ("imaging_quality_brisque", "Imaging quality (BRISQUE proxy)", True),
    ("outside_mask_psnr_db", "Fidelity outside mask PSNR (dB)", True),
    ("outside_mask_ssim", "Fidelity outside mask SSIM", True),
    ("effect_placement_iou", "Effect placement IoU", True),
    ("multiview_psnr_db", "Multi-view consistency PSNR (dB)", True),
    ("control_coupling_pearson", "Control coupling (Pearson)", True),
    ("llm_visual_quality", "LLM visual quality (1-5)", True),
    ("llm_motion_realism", "LLM motion realism (1-5)", True),
    ("llm_motion_consistency", "LLM motion consistency (1-5)", True),
)
PAPER_ONLY = {
    "Physical commonsense (VideoPhy-2 / VideoCon-Physics)": "not computed: weights not present (a 7B "
    "VideoCon-Physics checkpoint is needed)",
    "VBench imaging quality (MUSIQ, SPAQ)": "not computed: weights not present (MUSIQ SPAQ checkpoint)",
    "VBench motion smoothness (AMT-S)": "not computed: weights not present (AMT-S checkpoint)",
    "Human evaluation (1-5)": "not collected in this run (python -m flows.human_study builds the blinded kit)",
}
BACKEND_LABELS = {"physics": "physics-rendered effect", "diffusers": "diffusion effect",
                  "text_only": "w/o physics-guided conditions (text-only diffusion)", "none": "no effect"}


def method_label(variant_label: str, backend: str) -> str:
    return f"{variant_label}, {BACKEND_LABELS.get(backend, backend)}"


def video_metric_rows(refs: Mapping[str, Mapping[str, Any]]) -> pd.DataFrame:
    """One row per (object, seed, variant, backend): the video metrics (NaN where they do not apply)."""
    from tasks.core.scope import split_seed_scope

    rows = []
    for key, obj_refs in refs.items():
        obj, seed = split_seed_scope(key)
        for variant, vrefs in obj_refs.get("variants", {}).items():
            for backend, brefs in vrefs.get("backends", {}).items():
                ref = brefs.get("video_metrics")
                if ref is None:
                    continue
                try:
                    metrics = dict(read_group_attrs(ref.path)["attrs"]["metrics"])
                    llm = brefs.get("llm_evaluation")
                    scores = (read_group_attrs(llm.path)["attrs"].get("scores") or {}) if llm is not None else {}
                except (ArtifactError, KeyError):
                    continue
                metrics.update({f"llm_{q}": scores.get(q) for q in ("visual_quality", "motion_realism",
                                                                    "motion_consistency")})
                rows.append({"object": obj, "seed": seed, "variant": variant, "backend": backend,
                             **{k: (math.nan if v is None else float(v)) for k, v in metrics.items()}})
    return pd.DataFrame(rows)


def _mean(values: list[float]) -> float:
    """Mean over the values that are defined (NaN = does not apply); +inf (identical pixels) stays inf."""
    defined = [x for x in values if not math.isnan(x)]
    return sum(defined) / len(defined) if defined else math.nan


def _cell(x: float) -> str:
    if math.isinf(x):
        return "inf"
    return "n/a" if not math.isfinite(x) else f"{x:.3f}"


def table1(df: pd.DataFrame, labels: Mapping[str, str], backends_missing: Mapping[str, str]
           ) -> tuple[list[str], list[list[str]], list[list[bool]]]:
    """Table 1 layout: one row per method that ran (mean over objects where a metric applies), then the methods
    that could not run with the reason; columns our metrics and the paper's (n/a, reason in the caption)."""
    header = ["Method", *(name for _, name, _ in VIDEO_COLUMNS), *PAPER_ONLY]
    rows, values = [], []
    if not df.empty:
        for (variant, backend), sub in df.groupby(["variant", "backend"], sort=False):
            vals = [_mean(list(sub[key])) if key in sub else math.nan for key, _, _ in VIDEO_COLUMNS]
            values.append(vals)
            rows.append([method_label(labels.get(variant, variant), backend), *map(_cell, vals),
                         *("n/a" for _ in PAPER_ONLY)])
    best = []
    for vals in values:
        flags = [False]
        for col, (key, _, higher) in enumerate(VIDEO_COLUMNS):
            column = [v[col] for v in values if not math.isnan(v[col])]
            x = vals[col]
            flags.append(len(column) > 1 and not math.isnan(x) and x == (max(column) if higher else min(column)))
        best.append(flags + [False] * len(PAPER_ONLY))
    for backend, reason in backends_missing.items():
        rows.append([f"(not run) {BACKEND_LABELS.get(backend, backend)}: {reason}",
                     *("n/a" for _ in VIDEO_COLUMNS), *("n/a" for _ in PAPER_ONLY)])
        best.append([False] * len(header))
    return header, rows, best


def table3(df: pd.DataFrame, objects: list[str], labels: Mapping[str, str]
           ) -> tuple[list[str], list[list[str]], list[list[bool]]]:
    """Table 3 layout: rows (method, metric), columns the objects and the average over the objects where the
    metric applies; best method per column and metric in bold.  With several seeds a cell is the mean over the
    seeds (the spread is in Table 2 and in ``metrics.csv``)."""
    header = ["Method", "Metric", *objects, "Avg."]
    if df.empty:
        return header, [], []
    keys = ["variant", "backend", "object"]
    table = df.groupby(keys, sort=False).agg({k: lambda x: _mean(list(x)) for k in df.columns if k not in keys + ["seed"]})
    methods = list(dict.fromkeys(zip(df["variant"], df["backend"])))
    values = {}
    for variant, backend in methods:
        for key, _, _ in VIDEO_COLUMNS:
            vals = [float(table.loc[(variant, backend, o), key]) if (variant, backend, o) in table.index else math.nan
                    for o in objects]
            values[(variant, backend, key)] = vals + [_mean(vals)]
    rows, best = [], []
    for variant, backend in methods:
        for key, name, higher in VIDEO_COLUMNS:
            vals = values[(variant, backend, key)]
            rows.append([method_label(labels.get(variant, variant), backend), name, *map(_cell, vals)])
            flags = [False, False]
            for col, x in enumerate(vals):
                column = [values[(v, b, key)][col] for v, b in methods if not math.isnan(values[(v, b, key)][col])]
                flags.append(len(methods) > 1 and not math.isnan(x) and len(column) > 1
                             and x == (max(column) if higher else min(column)))
            best.append(flags)
    return header, rows, best


