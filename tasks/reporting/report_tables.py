"""Metric tables of a run: the object x variant rows, the paper's Table 2 layout, CSV and parquet.

Pure functions of the ``deformation_metrics`` artifacts (:mod:`tasks.evaluation.deformation_metrics`); the report
(:mod:`tasks.reporting.report`) renders what they return as markdown and HTML.
"""
from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from tasks.core.artifacts import ArtifactError, read_group_attrs
from tasks.core.scope import split_seed_scope

# (column in the metrics rows, heading in the tables, higher is better)
TABLE2 = (("bdc_t", "BDC-T", True), ("bdc_s", "BDC-S", True), ("sdc", "SDC", True), ("miou", "mIoU", True))
TRAJECTORY = (("ate", "ATE (mm)", False), ("mte", "MTE (mm)", False), ("tce", "TCE (mm/s)", False),
              ("cosine_similarity", "Cosine sim.", True))
_MILLI = {"ate", "mte", "tce"}  # shown in mm (mm/s); stored in SI


def metric_rows(refs: Mapping[str, Mapping[str, Any]]) -> pd.DataFrame:
    """One row per (object, seed, variant) with a column per metric (SI units, NaN where undefined)."""
    rows = []
    for key, obj_refs in refs.items():
        obj, seed = split_seed_scope(key)
        for variant, vrefs in obj_refs.get("variants", {}).items():
            ref = vrefs.get("deformation_metrics")
            if ref is None:
                continue
            try:
                metrics = read_group_attrs(ref.path)["attrs"]["metrics"]
            except (ArtifactError, KeyError):
                continue
            rows.append({"object": obj, "seed": seed, "variant": variant,
                         **{k: (math.nan if v is None else float(v)) for k, v in metrics.items()}})
    return pd.DataFrame(rows)


def force_match_note(refs: Mapping[str, Mapping[str, Any]], labels: Mapping[str, str]) -> Optional[str]:
    """Table 2's note on the ablation's input strength: for each force-matched variant (its rollout's
    ``force_calibration`` attribute, :mod:`tasks.physics.force_matched_rollout`) the calibrated K per object and its
    peak indentation against the prescribed one; None when no variant is force-matched."""
    found: dict[str, list[str]] = {}
    rtol: dict[str, float] = {}
    for key, obj_refs in refs.items():
        for variant, vrefs in obj_refs.get("variants", {}).items():
            ref = vrefs.get("mpm_rollout")
            try:
                cal = read_group_attrs(ref.path)["attrs"].get("force_calibration") if ref is not None else None
            except ArtifactError:
                cal = None
            if not cal:
                continue
            reached = cal.get("reached_indentation")
            rtol[variant] = float(cal["rtol"])
            found.setdefault(variant, []).append(
                f"{key} K {cal['force_per_coefficient']:.4g} N (peak {reached if reached is None else f'{reached:.3f}'}"
                f" / {cal['target_indentation']:.3f}{'' if cal['converged'] else ', not converged'})")
    if not found:
        return None
    return " ".join(
        f"Input strength: {labels.get(v, v)} is force-matched: its push's constant K (N per unit eq. 1 coefficient) is "
        f"calibrated per object so that its peak indentation under the fingers, up to the prescribed peak's frame, "
        f"equals the prescribed one (the full method's), within {100 * rtol[v]:g} %: the same input strength, reached by "
        f"force instead of imposed; " + "; ".join(items) + "." for v, items in found.items())


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
    """``metrics.csv`` and ``metrics.parquet`` (columns ``object``, ``seed``, ``variant``, one per metric; one row
    per seed)."""
    if df.empty:
        return []
    csv, parquet = Path(report_dir) / "metrics.csv", Path(report_dir) / "metrics.parquet"
    df.to_csv(csv, index=False)
    df.to_parquet(parquet, index=False)
    return [csv, parquet]


def seed_statistics(df: pd.DataFrame, variant: str, key: str, objects: Sequence[str],
                    averaged: Optional[Sequence[str]] = None) -> tuple[list[float], list[float], int]:
    """Per object, then for the average over the objects: the mean and the sample standard deviation (ddof 1; NaN
    with one seed) of metric ``key`` of ``variant`` over the seeds that ran, and the number of seeds.  The Avg.
    column is the mean over the objects ``averaged`` (default: those where the metric is defined), taken per seed,
    then over the seeds."""
    sub = df[df["variant"] == variant] if len(df) else df
    seeds = sorted(set(sub["seed"])) if len(sub) else []
    per_seed = np.full((max(len(seeds), 1), len(objects) + 1), np.nan)
    for i, seed in enumerate(seeds):
        rows = sub[sub["seed"] == seed].set_index("object")
        for j, obj in enumerate(objects):
            if obj in rows.index and key in rows.columns:
                per_seed[i, j] = float(rows.loc[obj, key])
        row = per_seed[i, :-1] if averaged is None else per_seed[i, [objects.index(o) for o in averaged]]
        finite = row[np.isfinite(row)]
        per_seed[i, -1] = finite.mean() if len(finite) else np.nan
    counts = np.isfinite(per_seed).sum(axis=0)
    means = [float(np.nanmean(c)) if n else math.nan for c, n in zip(per_seed.T, counts)]
    stds = [float(np.nanstd(c, ddof=1)) if n > 1 else math.nan for c, n in zip(per_seed.T, counts)]
    return means, stds, len(seeds)


