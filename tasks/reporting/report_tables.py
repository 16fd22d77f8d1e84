"""Metric tables of a run: the object x variant rows, the paper's Table 2 layout, CSV and parquet.

Pure functions of the ``deformation_metrics`` artifacts (:mod:`tasks.evaluation.deformation_metrics`); the report
(:mod:`tasks.reporting.report`) renders what they return as markdown and HTML.
"""
from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import pandas as pd

from tasks.core.artifacts import ArtifactError, read_group_attrs

# (column in the metrics rows, heading in the tables, higher is better)
TABLE2 = (("bdc_t", "BDC-T", True), ("bdc_s", "BDC-S", True), ("sdc", "SDC", True), ("miou", "mIoU", True))
TRAJECTORY = (("ate", "ATE (mm)", False), ("mte", "MTE (mm)", False), ("tce", "TCE (mm/s)", False),
              ("cosine_similarity", "Cosine sim.", True))
_MILLI = {"ate", "mte", "tce"}  # shown in mm (mm/s); stored in SI


def metric_rows(refs: Mapping[str, Mapping[str, Any]]) -> pd.DataFrame:
    """One row per (object, variant) with a column per metric (SI units, NaN where undefined)."""
    rows = []
    for obj, obj_refs in refs.items():
        for variant, vrefs in obj_refs.get("variants", {}).items():
            ref = vrefs.get("deformation_metrics")
            if ref is None:
                continue
            try:
                metrics = read_group_attrs(ref.path)["attrs"]["metrics"]
            except (ArtifactError, KeyError):
                continue
            rows.append({"object": obj, "variant": variant,
                         **{k: (math.nan if v is None else float(v)) for k, v in metrics.items()}})
    return pd.DataFrame(rows)


def stored_definitions(refs: Mapping[str, Mapping[str, Any]], step: str) -> dict[str, str]:
    """The metric definitions stored with the first ``step`` artifact of a run (per-variant or per-backend; they
    travel with the code version)."""
    for obj_refs in refs.values():
        for vrefs in obj_refs.get("variants", {}).values():
            for chain in (vrefs, *vrefs.get("backends", {}).values()):
                ref = chain.get(step)
                if ref is None:
                    continue
                try:
                    return dict(read_group_attrs(ref.path)["attrs"].get("definitions", {}))
                except ArtifactError:
                    continue
    return {}


def write_metric_files(df: pd.DataFrame, report_dir: Path) -> list[Path]:
    """``metrics.csv`` and ``metrics.parquet`` (columns ``object``, ``variant``, one per metric)."""
    if df.empty:
        return []
    csv, parquet = Path(report_dir) / "metrics.csv", Path(report_dir) / "metrics.parquet"
    df.to_csv(csv, index=False)
    df.to_parquet(parquet, index=False)
    return [csv, parquet]


def paper_layout(df: pd.DataFrame, metrics: Sequence[tuple[str, str, bool]], objects: Sequence[str],
                 labels: Mapping[str, str]) -> tuple[list[str], list[list[str]], list[list[bool]]]:
    """The paper's Table 2 shape: rows (method, metric), columns objects + Avg.

    Returns the header, the cell texts and, per cell, whether it is the best value of its metric and column
    across variants (bold in the paper).  Avg is the mean over the objects where the metric is defined."""
    header = ["Method", "Metric", *objects, "Avg."]
    if df.empty:
        return header, [], []
    table = df.set_index(["variant", "object"])
    variants = [v for v in labels if v in set(df["variant"])]
    values: dict[tuple[str, str], list[float]] = {}
    for v in variants:
        for key, _, _ in metrics:
            vals = [float(table.loc[(v, o), key]) if (v, o) in table.index and key in table.columns else math.nan
                    for o in objects]
            finite = [x for x in vals if math.isfinite(x)]
            vals.append(sum(finite) / len(finite) if finite else math.nan)
            values[(v, key)] = vals
    rows, best = [], []
    for v in variants:
        for key, name, higher in metrics:
            vals = values[(v, key)]
            scale = 1e3 if key in _MILLI else 1.0
            rows.append([labels[v], name, *("-" if not math.isfinite(x) else f"{scale * x:.3f}" for x in vals)])
            flags = [False, False]
            for col, x in enumerate(vals):
                column = [values[(w, key)][col] for w in variants if math.isfinite(values[(w, key)][col])]
                flags.append(len(variants) > 1 and math.isfinite(x) and len(column) > 1
                             and x == (max(column) if higher else min(column)))
            best.append(flags)
    return header, rows, best


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[str]],
                   best: Optional[Sequence[Sequence[bool]]] = None) -> str:
    """A GitHub markdown table; cells flagged in ``best`` are bold."""
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for i, row in enumerate(rows):
        cells = [f"**{c}**" if best is not None and best[i][j] else str(c) for j, c in enumerate(row)]
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out)


def html_table(header: Sequence[str], rows: Sequence[Sequence[str]],
               best: Optional[Sequence[Sequence[bool]]] = None) -> str:
    """The same table as HTML; best cells bold."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = []
    for i, row in enumerate(rows):
        cells = "".join(f"<td><b>{html.escape(str(c))}</b></td>" if best is not None and best[i][j]
                        else f"<td>{html.escape(str(c))}</td>" for j, c in enumerate(row))
        body.append(f"<tr>{cells}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"
