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
from tasks.evaluation.paper_weights import PAPER_WEIGHTS, RATING_COLUMN
from tasks.reporting.paper_reference import TABLE3 as PAPER_TABLE3
from tasks.reporting.paper_reference import object_rows, table1_rows

# (column, heading, higher is better)
VIDEO_COLUMNS = (
    ("temporal_flicker", "Temporal flicker", True),
    ("motion_smoothness", "Motion smoothness (RIFE/DIS interp.)", True),
    ("imaging_quality_brisque", "Imaging quality (BRISQUE proxy)", True),
    ("outside_mask_psnr_db", "Fidelity outside mask PSNR (dB) = render by construction", True),
    ("outside_mask_ssim", "Fidelity outside mask SSIM = render by construction", True),
    ("effect_placement_iou", "Effect placement IoU", True),
    ("multiview_psnr_db_initial", "Multi-view PSNR, held-out views, refined mask, 0 iterations (dB)", True),
    ("multiview_psnr_db", "Multi-view PSNR, held-out views, refined mask, after eq. 7 (dB)", True),
    ("multiview_psnr_gain_db", "Multi-view PSNR gain of eq. 7 (dB)", True),
    ("control_coupling_pearson", "Control coupling (Pearson)", True),
    ("llm_visual_quality", "LLM visual quality (1-5)", True),
    ("llm_motion_realism", "LLM motion realism (1-5)", True),
    ("llm_motion_consistency", "LLM motion consistency (1-5)", True),
)
# columns that equal the render by construction for every backend that composites it back outside the mask (the
# physics effect, diffusers): never bolded, never a win (only text_only paints outside the mask)
BY_CONSTRUCTION = frozenset({"outside_mask_psnr_db", "outside_mask_ssim"})
# the paper's metrics computed where their weights are present (tasks.evaluation.paper_metrics); the VideoPhy-2
# rater's mean 1-5 rating follows its [0, 1] share
PAPER_COLUMNS = tuple(c for spec in PAPER_WEIGHTS for c in (
    ((spec.metric, spec.heading, True),) + ((RATING_COLUMN + (True,),) if spec.metric == "physical_commonsense" else ())))
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
                metrics.update({k: math.nan for k, _, _ in VIDEO_COLUMNS if k not in metrics})  # older artifacts
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


def per_object(df: pd.DataFrame, key: str) -> dict[tuple[str, str], dict[str, float]]:
    """(variant, backend) -> object -> metric ``key`` (mean over the seeds; NaN where it does not apply)."""
    out: dict[tuple[str, str], dict[str, float]] = {}
    if df.empty:
        return out
    for (variant, backend), sub in df.groupby(["variant", "backend"], sort=False):
        vals = sub[key] if key in sub else pd.Series(math.nan, index=sub.index)
        out[(variant, backend)] = {o: _mean(list(v)) for o, v in vals.groupby(sub["object"], sort=False)}
    return out


def common_objects(values: Mapping[tuple[str, str], Mapping[str, float]]) -> list[str]:
    """The objects where every compared method has a value (a cell without counterpart is no comparison)."""
    methods = list(values.values())
    if not methods:
        return []
    return [o for o in methods[0] if all(not math.isnan(m.get(o, math.nan)) for m in methods)]


def _best_flags(vals: list[float], higher: bool, key: str) -> list[bool]:
    """Best of a column of ``vals`` (one per method): only when every method has a value, the column is not true by
    construction, and there is more than one method."""
    if key in BY_CONSTRUCTION or len(vals) < 2 or any(math.isnan(x) for x in vals):
        return [False] * len(vals)
    top = max(vals) if higher else min(vals)
    return [x == top for x in vals]


def table1(df: pd.DataFrame, labels: Mapping[str, str], backends_missing: Mapping[str, str]
           ) -> tuple[list[str], list[list[str]], list[list[bool]]]:
    """Table 1 layout: one row per method that ran, each column the mean over the objects where *every* method has
    a value (the last row counts them), bold the best only where every method has one and never in a column true
    by construction; then the methods that could not run with the reason, and the paper's rows (never bold)."""
    columns = VIDEO_COLUMNS + PAPER_COLUMNS
    header = ["Method", *(name for _, name, _ in columns), *PAPER_ONLY]
    rows, best = [], []
    if not df.empty:
        methods = list(dict.fromkeys(zip(df["variant"], df["backend"])))
        table = {m: [] for m in methods}
        counts = []
        for key, _, higher in columns:
            values = per_object(df, key)
            common = common_objects(values)
            means = [_mean([values[m][o] for o in common]) if common else math.nan for m in methods]
            for m, x in zip(methods, means):
                table[m].append(x)
            counts.append(len(common))
            for m, flag in zip(methods, _best_flags(means, higher, key)):
                table[m].append(flag)
        for m in methods:
            vals, flags = table[m][0::2], table[m][1::2]
            rows.append([method_label(labels.get(m[0], m[0]), m[1]), *map(_cell, vals), *("n/a" for _ in PAPER_ONLY)])
            best.append([False, *flags, *(False for _ in PAPER_ONLY)])
        rows.append(["objects averaged (where every method above has a value)", *(str(n) for n in counts),
                     *("-" for _ in PAPER_ONLY)])
        best.append([False] * len(header))
    for backend, reason in backends_missing.items():
        rows.append([f"(not run) {BACKEND_LABELS.get(backend, backend)}: {reason}",
                     *("n/a" for _ in columns), *("n/a" for _ in PAPER_ONLY)])
        best.append([False] * len(header))
    paper_rows, paper_best = table1_rows([k for k, _, _ in columns], len(PAPER_ONLY))
    return header, rows + paper_rows, best + paper_best


def table3(df: pd.DataFrame, objects: list[str], labels: Mapping[str, str]
           ) -> tuple[list[str], list[list[str]], list[list[bool]]]:
    """Table 3 layout: rows (method, metric), columns the objects and the average over the objects where every
    method has a value; bold the best per column only where every method has a value (never in a column true by
    construction).  With several seeds a cell is the mean over the seeds (the spread is in Table 2 and in
    ``metrics.csv``).  The paper's Table 3 follows as a reference block (never bold)."""
    header = ["Method", "Metric", *objects, "Avg."]
    paper_rows, paper_best = object_rows(PAPER_TABLE3, objects)
    if df.empty:
        return header, paper_rows, paper_best
    methods = list(dict.fromkeys(zip(df["variant"], df["backend"])))
    columns = VIDEO_COLUMNS + tuple(c for c in PAPER_COLUMNS if c[0] in df and df[c[0]].notna().any())
    values = {}
    for key, _, _ in columns:
        per = per_object(df, key)
        common = common_objects({m: {o: per[m].get(o, math.nan) for o in objects} for m in methods})
        for m in methods:
            vals = [per[m].get(o, math.nan) for o in objects]
            values[(*m, key)] = vals + [_mean([per[m][o] for o in common]) if common else math.nan]
    rows, best = [], []
    for variant, backend in methods:
        for key, name, higher in columns:
            vals = values[(variant, backend, key)]
            rows.append([method_label(labels.get(variant, variant), backend), name, *map(_cell, vals)])
            flags = [False, False]
            for col, x in enumerate(vals):
                column = [values[(v, b, key)][col] for v, b in methods]
                flags.append(_best_flags(column, higher, key)[methods.index((variant, backend))])
            best.append(flags)
    return header, rows + paper_rows, best + paper_best
