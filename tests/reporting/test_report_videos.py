"""The report a researcher watches: every video decodes to the rendered frame count and the tiled size, the
overview and the synced control plot are in the page (a real flow run on the real engine, tiny sizes)."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from tests.small_runs import SMALL


@pytest.fixture(scope="module")
def tomato_artifacts(tmp_path_factory) -> Path:
    """The tomato's whole chain (full variant) computed once for the report builds below; each test works on its
    own copy (the builds write their media cache into it), where the chain is then reused from disk."""
    from flows.pipeline import run_object_local
    from tests.conftest import compose

    root = tmp_path_factory.mktemp("tomato") / "artifacts"
    cfg = compose("evaluate", [f"paths.artifacts={root}", "object=tomato", "variant=full", *SMALL])
    run_object_local(cfg, cfg.object, cfg.variant, root)
    return root


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


def test_a_second_report_build_encodes_nothing_and_gives_the_same_page(tmp_path, compose_cfg, monkeypatch,
                                                                       tomato_artifacts):
    """Report media are cached by content under <artifacts>/.media: the second build of the same artifacts
    reuses every video and figure (no encoder call, cache files untouched) and writes a byte-identical page."""
    import tasks.reporting.watch as watch
    from flows.pipeline import PER_BACKEND, PER_OBJECT, PER_VARIANT, run_object_local
    from flows.runtime import RunTable
    from tasks.reporting.report import write_run_report

    cfg = compose_cfg("evaluate", [f"paths.artifacts={tmp_path / 'artifacts'}", "object=tomato", "variant=full",
                                   *SMALL])
    shutil.copytree(tomato_artifacts, tmp_path / "artifacts")
    flat = run_object_local(cfg, cfg.object, cfg.variant, tmp_path / "artifacts")
    assert all(ref.reused for ref in flat.values())
    pick = lambda steps: {s.name: flat[s.name] for s in steps if s.name in flat}  # noqa: E731
    refs = {"tomato": {**pick(PER_OBJECT), "variants": {"full": {**pick(PER_VARIANT),
                                                                  "backends": {"physics": pick(PER_BACKEND)}}}}}
    encoded = []
    real_encode = watch.encode_video
    monkeypatch.setattr(watch, "encode_video", lambda *a, **k: encoded.append(a[1]) or real_encode(*a, **k))
    cache = tmp_path / "artifacts" / ".media"

    def build() -> tuple[bytes, bytes]:
        report = write_run_report(tmp_path / "report", cfg={}, table=RunTable(), refs=refs, wall_seconds=1.0,
                                  variants={"full": "Full"}, media_cache=cache).parent
        return (report / "index.html").read_bytes(), (report / "tomato_full_stages.mp4").read_bytes()

    first = build()
    assert len(encoded) == 2  # the stages and the final video of the one scene
    entries = {p.name: p.stat().st_mtime_ns for p in cache.iterdir()}
    assert len(entries) >= 7 and not any(n.startswith(".") for n in entries)  # 2 videos, 5+ figures, no temp left
    assert build() == first  # byte-identical page and videos
    assert len(encoded) == 2, "the second build encoded a video again"
    assert {p.name: p.stat().st_mtime_ns for p in cache.iterdir()} == entries  # nothing redrawn


def test_scene_media_made_on_a_worker_are_the_report_s_own(tmp_path, compose_cfg, monkeypatch, tomato_artifacts):
    """The media of a scene made ahead (as the flow does on its task runner while other scenes still simulate)
    are exactly those a report build makes: same cache entries, and the report build then encodes no video and
    draws only the metric bars (which need every variant's metrics)."""
    import tasks.reporting.watch as watch
    from flows.pipeline import PER_BACKEND, PER_OBJECT, PER_VARIANT, run_object_local
    from flows.runtime import RunTable
    from tasks.reporting.report import cache_scene_media, write_run_report

    root = tmp_path / "artifacts"
    cfg = compose_cfg("evaluate", [f"paths.artifacts={root}", "object=tomato", "variant=full", *SMALL])
    shutil.copytree(tomato_artifacts, root)
    flat = run_object_local(cfg, cfg.object, cfg.variant, root)
    assert all(ref.reused for ref in flat.values())
    pick = lambda steps: {s.name: flat[s.name] for s in steps if s.name in flat}  # noqa: E731
    refs = {"tomato": {**pick(PER_OBJECT), "variants": {"full": {**pick(PER_VARIANT),
                                                                  "backends": {"physics": pick(PER_BACKEND)}}}}}

    def build(name: str) -> Path:
        return write_run_report(tmp_path / name, cfg={}, table=RunTable(), refs=refs, wall_seconds=1.0,
                                variants={"full": "Full"}, media_cache=root / ".media").parent

    build("reference")  # every medium made by the report build itself
    made_by_report = {p.name for p in (root / ".media").iterdir()}
    shutil.rmtree(root / ".media")
    # a second variant's task makes its scene's media alone (the object's own go with the first variant): stages
    # and final videos, rollout, snapshots, the released material's flight and the refinement figure
    assert cache_scene_media("tomato", refs["tomato"], "full", str(root), first=False) == 6
    # the first variant's task adds the object's own (signals, control, contact sheet): all but the scene's 6 and the
    # metric bars
    assert cache_scene_media("tomato", refs["tomato"], "full", str(root), first=True) == len(made_by_report) - 7
    ahead = {p.name for p in (root / ".media").iterdir()}
    encoded = []
    real_encode = watch.encode_video
    monkeypatch.setattr(watch, "encode_video", lambda *a, **k: encoded.append(a[1]) or real_encode(*a, **k))
    report = build("report")
    assert encoded == [], "the report build encoded a video the scene's media task had made"
    assert {p.name for p in (root / ".media").iterdir()} - ahead == made_by_report - ahead and \
        len(made_by_report - ahead) == 1  # the metric bars
    assert (report / "index.html").read_text().count("<video") == 2
    for medium in ("tomato_full_stages.mp4", "tomato_full_final.mp4", "tomato_contact_sheet.png"):
        assert (report / medium).read_bytes() == (tmp_path / "reference" / medium).read_bytes()


def test_an_object_whose_first_variant_failed_still_gets_its_media(tmp_path, compose_cfg, tomato_artifacts):
    """A variant whose simulation failed (its rollout raised, e.g. the energy guard) leaves no G-buffer; the object's
    contact sheet and videos then come from the variant that was rendered (the report of a main job whose rubber
    duck's full rollout failed crashed on the missing G-buffer of its first variant: TypeError)."""
    from flows.pipeline import PER_BACKEND, PER_OBJECT, PER_VARIANT, run_object_local
    from flows.runtime import RunTable
    from tasks.reporting.report import write_run_report

    root = tmp_path / "artifacts"
    cfg = compose_cfg("evaluate", [f"paths.artifacts={root}", "object=tomato", "variant=full", *SMALL])
    shutil.copytree(tomato_artifacts, root)
    flat = run_object_local(cfg, cfg.object, cfg.variant, root)
    pick = lambda steps: {s.name: flat[s.name] for s in steps if s.name in flat}  # noqa: E731
    full = {**pick(PER_VARIANT), "backends": {"physics": pick(PER_BACKEND)}}
    failed = {k: v for k, v in full.items() if k not in ("mpm_rollout", "gbuffer", "backends")}
    refs = {"tomato": {**pick(PER_OBJECT), "variants": {"no_dirichlet": failed, "full": full}}}
    report = write_run_report(tmp_path / "report", cfg={}, table=RunTable(), refs=refs, wall_seconds=1.0,
                              variants={"no_dirichlet": "w/o Dirichlet", "full": "Full"}).parent
    assert (report / "tomato_contact_sheet.png").stat().st_size > 0
    assert (report / "tomato_full_final.mp4").exists() and not (report / "tomato_no_dirichlet_final.mp4").exists()
