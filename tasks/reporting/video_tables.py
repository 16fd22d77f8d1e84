"""Video-metric tables in the paper's layouts: Table 1 (methods x metrics) and Table 3 (method x metric rows,
objects and the average as columns), from the ``video_metrics`` artifacts of a run.

Methods are what ran: variant (``full``, ``no_dirichlet``) x effect backend (``physics``, ``diffusers``,
``text_only``).  The paper's own rows that need weights we cannot ship are listed as "n/a" with the reason; its
VBench MUSIQ / AMT-S and VideoPhy-2 physical-commonsense columns are filled where their weights were present
(``paper_metrics``) and are "n/a" with the reason otherwise; its human column is always "n/a" with the reason.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import pandas as pd

from tasks.core.artifacts import ArtifactError, read_group_attrs
from tasks.evaluation.paper_weights import PAPER_WEIGHTS

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
# the paper's metrics computed where their weights are present (tasks.evaluation.paper_metrics)
PAPER_COLUMNS = tuple((spec.metric, spec.heading, True) for spec in PAPER_WEIGHTS)
# the paper's metrics never computed in a run
PAPER_ONLY = {
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
                    llm, paper = brefs.get("llm_evaluation"), brefs.get("paper_metrics")
                    scores = (read_group_attrs(llm.path)["attrs"].get("scores") or {}) if llm is not None else {}
                    paper_values = read_group_attrs(paper.path)["attrs"]["metrics"] if paper is not None else {}
                except (ArtifactError, KeyError):
                    continue
                metrics.update({f"llm_{q}": scores.get(q) for q in ("visual_quality", "motion_realism",
                                                                    "motion_consistency")})
                metrics.update({k: paper_values.get(k) for k, _, _ in PAPER_COLUMNS})
                rows.append({"object": obj, "seed": seed, "variant": variant, "backend": backend,
                             **{k: (math.nan if v is None else float(v)) for k, v in metrics.items()}})
    return pd.DataFrame(rows)


def paper_metric_reasons(refs: Mapping[str, Mapping[str, Any]]) -> dict[str, str]:
    """Why each paper metric is missing from the tables: heading -> reason, for the VBench metrics that no scene
    computed (the reasons their ``paper_metrics`` artifacts recorded, else "not set") and the never-computed ones."""
    found: dict[str, set[str]] = {spec.metric: set() for spec in PAPER_WEIGHTS}
    computed: set[str] = set()
    for obj_refs in refs.values():
        for vrefs in obj_refs.get("variants", {}).values():
            for brefs in vrefs.get("backends", {}).values():
                ref = brefs.get("paper_metrics")
                if ref is None:
                    continue
                try:
                    attrs = read_group_attrs(ref.path)["attrs"]
                except ArtifactError:
                    continue
                computed |= {k for k, v in attrs["metrics"].items() if v is not None}
                for metric, reason in attrs["reasons"].items():
                    found.get(metric, set()).add(reason)
    reasons = {spec.heading: "; ".join(sorted(found[spec.metric])) or spec.reason(None)
               for spec in PAPER_WEIGHTS if spec.metric not in computed}
    return {**reasons, **PAPER_ONLY}


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
    columns = VIDEO_COLUMNS + PAPER_COLUMNS
    header = ["Method", *(name for _, name, _ in columns), *PAPER_ONLY]
    rows, values = [], []
    if not df.empty:
        for (variant, backend), sub in df.groupby(["variant", "backend"], sort=False):
            vals = [_mean(list(sub[key])) if key in sub else math.nan for key, _, _ in columns]
            values.append(vals)
            rows.append([method_label(labels.get(variant, variant), backend), *map(_cell, vals),
                         *("n/a" for _ in PAPER_ONLY)])
    best = []
    for vals in values:
        flags = [False]
        for col, (key, _, higher) in enumerate(columns):
            column = [v[col] for v in values if not math.isnan(v[col])]
            x = vals[col]
            flags.append(len(column) > 1 and not math.isnan(x) and x == (max(column) if higher else min(column)))
        best.append(flags + [False] * len(PAPER_ONLY))
    for backend, reason in backends_missing.items():
        rows.append([f"(not run) {BACKEND_LABELS.get(backend, backend)}: {reason}",
                     *("n/a" for _ in columns), *("n/a" for _ in PAPER_ONLY)])
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
    columns = VIDEO_COLUMNS + tuple(c for c in PAPER_COLUMNS if c[0] in df and df[c[0]].notna().any())
    values = {}
    for variant, backend in methods:
        for key, _, _ in columns:
            vals = [float(table.loc[(variant, backend, o), key]) if (variant, backend, o) in table.index else math.nan
                    for o in objects]
            values[(variant, backend, key)] = vals + [_mean(vals)]
    rows, best = [], []
    for variant, backend in methods:
        for key, name, higher in columns:
            vals = values[(variant, backend, key)]
            rows.append([method_label(labels.get(variant, variant), backend), name, *map(_cell, vals)])
            flags = [False, False]
            for col, x in enumerate(vals):
                column = [values[(v, b, key)][col] for v, b in methods if not math.isnan(values[(v, b, key)][col])]
                flags.append(len(methods) > 1 and not math.isnan(x) and len(column) > 1
                             and x == (max(column) if higher else min(column)))
            best.append(flags)
    return header, rows, best