def within_spread(mean_a: float, std_a: float, mean_b: float, std_b: float) -> bool:
    """Whether two variants' means differ by no more than the seed spread of a single-seed difference,
    ``|mean_a - mean_b| <= sqrt(std_a^2 + std_b^2)`` (False when either spread is unknown)."""
    spread = math.hypot(std_a, std_b)
    return math.isfinite(spread) and abs(mean_a - mean_b) <= spread


def paper_layout(df: pd.DataFrame, metrics: Sequence[tuple[str, str, bool]], objects: Sequence[str],
                 labels: Mapping[str, str]) -> tuple[list[str], list[list[str]], list[list[bool]]]:
    """The paper's Table 2 shape: rows (method, metric), columns objects + Avg.

    Returns the header, the cell texts and, per cell, whether it is the best value of its metric and column
    across variants (bold in the paper).  Avg is the mean over the objects where every variant has the metric (a
    value without counterpart is no comparison), marked ``(n of N)`` when that is not every object.  With
    more than one seed a cell is ``mean ± std`` over the seeds (:func:`seed_statistics`) and the best is taken on
    the means; a cell marked ``≈`` is within the seed spread of the best variant's (:func:`within_spread`): that
    difference is not resolved by the seeds that ran."""
    header = ["Method", "Metric", *objects, "Avg."]
    if df.empty:
        return header, [], []
    df = df if "seed" in df.columns else df.assign(seed=0)
    variants = [v for v in labels if v in set(df["variant"])]
    defined = {(v, key): seed_statistics(df, v, key, objects)[0][:-1] for v in variants for key, _, _ in metrics}
    common = {key: [o for j, o in enumerate(objects) if all(math.isfinite(defined[(v, key)][j]) for v in variants)]
              for key, _, _ in metrics}
    stats = {(v, key): seed_statistics(df, v, key, objects, common[key]) for v in variants for key, _, _ in metrics}
    rows, best = [], []
    for v in variants:
        for key, name, higher in metrics:
            means, stds, n_seeds = stats[(v, key)]
            scale = 1e3 if key in _MILLI else 1.0
            cells, flags = [], [False, False]
            for col, (x, sd) in enumerate(zip(means, stds)):
                others = {w: (stats[(w, key)][0][col], stats[(w, key)][1][col]) for w in variants
                          if math.isfinite(stats[(w, key)][0][col])}
                top = (max if higher else min)(others, key=lambda w: others[w][0]) if others else None
                flags.append(len(variants) > 1 and math.isfinite(x) and len(others) > 1 and x == others[top][0])
                text = "-" if not math.isfinite(x) else f"{scale * x:.3f}"
                if n_seeds > 1 and math.isfinite(x):
                    text += f" ± {scale * sd:.3f}" if math.isfinite(sd) else " ± -"
                    rivals = [w for w in others if w != top] if v == top else [top]
                    if any(within_spread(x, sd, *others[w]) for w in rivals):
                        text += " ≈"
                cells.append(text)
            if len(common[key]) < len(objects) and math.isfinite(means[-1]):
                cells[-1] += f" ({len(common[key])} of {len(objects)})"
            rows.append([labels[v], name, *cells])
            best.append(flags)
    return header, rows, best


def with_paper_rows(title: str, header: list[str], rows: list[list[str]], best: list[list[bool]],
                    objects: Sequence[str]) -> tuple[str, list[str], list[list[str]], list[list[bool]]]:
    """A Table 2 (``title``, header, rows, bold flags) with the paper's Table 2 appended as a reference block
    labelled "paper (their metric definitions are not published)", in our object columns, never bold."""
    from tasks.reporting.paper_reference import TABLE2 as PAPER_TABLE2
    from tasks.reporting.paper_reference import object_rows

    paper, flags = object_rows(PAPER_TABLE2, objects)
    return title, header, list(rows) + paper, list(best) + flags


def seed_note(df: pd.DataFrame) -> Optional[str]:
    """The caption line of a table of several seeds' runs (None with one seed)."""
    seeds = sorted(set(df["seed"])) if len(df) and "seed" in df.columns else []
    if len(seeds) < 2:
        return None
    return (f"Mean ± sample standard deviation over {len(seeds)} sampling seeds {seeds} (Avg.: the mean over the "
            "objects per seed, then over the seeds); bold: best mean; ≈: the difference to the best variant in that "
            "column is within the seed spread (|Δ mean| <= sqrt(std_a² + std_b²)), i.e. not resolved by these seeds.")


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
