"""Which criterion makes the force-driven ablation as hard as the full squeeze:  ``python -m flows.studies.force_match``
(docs/results/force-matched-ablation.md).

    python -m flows.studies.force_match                                   # the eight objects, seed 0
    python -m flows.studies.force_match objects=[can,clay] simulate=true  # K_R's indentation simulated
    python -m flows.studies.force_match objects=[rubber_duck] sampling.seed=1 paths.artifacts=/tmp/art

Per object (the pipeline's config ``conf/evaluate.yaml`` with the pipeline keys given on the command line): the
full variant's rollout (cached pipeline steps, :func:`flows.pipeline.run_object_local`) gives the peak total normal
reaction of its Dirichlet fingers and the reaction-matched constant K_R
(:func:`tasks.verification.force_criteria.reaction_matched_constant`); the force-matched ``no_dirichlet``'s
rollout (:mod:`tasks.physics.force_matched_rollout`) gives the indentation-matched K and its calibration runs.  The peak indentation at K_R
is read off those runs' (K, peak indentation) curve (log-log interpolation; NaN outside the range the runs spanned)
or, with ``simulate=true``, simulated over the calibration window (:func:`tasks.physics.force_match.peak_indentation`).
Prints one row per object and writes ``<out>/force_match_study.md`` and ``.csv``.  No Prefect server: one process.
Config: ``conf/study/force_match.yaml``; rows and table: :mod:`tasks.verification.force_criteria`.
"""
from __future__ import annotations

import platform
from datetime import datetime
from pathlib import Path

import hydra
from omegaconf import DictConfig

from conf.study.schema import ForceMatchStudyConfig, register_study_configs

register_study_configs()

UNTIL = "mpm_rollout"  # the last pipeline step each variant's run needs


def object_row(obj: str, overrides: list[str], simulate: bool) -> dict:
    """One object's row (:func:`tasks.verification.force_criteria.criterion_row`): its full and its force-matched
    chains up to the rollout (the force-matched one calibrates first), on the pipeline's config with ``overrides``."""
    from flows.pipeline import evaluate_config, run_object_local
    from tasks.core.artifacts import read_artifact
    from tasks.physics.force_match import peak_indentation
    from tasks.physics.preload_state import preload_from_artifact
    from tasks.verification.force_criteria import criterion_row

    full = evaluate_config([f"object={obj}", "variant=full", *overrides])
    matched = evaluate_config([f"object={obj}", "variant=no_dirichlet", *overrides])
    refs = run_object_local(full, full.object, full.variant, full.paths.artifacts, until=UNTIL)
    cal = run_object_local(matched, matched.object, matched.variant, matched.paths.artifacts, until=UNTIL)
    a = {k: read_artifact(refs[k]) for k in ("object_model", "mpm_particles", "signal_smoothing", "force_coefficients",
                                             "contact_patches", "dirichlet_field", "material_oracle", "mpm_rollout",
                                             "gravity_preload")}
    coefficients = a["force_coefficients"]["force_coefficients"]
    preloaded = preload_from_artifact(a["gravity_preload"].arrays, a["gravity_preload"].attrs)  # one for every run

    def simulated(k: float, last: int) -> float:
        body = {**a["object_model"].arrays, **a["mpm_particles"].arrays}
        attrs = {**a["object_model"].attrs, **a["mpm_particles"].attrs, "name": a["object_model"].ref.scope}
        return peak_indentation(body, attrs, a["dirichlet_field"].arrays, coefficients, a["contact_patches"].arrays,
                                a["signal_smoothing"]["time"], a["material_oracle"].attrs["materials"],
                                dict(matched.mpm), dict(matched.simulation), k, last, preloaded)

    return criterion_row(obj, a["mpm_rollout"], a["contact_patches"], coefficients,
                         read_artifact(cal["mpm_rollout"], names=[]).attrs["force_calibration"],
                         simulated if simulate else None)


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/force_match")
def main(cfg: DictConfig) -> None:
    import pandas as pd

    from flows.studies.overrides import pipeline_overrides
    from tasks.verification.force_criteria import criterion_table

    extra = pipeline_overrides(ForceMatchStudyConfig)
    if any(o.lstrip("+~").split("=")[0] in ("object", "variant") for o in extra):
        raise SystemExit("input error: object= and variant= are set per run by this study: list the objects in "
                         "objects=[...]")
    known = sorted(p.stem for p in (Path(__file__).resolve().parents[2] / "conf" / "object").glob("*.yaml"))
    for bad in (o for o in cfg.objects if o not in known):
        raise SystemExit(f"input error: objects: unknown object {bad!r}; one of {known}")
    rows = []
    for obj in cfg.objects:
        rows.append(object_row(obj, extra, bool(cfg.simulate)))
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in rows[-1].items()),
              flush=True)
    how = "simulated over the calibration window" if cfg.simulate else "read off the calibration runs"
    lines = [f"# Force-matched ablation: reaction- vs indentation-matched constants ({datetime.now():%Y-%m-%d %H:%M}, "
             f"{platform.node()}, Warp CPU)", "",
             f"Default grid config (`conf/evaluate.yaml`){' plus ' + ' '.join(extra) if extra else ''}, seed "
             f"{cfg.sampling.seed}.  Indentation at K_R {how}.  Calibration s: the calibration runs' wall seconds on "
             "this shared machine.", "", criterion_table(rows)]
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "force_match_study.md").write_text("\n".join(lines) + "\n")
    pd.DataFrame(rows).to_csv(out / "force_match_study.csv", index=False)
    print(f"wrote {out / 'force_match_study.md'}")


if __name__ == "__main__":
    main()
