"""Error against run time of the render and effect knobs (issue 14): the error measures on known answers, the
tables a reader sees (default, reference and this run marked; diffusion steps stated as not measured), the run
report's section, and one tiny real study through the cached steps."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tasks.reporting.render_knobs import SECTION_TITLE, report_section
from tasks.verification.render_convergence import (
    DIFFUSION_NOTE,
    held_frames,
    image_errors,
    knob_row,
    knob_tables,
    resized,
    write_study,
)

REPO = Path(__file__).resolve().parents[2]


def _study(overrides: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``python -m flows.studies.render_convergence`` with ``overrides``."""
    return subprocess.run([sys.executable, "-m", "flows.studies.render_convergence", *overrides], cwd=cwd,
                          env=dict(os.environ, PYTHONPATH=str(REPO)), capture_output=True, text=True, timeout=900)


def test_image_errors_of_a_known_offset_and_of_identical_images():
    a = np.full((2, 3, 8, 8, 3), 100, np.uint8)
    assert image_errors(a, a) == {"rgb_error": 0.0, "psnr_db": math.inf}
    b = a + np.uint8(51)  # 0.2 in [0, 1]
    e = image_errors(b, a)
    assert e["rgb_error"] == pytest.approx(0.2) and e["psnr_db"] == pytest.approx(10 * math.log10(1 / 0.04))
    region = np.zeros(a.shape[:-1], bool)
    region[:, :, :2] = True
    c = a.copy()
    c[:, :, 4:] = 0  # differs only outside the region
    assert image_errors(c, a, region)["rgb_error"] == 0.0
    assert math.isnan(image_errors(c, a, np.zeros_like(region))["rgb_error"])
    with pytest.raises(ValueError, match="cannot be compared"):
        image_errors(a[:, :, :4], a)


def test_resized_keeps_a_flat_image_and_a_horizontal_ramp():
    flat = np.full((1, 2, 4, 4, 3), 77, np.uint8)
    assert (resized(flat, 8, 8) == 77).all() and resized(flat, 8, 8).shape == (1, 2, 8, 8, 3)
    ramp = np.repeat(np.repeat(np.arange(0, 256, 32, dtype=np.uint8)[None, :, None], 8, 0), 3, 2)[None, None]
    up = resized(ramp, 16, 16)[0, 0, :, :, 0].astype(int)
    assert (np.diff(up, axis=1) >= 0).all() and (up == up[:1]).all()  # still increasing in x, constant in y


def test_held_frames_show_the_latest_rendered_frame():
    rgb = np.arange(3)[None, :, None, None, None] * np.ones((2, 3, 1, 1, 3), np.uint8)  # frame k has value k
    shown = held_frames(rgb, [0, 2, 4], [0, 1, 2, 3, 4, 5])
    assert shown[0, :, 0, 0, 0].tolist() == [0, 0, 1, 1, 2, 2]
    with pytest.raises(ValueError, match="start after"):
        held_frames(rgb, [1, 3, 5], [0, 1])


def _rows():
    return [knob_row("resolution", w, s, {"rgb_error": e, "psnr_db": p}, default=192, reference=384, frames=46)
            for w, s, e, p in ((96, 1.0, 0.03, 25.0), (192, 2.5, 0.01, 33.0), (384, 8.0, 0.0, math.inf))] + [
        knob_row("refinement", n, s, {"rgb_error": e, "psnr_db": 30.0}, default=60, reference=240, loss_train=0.1,
                 loss_held_out=math.nan) for n, s, e in ((0, 0.5, 0.08), (60, 6.0, 0.01), (240, 24.0, 0.0))]


def test_tables_mark_the_default_the_reference_and_this_run():
    md = knob_tables(_rows(), {"resolution": 96, "refinement": 60})
    assert "**render.width = render.height (px)**" in md and "time: the `gbuffer` step" in md
    assert "| 192 (default) | 2.5 | 0.01 | 33 | 46 |" in md
    assert "| 384 (reference) | 8 | 0 | inf | 46 |" in md
    assert "| 96 (this run) | 1 | 0.03 | 25 | 46 |" in md
    assert "| 60 (default) | 6 | 0.01 | 30 | 0.1 | - |" in md  # held-out loss not available: "-"
    assert "frame_stride" not in md  # a knob without rows has no table
    assert md.endswith(f"- {DIFFUSION_NOTE}") and "not measured: needs weights" in DIFFUSION_NOTE


