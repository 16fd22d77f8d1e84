"""Per-finger force coefficients, paper eq. 1, with bidirectional activation.

Paper sec. "Squeezing Control Mapping", eq. 1::

    c_k,t = w_k * max(u~_k,t - beta, 0) ** gamma

u~ is the de-biased flexion (1, from :func:`tasks.control.signal_smoothing.smooth_signals`), beta the activation
threshold, gamma the nonlinearity index and w_k the finger weight.  The paper says the mapping "supports
bidirectional activation to better capture different stages of squeezing behavior" without giving the
formula; the release branch below is this project's definition.

Bidirectional activation (per finger, frame by frame)
-----------------------------------------------------
* Flexion rate ``r_t = du~/dt`` (1/s) by central differences at the frame rate (one-sided at the ends).
* Loading/hold (``r_t >= -release_rate_threshold``): eq. 1, ``c = L(u) = w max(u - beta, 0)^gamma``.
* Releasing (``r_t < -release_rate_threshold``): when a release starts, the previous frame's (u, c) are
  stored as (u_peak, c_peak) and ``c = c_peak * min(max(u - beta, 0) / max(u_peak - beta, eps), 1) ^
  release_gamma``.  This is continuous at the switch (equals c_peak at u = u_peak) and reaches 0 at
  u <= beta.  With release_gamma > gamma the force drops faster than it rose (hysteresis).
* Re-loading after a (partial) release: jumping back onto eq. 1 would be a discontinuity, because the release
  curve lies below L.  From the switch point (u_s, c_s) the coefficient follows
  ``c = max(0, L(u) - (L(u_s) - c_s) * max(u_peak - u, 0) / (u_peak - u_s))`` and rejoins eq. 1 exactly at the
  previous release's u_peak (a minor hysteresis loop).  A hold inside a release (rate back above
  -threshold) is such a re-load with u ~ u_s, so c stays at c_s.  When u_s >= u_peak, or the release ended
  at zero force (u_s <= beta), eq. 1 is used directly (continuous there).
* Phase: 0 idle (c = 0), 1 loading/hold, -1 releasing.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from conf.hand import FINGERS
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step

__all__ = ["force_coefficients", "loading_curve", "PHASE_IDLE", "PHASE_LOADING", "PHASE_RELEASING"]

PHASE_IDLE, PHASE_LOADING, PHASE_RELEASING = 0, 1, -1
_EPS = 1e-9


def loading_curve(u: np.ndarray | float, weight: np.ndarray | float, beta: float, gamma: float) -> np.ndarray:
    """Paper eq. 1: ``w * max(u - beta, 0) ** gamma`` (dimensionless)."""
    return np.asarray(weight) * np.maximum(np.asarray(u, dtype=np.float64) - beta, 0.0) ** gamma


def _validate(flexion: np.ndarray, frame_rate: float, weights: Sequence[float], beta: float, gamma: float,
              release_gamma: float, release_rate_threshold: float) -> np.ndarray:
    w = np.asarray(weights, dtype=np.float64).ravel() if np.ndim(weights) else np.array([weights], float)
    if w.size != len(FINGERS):
        raise ValueError(f"control.force.weights must have {len(FINGERS)} values ({', '.join(FINGERS)}), "
                         f"got {w.size}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError(f"control.force.weights must be finite and >= 0, got {w.tolist()}")
    if not (math.isfinite(beta) and 0 <= beta < 1):
        raise ValueError(f"control.force.beta must be in [0, 1), got {beta}")
    if not (math.isfinite(gamma) and gamma > 0):
        raise ValueError(f"control.force.gamma must be > 0, got {gamma}")
    if not (math.isfinite(release_gamma) and release_gamma > 0):
        raise ValueError(f"control.force.release_gamma must be > 0, got {release_gamma}")
    if not (math.isfinite(release_rate_threshold) and release_rate_threshold >= 0):
        raise ValueError(f"control.force.release_rate_threshold must be >= 0 (1/s), got {release_rate_threshold}")
    if not (math.isfinite(frame_rate) and frame_rate > 0):
        raise ValueError(f"control.smoothing.frame_rate must be > 0, got {frame_rate}")
    if flexion.ndim != 2 or flexion.shape[1] != len(FINGERS) or flexion.shape[0] < 1:
        raise ValueError(f"flexion must have shape (frame, {len(FINGERS)}), got {flexion.shape}")
    if not np.isfinite(flexion).all():
        row = int(np.flatnonzero(~np.isfinite(flexion).all(axis=1))[0])
        raise ValueError(f"flexion is not finite at frame {row}; smooth the signals first")
    return w


def force_coefficients(
    flexion: np.ndarray,
    frame_rate: float,
    weights: Sequence[float],
    beta: float,
    gamma: float,
    release_gamma: float,
    release_rate_threshold: float,
) -> dict[str, Array]:
    """Force coefficients c_k,t (paper eq. 1) with bidirectional activation (module docstring).

    Parameters
    ----------
    flexion:
        De-biased flexion u~ (frame, finger), 1, in [0, 1] (values outside are clipped).
    frame_rate:
        Frame rate (Hz) of ``flexion``, used for the flexion rate (1/s).
    weights:
        w_k, 5 values thumb..pinky (``control.force.weights``), 1.
    beta:
        Activation threshold in [0, 1) (``control.force.beta``), 1.
    gamma:
        Loading nonlinearity > 0 (``control.force.gamma``), 1.
    release_gamma:
        Release nonlinearity > 0 (``control.force.release_gamma``), 1.
    release_rate_threshold:
        Flexion rate (1/s) below ``-release_rate_threshold`` counts as releasing
        (``control.force.release_rate_threshold``).

    Returns
    -------
    ``force_coefficients`` (frame, finger) 1 float64; ``phase`` (frame, finger) int8 (0 idle, 1 loading/hold,
    -1 releasing); ``flexion_rate`` (frame, finger) 1/s.
    """
    u = np.asarray(flexion, dtype=np.float64)
    w = _validate(u, float(frame_rate), weights, float(beta), float(gamma), float(release_gamma),
                  float(release_rate_threshold))
    u = np.clip(u, 0.0, 1.0)
    n, nf = u.shape
    rate = np.gradient(u, 1.0 / frame_rate, axis=0) if n >= 2 else np.zeros_like(u)
    load = loading_curve(u, w, beta, gamma)

    c = np.zeros_like(u)
    phase = np.zeros(u.shape, dtype=np.int8)
    thr = float(release_rate_threshold)
    for k in range(nf):
        wk = float(w[k])
        releasing = False
        u_peak = c_peak = 0.0  # anchor of the current release
        reload_from: tuple[float, float, float] | None = None  # (u_s, c_s, u_peak of the last release)
        u_prev = c_prev = 0.0
        for t in range(n):
            ut = float(u[t, k])
            if rate[t, k] < -thr:
                if not releasing:
                    releasing = True
                    reload_from = None
                    if t == 0:
                        u_peak, c_peak = ut, float(load[t, k])
                    else:
                        u_peak, c_peak = u_prev, c_prev
                ratio = max(ut - beta, 0.0) / max(u_peak - beta, _EPS)
                ct = c_peak * min(ratio, 1.0) ** release_gamma if c_peak > 0 else 0.0
                ph = PHASE_RELEASING
            else:
                if releasing:
                    releasing = False
                    reload_from = (u_prev, c_prev, u_peak) if (u_prev > beta and c_prev > 0) else None
                lt = float(load[t, k])
                if reload_from is not None:
                    u_s, c_s, u_top = reload_from
                    if ut >= u_top or u_top <= u_s:
                        reload_from = None
                        ct = lt
                    else:
                        offset = wk * max(u_s - beta, 0.0) ** gamma - c_s
                        ct = max(0.0, lt - offset * (u_top - ut) / (u_top - u_s))
                else:
                    ct = lt
                ph = PHASE_LOADING
            if ct <= 0.0:
                ct, ph = 0.0, PHASE_IDLE
            c[t, k], phase[t, k] = ct, ph
            u_prev, c_prev = ut, ct
    return {
        "force_coefficients": Array(c, ("frame", "finger"), "1", "force coefficients c_k,t (paper eq. 1)"),
        "phase": Array(phase, ("frame", "finger"), "1", "0 idle, 1 loading/hold, -1 releasing"),
        "flexion_rate": Array(rate, ("frame", "finger"), "1/s", "du~/dt by central differences"),
    }


# ----------------------------------------------------------------------------------------------- Prefect step


@artifact_step("force_coefficients", inputs=("signal_smoothing",),
               reads=("control.force", "control.smoothing.frame_rate"),
               outputs=("force_coefficients", "phase", "flexion_rate"))
def force_coefficients_step(inputs, params):
    """Eq. 1 per finger and frame."""
    f = params["control.force"]
    out = force_coefficients(inputs["signal_smoothing"]["flexion"], params["control.smoothing.frame_rate"],
                             f["weights"], f["beta"], f["gamma"], f["release_gamma"], f["release_rate_threshold"])
    return out, {"peak": [float(v) for v in out["force_coefficients"].data.max(axis=0)]}
