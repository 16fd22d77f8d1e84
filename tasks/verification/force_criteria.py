"""Which criterion makes the force-driven ablation as hard as the full squeeze (``python -m flows.studies.force_match``,
docs/results/force-matched-ablation.md): the reaction-matched constant of a full run, the indentation it would reach
(read off the calibration runs or simulated), and the study's row and table.

The force mode's total normal push is ``K sum_k c_k,t`` N before its balance (:func:`tasks.physics.rollout_fingers.
force_patch`); matching it to the full run's peak total normal finger reaction ``max_t sum_k |R_k . n_k|`` gives
``K_R = max_t sum_k |R_k . n_k| / max_t sum_k c_k,t`` (N per unit eq. 1 coefficient).  The indentation-matched
constant is the force-matched rollout's (:mod:`tasks.physics.force_matched_rollout`, attribute ``force_calibration``).
"""
from __future__ import annotations

from typing import Any, Callable, Optional

import numpy as np

from tasks.core.tables import markdown_table
from tasks.physics.force_match import calibration_window

COLUMNS = (("object", "object"), ("peak_reaction_N", "peak sum |R.n| (N)"), ("peak_sum_c", "peak sum c"),
           ("K_reaction", "K_R reaction-matched (N per unit c)"), ("K_indentation", "K indentation-matched"),
           ("indentation_at_K_reaction", "indentation at K_R"), ("prescribed", "prescribed peak"),
           ("ratio_reaction", "at K_R / prescribed"), ("indentation_at_K_indentation", "reached at K"),
           ("converged", "converged"), ("runs", "calibration runs"), ("calibration_s", "calibration s"),
           ("window_last_frame", "window last frame"))


def reaction_matched_constant(reaction: np.ndarray, normals: np.ndarray, coefficients: np.ndarray,
                              active: np.ndarray) -> tuple[float, float, float]:
    """(K_R N per unit coefficient, peak total normal reaction N, peak total coefficient 1): ``reaction`` (frame,
    finger, xyz) N of the Dirichlet fingers, ``normals`` (frame, finger, xyz) the patch normals, ``coefficients``
    (frame, finger) c_k,t, ``active`` (frame, finger) bool."""
    normal = np.abs(np.einsum("fkx,fkx->fk", np.asarray(reaction, np.float64), np.asarray(normals, np.float64)))
    peak_r = float(normal.sum(axis=1).max())
    peak_c = float((np.asarray(coefficients, np.float64) * active).sum(axis=1).max())
    return peak_r / peak_c, peak_r, peak_c


def interpolated_indentation(constants: np.ndarray, indentations: np.ndarray, k: float) -> float:
    """The peak indentation at ``k`` read off calibration runs (``constants`` N, ``indentations`` 1; failed runs
    (inf) left out) by log-log interpolation; NaN outside the constants the runs spanned."""
    ks, ds = np.asarray(constants, np.float64), np.asarray(indentations, np.float64)
    ok = np.isfinite(ds) & (ds > 0)
    ks, ds = ks[ok], ds[ok]
    order = np.argsort(ks)
    if not len(ks) or not ks.min() <= k <= ks.max():
        return float("nan")
    return float(np.exp(np.interp(np.log(k), np.log(ks[order]), np.log(ds[order]))))


def criterion_row(name: str, rollout: Any, patches: Any, coefficients: np.ndarray, calibration: dict,
                  simulate: Optional[Callable[[float, int], float]] = None) -> dict:
    """One object's row: its full run's ``mpm_rollout`` and ``contact_patches`` artifacts, its eq. 1 force
    ``coefficients`` (frame, finger), the force-matched rollout's ``force_calibration`` attributes
    (:mod:`tasks.physics.force_matched_rollout`); the indentation at K_R is ``simulate(K_R, last_frame)`` when given,
    else read off the calibration runs."""
    k_r, peak_r, peak_c = reaction_matched_constant(rollout["reaction_force"], patches["patch_normals"], coefficients,
                                                    patches["patch_active"])
    last, target = calibration_window(rollout["predicted_squeeze_strain"])
    runs = calibration["runs"]
    ks = np.array([r["constant"] for r in runs], np.float64)
    ds = np.array([np.inf if r["peak_indentation"] is None else r["peak_indentation"] for r in runs], np.float64)
    reached = simulate(k_r, last) if simulate is not None else interpolated_indentation(ks, ds, k_r)
    return {"object": name, "peak_reaction_N": peak_r, "peak_sum_c": peak_c, "K_reaction": k_r,
            "K_indentation": calibration["force_per_coefficient"], "indentation_at_K_reaction": reached,
            "prescribed": target, "ratio_reaction": reached / target,
            "indentation_at_K_indentation": calibration["reached_indentation"], "converged": calibration["converged"],
            "runs": len(runs), "calibration_s": float(np.sum(calibration.get("run_seconds", np.nan))), "window_last_frame": last}


def criterion_table(rows: list[dict]) -> list[str]:
    """The study's markdown table (one row per object)."""
    def cell(v: Any) -> str:
        return f"{v:.4g}" if isinstance(v, float) else str(v)

    return markdown_table([h for _, h in COLUMNS], [[cell(r[k]) for k, _ in COLUMNS] for r in rows])
