"""Which criterion makes the force-driven ablation as hard as the full squeeze (docs/results/force-matched-ablation.md).

Per object (default grid, ``sampling.seed``): the full variant's rollout (cached pipeline steps,
:func:`flows.pipeline.run_object_local`) gives the peak total normal reaction of its Dirichlet fingers,
``max_t sum_k |R_k . n_k|``; the reaction-matched constant is that over the peak total push coefficient,
``K_R = max_t sum_k |R_k . n_k| / max_t sum_k c_k,t`` (the force mode's total normal push is ``K sum_k c_k,t``
before its balance).  The force-driven squeeze pushed with K_R over the calibration window
(:func:`tasks.physics.force_match.peak_indentation`) reaches a peak indentation that is compared with the
prescribed one, and with the indentation-matched constant of the ``force_calibration`` step (the default
``no_dirichlet``).  Without ``+simulate=true`` the indentation at K_R is read off the calibration runs' (K, peak
indentation) curve (log-log interpolation; NaN outside the range the runs spanned) instead of simulated.  Prints
one row per object and writes them as CSV::

    python -m flows.force_match_study [grid.objects=[can,clay]] [+simulate=true] [+out=/tmp/force_match.csv]
"""
from __future__ import annotations

import sys

import numpy as np


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


def main(overrides: list[str]) -> None:
    import pandas as pd

    from flows.pipeline import evaluate_config, run_object_local
    from flows.selection import selected_objects
    from tasks.physics.force_match import calibration_window, peak_indentation

    out = next((o.split("=", 1)[1] for o in overrides if o.startswith("+out=")), None)
    simulate = "+simulate=true" in overrides
    cfg = evaluate_config([o for o in overrides if not o.startswith(("+out=", "+simulate="))])
    rows = []
    for obj in selected_objects(cfg):
        refs = run_object_local(cfg, obj, cfg.variants.full, cfg.paths.artifacts, until="mpm_rollout")
        matched = run_object_local(cfg, obj, cfg.variants.no_dirichlet, cfg.paths.artifacts, until="force_calibration")
        from tasks.core.artifacts import read_artifact

        a = {k: read_artifact(refs[k]) for k in ("object_model", "signal_smoothing", "force_coefficients",
                                                  "contact_patches", "dirichlet_field", "material_oracle",
                                                  "mpm_rollout")}
        cal_art = read_artifact(matched["force_calibration"])
        cal = cal_art.attrs
        r, p = a["mpm_rollout"], a["contact_patches"]
        k_r, peak_r, peak_c = reaction_matched_constant(r["reaction_force"], p["patch_normals"],
                                                        a["force_coefficients"]["force_coefficients"],
                                                        p["patch_active"])
        last, target = calibration_window(r["predicted_squeeze_strain"])
        if simulate:
            reached = peak_indentation(a["object_model"].arrays, {**a["object_model"].attrs, "name": obj.name},
                                       a["dirichlet_field"].arrays, a["force_coefficients"]["force_coefficients"],
                                       p.arrays, a["signal_smoothing"]["time"],
                                       a["material_oracle"].attrs["materials"], dict(cfg.mpm), dict(cfg.simulation),
                                       k_r, last)
        else:
            reached = interpolated_indentation(cal_art["constant"], cal_art["peak_indentation"], k_r)
        row = {"object": obj.name, "peak_reaction_N": peak_r, "peak_sum_c": peak_c, "K_reaction": k_r,
               "indentation_at_K_reaction": reached, "prescribed": target, "ratio_reaction": reached / target,
               "K_indentation": cal["force_per_coefficient"], "indentation_at_K_indentation": cal["reached_indentation"],
               "converged": cal["converged"], "window_last_frame": last}
        rows.append(row)
        print(" ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()), flush=True)
    df = pd.DataFrame(rows)
    print(df.to_string(index=False))
    if out:
        df.to_csv(out, index=False)


if __name__ == "__main__":
    main(sys.argv[1:])
