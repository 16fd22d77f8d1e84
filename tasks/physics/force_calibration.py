"""The steps of the force-matched ablation (paper Table 2, "VirSqueezer w/o Dirichlet Boundary Constraint"): the
per-object calibration of the force-driven push's constant K (``force_calibration``) and the force-driven rollout
pushed with it (:data:`force_matched_rollout_step`, wired in place of
:data:`tasks.physics.mpm_rollout.mpm_rollout_step` for a variant with ``variant.force_match != none``,
:mod:`flows.pipeline`).  The criterion and the search are in :mod:`tasks.physics.force_match`.
"""
from __future__ import annotations

import math

import numpy as np

from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.physics.force_match import (
    FORCE_MATCHES,
    ROLLOUT_OUTPUTS,
    Calibration,
    calibrate,
    calibration_window,
    mpm_rollout,
    peak_indentation,
    squeeze_regions,
)


@artifact_step("force_calibration",
               inputs=("object_model", "signal_smoothing", "force_coefficients", "contact_patches", "dirichlet_field",
                       "material_oracle"),
               reads=("mpm", "simulation", "variant.boundary", "variant.force_match", "variant.force_match_rtol",
                      "variant.force_match_runs"),
               outputs=("constant", "peak_indentation"))
def force_calibration_step(inputs, params):
    """K (N per unit eq. 1 coefficient) of the force-driven ablation such that its peak indentation under the patches
    equals the prescribed one (``variant.force_match=indentation``), or the configured K (``none``)."""
    if params["variant.boundary"] != "force":
        raise ValueError(f"force_calibration: variant.boundary must be force, got {params['variant.boundary']!r}")
    mode = params["variant.force_match"]
    if mode not in FORCE_MATCHES:
        raise ValueError(f"variant.force_match must be one of {FORCE_MATCHES}, got {mode!r}")
    obj, field_ = inputs["object_model"], inputs["dirichlet_field"].arrays
    patches, times = inputs["contact_patches"].arrays, inputs["signal_smoothing"]["time"]
    forces = inputs["force_coefficients"]["force_coefficients"]
    attrs = {**obj.attrs, "name": obj.ref.scope}
    sim, k0 = dict(params["simulation"]), float(params["simulation"]["force_per_coefficient"])
    last, target = calibration_window(squeeze_regions(attrs, field_, patches, len(times)).predicted)
    if mode == "none":
        cal = Calibration(constant=k0, target=target, rtol=math.inf, runs=[], converged=True)
    else:
        runs = int(params["variant.force_match_runs"])

        def indentation(k: float) -> float:
            d = peak_indentation(obj.arrays, attrs, field_, forces, patches, times,
                                 inputs["material_oracle"].attrs["materials"], params["mpm"], sim, k, last)
            report_progress(len(cal_runs) + 1, runs, unit="calibration run")
            cal_runs.append(k)
            return d

        cal_runs: list[float] = []
        cal = calibrate(indentation, target, k0, rtol=float(params["variant.force_match_rtol"]), max_runs=runs)
    ks = np.array([k for k, _ in cal.runs], np.float64)
    ds = np.array([d for _, d in cal.runs], np.float64)
    arrays = {"constant": Array(ks, ("run",), "N", "K of each calibration run (N per unit force coefficient)"),
              "peak_indentation": Array(ds, ("run",), "1",
                                        "peak squeeze strain of each calibration run (inf: the run failed)")}
    reached = cal.reached if cal.runs else math.nan
    return arrays, {"force_match": mode, "force_per_coefficient": cal.constant, "configured": k0,
                    "target_indentation": target, "reached_indentation": reached, "window_last_frame": last,
                    "rtol": None if math.isinf(cal.rtol) else cal.rtol, "converged": cal.converged,
                    "criterion": "peak squeeze strain under the patches (max over fingers and frames up to the "
                                 "predicted peak) = the eq. 3 field's predicted peak"}


@artifact_step("mpm_rollout",
               inputs=("object_model", "signal_smoothing", "force_coefficients", "contact_patches", "dirichlet_field",
                       "material_oracle", "force_calibration"),
               reads=("mpm", "simulation", "variant.boundary"),
               outputs=ROLLOUT_OUTPUTS)
def force_matched_rollout_step(inputs, params):
    """The force-driven squeeze (``variant.boundary=force``) pushed with the calibrated K of ``force_calibration``
    instead of ``simulation.force_per_coefficient``; otherwise :data:`tasks.physics.mpm_rollout.mpm_rollout_step`."""
    obj, cal = inputs["object_model"], inputs["force_calibration"]
    sim = {**dict(params["simulation"]), "force_per_coefficient": float(cal.attrs["force_per_coefficient"])}
    arrays, attrs = mpm_rollout(obj.arrays, {**obj.attrs, "name": obj.ref.scope}, inputs["dirichlet_field"].arrays,
                                inputs["force_coefficients"]["force_coefficients"], inputs["contact_patches"].arrays,
                                inputs["signal_smoothing"]["time"], inputs["material_oracle"].attrs["materials"],
                                params["mpm"], sim, params["variant.boundary"])
    attrs = {**attrs, "force_per_coefficient": sim["force_per_coefficient"],
             "force_match": cal.attrs["force_match"]}
    return arrays, attrs
