"""Finger modes compared on Table 2:  ``python -m flows.studies.fingers`` (particle pins, grid-node points, colliders).

    python -m flows.studies.fingers objects=[rubber_ball,clay,rubber_duck]
    python -m flows.studies.fingers objects=[clay] modes=[surface_dirichlet,surface_collider]
    python -m flows.studies.fingers objects=[clay] modes=[surface_collider] mpm.quasi_static_damping=0.8
    python -m flows.studies.fingers objects=[can,clay] modes=[grid_dirichlet,grid_particles] spacings=[4,3,2.5]
    python -m flows.studies.fingers objects=[rubber_ball,rubber_duck] modes=[grid_dirichlet] \
        mpm.thin_walls=membrane sampling.thin_wall_layers=2

Runs each object's chain through the cached pipeline steps up to the deformation metrics
(:func:`flows.pipeline.run_object_local`, full variant, the default grid's config ``conf/evaluate.yaml`` with the
mode's overrides, then the pipeline keys given on the command line: ``mpm.*``, ``sampling.*``, ``paths.artifacts``)
and prints one row per object and mode: BDC-T, BDC-S, SDC, mIoU (Table 2), the rollout's wall seconds (its step's
compute time on this shared machine), its substeps and the per-finger reaction (peak over frames and fingers of
|reaction|, N; mean of the per-finger peaks).  Writes ``<out>/finger_study.md``.  No Prefect server: one process,
one run after the other.  Config: ``conf/study/fingers.yaml``; rows and tables: :mod:`tasks.verification.finger_modes`.

``spacings`` adds finer particle spacings (mm) beside the default: the grid refines with them (dx = 2 x spacing)
and the substeps per frame rise as 800 / spacing, which keeps the mass scale (s ~ (dt / dx)^2) of the convergence
study's reference (``conf/study/convergence.yaml``); the default (4 mm, 100 substeps) scales mass 4x more.  Then
each object gets a second table: every run's surface distance (:func:`tasks.verification.convergence.position_error`,
% of the bounding-box diagonal) from the finest run of each mode, so one sees whether a mode's Table 2 scores at
the default spacing are what that mode converges to, and whether the two modes converge to the same motion.
"""
from __future__ import annotations

import platform
from datetime import datetime
from pathlib import Path

import hydra
from omegaconf import DictConfig

from conf.study.schema import FingerStudyConfig, register_study_configs

register_study_configs()


def run_case(obj: str, overrides: list[str]) -> dict:
    """One object's full-variant chain up to the deformation metrics (the pipeline's config with ``overrides``);
    returns the row of the table (:func:`tasks.verification.finger_modes.case_row`)."""
    from flows.pipeline import evaluate_config, run_object_local
    from tasks.core.artifacts import read_artifact
    from tasks.verification.finger_modes import UNTIL, case_row

    cfg = evaluate_config([f"object={obj}", "variant=full", *overrides])
    refs = run_object_local(cfg, cfg.object, cfg.variant, cfg.paths.artifacts, until=UNTIL)
    return case_row(read_artifact(refs["mpm_rollout"]), read_artifact(refs["deformation_metrics"]),
                    refs["mpm_rollout"].compute_seconds)


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/fingers")
def main(cfg: DictConfig) -> None:
    from flows.studies.overrides import pipeline_overrides
    from tasks.verification.convergence import spacing_overrides
    from tasks.verification.finger_modes import MODES, distance_table, table_row

    extra = pipeline_overrides(FingerStudyConfig)
    if any(o.lstrip("+~").split("=")[0] == "object" for o in extra):
        raise SystemExit("input error: object= is set per run by this study: list the objects in objects=[...]")
    for bad in (m for m in cfg.modes if m not in MODES):
        raise SystemExit(f"input error: modes: unknown finger mode {bad!r}; one of {list(MODES)}")
    for bad in (v for v in cfg.spacings if not v > 0):
        raise SystemExit(f"input error: spacings: a particle spacing must be > 0 mm, got {bad:g}")
    from tasks.physics.mpm import SimulationError

    lines = [f"# Finger modes on Table 2 ({datetime.now():%Y-%m-%d %H:%M}, {platform.node()}, Warp CPU)", "",
             "Full variant, default grid config (`conf/evaluate.yaml`) plus the mode's overrides: "
             + "; ".join(f"`{m}`: {' '.join(MODES[m])}" for m in cfg.modes)
             + (f"; every mode also {' '.join(extra)}" if extra else "") + ".  Seconds: the rollout step's "
             "wall time on this shared machine.  Reaction: |reaction| per finger (N), peak over frames and fingers "
             "/ mean of the touching fingers' peaks.  Strain: peak squeeze strain observed / prescribed (eq. 3).", "",
             "| object | mode | spacing | BDC-T | BDC-S | SDC | mIoU | rollout s | substeps | reaction peak / mean (N) "
             "| feedback peak (N, rule) | strain obs / pred | KE/IE |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    spacings = [None, *sorted(cfg.spacings, reverse=True)]  # coarse to fine: each mode's finest run is its last
    distances: list[str] = []
    for obj in cfg.objects:
        runs: dict[tuple[str, str], dict] = {}
        for spacing in spacings:
            label = "default" if spacing is None else f"{spacing:g} mm"
            for mode in cfg.modes:
                try:
                    r = run_case(obj, MODES[mode] + spacing_overrides(spacing) + extra)
                except SimulationError as failed:  # a diverged case is a result of the study, not its end
                    why = "; a pinned particle" if "it is pinned" in str(failed) else ""
                    line = f"| {obj} | {mode} | {label} | failed: {str(failed).split('. ')[0]}{why} |"
                    print(line, flush=True)
                    lines.append(line)
                    continue
                runs[mode, label] = r
                line = table_row(obj, mode, label, r)
                print(line, flush=True)
                lines.append(line)
        if cfg.spacings and runs:
            distances += ["", *distance_table(obj, runs)]
    if distances:
        lines += ["", "## Against resolution", "", "Surface distance (RMS over frames and Gaussians of |x - x_ref|, % "
                  "of the bounding-box diagonal) / reaction error (relative L2 of the per-finger |reaction| over frames "
                  "and fingers, %) of every run from each mode's finest run.", *distances]
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "finger_study.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'finger_study.md'}")


if __name__ == "__main__":
    main()
