"""Finger modes compared on Table 2:  ``python -m flows.finger_study`` (grid-node Dirichlet fingers vs collider fingers).

    python -m flows.finger_study --objects rubber_ball clay rubber_duck
    python -m flows.finger_study --objects clay --modes surface_dirichlet surface_collider
    python -m flows.finger_study --objects clay --modes surface_collider --extra mpm.quasi_static_damping=0.8

Runs each object's chain through the cached pipeline steps up to the deformation metrics
(:func:`flows.pipeline.run_object_local`, full variant, the default grid's config ``conf/evaluate.yaml`` with the
mode's overrides) and prints one row per object and mode: BDC-T, BDC-S, SDC, mIoU (Table 2), the rollout's wall
seconds (its step's compute time on this shared machine), its substeps and the per-finger reaction (peak over
frames and fingers of |reaction|, N; mean of the per-finger peaks).  Writes ``<out>/finger_study.md``.  No Prefect
server: one process, one run after the other.
"""
from __future__ import annotations

import argparse
import platform
from datetime import datetime
from pathlib import Path

MODES = {  # name -> config overrides
    "grid_dirichlet": ["mpm.contact=grid", "mpm.fingers=dirichlet"],  # the default
    "grid_particles": ["mpm.contact=grid", "mpm.fingers=particles"],
    "surface_dirichlet": ["mpm.contact=surface", "mpm.fingers=dirichlet"],
    "surface_collider": ["mpm.contact=surface", "mpm.fingers=collider"],
}
METRICS = ("bdc_t", "bdc_s", "sdc", "miou")


def run_case(obj: str, overrides: list[str], root: str) -> dict:
    """One object's full-variant chain up to the deformation metrics; returns the row of the table."""
    import numpy as np
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from conf.schema import register_configs
    from flows.pipeline import run_object_local
    from tasks.core.artifacts import read_artifact

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(Path(__file__).resolve().parents[1] / "conf"), version_base="1.3"):
        cfg = compose(config_name="evaluate", overrides=[f"object={obj}", "variant=full", *overrides])
    refs = run_object_local(cfg, cfg.object, cfg.variant, root, until="deformation_metrics")
    rollout, metrics = read_artifact(refs["mpm_rollout"]), read_artifact(refs["deformation_metrics"])
    reaction = np.linalg.norm(np.asarray(rollout["reaction_force"]), axis=-1)  # (frame, finger) N
    touched = reaction.max(axis=0) > 0
    row = {k: metrics.attrs["metrics"].get(k) for k in METRICS}
    row.update(seconds=refs["mpm_rollout"].compute_seconds, substeps=int(rollout.attrs["substeps_total"]),
               reaction_peak=float(reaction.max()),
               reaction_mean_peak=float(reaction.max(axis=0)[touched].mean()) if touched.any() else 0.0,
               feedback_peak=float(np.asarray(rollout["feedback_force"]).max()),
               feedback_rule=rollout.attrs["feedback_rule"],
               strain_peak=float(np.asarray(rollout["squeeze_strain"]).max()),
               predicted_peak=float(np.asarray(rollout["predicted_squeeze_strain"]).max()),
               ke_ie=rollout.attrs["quasi_static"]["max_ke_ie_in_contact"])
    return row


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="*", default=["rubber_ball", "clay", "rubber_duck"])
    ap.add_argument("--modes", nargs="*", default=list(MODES), choices=list(MODES))
    ap.add_argument("--extra", nargs="*", default=[], help="config overrides added to every mode")
    ap.add_argument("--artifacts", default="artifacts", help="artifact root (the cache the runs share)")
    ap.add_argument("--out", default="reports/fingers", help="folder of finger_study.md")
    args = ap.parse_args(argv)

    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    lines = [f"# Finger modes on Table 2 ({datetime.now():%Y-%m-%d %H:%M}, {platform.node()}, Warp CPU)", "",
             "Full variant, default grid config (`conf/evaluate.yaml`) plus the mode's overrides: "
             + "; ".join(f"`{m}`: {' '.join(MODES[m])}" for m in args.modes)
             + (f"; every mode also {' '.join(args.extra)}" if args.extra else "") + ".  Seconds: the rollout step's "
             "wall time on this shared machine.  Reaction: |reaction| per finger (N), peak over frames and fingers "
             "/ mean of the touching fingers' peaks.  Strain: peak squeeze strain observed / prescribed (eq. 3).", "",
             "| object | mode | BDC-T | BDC-S | SDC | mIoU | rollout s | substeps | reaction peak / mean (N) "
             "| feedback peak (N, rule) | strain obs / pred | KE/IE |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for obj in args.objects:
        for mode in args.modes:
            r = run_case(obj, MODES[mode] + list(args.extra), args.artifacts)
            line = (f"| {obj} | {mode} | {' | '.join(fmt(r[k]) for k in METRICS)} | {r['seconds']:.0f} | "
                    f"{r['substeps']} | {r['reaction_peak']:.2f} / {r['reaction_mean_peak']:.2f} | "
                    f"{r['feedback_peak']:.2f} ({r['feedback_rule'].replace('|', '')}) | {r['strain_peak']:.3f} / "
                    f"{r['predicted_peak']:.3f} | {r['ke_ie']:.3f} |")
            print(line, flush=True)
            lines.append(line)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "finger_study.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'finger_study.md'}")


if __name__ == "__main__":
    main()
