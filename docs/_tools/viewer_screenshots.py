"""The viewer tutorial's pictures: the viewer of one cached scene at rest, at the peak squeeze (contact patches and
constrained points on) and after the release, as headless Chromium draws it (docs/tutorials/viewer.md).

    python docs/_tools/viewer_screenshots.py docs/images object=tomato paths.artifacts=artifacts [overrides...]

The overrides are ``python -m flows.view``'s (the scene must be cached: the viewer computes nothing).  Writes
``viewer-rest.png``, ``viewer-peak.png`` and ``viewer-release.png`` into the folder given first.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))


def main(out: Path, overrides: list[str]) -> None:
    from hydra import compose, initialize_config_dir

    from conf.view_schema import register_view_config
    from flows.view import load_scenes
    from tasks.reporting.viewer import SqueezeViewer, browser_screenshot

    register_view_config()
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="view", overrides=overrides)
    scenes = load_scenes(cfg, overrides)
    first = scenes[0]
    peak = int(np.argmax(first.force_coefficients.sum(axis=1)))
    moments = {"rest": 0, "peak": peak, "release": first.n_frames - 1}
    viewer = SqueezeViewer(scenes, port=0)
    try:
        for name, frame in moments.items():
            viewer.set_frame(frame, force=True)
            path = browser_screenshot(viewer.url, out / f"viewer-{name}.png", 1400, 820)
            print(f"{path} (frame {frame}, t = {first.time[frame]:.2f} s)")
    finally:
        viewer.stop()


if __name__ == "__main__":
    main(Path(sys.argv[1]), sys.argv[2:])
