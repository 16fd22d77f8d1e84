"""What one frame update of the 4D viewer costs: server-side milliseconds per :meth:`SqueezeViewer.set_frame` (the
frame's splats and layers computed and queued) and the bytes a connected client receives for it (viser's
websocket, a real client of its protocol).  Used by ``python -m flows.bench.viewer``."""
from __future__ import annotations

import asyncio
import threading
import time
from dataclasses import dataclass

import numpy as np
import viser

from tasks.reporting.viewer import SqueezeViewer


class _Client:
    """A websocket client of viser's protocol in its own thread, counting the bytes it receives."""

    def __init__(self, url: str):
        self.received = 0
        self.messages = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=lambda: asyncio.run(self._run(url)), daemon=True)
        self._thread.start()
        if not self._ready.wait(30):
            raise RuntimeError(f"no websocket connection to {url}")

    async def _run(self, url: str) -> None:
        import websockets

        async with websockets.connect(url, subprotocols=[f"viser-v{viser.__version__}"], max_size=None) as ws:
            self._ready.set()
            while not self._stop.is_set():
                try:
                    data = await asyncio.wait_for(ws.recv(), timeout=0.1)
                except asyncio.TimeoutError:
                    continue
                with self._lock:
                    self.received += len(data)
                    self.messages += 1

    def count(self) -> int:
        with self._lock:
            return self.received

    def settle(self, quiet_s: float = 0.3, timeout_s: float = 30.0) -> int:
        """The byte count once nothing has arrived for ``quiet_s``."""
        last, since, deadline = self.count(), time.monotonic(), time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            time.sleep(0.05)
            now = self.count()
            if now != last:
                last, since = now, time.monotonic()
            elif time.monotonic() - since >= quiet_s:
                break
        return last

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@dataclass(frozen=True)
class FrameUpdateCost:
    """Per frame update (every frame of the squeeze once, in order): server ms and bytes received."""

    gaussians: int  # splats per frame, all scenes (surface + every released particle)
    server_ms: np.ndarray
    bytes_received: np.ndarray

    def summary(self) -> str:
        ms, b = self.server_ms, self.bytes_received
        return (f"{self.gaussians} Gaussians: server {np.median(ms):.1f} ms per frame update (median; p90 "
                f"{np.percentile(ms, 90):.1f}, max {ms.max():.1f}), {np.median(b) / 1e3:.0f} kB sent per frame "
                f"(median; max {b.max() / 1e3:.0f} kB) = {np.median(b) / self.gaussians:.1f} B per Gaussian")


def measure_frame_updates(viewer: SqueezeViewer) -> FrameUpdateCost:
    """Step ``viewer`` through every frame with one client connected; time each :meth:`set_frame` on the server
    and count the bytes the client receives for it (waiting until the websocket is quiet between frames)."""
    client = _Client(viewer.url.replace("http", "ws"))
    try:
        client.settle()  # the initial scene
        n = viewer.scenes[0].n_frames
        ms, sent = np.zeros(n), np.zeros(n)
        for k, frame in enumerate([*range(1, n), 0]):
            before = client.count()
            t0 = time.perf_counter()
            viewer.set_frame(frame)
            ms[k] = 1e3 * (time.perf_counter() - t0)
            sent[k] = client.settle() - before
    finally:
        client.close()
    return FrameUpdateCost(sum(len(node.splats.centers) for node in viewer.nodes), ms, sent)
