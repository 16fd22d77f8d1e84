"""The force-matched ablation's rollout (paper Table 2, "VirSqueezer w/o Dirichlet Boundary Constraint"): the
force-driven squeeze with its constant K (N per unit eq. 1 coefficient) calibrated per object so that its peak
indentation under the patches equals the prescribed one (``variant.force_match=indentation``); wired in place of
:data:`tasks.physics.mpm_rollout.mpm_rollout_step` for such a variant (:mod:`flows.pipeline`).  The criterion, the
search and the calibration runs are in :mod:`tasks.physics.force_match`: the accepted calibration run is the
rollout, so a first guess within the tolerance (the object's ``force_per_coefficient``, measured on the default grid)
costs one rollout, as the uncalibrated push does.
"""
from __future__ import annotations

import math

from tasks.core.step import artifact_step, report_progress
from tasks.physics.force_match import force_matched_rollout
from tasks.physics.preload_state import preload_from_artifact
from tasks.physics.rollout_records import ROLLOUT_OUTPUTS


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


@artifact_step("mpm_rollout",
               inputs=("object_model", "mpm_particles", "signal_smoothing", "force_coefficients", "contact_patches",
                       "dirichlet_field", "material_oracle", "gravity_preload"),
               reads=("mpm", "simulation", "variant.boundary", "variant.force_match", "variant.force_match_rtol",
                      "variant.force_match_runs", "object.force_per_coefficient"),
               outputs=ROLLOUT_OUTPUTS)
def force_matched_rollout_step(inputs, params):
    """The force-driven squeeze (``variant.boundary=force``) pushed with the K that matches the prescribed peak
    indentation, calibrated from the object's ``force_per_coefficient`` (else ``simulation.force_per_coefficient``);
    the rollout artifact of :data:`tasks.physics.mpm_rollout.mpm_rollout_step` with the calibration in its attributes
    (``force_calibration``: the constant, each run's K, peak indentation and wall seconds, the target, whether it
    converged).  Every calibration run starts from the body's gravity preload (the ``gravity_preload`` step's)."""
    if params["variant.boundary"] != "force":
        raise ValueError(f"variant.force_match: calibrates a force-driven push; variant.boundary must be force, got "
                         f"{params['variant.boundary']!r}")
    if params["variant.force_match"] != "indentation":
        raise ValueError(f"variant.force_match: this rollout calibrates the indentation, got "
                         f"{params['variant.force_match']!r} (none: the plain mpm_rollout step)")
    obj, particles, pre = inputs["object_model"], inputs["mpm_particles"], inputs["gravity_preload"]
    sim = dict(params["simulation"])
    prior = params["object.force_per_coefficient"]
    k0 = float(prior if prior is not None else sim["force_per_coefficient"])
    runs = int(params["variant.force_match_runs"])
    arrays, attrs, cal, seconds = force_matched_rollout(
        {**obj.arrays, **particles.arrays}, {**obj.attrs, **particles.attrs, "name": obj.ref.scope},
        inputs["dirichlet_field"].arrays, inputs["force_coefficients"]["force_coefficients"],
        inputs["contact_patches"].arrays, inputs["signal_smoothing"]["time"],
        inputs["material_oracle"].attrs["materials"], params["mpm"], sim, k0, float(params["variant.force_match_rtol"]),
        runs, progress=lambda done, total: report_progress(done, total, unit="calibration run"),
        preloaded=preload_from_artifact(pre.arrays, pre.attrs))
    calibration = {
        "force_match": "indentation", "force_per_coefficient": cal.constant,
        "first_guess": k0, "first_guess_from": "object" if prior is not None else "simulation",
        "target_indentation": cal.target, "reached_indentation": _finite_or_none(cal.reached), "rtol": cal.rtol,
        "converged": cal.converged, "jump": list(cal.jump) if cal.jump else None,
        "runs": [{"constant": k, "peak_indentation": _finite_or_none(d)} for k, d in cal.runs],
        "rerun": len(seconds) > len(cal.runs),  # wall seconds stay out: the artifact's digest must be deterministic
        "criterion": "peak squeeze strain under the patches (max over fingers and frames up to the predicted peak) "
                     "= the eq. 3 field's predicted peak"}
    return arrays, {**attrs, "force_per_coefficient": cal.constant, "force_calibration": calibration}
