"""The interactive 4D viewer (python -m flows.view) on a tiny cached squeeze of the tomato (it ruptures and releases
its juice): the scene's known answers against the rollout's and the recording's own arrays, the one-line message
for a scene that is not cached, and a real viser server with real clients (a websocket client of viser's protocol,
an HTTP GET of its page and headless Chromium drawing it through SwiftShader)."""
from __future__ import annotations

import asyncio
import shutil
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import numpy as np
import psutil
import pytest

from tests.conftest import REPO, compose

viser = pytest.importorskip("viser", reason="the viewer's extra: pip install -e '.[view]'")

SMALL = ["sampling.surface_points=600", "sampling.particle_spacing=0.004", "signal.duration=1.5",
         "control.smoothing.frame_rate=15", "mpm.target_substeps_per_frame=10", "runner=sequential",
         "render.views=2", "render.width=32", "render.height=32", "render.frame_stride=5"]


def view_config(root: Path, extra: list[str] = ()):
    from conf.view_schema import register_view_config

    register_view_config()
    return compose("view", [f"paths.artifacts={root}", "object=tomato", *SMALL, *extra])


@pytest.fixture(scope="module")
def cached(tmp_path_factory):
    """The tomato's steps up to the rollout, both variants, cached as the flow caches them; the raw artifacts."""
    from flows.pipeline import run_object_local
    from tasks.core.artifacts import read_artifact

    root = tmp_path_factory.mktemp("viewer") / "artifacts"
    cfg = view_config(root)
    refs = {name: run_object_local(cfg, cfg.object, cfg.variants[name], root, until="mpm_rollout")
            for name in ("full", "no_dirichlet")}
    raw = {name: {step: read_artifact(ref) for step, ref in r.items()} for name, r in refs.items()}
    return root, cfg, raw


@pytest.fixture(scope="module")
def scenes(cached):
    from flows.view import load_scenes

    root, cfg, _ = cached
    return load_scenes(cfg, [])


def test_the_viewer_config_finds_the_grids_artifacts():
    """conf/view.yaml repeats the grid's groups: every step reads the same values (same cache keys) as a
    `python -m flows.evaluate` run with the same overrides."""
    from flows.pipeline import STEPS, step_params

    view = view_config(Path("a"), ["variant=no_dirichlet"])
    grid = compose("evaluate", ["paths.artifacts=a", "object=tomato", *SMALL, "variant=no_dirichlet"])
    for step in STEPS:
        assert step_params(step, view, view.object, view.variant) == step_params(step, grid, grid.object, grid.variant), step.name


def test_the_scene_is_the_rollouts_and_the_recordings(cached, scenes):
    from tasks.physics.labels import INTERIOR
    from tasks.reporting.viewer_scene import SPLAT_UNIT, frame_splats, hand_segments

    _, _, raw = cached
    assert [s.label for s in scenes] == ["tomato [Full VirSqueezer]",
                                         "tomato [VirSqueezer w/o Dirichlet Boundary Constraint]"]
    for scene, variant in zip(scenes, ("full", "no_dirichlet")):
        rollout, smoothed = raw[variant]["mpm_rollout"], raw[variant]["signal_smoothing"]
        event = rollout.attrs["threshold_event"]
        released = int((rollout["released"] & (rollout["particle_material"] == INTERIOR)).sum()) if "released" in rollout else 0
        n_surface = len(raw[variant]["object_model"]["gaussian_colors"])
        for frame in range(scene.n_frames):
            splats = frame_splats(scene, frame)
            expected = released if event["crossed"] and frame >= event["frame"] else 0
            assert splats.n_released == expected == int((splats.opacities[n_surface:] > 0).sum())
            assert len(splats.centers) == n_surface + released  # one buffer size for every frame
            np.testing.assert_allclose(splats.centers[:n_surface] * SPLAT_UNIT, rollout["gaussian_positions"][frame],
                                       atol=1e-7)
            np.testing.assert_array_equal(scene.fingertips[frame], smoothed["fingertip_positions"][frame])
            np.testing.assert_array_equal(hand_segments(scene, frame)[:, 1], smoothed["fingertip_positions"][frame])
        assert scene.rupture_frame == (event["frame"] if event["crossed"] else None)
    # the squeeze the test relies on: the full method ruptures the tomato mid-squeeze and releases juice
    assert scenes[0].rupture_frame is not None and 0 < scenes[0].rupture_frame < scenes[0].n_frames - 1
    assert scenes[0].released_visible[-1].sum() > 0


