"""Renderer benchmark: the Gaussian rasteriser's time per frame against its physical floor.

    python -m flows.bench.render                                   # 192 and 384 px (G-buffer, videos), the grid's sizes
    python -m flows.bench.render resolutions=[128,192] sizes=[3000] backends=[warp]

Prints forward and forward+backward time per frame and view for every backend, resolution and number of Gaussians,
with the work counts, the floors and the ratios to them, then each backend's median cost and ratio to the floor
at every resolution side by side (the scene, the floor model and measured figures:
:mod:`tasks.render.benchmark`).  Config: ``conf/study/bench_render.yaml`` (keys:
:class:`conf.study.schema.RenderBenchConfig`).
"""
from __future__ import annotations

import hydra
from omegaconf import DictConfig

from conf.study.schema import register_study_configs

register_study_configs()

BACKENDS = ("torch", "warp-scalar", "warp")


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/bench_render")
def main(cfg: DictConfig) -> list[dict]:
    for bad in (b for b in cfg.backends if b not in BACKENDS):
        raise SystemExit(f"input error: backends: unknown renderer {bad!r}; one of {list(BACKENDS)}")
    for key in ("resolutions", "sizes"):
        for bad in (v for v in cfg[key] or () if not v >= 1):
            raise SystemExit(f"input error: {key} must be >= 1, got {bad}")
    from tasks.render.benchmark import main as render_benchmark

    given = {k: tuple(cfg[k]) for k in ("resolutions", "sizes", "backends") if cfg[k] is not None}
    return render_benchmark(**given)


if __name__ == "__main__":
    main()
