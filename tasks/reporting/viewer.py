"""The interactive 4D viewer of a squeeze: a viser server (three.js client in the browser) drawing
:class:`tasks.reporting.viewer_scene.SqueezeScene` s, with a time slider, playback and toggles.

Drawn per scene (the compared variant beside the first, at the same instant): the object's Gaussians and the
released material as real splats, the hand (fingertips, fingers from the palm, palm frame), the contact patches
(eq. 2), the constrained points coloured by prescribed displacement (eq. 3) and the fingers' reaction arrows.  The
GUI: a frame slider with the rupture marked, play/pause at real time or slow motion, frame stepping, the rig views
of the report, toggles for each layer, and the flexion and force-coefficient curves (eq. 1) with a marker at the
current instant.  A frame change sends, per scene, one splat buffer (centres, covariances, colours: 32 bytes per
Gaussian, the client's format) and the small hand, patch and arrow layers; nothing is sent for a layer switched off.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import viser

from conf.hand import FINGERS
from tasks.reporting.viewer_scene import (
    SPLAT_UNIT,
    SqueezeScene,
    constrained_points,
    force_arrows,
    frame_splats,
    hand_segments,
    patch_outlines,
    rig_camera_poses,
    side_offset,
)

SPEEDS = {"real time": 1.0, "1/4 x": 0.25, "1/10 x": 0.1}  # playback rates offered
_FINGER_RGB = np.array([[230, 25, 75], [60, 180, 75], [0, 130, 200], [245, 130, 48], [145, 30, 180]], np.uint8)
_TABLE_RGB = (200, 196, 186)


@dataclass
class _SceneNodes:
    """The viser handles of one scene's layers."""

    scene: SqueezeScene
    offset: np.ndarray
    splats: Any = None
    tips: Any = None
    fingers: Any = None
    palm: Any = None
    patches: Any = None
    points: Any = None
    arrows: Any = None
    extra: dict[str, Any] = field(default_factory=dict)


