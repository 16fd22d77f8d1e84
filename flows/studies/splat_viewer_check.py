"""Colour check in a real web splat viewer (issue 44):  ``python -m flows.studies.splat_viewer_check [WORKDIR]``

Writes a cube of opaque Gaussians of a known display colour (sRGB (224, 51, 35), the tomato's) with our PLY writer,
renders it with our rasteriser, and opens the same file in ``@mkkellogg/gaussian-splats-3d`` (installed from the npm
registry into WORKDIR, default a temporary folder) served on 127.0.0.1 and shot with headless Chromium (SwiftShader
WebGL).  Prints both centre pixels and exits non-zero when they differ by more than 3/255 in any channel.  Needs
``npm`` and ``chromium`` (``apt-get install -y chromium``); not a test because it downloads a package.
"""
from __future__ import annotations

import functools
import http.server
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tasks.control.gaussian_ply import read_gaussian_ply, srgb_to_linear, write_gaussian_ply
from tasks.render.cameras import look_at
from tasks.render.colour import to_srgb_uint8
from tasks.render.splat import rasterization

DISPLAY = (224, 51, 35)
SIZE = 400
PAGE = """<!doctype html><html><head><style>body{margin:0;background:#000}</style>
<script type="importmap">{"imports":{"three":"./node_modules/three/build/three.module.js","@mkkellogg/gaussian-splats-3d":"./node_modules/@mkkellogg/gaussian-splats-3d/build/gaussian-splats-3d.module.js"}}</script>
</head><body>
<script type="module">
import * as G from '@mkkellogg/gaussian-splats-3d';
const viewer = new G.Viewer({cameraUp: [0, 0, 1], initialCameraPosition: [0, -0.25, 0], initialCameraLookAt: [0, 0, 0],
  sharedMemoryForWorkers: false, gpuAcceleratedSort: false, useBuiltInControls: false, selfDrivenMode: true});
viewer.addSplatScene('known.ply', {showLoadingUI: false, progressiveLoad: false, format: G.SceneFormat.Ply}).then(() => {
  viewer.start(); setTimeout(() => { document.title = 'rendered'; }, 4000); }).catch(e => { document.title = 'error ' + e; });
</script></body></html>"""  # noqa: E501


def known_ply(path: Path) -> Path:
    g = np.linspace(-0.03, 0.03, 16)
    means = np.stack(np.meshgrid(g, g, g), -1).reshape(-1, 3)
    n = len(means)
    return write_gaussian_ply(path, means, np.full((n, 3), 0.006), np.tile([1.0, 0, 0, 0], (n, 1)),
                              np.full(n, 0.99), np.tile(srgb_to_linear(np.array(DISPLAY) / 255.0), (n, 1)))


def our_centre(path: Path) -> np.ndarray:
    g = read_gaussian_ply(path)
    focal = 0.5 * SIZE / np.tan(np.radians(25.0))
    K = torch.tensor([[[focal, 0, SIZE / 2], [0, focal, SIZE / 2], [0, 0, 1]]], dtype=torch.float32)
    view = torch.as_tensor(look_at(np.array([0.0, -0.25, 0.0]), np.zeros(3))[None], dtype=torch.float32)
    colors, _, _ = rasterization(*(torch.as_tensor(g[k]) for k in ("means", "rotations", "scales", "opacities",
                                                                     "colors")), view, K, SIZE, SIZE,
                                 render_mode="RGB")
    return to_srgb_uint8(colors[0, SIZE // 2, SIZE // 2].numpy())


def viewer_centre(folder: Path) -> np.ndarray:
    if not (folder / "node_modules" / "@mkkellogg" / "gaussian-splats-3d").is_dir():
        subprocess.run(["npm", "init", "-y"], cwd=folder, check=True, capture_output=True)
        subprocess.run(["npm", "install", "@mkkellogg/gaussian-splats-3d", "three"], cwd=folder, check=True,
                       capture_output=True)
    (folder / "index.html").write_text(PAGE)
    class Quiet(http.server.SimpleHTTPRequestHandler):
        def log_message(self, *args) -> None:
            pass

    handler = functools.partial(Quiet, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        shot = folder / "viewer.png"
        subprocess.run(["chromium", "--headless", "--no-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
                        "--enable-unsafe-swiftshader", f"--window-size={SIZE},{SIZE}", "--virtual-time-budget=15000",
                        f"--screenshot={shot}", f"http://127.0.0.1:{server.server_address[1]}/index.html"],
                       check=True, capture_output=True, timeout=120)
    finally:
        server.shutdown()
    return np.asarray(Image.open(shot).convert("RGB"))[SIZE // 2, SIZE // 2]


def main(workdir: str | None = None) -> int:
    folder = Path(workdir or tempfile.mkdtemp(prefix="splat-viewer-"))
    folder.mkdir(parents=True, exist_ok=True)
    ply = known_ply(folder / "known.ply")
    ours, theirs = our_centre(ply), viewer_centre(folder)
    diff = int(np.abs(ours.astype(int) - theirs.astype(int)).max())
    print(f"display colour {DISPLAY}; our render {tuple(int(c) for c in ours)}; @mkkellogg/gaussian-splats-3d "
          f"{tuple(int(c) for c in theirs)}; largest difference {diff}/255 (limit 3)")
    return 0 if diff <= 3 else 1


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:2]))
