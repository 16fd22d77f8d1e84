"""Cost of the watched videos (issue 44): CPU seconds per stage of the ``display_video`` step for one scene.

    python -m flows.bench.video ARTIFACTS SCENE [HYDRA OVERRIDES ...]
    python -m flows.bench.video artifacts orange render.closeup=false

Reads the newest artifact of every input of ``display_video`` for ``SCENE`` under ``ARTIFACTS`` (a main-job or
``flows.squeeze`` store that ran the scene once: one variant), composes ``conf/squeeze.yaml`` with the overrides for
the step's parameters, runs :func:`tasks.generation.display_video.display_video` with a
:class:`~tasks.generation.display_video.StageClock` and prints the CPU seconds (``time.process_time``, the better
figure on a shared machine) per stage: set-up, surface Gaussians (every view at once), liquid kernels (once per
frame), released material, hand (orbit views and close-up apart), encode.  Writes nothing to the store.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from conf.schema import register_configs
from tasks.core.artifacts import newest_artifact

register_configs()


def main(argv: list[str]) -> dict[str, float]:
    if len(argv) < 2:
        raise SystemExit(__doc__)
    root, scene, overrides = Path(argv[0]), argv[1], argv[2:]
    from hydra import compose, initialize_config_dir

    from flows.pipeline import step_params
    from tasks.generation.display_video import StageClock, display_video, display_video_step

    conf = Path(__file__).resolve().parents[2] / "conf"
    with initialize_config_dir(config_dir=str(conf), version_base="1.3"):
        cfg = compose(config_name="squeeze", overrides=[f"object={scene}", *overrides])
    params = step_params(display_video_step, cfg, cfg.object)
    inputs = {step: newest_artifact(root, scene, step) for step in display_video_step.spec.inputs}
    clock, wall = StageClock(), time.perf_counter()
    arrays, attrs = display_video(inputs, params, clock)
    wall = time.perf_counter() - wall
    views, frames = arrays["frames"].data.shape[:2]
    total = sum(clock.seconds.values())
    print(f"{scene}: {views} views ({', '.join(attrs['views'])}) x {frames} frames at {attrs['size'][0]} px, "
          f"released: {attrs['released']}; CPU {total:.1f} s, wall {wall:.1f} s")
    for stage, seconds in sorted(clock.seconds.items(), key=lambda kv: -kv[1]):
        print(f"  {stage:28s} {seconds:7.2f} s  {100 * seconds / max(total, 1e-9):5.1f} %")
    return clock.seconds


if __name__ == "__main__":
    main(sys.argv[1:])