class SqueezeViewer:
    """A viser server showing ``scenes`` (the first at the origin, each further one beside it along y).

    ``host``/``port``: where it listens (port 0: a free one; :attr:`url`).  ``speed``: playback rate at start
    (1 = real time).  :meth:`set_frame` moves every scene to a frame (what the slider does); :meth:`stop` shuts
    the server down."""

    def __init__(self, scenes: Sequence[SqueezeScene], host: str = "127.0.0.1", port: int = 0, speed: float = 1.0,
                 verbose: bool = False):
        if not scenes:
            raise ValueError("the viewer needs at least one scene")
        lengths = {s.n_frames for s in scenes}
        if len(lengths) != 1:
            raise ValueError(f"the compared scenes have different frame counts {sorted(lengths)}: they cannot share "
                             "one time slider")
        self.scenes = list(scenes)
        self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.server.scene.set_up_direction("+z")
        self.frame = 0
        self._lock = threading.RLock()
        self._playing = threading.Event()
        self._stopped = threading.Event()
        self._speed = float(speed)
        offsets = [np.zeros(3)]
        for _ in self.scenes[1:]:
            offsets.append(offsets[-1] + side_offset(self.scenes[0]))
        self.nodes = [_SceneNodes(s, o) for s, o in zip(self.scenes, offsets)]
        self._build_static()
        self._build_gui()
        self.set_frame(0)
        self._player = threading.Thread(target=self._play_loop, name="squeeze-viewer-player", daemon=True)
        self._player.start()

    # ------------------------------------------------------------------------------------------------ scene
    @property
    def url(self) -> str:
        return f"http://{self.server.get_host()}:{self.server.get_port()}"

    def _build_static(self) -> None:
        first = self.scenes[0]
        reach = float(np.ptp(first.gaussian_positions[0], axis=0).max())
        span = np.stack([n.offset for n in self.nodes])
        middle = first.center + 0.5 * (span.min(axis=0) + span.max(axis=0))
        size = 4 * reach + float(np.ptp(span[:, 1]))
        self.server.scene.add_grid("/table", width=size, height=size, plane="xy", cell_size=reach / 4,
                                   section_size=reach, cell_color=_TABLE_RGB, section_color=(150, 146, 138),
                                   position=(middle[0], middle[1], first.table_height))
        for k, node in enumerate(self.nodes):
            label = f"/{k}"
            node.extra["title"] = self.server.scene.add_label(
                f"{label}/title", node.scene.label,
                position=tuple(node.offset + node.scene.center + [0, 0, 0.8 * reach]))
        # the rig's cameras, aimed at the middle of the compared scenes and backed off to keep them all in view
        widen = 1.0 + float(np.linalg.norm(span.max(axis=0) - span.min(axis=0))) / max(reach, 1e-9) / 2
        shift = middle - first.center
        self._rig = [(look + shift + widen * (pos - look), look + shift, up)
                     for pos, look, up in ((p, first.center, u) for p, _, u in rig_camera_poses(first.rig_viewmats))]
        position, look_at, up = self._rig[0]
        self.server.initial_camera.position = tuple(position)
        self.server.initial_camera.look_at = tuple(look_at)
        self.server.initial_camera.up = tuple(up)
        self.server.initial_camera.fov = float(2 * np.arctan(first.rig_Ks[0][1, 2] / first.rig_Ks[0][1, 1]))  # vertical
        self.server.initial_camera.near = 0.002

    def _build_gui(self) -> None:
        gui, first = self.server.gui, self.scenes[0]
        n = first.n_frames
        marks = [(0, f"{first.time[0]:.2f} s"), (n - 1, f"{first.time[-1]:.2f} s")]
        ruptures = sorted({s.rupture_frame for s in self.scenes if s.rupture_frame is not None})
        marks += [(f, "rupture") for f in ruptures]
        with gui.add_folder("Time"):
            self.slider = gui.add_slider("frame", 0, n - 1, 1, 0, marks=tuple(marks),
                                         hint="simulated frame; 'rupture': the rollout's threshold event")
            self.clock = gui.add_markdown(self._clock_text(0))
            self.play = gui.add_checkbox("play", False)
            self.speed = gui.add_dropdown("speed", tuple(SPEEDS), initial_value=self._speed_label())
            back, step = gui.add_button("< frame"), gui.add_button("frame >")
        with gui.add_folder("Show"):
            self.show = {name: gui.add_checkbox(name, True) for name in
                         ("released material", "hand", "contact patches (eq. 2)", "constrained points (eq. 3)",
                          "reaction arrows")}
        with gui.add_folder("Rig views"):
            for k in range(len(self._rig)):
                gui.add_button(f"view {k}").on_click(lambda event, k=k: self._to_rig_view(event.client, k))
        self.plots = []
        with gui.add_folder("Controls (eq. 1)"):
            for title, values in (("flexion", first.flexion), ("force coefficient", first.force_coefficients)):
                self.plots.append((values, gui.add_uplot(
                    self._plot_data(values, 0), self._plot_series(), title=f"{title} ({first.label})", aspect=1.4,
                    scales={"x": {"time": False, "auto": True},  # a fixed y range: the marker series is NaN but
                            "y": {"auto": False, "range": [min(0.0, float(values.min())),  # at one instant
                                                           1.05 * max(1.0, float(values.max()))]}},
                    axes=({"label": "t (s)"}, {}), legend={"show": False})))

        self.slider.on_update(lambda _: self.set_frame(int(self.slider.value)))
        self.play.on_update(lambda _: self._playing.set() if self.play.value else self._playing.clear())
        self.speed.on_update(lambda _: setattr(self, "_speed", SPEEDS[self.speed.value]))
        back.on_click(lambda _: self._step(-1))
        step.on_click(lambda _: self._step(+1))
        for box in self.show.values():
            box.on_update(lambda _: self.set_frame(self.frame, force=True))

    def _speed_label(self) -> str:
        return min(SPEEDS, key=lambda k: abs(SPEEDS[k] - self._speed))

    def _clock_text(self, frame: int) -> str:
        s = self.scenes[0]
        state = "" if s.rupture_frame is None else (" - ruptured" if frame >= s.rupture_frame else " - intact")
        return f"t = {s.time[frame]:.3f} s, frame {frame}/{s.n_frames - 1}{state}"

    @staticmethod
    def _plot_series() -> tuple:
        series: list[dict] = [{"label": "t (s)"}]
        series += [{"label": f, "stroke": "#%02x%02x%02x" % tuple(c), "width": 1.5} for f, c in zip(FINGERS, _FINGER_RGB)]
        series.append({"label": "now", "stroke": "#000000", "width": 0, "points": {"show": True, "size": 7}})
        return tuple(series)

    def _plot_data(self, values: np.ndarray, frame: int) -> tuple[np.ndarray, ...]:
        t = self.scenes[0].time
        marker = np.full(len(t), np.nan)
        marker[frame] = float(np.max(values[frame]))  # on the highest finger's curve
        return (t, *(values[:, i] for i in range(values.shape[1])), marker)

    # ------------------------------------------------------------------------------------------------ frames
    def set_frame(self, frame: int, force: bool = False) -> None:
        """Draw every scene at ``frame`` (0 .. n_frames - 1): splats, released material, hand, patches, points,
        arrows as their toggles say; the slider, clock and curve markers follow."""
        frame = int(np.clip(frame, 0, self.scenes[0].n_frames - 1))
        with self._lock:
            if frame == self.frame and not force and self.nodes[0].splats is not None:
                return
            self.frame = frame
            with self.server.atomic():
                for k, node in enumerate(self.nodes):
                    self._draw(k, node, frame)
                if int(self.slider.value) != frame:
                    self.slider.value = frame
                self.clock.content = self._clock_text(frame)
                for values, plot in self.plots:
                    plot.data = self._plot_data(values, frame)

    def _draw(self, k: int, node: _SceneNodes, frame: int) -> None:
        scene, scn, root = node.scene, self.server.scene, f"/{k}"
        splats = frame_splats(scene, frame, node.offset, released=self.show["released material"].value)
        if node.splats is None:
            node.splats = scn.add_gaussian_splats(f"{root}/gaussians", splats.centers, splats.covariances,
                                                  splats.rgbs, splats.opacities, scale=SPLAT_UNIT)
        else:
            node.splats.set_gaussians(splats.centers, splats.covariances, splats.rgbs, splats.opacities)
        off = node.offset
        show_hand = self.show["hand"].value
        tips = scene.fingertips[frame] + off
        node.tips = _points(scn, node.tips, f"{root}/hand/fingertips", tips, _FINGER_RGB, 0.004, show_hand)
        node.fingers = _segments(scn, node.fingers, f"{root}/hand/fingers", hand_segments(scene, frame) + off,
                                 _FINGER_RGB, show_hand)
        if node.palm is None:
            node.palm = scn.add_frame(f"{root}/hand/palm", axes_length=0.012, axes_radius=0.0008)
        node.palm.position, node.palm.wxyz = scene.palm_position[frame] + off, scene.palm_orientation[frame]
        node.palm.visible = show_hand
        outline = patch_outlines(scene, frame) + off
        node.patches = _segments(scn, node.patches, f"{root}/contact_patches", outline, (255, 200, 0),
                                 self.show["contact patches (eq. 2)"].value and len(outline) > 0)
        points, colors = constrained_points(scene, frame)
        node.points = _points(scn, node.points, f"{root}/constrained_points", points + off,
                              (colors * 255).astype(np.uint8), 0.0015,
                              self.show["constrained points (eq. 3)"].value and len(points) > 0)
        node.arrows = _segments(scn, node.arrows, f"{root}/reaction", force_arrows(scene, frame) + off,
                                _FINGER_RGB, self.show["reaction arrows"].value)

    def _step(self, delta: int) -> None:
        self.play.value = False
        self._playing.clear()
        self.set_frame((self.frame + delta) % self.scenes[0].n_frames)

    def _play_loop(self) -> None:
        while not self._stopped.is_set():
            if not self._playing.wait(timeout=0.2):
                continue
            start = time.perf_counter()
            self.set_frame((self.frame + 1) % self.scenes[0].n_frames)
            period = 1.0 / (self.scenes[0].frame_rate * max(self._speed, 1e-3))
            self._stopped.wait(max(0.0, period - (time.perf_counter() - start)))

    def _to_rig_view(self, client: viser.ClientHandle | None, k: int) -> None:
        position, look_at, up = self._rig[k]
        for c in ([client] if client is not None else self.server.get_clients().values()):
            with c.atomic():
                c.camera.position, c.camera.look_at, c.camera.up_direction = position, look_at, up

    # ------------------------------------------------------------------------------------------------ output
    def record(self, path: str | Path, speed: float = 1.0) -> Path:
        """Write the whole squeeze as a self-contained HTML page (viser's scene serializer and its client) that
        plays without a Python server: every frame's scene, ``1 / (frame_rate x speed)`` s apart."""
        serializer = self.server.get_scene_serializer()
        period = 1.0 / (self.scenes[0].frame_rate * speed)
        for frame in range(self.scenes[0].n_frames):
            self.set_frame(frame, force=True)
            serializer.insert_sleep(period)
        # the scene's first messages hold views of the live splat buffers (updated in place): back to frame 0,
        # so that the recording starts (and loops) from the rest state, not from the last frame
        self.set_frame(0, force=True)
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(serializer.as_html())
        return path

    def stop(self) -> None:
        """Stop playback and the server (its threads and port)."""
        self._stopped.set()
        self._playing.set()
        self._player.join(timeout=5)
        self.server.stop()


