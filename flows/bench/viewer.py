"""4D viewer benchmark: server-side milliseconds and bytes sent per frame update (python -m flows.view's scene).

    python -m flows.bench.viewer object=plush_toy compare=null          # the default grid's cached plush toy
    python -m flows.bench.viewer object=tomato paths.artifacts=/tmp/a sampling.surface_points=600 ...

The same config and overrides as ``python -m flows.view`` (conf/view.yaml): the scene is read from the cached
artifacts (one line naming the command that makes them when it is not).  Steps a viewer with one real websocket
client through every frame and prints the figures (:mod:`tasks.reporting.viewer_benchmark`).
"""
from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from conf.view_schema import register_view_config

register_view_config()


@hydra.main(version_base="1.3", config_path="../../conf", config_name="view")
def main(cfg: DictConfig) -> None:
    from flows import USER_PREFECT_PATHS
    from flows.lifecycle import follow_artifacts
    from flows.view import ViewerInputError, load_scenes, task_overrides

    follow_artifacts(cfg.paths.artifacts, USER_PREFECT_PATHS)
    try:
        scenes = load_scenes(cfg, task_overrides())
    except ViewerInputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    from tasks.reporting.viewer import SqueezeViewer
    from tasks.reporting.viewer_benchmark import measure_frame_updates

    viewer = SqueezeViewer(scenes, host=cfg.host, port=0)
    try:
        cost = measure_frame_updates(viewer)
    finally:
        viewer.stop()
    print(f"{', '.join(s.label for s in scenes)}, {scenes[0].n_frames} frames: {cost.summary()}")


if __name__ == "__main__":
    main()