def test_a_scene_not_cached_is_one_line_naming_the_command(tmp_path):
    """Nothing cached under paths.artifacts: exit 2, one line naming the command that makes the artifacts, no
    traceback, nothing computed."""
    root = tmp_path / "empty"
    cmd = [sys.executable, "-m", "flows.view", "object=tomato", "seed=2", "port=0", f"paths.artifacts={root}"]
    out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    assert lines[0].startswith("error: tomato@seed2/object_model is not cached in ")
    assert (f"run `python -m flows.evaluate object=tomato sampling.seed=2 paths.artifacts={root} "
            "grid.variants=[full,no_dirichlet]` first") in lines[0]
    assert not list(root.glob("*/*/*.zarr"))


def _viewer(scenes):
    from tasks.reporting.viewer import SqueezeViewer

    return SqueezeViewer(scenes, host="127.0.0.1", port=0)


async def _receive(url: str, version: str, until: float) -> int:
    """Bytes a websocket client of viser's protocol receives from ``url`` until ``until`` (monotonic s)."""
    import websockets

    got = 0
    async with websockets.connect(url, subprotocols=[f"viser-v{version}"], max_size=None) as ws:
        while time.monotonic() < until:
            try:
                got += len(await asyncio.wait_for(ws.recv(), timeout=max(0.05, until - time.monotonic())))
            except asyncio.TimeoutError:
                break
    return got


def test_a_real_server_serves_the_scene_to_real_clients(scenes):
    viewer = _viewer(scenes)
    try:
        assert viewer.server.get_host() == "127.0.0.1" and viewer.server.get_port() > 0
        with urllib.request.urlopen(viewer.url, timeout=30) as page:
            assert page.status == 200 and b"<html" in page.read(4096).lower()
        # a websocket client receives the whole scene: at least every splat buffer of both scenes (32 B/Gaussian)
        received = asyncio.run(_receive(viewer.url.replace("http", "ws"), viser.__version__, time.monotonic() + 5))
        splat_bytes = sum(32 * len(n.splats.centers) for n in viewer.nodes)
        assert received > splat_bytes > 0
        # the slider moves the served splats: the served buffer holds the new frame's positions
        rupture = scenes[0].rupture_frame
        before = viewer.nodes[0].splats.centers.copy()
        viewer.slider.value = scenes[0].n_frames - 1
        deadline = time.monotonic() + 10
        while viewer.frame != scenes[0].n_frames - 1 and time.monotonic() < deadline:
            time.sleep(0.05)
        after = viewer.nodes[0].splats.centers
        n_surface = len(scenes[0].gaussian_colors)
        assert len(after) == len(before) == n_surface + scenes[0].released_visible[-1].sum()
        assert np.abs(after[:n_surface] - before[:n_surface]).max() > 0.01  # cm: the squeezed surface moved
        opacity = viewer.nodes[0].splats.opacities[n_surface:]  # uint8: the released juice is drawn now
        assert opacity.min() > 0
        served = viewer.slider._impl.props._marks  # the marks the client draws under the slider
        # one mark per distinct rupture frame of the scenes shown (the force-matched ablation ruptures too)
        ruptures = sorted({s.rupture_frame for s in scenes if s.rupture_frame is not None})
        assert rupture in ruptures and [m.value for m in served if m.label == "rupture"] == ruptures
    finally:
        viewer.stop()
    with pytest.raises(OSError):
        urllib.request.urlopen(viewer.url, timeout=5)


