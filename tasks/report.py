"""Run reports: the per-task table, per-object control plots, and where every artifact lives.

Writes ``<report_dir>/report.md``, ``index.html`` (self-contained: images embedded, opens offline),
``tasks.csv`` and one PNG per object.  Pure functions of artifacts; the flow calls :func:`write_run_report`.
"""
from __future__ import annotations

import base64
import html
import json
import subprocess
from pathlib import Path
from typing import Any, Mapping, Optional

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from conf.schema import FINGERS  # noqa: E402
from tasks.artifacts import ArtifactError, ArtifactRef, read_artifact  # noqa: E402


def code_revision() -> str:
    """The git revision of the code that produced the run (``unknown`` outside a checkout)."""
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                             cwd=Path(__file__).parent, timeout=5)
        dirty = subprocess.run(["git", "status", "--porcelain"], capture_output=True, text=True,
                               cwd=Path(__file__).parent, timeout=5)
        return rev.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "") if rev.returncode == 0 else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def control_figure(obj: str, refs: Mapping[str, Optional[ArtifactRef]], path: Path) -> Optional[Path]:
    """Flexion, force coefficients (eq. 1) and contact patch area (eq. 2) per finger over time."""
    try:
        frames = read_artifact(refs["signal_smoothing"])
        forces = read_artifact(refs["force_coefficients"])
        patches = read_artifact(refs["contact_patches"])
    except (KeyError, TypeError, ArtifactError, AttributeError):
        return None
    t = frames["time"]
    fig, axes = plt.subplots(3, 1, figsize=(7.5, 6.6), sharex=True)
    for k, finger in enumerate(FINGERS):
        axes[0].plot(t, frames["flexion_raw"][:, k], color=f"C{k}", alpha=0.3, lw=0.8)
        axes[0].plot(t, frames["flexion"][:, k], color=f"C{k}", label=finger)
        axes[1].plot(t, forces["force_coefficients"][:, k], color=f"C{k}")
        axes[2].plot(t, patches["patch_areas"][:, k] * 1e4, color=f"C{k}")
    axes[0].set_ylabel("flexion (1)\nfaint: resampled raw")
    axes[1].set_ylabel("force coeff. c (1)")
    axes[2].set_ylabel("patch area (cm$^2$)")
    axes[2].set_xlabel("time (s)")
    axes[0].legend(ncol=5, fontsize=8, loc="upper right")
    axes[0].set_title(f"{obj}: squeezing control mapping")
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _embed(png: Path) -> str:
    return "data:image/png;base64," + base64.b64encode(png.read_bytes()).decode()


def write_run_report(report_dir: Path, *, cfg: Mapping[str, Any], table, refs: Mapping[str, Mapping[str, Any]],
                     wall_seconds: float, sections: Optional[list[tuple[str, str]]] = None) -> Path:
    """Write the report folder for one flow run and return the path of ``report.md``.

    ``sections`` are extra (title, markdown) blocks contributed by later stages.
    """
    report_dir = Path(report_dir)
    report_dir.mkdir(parents=True, exist_ok=True)
    df = table.frame()
    df.to_csv(report_dir / "tasks.csv", index=False)
    (report_dir / "config.json").write_text(json.dumps(cfg, indent=2, default=str))
    revision = code_revision()
    figures: dict[str, Path] = {}
    for obj, obj_refs in refs.items():
        png = control_figure(obj, obj_refs, report_dir / f"{obj}_control.png")
        if png:
            figures[obj] = png

    md = [f"# VirSqueezer run `{report_dir.name}`", "",
          f"- wall time: {wall_seconds:.1f} s; tasks: {table.summary()}",
          f"- code revision: `{revision}`; config: `config.json`", "",
          "## Per-task table", "", "```", table.to_text(), "```", ""]
    for title, body in sections or []:
        md += [f"## {title}", "", body, ""]
    md += ["## Objects", ""]
    for obj in refs:
        md.append(f"### {obj}")
        if obj in figures:
            md.append(f"![{obj} control]({figures[obj].name})")
        md.append("")
        md.append("| step | artifact |")
        md.append("|---|---|")
        for step, ref in refs[obj].items():
            md.append(f"| {step} | `{ref.path if ref else '(not produced)'}` |")
        md.append("")
    (report_dir / "report.md").write_text("\n".join(md))

    body = [f"<h1>VirSqueezer run {html.escape(report_dir.name)}</h1>",
            f"<p>wall time {wall_seconds:.1f} s; tasks: {html.escape(table.summary())}; code revision "
            f"<code>{html.escape(revision)}</code></p>",
            "<h2>Per-task table</h2>", df.drop(columns=["artifact"]).to_html(index=False, float_format="%.2f")]
    for title, text in sections or []:
        body += [f"<h2>{html.escape(title)}</h2>", f"<pre>{html.escape(text)}</pre>"]
    body.append("<h2>Objects</h2>")
    for obj in refs:
        body.append(f"<h3>{html.escape(obj)}</h3>")
        if obj in figures:
            body.append(f'<img alt="{html.escape(obj)}" src="{_embed(figures[obj])}" style="max-width:800px">')
        body.append("<ul>" + "".join(
            f"<li>{html.escape(step)}: <code>{html.escape(ref.path if ref else '(not produced)')}</code></li>"
            for step, ref in refs[obj].items()) + "</ul>")
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>VirSqueezer report</title>"
            "<style>body{font-family:sans-serif;max-width:1000px;margin:auto}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:2px 6px;font-size:13px}</style></head><body>"
            + "\n".join(body) + "</body></html>")
    (report_dir / "index.html").write_text(page)
    return report_dir / "report.md"
