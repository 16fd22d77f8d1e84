"""Does the body stay put on the table?  ``python -m flows.studies.table_hold <object> <variant> [pipeline keys]``
(docs/limits/table-contact.md, "The hold").

    python -m flows.studies.table_hold plush_toy full mpm.contact=surface mpm.table_hold=footprint
    python -m flows.studies.table_hold rubber_ball no_dirichlet mpm.contact=surface
    python -m flows.studies.table_hold clay no_dirichlet mpm.contact=grid --frames=all

One object's rollout through the cached pipeline steps up to its gravity preload (:func:`flows.pipeline.run_object_local`,
the evaluation grid's config ``conf/evaluate.yaml`` with the keys given), then the rollout itself, up to three frames
past the eq. 3 field's predicted peak (``--frames=all``: the whole session), measured by
:func:`tasks.verification.table_hold.hold_case`: the body's tilt, its footprint's slide and lift, the squeeze strain,
KE/IE and the wall time.  A force-matched variant (``no_dirichlet``) pushes with the object's first guess
(``object.force_per_coefficient``, calibrated on the grid table), not a new calibration.  Prints one line and the
per-frame tilt; side views of the particles go to ``<paths.reports>/table_hold/``.  No Prefect server: one process.
"""
from __future__ import annotations

import sys
from pathlib import Path


def main(argv: list[str]) -> None:
    from flows.pipeline import evaluate_config, run_object_local, step_params
    from tasks.core.artifacts import read_artifact
    from tasks.physics.mpm_rollout import mpm_rollout_step
    from tasks.physics.preload_state import preload_from_artifact
    from tasks.verification.table_hold import hold_case, summary

    whole = "--frames=all" in argv
    args = [a for a in argv if a != "--frames=all"]
    if len(args) < 2 or "=" in args[0] or "=" in args[1]:
        raise SystemExit("input error: usage: python -m flows.studies.table_hold <object> <variant> [key=value ...]"
                         " [--frames=all]")
    obj, variant, overrides = args[0], args[1], args[2:]
    cfg = evaluate_config([f"object={obj}", f"variant={variant}", *overrides])
    refs = run_object_local(cfg, cfg.object, None, cfg.paths.artifacts, until="gravity_preload")
    art = {k: read_artifact(v) for k, v in refs.items()}
    params = step_params(mpm_rollout_step, cfg, cfg.object, cfg.variant)
    sim = dict(params["simulation"])
    if cfg.variant.get("force_match", "none") != "none" and cfg.object.force_per_coefficient:
        sim["force_per_coefficient"] = float(cfg.object.force_per_coefficient)
    out = Path(cfg.paths.reports) / "table_hold"
    out.mkdir(parents=True, exist_ok=True)
    model, particles = art["object_model"], art["mpm_particles"]
    res = hold_case({**model.arrays, **particles.arrays}, {**model.attrs, **particles.attrs, "name": model.ref.scope},
                    art["dirichlet_field"].arrays, art["force_coefficients"]["force_coefficients"],
                    art["contact_patches"].arrays, art["signal_smoothing"]["time"],
                    art["material_oracle"].attrs["materials"], params["mpm"], sim, params["variant.boundary"],
                    preload_from_artifact(art["gravity_preload"].arrays, art["gravity_preload"].attrs),
                    extra=10 ** 6 if whole else 3, snapshots=str(out / f"{obj}_{variant}"))
    print(f"{obj} {variant} {' '.join(overrides)} (K = {sim.get('force_per_coefficient')} N): {summary(res)}")
    print("tilt (deg) per frame:", " ".join(f"{t:.2f}" for t in res["tilt"]))


if __name__ == "__main__":
    main(sys.argv[1:])