@pytest.mark.skipif(shutil.which("chromium") is None, reason="headless Chromium (Debian's chromium) not installed")
def test_headless_chromium_draws_the_object(scenes, tmp_path):
    from PIL import Image

    from tasks.reporting.viewer import browser_screenshot

    viewer = _viewer(scenes[:1])
    before = {p.pid for p in psutil.Process().children(recursive=True)}
    try:
        viewer.show["hand"].value = False  # the object alone in the middle of the picture
        viewer.set_frame(0, force=True)
        shot = np.asarray(Image.open(browser_screenshot(viewer.url, tmp_path / "viewer.png", 800, 600)).convert("RGB"))
    finally:
        viewer.stop()
    left = {p.pid for p in psutil.Process().children(recursive=True)} - before
    assert not left, f"processes left: {left}"
    centre = shot[250:350, 350:450].astype(int)
    # the tomato's red splats fill the centre of rig view 0; the background is white, the table grid grey
    red = (centre[..., 0] - centre[..., 1] > 60) & (centre[..., 0] > 120)
    assert red.mean() > 0.5, f"centre colour {centre.reshape(-1, 3).mean(axis=0)}"
    assert shot[:40].reshape(-1, 3).mean() > 200  # the sky above stays the background's


def _read_recording(path: Path) -> dict:
    """The messages of a self-contained viser recording (viser's layout: the base64 scene in the page, an 8-byte
    size, then zstd of [8-byte msgpack length][msgpack][binary buffers])."""
    import base64
    import re

    import msgspec
    import zstandard

    data = base64.b64decode(re.search(r'__VISER_EMBED_DATA__="([^"]+)"', path.read_text())[1])
    inner = zstandard.ZstdDecompressor().decompressobj().decompress(data[8:])
    return msgspec.msgpack.decode(inner[8:8 + int.from_bytes(inner[:8], "little")])


def test_the_recording_holds_every_frame_and_plays_without_a_server(scenes, tmp_path):
    viewer = _viewer(scenes)
    try:
        path = viewer.record(tmp_path / "tomato.html", speed=0.5)
    finally:
        viewer.stop()
    doc = _read_recording(path)
    n = scenes[0].n_frames
    assert doc["durationSeconds"] == pytest.approx(n / (scenes[0].frame_rate * 0.5))
    for k in range(len(scenes)):  # frame 0 in the scene's first state, then one splat update per frame, back to 0
        updates = [t for t, m in doc["messages"] if m.get("name") == f"/{k}/gaussians"
                   and m["type"] == "SceneNodeUpdateMessage"]
        moving = sum(1 for f in range(1, n) if not np.array_equal(scenes[k].gaussian_positions[f],
                                                                   scenes[k].gaussian_positions[f - 1]))
        assert len(updates) == moving + 1 and updates == sorted(updates)


def test_the_frame_update_benchmark_counts_what_a_client_receives(scenes):
    from tasks.reporting.viewer_benchmark import measure_frame_updates

    viewer = _viewer(scenes)
    try:
        cost = measure_frame_updates(viewer)
    finally:
        viewer.stop()
    n_gaussians = sum(len(s.gaussian_colors) + int(s.released_visible.any(axis=0).sum()) for s in scenes)
    assert cost.gaussians == n_gaussians and len(cost.server_ms) == scenes[0].n_frames
    # a frame where the squeeze moves sends both scenes' splat buffers (32 B per Gaussian) and the small layers
    assert cost.bytes_received.max() >= 32 * sum(len(node.splats.centers) for node in viewer.nodes)
    assert (cost.server_ms > 0).all()


def test_the_report_links_the_recordings_written_beside_it(tmp_path):
    from tasks.reporting.report import viewer_lines

    report = tmp_path / "reports" / "evaluate-1"
    refs = {"tomato": {"variants": {"full": {}, "no_dirichlet": {}}}, "can@seed1": {"variants": {"full": {}}}}
    assert "none written yet" in viewer_lines(report, refs)[0]
    (tmp_path / "reports" / "viewer").mkdir(parents=True)
    for name in ("tomato_no_dirichlet.html", "can@seed1_full.html", "clay_full.html"):
        (tmp_path / "reports" / "viewer" / name).write_text("<html></html>")
    line = viewer_lines(report, refs)[0]
    assert line.endswith(": [tomato no_dirichlet](../viewer/tomato_no_dirichlet.html), "
                         "[can@seed1 full](../viewer/can@seed1_full.html).")
