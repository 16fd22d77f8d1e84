"""Finger modes compared on Table 2 (``python -m flows.studies.fingers``): the modes' config overrides, one run's
row from its rollout and deformation metrics artifacts, and the study's markdown tables.

A mode is how the fingers act on the MPM body (particle pins, grid-node Dirichlet points, surface colliders) and
which contact the body has with them (``mpm.contact``).  Reactions in N, positions in m; the surface distance is
% of the bounding-box diagonal (:func:`tasks.verification.convergence.position_error`).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from tasks.verification.convergence import distances_from, reaction_force_error

MODES = {  # name -> config overrides
    "grid_dirichlet": ["mpm.contact=grid", "mpm.fingers=dirichlet"],
    "grid_particles": ["mpm.contact=grid", "mpm.fingers=particles"],  # the default before issue 50
    "surface_dirichlet": ["mpm.contact=surface", "mpm.fingers=dirichlet"],
    "surface_particles": ["mpm.contact=surface", "mpm.fingers=particles"],  # the default (table at the surface)
    "surface_collider": ["mpm.contact=surface", "mpm.fingers=collider"],
}
METRICS = ("bdc_t", "bdc_s", "sdc", "miou")
UNTIL = "deformation_metrics"  # the last pipeline step a run needs


def case_row(rollout: Any, metrics: Any, seconds: float) -> dict:
    """The row of the table from one run's ``mpm_rollout`` and ``deformation_metrics`` artifacts and the rollout's
    compute ``seconds``; under ``positions`` the surface Gaussians' trajectories (frame, point, xyz) m, under
    ``reactions`` the fingers' |reaction| (frame, finger) N."""
    reaction = np.linalg.norm(np.asarray(rollout["reaction_force"]), axis=-1)  # (frame, finger) N
    touched = reaction.max(axis=0) > 0
    row = {k: metrics.attrs["metrics"].get(k) for k in METRICS}
    row.update(seconds=seconds, substeps=int(rollout.attrs["substeps_total"]),
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
    """One markdown row of the study's table from :func:`case_row`'s row ``r``: a metric the run has not is ``-``,
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
