"""The run report's section on the render and effect knobs: the latest study of ``python -m
flows.studies.render_convergence`` under the run's reports folder (:mod:`tasks.verification.render_convergence`
writes it), else the study of record shipped with the code, with the default and this run's setting marked.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from tasks.verification.render_convergence import STUDY_DIR, STUDY_FILE, knob_tables

SECTION_TITLE = "Render and effect knobs: error against run time (python -m flows.studies.render_convergence)"
# the study of record (python -m flows.studies.render_convergence on the default tomato), shown where a reports
# folder has none of its own: every report states each setting's time and error
RECORD = Path(__file__).resolve().parents[2] / "conf" / "render_knobs_measured.json"


def latest_study(reports_root: str | Path) -> tuple[Path, dict] | None:
    """The newest ``<reports_root>/render_convergence/*/render_knobs.json`` and its content (None: no study)."""
    found = sorted(Path(reports_root).glob(f"{STUDY_DIR}/*/{STUDY_FILE}"), key=lambda p: p.stat().st_mtime)
    for path in reversed(found):
        try:
            return path, json.loads(path.read_text())
        except (OSError, ValueError):
            continue
    return None


def current_settings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """knob -> the value a run config sets (for marking "this run" in the study's tables)."""
    render, refinement = cfg.get("render") or {}, cfg.get("refinement") or {}
    return {"resolution": render.get("width"), "frame_stride": render.get("frame_stride"),
            "refinement": refinement.get("iterations")}


def report_section(cfg: Mapping[str, Any]) -> tuple[str, str] | None:
    """The run report's (title, markdown): the latest study under the run's ``paths.reports`` (else the study of
    record, ``RECORD``) with the default and this run's setting marked; None without ``paths.reports``."""
    reports_root = (cfg.get("paths") or {}).get("reports")
    if reports_root is None:
        return None
    found = latest_study(reports_root)
    if found is None:
        path, study = RECORD, json.loads(RECORD.read_text())
        source = (f"From the study of record shipped with the code (`{RECORD.name}`); no study in this reports "
                  "folder yet: `python -m flows.studies.render_convergence` measures them on this machine")
    else:
        path, study = found
        source = f"From `{path}`"
    meta = study.get("meta", {})
    return SECTION_TITLE, (f"{source} ({meta.get('object')}, {meta.get('variant')}; written {meta.get('written')}; "
                           f"{meta.get('machine')}).\n\n" + knob_tables(study["rows"], current_settings(cfg)))