def test_the_run_report_section_reads_the_latest_study(tmp_path):
    assert report_section({}) is None
    cfg = {"paths": {"reports": str(tmp_path)}, "render": {"width": 192, "frame_stride": 2},
           "refinement": {"iterations": 60}}
    title, text = report_section(cfg)  # no study here yet: the study of record shipped with the code
    assert title == SECTION_TITLE and text.startswith("From the study of record shipped with the code "
                                                      "(`render_knobs_measured.json`); no study in this reports folder")
    assert "| 192 (default) |" in text and "| 2 (default) |" in text and "| 60 (default) |" in text
    path = write_study(tmp_path / "render_convergence" / "tomato-1", _rows(), {"object": "tomato", "variant": "full",
                                                                               "written": "today", "machine": "x"})
    assert json.loads(path.read_text())["rows"][2]["psnr_db"] == math.inf
    assert "| 192 (default) |" in (path.parent / "render_knobs.md").read_text()
    _, text = report_section(cfg)
    assert text.startswith(f"From `{path}` (tomato, full; written today; x).")
    assert "| 192 (default) | 2.5 |" in text and "(this run)" not in text


# ------------------------------------------------------------------------------------------ the real flow, tiny
TINY = ["object=tomato", "sampling.surface_points=600", "sampling.particle_spacing=0.004", "signal.duration=1.5",
        "control.smoothing.frame_rate=15", "mpm.target_substeps_per_frame=10", "render.views=2", "render.width=24",
        "render.height=24", "render.frame_stride=2", "refinement.iterations=2", "render_study.resolutions=[16,24,32]",
        "render_study.frame_strides=[1,2]", "render_study.refinement_iterations=[0,2,4]"]


def test_a_tiny_study_measures_every_knob_and_a_rerun_is_cached(tmp_path):
    overrides = [f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}", "run_name=tiny",
                 *TINY]
    out = _study(overrides, tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    path = tmp_path / "reports" / "render_convergence" / "tiny" / "render_knobs.json"
    rows = json.loads(path.read_text())["rows"]
    by = {(r["knob"], r["setting"]): r for r in rows}
    assert sorted(by) == [("frame_stride", 1), ("frame_stride", 2), ("refinement", 0), ("refinement", 2),
                          ("refinement", 4), ("resolution", 16), ("resolution", 24), ("resolution", 32)]
    for ref in (("resolution", 32), ("frame_stride", 1), ("refinement", 4)):
        assert by[ref]["reference"] and by[ref]["rgb_error"] == 0.0
    assert by[("resolution", 24)]["default"] and by[("frame_stride", 2)]["default"] and by[("refinement", 2)]["default"]
    assert 0 < by[("resolution", 16)]["rgb_error"] < 0.2 and 0 < by[("frame_stride", 2)]["rgb_error"] < 0.2
    assert by[("refinement", 0)]["rgb_error"] > 0 and all(r["seconds"] > 0 for r in rows)
    assert by[("frame_stride", 2)]["frames"] * 2 - 1 <= by[("frame_stride", 1)]["frames"]
    assert _study(overrides, tmp_path).returncode == 0
    again = json.loads(path.read_text())["rows"]
    assert [r["seconds"] for r in again] == [r["seconds"] for r in rows]  # served from the cache, same times


def test_a_bad_setting_list_is_one_line_naming_the_key(tmp_path):
    out = _study([f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}",
                  "render_study.resolutions=[8,64]"], tmp_path)
    assert out.returncode == 1 and out.stderr.strip().splitlines()[-1] == (
        "config error: render_study.resolutions must list at least two distinct values >= 16, got [8, 64]")
    assert not (tmp_path / "artifacts").exists()  # refused before any work
