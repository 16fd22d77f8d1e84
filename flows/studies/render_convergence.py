"""Render and effect knobs, error against run time:  ``python -m flows.studies.render_convergence``
(``object=NAME``; config ``conf/study/render_convergence.yaml``).

Runs the object's default chain (one variant, up to the eq. 7 refinement) through the cached steps
(:func:`flows.pipeline.run_object_local`, no Prefect), then the ``gbuffer`` step once per ``render_study.resolutions``
and ``render_study.frame_strides`` setting and the ``appearance_refinement`` step once per
``render_study.refinement_iterations`` setting (each on the default chain's other artifacts), so a rerun is served
from the cache.  Measures every setting against its knob's finest one and writes
``<paths.reports>/render_convergence/<run>/render_knobs.{md,json}`` (:mod:`tasks.verification.render_convergence`);
every run report shows the latest.  Kept out of the main job: it renders the object ~10 more times.
"""
from __future__ import annotations

import os
import platform
from datetime import datetime
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from conf.study.render_convergence_schema import register_render_study_config, validate_render_study

register_render_study_config()


def run_render_study(cfg: DictConfig) -> Path:
    """Validate, run the settings through the cached steps, write the study; returns its JSON path."""
    from conf.schema import ConfigError
    from flows.preflight import preflight

    try:
        validate_render_study(cfg)
    except ConfigError as exc:
        raise SystemExit(f"config error: {exc}") from None
    preflight(cfg)  # the base config and its input files, one line before anything starts
    from flows.pipeline import appearance_refinement_step, gbuffer_step, run_object_local, seed_scope, step_params
    from tasks.verification import render_convergence as rc

    obj, variant, root = cfg.object, cfg.variant, str(cfg.paths.artifacts)
    base = run_object_local(cfg, obj, variant, root, until=appearance_refinement_step.name)

    def at(step, overrides: list[str]):
        setting = OmegaConf.merge(cfg, OmegaConf.from_dotlist(overrides))
        return step.run_local(root=root, scope=seed_scope(obj.name, int(cfg.sampling.seed)),
                              params=step_params(step, setting, obj, variant),
                              inputs={n: base[n] for n in step.spec.inputs})

    study = cfg.render_study
    rows = [
        *rc.resolution_rows({w: at(gbuffer_step, [f"render.width={w}", f"render.height={w}"])
                             for w in study.resolutions}, cfg.render.width),
        *rc.stride_rows({s: at(gbuffer_step, [f"render.frame_stride={s}"]) for s in study.frame_strides},
                        cfg.render.frame_stride),
        *rc.refinement_rows({n: at(appearance_refinement_step, [f"refinement.iterations={n}"])
                             for n in study.refinement_iterations}, base["conditions"], cfg.refinement.iterations),
    ]
    meta = {"object": obj.name, "variant": variant.name, "written": f"{datetime.now():%Y-%m-%d %H:%M}",
            "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores, load average at the end "
                       f"{os.getloadavg()[0]:.1f}",
            "base": {"render.width": cfg.render.width, "render.frame_stride": cfg.render.frame_stride,
                     "refinement.iterations": cfg.refinement.iterations}}
    run_name = cfg.run_name or f"{obj.name}-{datetime.now():%Y%m%d-%H%M%S}"
    path = rc.write_study(Path(cfg.paths.reports) / rc.STUDY_DIR / run_name, rows, meta)
    print(rc.knob_tables(rows))
    print(f"study: {path.with_suffix('.md').resolve()}")
    return path


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/render_convergence")
def main(cfg: DictConfig) -> None:
    run_render_study(cfg)


if __name__ == "__main__":
    main()
