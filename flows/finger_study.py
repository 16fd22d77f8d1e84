"""Finger modes compared on Table 2:  ``python -m flows.finger_study`` (particle pins, grid-node points, colliders).

    python -m flows.finger_study --objects rubber_ball clay rubber_duck
    python -m flows.finger_study --objects clay --modes surface_dirichlet surface_collider
    python -m flows.finger_study --objects clay --modes surface_collider --extra mpm.quasi_static_damping=0.8
    python -m flows.finger_study --objects can clay --modes grid_dirichlet grid_particles --spacings 4 3 2.5
    python -m flows.finger_study --objects rubber_ball rubber_duck --modes grid_dirichlet \
        --extra mpm.thin_walls=membrane sampling.thin_wall_layers=2

Runs each object's chain through the cached pipeline steps up to the deformation metrics
(:func:`flows.pipeline.run_object_local`, full variant, the default grid's config ``conf/evaluate.yaml`` with the
mode's overrides) and prints one row per object and mode: BDC-T, BDC-S, SDC, mIoU (Table 2), the rollout's wall
seconds (its step's compute time on this shared machine), its substeps and the per-finger reaction (peak over
frames and fingers of |reaction|, N; mean of the per-finger peaks).  Writes ``<out>/finger_study.md``.  No Prefect
server: one process, one run after the other.

``--spacings`` adds finer particle spacings (mm) beside the default: the grid refines with them (dx = 2 x spacing)
and the substeps per frame rise as 800 / spacing, which keeps the mass scale (s ~ (dt / dx)^2) of the convergence
study's reference (``conf/convergence.yaml``); the default (4 mm, 100 substeps) scales mass 4x more.  Then each
object gets a second table: every run's surface distance (:func:`tasks.verification.convergence.position_error`,
% of the bounding-box diagonal) from the finest run of each mode, so one sees whether a mode's Table 2 scores at
the default spacing are what that mode converges to, and whether the two modes converge to the same motion.
"""
from __future__ import annotations

import argparse
import platform
from datetime import datetime
from pathlib import Path

MODES = {  # name -> config overrides
    "grid_dirichlet": ["mpm.contact=grid", "mpm.fingers=dirichlet"],
    "grid_particles": ["mpm.contact=grid", "mpm.fingers=particles"],  # the default
    "surface_dirichlet": ["mpm.contact=surface", "mpm.fingers=dirichlet"],
    "surface_collider": ["mpm.contact=surface", "mpm.fingers=collider"],
}
METRICS = ("bdc_t", "bdc_s", "sdc", "miou")


def spacing_overrides(spacing_mm: float | None) -> list[str]:
    """The overrides of one particle spacing (mm) at the convergence study's mass scale; None: the default."""
    if spacing_mm is None:
        return []
    return [f"sampling.particle_spacing={spacing_mm / 1000:g}", f"mpm.target_substeps_per_frame={round(800 / spacing_mm)}"]


def run_case(obj: str, overrides: list[str], root: str) -> dict:
    """One object's full-variant chain up to the deformation metrics; returns the row of the table (and, under
    ``positions``, the surface Gaussians' trajectories (frame, point, xyz) m, under ``reactions`` the fingers'
    |reaction| (frame, finger) N)."""
    import numpy as np

    from flows.pipeline import evaluate_config, run_object_local
    from tasks.core.artifacts import read_artifact

    cfg = evaluate_config([f"object={obj}", "variant=full", *overrides])
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
               ke_ie=rollout.attrs["quasi_static"]["max_ke_ie_in_contact"],
               positions=np.asarray(rollout["gaussian_positions"], np.float64), reactions=reaction)
    return row


def table_row(obj: str, mode: str, label: str, r: dict) -> str:
    """One markdown row of the study's table from :func:`run_case`'s row ``r``: a metric the run has not is ``-``,
    a quasi-static measure the rollout stored as None (kinetic energy without internal energy in a contact, or no
    contact judged) is ``inf / none``."""
    fmt = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    ke_ie = "inf / none" if r["ke_ie"] is None else f"{r['ke_ie']:.3f}"
    return (f"| {obj} | {mode} | {label} | {' | '.join(fmt(r[k]) for k in METRICS)} | {r['seconds']:.0f} | "
            f"{r['substeps']} | {r['reaction_peak']:.2f} / {r['reaction_mean_peak']:.2f} | "
            f"{r['feedback_peak']:.2f} ({r['feedback_rule'].replace('|', '')}) | {r['strain_peak']:.3f} / "
            f"{r['predicted_peak']:.3f} | {ke_ie} |")