def _points(scn: Any, handle: Any, name: str, points: np.ndarray, colors: Any, size: float, visible: bool) -> Any:
    """Create or update a point cloud layer (nothing is sent while it is hidden)."""
    if not visible:
        if handle is not None:
            handle.visible = False
        return handle
    colors = np.broadcast_to(np.asarray(colors, np.uint8), points.shape)
    if handle is None:
        return scn.add_point_cloud(name, points.astype(np.float32), colors, point_size=size, point_shape="circle")
    handle.points, handle.colors, handle.visible = points.astype(np.float32), colors, True
    return handle


def _segments(scn: Any, handle: Any, name: str, segments: np.ndarray, colors: Any, visible: bool) -> Any:
    """Create or update a line-segment layer (nothing is sent while it is hidden)."""
    if not visible:
        if handle is not None:
            handle.visible = False
        return handle
    colors = np.broadcast_to(np.asarray(colors, np.uint8)[..., None, :] if np.ndim(colors) == 2 else
                             np.asarray(colors, np.uint8), segments.shape)
    if handle is None:
        return scn.add_line_segments(name, segments.astype(np.float32), colors, line_width=3.0)
    handle.points, handle.colors, handle.visible = segments.astype(np.float32), colors, True
    return handle


def browser_screenshot(url: str, out: str | Path, width: int = 1280, height: int = 800, timeout_s: float = 120.0,
                       ready_text: str = "t = ", after_s: float | None = None, browser: str = "chromium") -> Path:
    """A PNG of the viewer page at ``url`` as headless Chromium draws it (WebGL through SwiftShader, no GPU).

    Driven over the DevTools protocol: the page is opened, the capture waits until the page shows ``ready_text``
    (the GUI's clock line: the scene's messages have arrived) and then until two captures 1 s apart are identical
    (the canvas has drawn and the fade-in is over) or, with ``after_s``, that many seconds (a recording that plays
    on never settles).  The browser runs in its own process group, ended when done."""
    import asyncio
    import base64
    import json
    import os
    import signal
    import subprocess
    import tempfile
    import urllib.request

    import websockets

    out = Path(out).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)

    async def drive(ws_url: str) -> bytes:
        async with websockets.connect(ws_url, max_size=None) as ws:
            ids = iter(range(1, 1 << 30))

            async def call(method: str, **params: Any) -> dict:
                key = next(ids)
                await ws.send(json.dumps({"id": key, "method": method, "params": params}))
                while True:
                    reply = json.loads(await ws.recv())
                    if reply.get("id") == key:
                        if "error" in reply:
                            raise RuntimeError(f"{browser} {method}: {reply['error']}")
                        return reply["result"]

            await call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                       mobile=False)
            await call("Page.navigate", url=url)
            text = json.dumps(ready_text)
            while not (await call("Runtime.evaluate", expression=f"document.body.innerText.includes({text})",
                                  returnByValue=True))["result"].get("value"):
                await asyncio.sleep(0.5)
            if after_s is not None:
                await asyncio.sleep(after_s)
                return base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])
            previous = None
            while True:
                await asyncio.sleep(1.0)
                shot = base64.b64decode((await call("Page.captureScreenshot", format="png"))["data"])
                if shot == previous:
                    return shot
                previous = shot

    with tempfile.TemporaryDirectory(prefix="viewer-chromium-") as profile:
        cmd = [browser, "--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
               "--hide-scrollbars", "--no-first-run", f"--user-data-dir={profile}", "--remote-debugging-port=0",
               f"--window-size={width},{height}", "about:blank"]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            port_file, deadline = Path(profile) / "DevToolsActivePort", time.monotonic() + 30
            while not port_file.exists() or not port_file.read_text().strip():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"{browser} did not open its DevTools port (exit code {proc.poll()})")
                time.sleep(0.1)
            port = int(port_file.read_text().split()[0])
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as reply:
                page = next(t for t in json.load(reply) if t["type"] == "page")
            png = asyncio.run(asyncio.wait_for(drive(page["webSocketDebuggerUrl"]), timeout_s))
        finally:
            try:
                os.killpg(proc.pid, signal.SIGKILL)  # the browser's helpers (zygote, GPU process) with it
            except ProcessLookupError:
                pass
            proc.wait()
    out.write_bytes(png)
    return out
