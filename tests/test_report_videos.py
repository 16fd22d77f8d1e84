"""The report a researcher watches: every video decodes to the rendered frame count and the tiled size, the
overview and the synced control plot are in the page (a real flow run on the real engine, tiny sizes)."""
from __future__ import annotations

from pathlib import Path

from test_pipeline_cache import SMALL


def test_each_report_video_decodes_to_the_expected_frames_and_size(prefect_server, tmp_path, compose_cfg):
    from flows.pipeline import run
    from tasks.core.artifacts import read_artifact
    from tasks.reporting.video import decode_video

    cfg = compose_cfg("evaluate", [f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'r'}",
                                   "grid.objects=[tomato]", *SMALL])
    out = run(cfg, "test")
    report = Path(out["report"])
    [g_path] = (tmp_path / "artifacts" / "tomato" / "gbuffer").glob("*.zarr")
    from tasks.core.artifacts import ArtifactRef, read_group_attrs

    g = read_artifact(ArtifactRef(rel=f"tomato/gbuffer/{g_path.name}", digest=read_group_attrs(g_path)["digest"],
                                  step="gbuffer", scope="tomato").at(tmp_path / "artifacts"))
    views, frames, height, width = g["mask"].shape
    final, fps = decode_video(report / "tomato_full_final.mp4")
    assert final.shape == (frames, height, width, 3) and fps == 15 / 5  # 15 Hz frames, every 5th rendered
    stages, _ = decode_video(report / "tomato_full_stages.mp4")
    label_px, columns = 20, 4  # render, conditions, final, refined 4D Gaussians
    assert stages.shape == (frames, views * (label_px + height), columns * width, 3)
    page = (report / "index.html").read_text()
    assert page.count("<video") >= 2 and 'class="plot"' in page and "timeupdate" in page