def distance_table(obj: str, runs: dict[tuple[str, str], dict]) -> list[str]:
    """Markdown rows: each run's surface distance (% of the bounding-box diagonal,
    :func:`tasks.verification.convergence.distances_from`) and reaction error (relative L2 over frames and fingers,
    :func:`~tasks.verification.convergence.reaction_force_error`) from each mode's finest run.  A failed case has
    no run, so a mode's finest is its last that ran."""
    from tasks.verification.convergence import distances_from, reaction_force_error

    finest: dict[str, tuple[str, str]] = {}
    for key in runs:  # coarse to fine: each mode's last run is its finest
        finest[key[0]] = key
    dist = distances_from({key: r["positions"] for key, r in runs.items()}, finest)

    def cell(key: tuple[str, str], mode: str) -> str:
        react = reaction_force_error(runs[key]["reactions"], runs[finest[mode]]["reactions"])
        return f"{100 * dist[key][mode]:.3f} / {100 * react:.0f}"

    rows = [f"| {obj} | {m} | {s} | " + " | ".join(cell((m, s), o) for o in finest) + " |" for m, s in runs]
    head = " | ".join(f"from {o} at {finest[o][1]}" for o in finest)
    return [f"| object | mode | spacing | {head} |", "|---|---|---|" + "---|" * len(finest), *rows]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="*", default=["rubber_ball", "clay", "rubber_duck"])
    ap.add_argument("--modes", nargs="*", default=list(MODES), choices=list(MODES))
    ap.add_argument("--extra", nargs="*", default=[], help="config overrides added to every mode")
    ap.add_argument("--spacings", nargs="*", type=float, default=[],
                    help="finer particle spacings (mm) run beside the default, coarse to fine (module doc)")
    ap.add_argument("--artifacts", default="artifacts", help="artifact root (the cache the runs share)")
    ap.add_argument("--out", default="reports/fingers", help="folder of finger_study.md")
    args = ap.parse_args(argv)
    from tasks.physics.mpm import SimulationError

    lines = [f"# Finger modes on Table 2 ({datetime.now():%Y-%m-%d %H:%M}, {platform.node()}, Warp CPU)", "",
             "Full variant, default grid config (`conf/evaluate.yaml`) plus the mode's overrides: "
             + "; ".join(f"`{m}`: {' '.join(MODES[m])}" for m in args.modes)
             + (f"; every mode also {' '.join(args.extra)}" if args.extra else "") + ".  Seconds: the rollout step's "
             "wall time on this shared machine.  Reaction: |reaction| per finger (N), peak over frames and fingers "
             "/ mean of the touching fingers' peaks.  Strain: peak squeeze strain observed / prescribed (eq. 3).", "",
             "| object | mode | spacing | BDC-T | BDC-S | SDC | mIoU | rollout s | substeps | reaction peak / mean (N) "
             "| feedback peak (N, rule) | strain obs / pred | KE/IE |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for bad in (v for v in args.spacings if not v > 0):
        ap.error(f"--spacings: a particle spacing must be > 0 mm, got {bad:g}")
    spacings = [None, *sorted(args.spacings, reverse=True)]  # coarse to fine: each mode's finest run is its last
    distances: list[str] = []
    for obj in args.objects:
        runs: dict[tuple[str, str], dict] = {}
        for spacing in spacings:
            label = "default" if spacing is None else f"{spacing:g} mm"
            for mode in args.modes:
                try:
                    r = run_case(obj, MODES[mode] + spacing_overrides(spacing) + list(args.extra), args.artifacts)
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
        if args.spacings and runs:
            distances += ["", *distance_table(obj, runs)]
    if distances:
        lines += ["", "## Against resolution", "", "Surface distance (RMS over frames and Gaussians of |x - x_ref|, % "
                  "of the bounding-box diagonal) / reaction error (relative L2 of the per-finger |reaction| over frames "
                  "and fingers, %) of every run from each mode's finest run.", *distances]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "finger_study.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out / 'finger_study.md'}")


if __name__ == "__main__":
    main()
