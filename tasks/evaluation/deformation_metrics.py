"""Squeezing-controlled deformation metrics (paper sec. "Evaluation for Squeezing Controlled Deformation", Table 2).

The paper states only the intent of BDC-T, BDC-S, SDC and mIoU (and, in its Supplementary Part 6, of the
trajectory metrics ATE, MTE, time consistency error and cosine similarity).  This module fixes exact
definitions; :data:`DEFINITIONS` holds them as plain text (the report prints them).  All four main scores are
in [0, 1], higher is better.  Conventions shared by every metric:

* a finger *touches* when its predicted squeeze strain (from the prescribed eq. 3 field) is not identically 0;
* the observed non-rigid displacement ``u_obs`` of the surface points is their motion from frame 0 after the
  best rigid motion of the whole surface is removed (Umeyama fit), so moving or tilting the object scores no
  deformation;
* a metric with no frame, finger or pair to average over is NaN (in the step's JSON attrs: None), never an
  error: e.g. a session in which no finger touches the object has NaN trajectory metrics ("no contact").
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from conf.hand import N_FINGERS
from conf.metrics_schema import MetricsConfig, validate_metrics
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step
from tasks.evaluation.metric_ranges import check_metrics
from tasks.physics.regions import finger_regions

__all__ = ["DEFINITIONS", "bdc_s", "bdc_t", "concordance", "deformation_metrics", "deformation_metrics_step",
           "finger_trajectories", "miou", "nonrigid_displacement", "pearson", "physical_figures", "sdc",
           "touching_fingers", "trajectory_metrics", "umeyama"]

DEFINITIONS: dict[str, str] = {
    "bdc_t": (
        "BDC-T (temporal boundary-deformation consistency, 1, in [0, 1]): for each finger k that touches (its "
        "predicted squeeze strain is not identically 0), Lin's concordance correlation coefficient between the "
        "prescribed series a = predicted_squeeze_strain[:, k] (squeeze strain of the eq. 3 field) and the observed "
        "series b = squeeze_strain[:, k] (same measure on the simulated surface), CCC = 2 cov(a, b) / (var a + "
        "var b + (mean a - mean b)^2) with population moments over all frames, clipped to [0, 1]; BDC-T is the "
        "mean over the touching fingers. Unlike a correlation, CCC also penalises scale and offset differences "
        "(b = c a scores 2c / (1 + c^2) for zero-mean a)."),
    "sdc": (
        "SDC (squeezing-deformation coupling, 1, in [0, 1]): mean over the touching fingers of max(0, Pearson "
        "correlation over all frames between the force coefficient c_k,t of eq. 1 and the observed squeeze strain "
        "of finger k). Scale-free, because control and deformation have different units. A series with zero "
        "variance has correlation 0 (no evidence of coupling)."),
    "nonrigid_displacement": (
        "Observed non-rigid displacement u_obs (m): u_obs[t] = x[t] - (R_t x[0] + t_t), x = gaussian_positions "
        "(the simulated surface points), (R_t, t_t) the least-squares rigid motion (Umeyama 1991, rotation with "
        "the reflection fix, no scale) of x[0] onto x[t]. A rigidly moved or tilted object has u_obs = 0. "
        "nonrigid_displacement_rms[t] = sqrt(mean_i |u_obs[t, i]|^2)."),
    "bdc_s": (
        "BDC-S (spatial boundary-deformation consistency, 1, in [0, 1]): for each frame t whose Dirichlet set "
        "A_t = {i: constrained[t, i]} is non-empty, D_t = the |A_t| surface points with the largest "
        "|u_obs[t, i]| (ties broken by the lower point index), IoU_t = |A_t & D_t| / |A_t | D_t|; BDC-S is the "
        "mean of IoU_t over those frames. It asks whether the most deformed points are the finger-constrained "
        "ones (the mIoU paradigm with the region size fixed by the contact set)."),
    "miou": (
        "mIoU (deformed region vs. region inferred from the controls, 1, in [0, 1]): for each frame t with "
        "m_t = max_i |prescribed[t, i]| > 0 (prescribed = the eq. 3 displacement field), delta_t = "
        "region_fraction * m_t, I_t = {i: |prescribed[t, i]| >= delta_t}, O_t = {i: |u_obs[t, i]| >= delta_t}, "
        "IoU_t = |I_t & O_t| / |I_t | O_t|; the 'm' is the mean of IoU_t over those frames (not over classes)."),
    "ate": (
        "ATE (absolute trajectory error, m): for finger k with contact frames C_k (patch_active[:, k]) and first "
        "contact frame t_k0, the sensed trajectory dp_k(t) = fingertip_positions[t, k] - fingertip_positions"
        "[t_k0, k] and the reconstructed one dq_k(t) = q_k(t) - q_k(t_k0), q_k(t) the mean of gaussian_positions"
        "[t] over finger k's region (the largest set of points finger k ever constrained; a fixed set, so q_k "
        "follows the same material points). All pairs (k, t in C_k) are stacked; ATE is the RMS of "
        "|dp - (s R dq + t)| after the Umeyama alignment of dq onto dp (rotation and translation; scale s too "
        "when ate_with_scale, else s = 1)."),
    "mte": "MTE (mean trajectory error, m): mean over the stacked contact pairs of |dp - dq| (no alignment).",
    "tce": (
        "TCE (time consistency error, m/s): RMS over consecutive contact-frame pairs (t, t+1 both in C_k) of "
        "|(dp(t+1) - dp(t)) - (dq(t+1) - dq(t))| / frame_dt: the velocity mismatch of the two trajectories."),
    "cosine_similarity": (
        "Cosine similarity (1, in [-1, 1]): mean over consecutive contact-frame pairs whose sensed and "
        "reconstructed increments are both longer than min_motion of the cosine of the angle between "
        "dp(t+1) - dp(t) and dq(t+1) - dq(t)."),
    "volume_ratio": (
        "volume_ratio[t] (1) = sum_p v0_p J_p(t) / sum_p v0_p over all rollout particles (shell then interior), "
        "v0 the rest volumes of the object's particles and J = det F."),
    "max_volume_change": "max_volume_change (1) = max_t |volume_ratio[t] - 1|.",
    "max_squeeze_strain": "max_squeeze_strain (1) = max over frames and fingers of the observed squeeze strain.",
    "rebound_ratio": (
        "rebound_ratio (1) = 1 - m(T-1) / max_t m(t) with m(t) = max_k squeeze_strain[t, k]: 1 = full rebound, "
        "0 = the peak dent is kept at the last frame (> 1 if the region ends bulged outwards); NaN when the peak "
        "strain is below 1e-6."),
    "peak_reaction_force": "peak_reaction_force (N, per finger) = max_t |reaction_force[t, k]| (Dirichlet mode).",
    "peak_applied_force": "peak_applied_force (N, per finger) = max_t |applied_force[t, k]| (force mode).",
    "peak_feedback_force": "peak_feedback_force (N, per finger) = max_t feedback_force[t, k] (glove resistance).",
    "max_ke_ie_in_contact": (
        "max_ke_ie_in_contact (1) = the largest value of the quasi-static check's measure (mass scaling, "
        "tasks/physics/mpm/mass_scaling.py) over the contacts it judges: sum KE / sum (IE + plastic work dissipated so far, "
        "Abaqus' ALLIE) of the mass-scaled material over "
        "the checked frames of one contact, a frame being checked when a finger loads the object, past the "
        "contact's first frames and before a rupture; NaN when no contact is judged (no mass scaling, no contact)."),
    "quasi_static_warned": (
        "quasi_static_warned = 1 when the check warned (a contact's KE/IE > mpm.quasi_static_ke_ie_max: the "
        "squeeze was dynamic in the scaled time), 0 when it passed, NaN when no contact is judged."),
    "threshold_time": "threshold_time (s): time of the squeeze-threshold crossing (rupture); NaN when not crossed.",
}

_TINY = 1e-300


# ----------------------------------------------------------------------------------------------- validation
def _shape_text(shape: tuple) -> str:
    return "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"


def _checked(name: str, value: Any, expected: tuple, dtype: Any = np.float64) -> np.ndarray:
    """``value`` as an array of ``expected`` shape (entries: int or None for any size), else a ValueError."""
    a = np.asarray(value.data if isinstance(value, Array) else value, dtype=dtype)
    if a.ndim != len(expected) or any(e is not None and s != e for s, e in zip(a.shape, expected)):
        want = _shape_text(tuple("n" if e is None else e for e in expected))
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    return a


def _mean_or_nan(values: np.ndarray) -> float:
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else math.nan


# ----------------------------------------------------------------------------------------------- BDC-T, SDC
def concordance(a: np.ndarray, b: np.ndarray) -> float:
    """Lin's concordance correlation coefficient (1, in [-1, 1]) of two series of equal length.

    CCC = 2 cov(a, b) / (var a + var b + (mean a - mean b)^2) with population (1/n) moments.  Two identical
    constant series give 1; two different constant series give 0.
    """
    a = _checked("a", a, (None,))
    b = _checked("b", b, (a.shape[0],))
    if a.size == 0:
        raise ValueError("a must have at least one frame, got 0")
    da, db = a - a.mean(), b - b.mean()
    num = 2.0 * np.mean(da * db)
    den = np.mean(da * da) + np.mean(db * db) + (a.mean() - b.mean()) ** 2
    if den <= _TINY:
        return 1.0 if np.array_equal(a, b) else 0.0
    return float(num / den)


def pearson(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation (1, in [-1, 1]) of two series of equal length; 0 when either has zero variance."""
    a = _checked("a", a, (None,))
    b = _checked("b", b, (a.shape[0],))
    da, db = a - a.mean(), b - b.mean()
    den = math.sqrt(float(np.sum(da * da)) * float(np.sum(db * db)))
    return float(np.sum(da * db) / den) if den > _TINY else 0.0


def touching_fingers(predicted_strain: np.ndarray) -> np.ndarray:
    """(finger,) bool: the finger's predicted squeeze strain (frame, finger) is not identically 0."""
    p = _checked("predicted_squeeze_strain", predicted_strain, (None, N_FINGERS))
    return np.any(p != 0.0, axis=0)


def bdc_t(predicted_strain: np.ndarray, observed_strain: np.ndarray) -> tuple[float, np.ndarray]:
    """BDC-T (1, in [0, 1]) and its per-finger values (finger,) (NaN for fingers that never touch).

    Per touching finger k (predicted strain not identically 0): clip(CCC(predicted[:, k], observed[:, k]), 0, 1)
    (:func:`concordance`, population moments); BDC-T = mean over touching fingers, NaN if none touches.
    ``predicted_strain`` = rollout ``predicted_squeeze_strain`` (frame, finger), ``observed_strain`` = rollout
    ``squeeze_strain`` (frame, finger), both 1.
    """
    p = _checked("predicted_squeeze_strain", predicted_strain, (None, N_FINGERS))
    o = _checked("squeeze_strain", observed_strain, p.shape)
    per = np.full(N_FINGERS, np.nan)
    for k in np.flatnonzero(touching_fingers(p)):
        per[k] = min(max(concordance(p[:, k], o[:, k]), 0.0), 1.0)
    return _mean_or_nan(per), per


def sdc(force_coefficients: np.ndarray, observed_strain: np.ndarray, touching: np.ndarray | None = None
        ) -> tuple[float, np.ndarray]:
    """SDC (1, in [0, 1]) and its per-finger values (finger,) (NaN for fingers that never touch).

    Per touching finger k: max(0, Pearson(force_coefficients[:, k], observed_strain[:, k])) over all frames
    (:func:`pearson`); SDC = mean over touching fingers, NaN if none.  ``touching`` (finger,) bool defaults to
    "force coefficient not identically 0"; the step passes :func:`touching_fingers` of the predicted strain.
    """
    c = _checked("force_coefficients", force_coefficients, (None, N_FINGERS))
    o = _checked("squeeze_strain", observed_strain, c.shape)
    touch = np.any(c != 0.0, axis=0) if touching is None else _checked("touching", touching, (N_FINGERS,), bool)
    per = np.full(N_FINGERS, np.nan)
    for k in np.flatnonzero(touch):
        per[k] = max(pearson(c[:, k], o[:, k]), 0.0)
    return _mean_or_nan(per), per


# ----------------------------------------------------------------------------------------------- rigid motion
def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (or rigid) transform: (s, R, t) minimising sum_i |dst_i - (s R src_i + t)|^2.

    Umeyama (1991): with the centred point sets and Sigma = dst_c^T src_c / n = U D V^T, R = U S V^T with
    S = diag(1, ..., 1, sign(det U det V)) (the reflection fix: R is always a proper rotation, det R = +1),
    s = trace(D S) / (mean_i |src_c,i|^2) when ``with_scale`` (1 when src is a single point), else s = 1, and
    t = mean(dst) - s R mean(src).  ``src``, ``dst`` (n, d), any unit (t has it).
    """
    src = _checked("src", src, (None, None))
    dst = _checked("dst", dst, src.shape)
    if src.shape[0] == 0:
        raise ValueError("src must hold at least one point, got 0")
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    sc, dc = src - mu_s, dst - mu_d
    U, D, Vt = np.linalg.svd(dc.T @ sc / src.shape[0])
    S = np.ones(src.shape[1])
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[-1] = -1.0
    R = (U * S) @ Vt
    var_s = float(np.mean(np.sum(sc * sc, axis=1)))
    s = float(np.sum(D * S) / var_s) if with_scale and var_s > _TINY else 1.0
    return s, R, mu_d - s * R @ mu_s


def nonrigid_displacement(positions: np.ndarray) -> np.ndarray:
    """u_obs (frame, point, xyz) m: surface motion from frame 0 with the best rigid motion removed.

    u_obs[t] = x[t] - (R_t x[0] + t_t), (R_t, t_t) = :func:`umeyama` (no scale) of x[0] onto x[t];
    ``positions`` = rollout ``gaussian_positions`` (frame, point, xyz) m.
    """
    x = _checked("gaussian_positions", positions, (None, None, 3))
    if x.shape[0] == 0 or x.shape[1] == 0:
        raise ValueError(f"gaussian_positions must hold at least one frame and one point, got {x.shape}")
    u = np.empty_like(x)
    for f in range(x.shape[0]):
        _, R, t = umeyama(x[0], x[f])
        u[f] = x[f] - (x[0] @ R.T + t)
    return u


# ----------------------------------------------------------------------------------------------- BDC-S, mIoU
def _iou(a: np.ndarray, b: np.ndarray) -> float:
    union = np.count_nonzero(a | b)
    return np.count_nonzero(a & b) / union if union else math.nan


def bdc_s(constrained: np.ndarray, u_obs: np.ndarray) -> tuple[float, np.ndarray]:
    """BDC-S (1, in [0, 1]) and IoU_t per frame (frame,) (NaN where no point is constrained).

    A_t = {i: constrained[t, i]}; D_t = the |A_t| points with the largest |u_obs[t, i]| (ties: lower index
    first); IoU_t = |A & D| / |A | D|; BDC-S = mean over frames with A_t non-empty (NaN if none).
    ``constrained`` (frame, point) bool (dirichlet field), ``u_obs`` (frame, point, xyz) m.
    """
    A = _checked("constrained", constrained, (None, None), bool)
    u = _checked("u_obs", u_obs, (*A.shape, 3))
    mag = np.linalg.norm(u, axis=-1)
    iou = np.full(A.shape[0], np.nan)
    for f in range(A.shape[0]):
        n = int(np.count_nonzero(A[f]))
        if n:
            D = np.zeros(A.shape[1], bool)
            D[np.argsort(-mag[f], kind="stable")[:n]] = True
            iou[f] = _iou(A[f], D)
    return _mean_or_nan(iou), iou


def miou(prescribed: np.ndarray, u_obs: np.ndarray, region_fraction: float = 0.1) -> tuple[float, np.ndarray]:
    """mIoU (1, in [0, 1]) and IoU_t per frame (frame,) (NaN where nothing is prescribed).

    For frames with m_t = max_i |prescribed[t, i]| > 0: delta_t = region_fraction * m_t,
    I_t = {|prescribed| >= delta_t}, O_t = {|u_obs| >= delta_t}, IoU_t = |I & O| / |I | O|; mIoU = mean over
    those frames (NaN if none).  ``prescribed`` = field ``displacement`` and ``u_obs`` (frame, point, xyz) m.
    """
    if not 0.0 < region_fraction < 1.0:
        raise ValueError(f"region_fraction must be in (0, 1), got {region_fraction}")
    p = np.linalg.norm(_checked("displacement", prescribed, (None, None, 3)), axis=-1)
    o = np.linalg.norm(_checked("u_obs", u_obs, (*p.shape, 3)), axis=-1)
    iou = np.full(p.shape[0], np.nan)
    for f in range(p.shape[0]):
        peak = p[f].max(initial=0.0)
        if peak > 0.0:
            delta = region_fraction * peak
            iou[f] = _iou(p[f] >= delta, o[f] >= delta)
    return _mean_or_nan(iou), iou


# ----------------------------------------------------------------------------------------------- trajectories
def finger_trajectories(fingertips: np.ndarray, positions: np.ndarray, region: np.ndarray, contact: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Sensed dp and reconstructed dq (frame, finger, xyz) m, NaN outside each finger's contact frames.

    dp_k(t) = fingertips[t, k] - fingertips[t_k0, k], dq_k(t) = q_k(t) - q_k(t_k0), t_k0 the first frame with
    contact[:, k], q_k(t) = mean of positions[t, i] over the fixed point set region[k].  A finger without
    contact, or with contact but an empty region, is NaN throughout.  ``fingertips`` (frame, finger, xyz) m,
    ``positions`` (frame, point, xyz) m, ``region`` (finger, point) bool, ``contact`` (frame, finger) bool.
    """
    tips = _checked("fingertip_positions", fingertips, (None, N_FINGERS, 3))
    x = _checked("gaussian_positions", positions, (tips.shape[0], None, 3))
    reg = _checked("region", region, (N_FINGERS, x.shape[1]), bool)
    act = _checked("patch_active", contact, (tips.shape[0], N_FINGERS), bool)
    dp = np.full(tips.shape, np.nan)
    dq = np.full(tips.shape, np.nan)
    for k in range(N_FINGERS):
        frames = np.flatnonzero(act[:, k])
        if frames.size == 0 or not reg[k].any():
            continue
        q = x[frames][:, reg[k]].mean(axis=1)
        dp[frames, k] = tips[frames, k] - tips[frames[0], k]
        dq[frames, k] = q - q[0]
    return dp, dq


def trajectory_metrics(sensed: np.ndarray, reconstructed: np.ndarray, contact: np.ndarray, frame_dt: float,
                       ate_with_scale: bool = False, min_motion: float = 1e-5) -> dict[str, float]:
    """ATE (m), MTE (m), TCE (m/s) and cosine similarity (1) of two displacement trajectories.

    ``sensed`` dp and ``reconstructed`` dq (frame, finger, xyz) m, ``contact`` (frame, finger) bool.  Stacked
    over all (k, t) with contact[t, k]: ATE = RMS |dp - (s R dq + t)| after :func:`umeyama` of dq onto dp
    (scale only if ``ate_with_scale``); MTE = mean |dp - dq|.  Over consecutive pairs (t, t+1 both in contact)
    with e = Delta dp - Delta dq: TCE = RMS |e| / frame_dt; cosine = mean cos angle(Delta dp, Delta dq) over the
    pairs where both increments are longer than ``min_motion`` (m).  Metrics with nothing to average are NaN.
    Also returns the counts ``n_points``, ``n_pairs`` and ``n_cosine_pairs``.
    """
    dp = _checked("sensed", sensed, (None, N_FINGERS, 3))
    dq = _checked("reconstructed", reconstructed, dp.shape)
    act = _checked("contact", contact, dp.shape[:2], bool)
    if not (math.isfinite(frame_dt) and frame_dt > 0):
        raise ValueError(f"frame_dt must be > 0 s (frame times must increase), got {frame_dt}")
    if not (math.isfinite(min_motion) and min_motion >= 0):
        raise ValueError(f"min_motion must be >= 0 m, got {min_motion}")
    out = {"ate": math.nan, "mte": math.nan, "tce": math.nan, "cosine_similarity": math.nan,
           "n_points": 0, "n_pairs": 0, "n_cosine_pairs": 0}
    P, Q = dp[act], dq[act]
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise ValueError("sensed and reconstructed must be finite on every contact frame; build them with "
                         "finger_trajectories")
    if len(P) == 0:
        return out
    s, R, t = umeyama(Q, P, with_scale=ate_with_scale)
    out["ate"] = float(np.sqrt(np.mean(np.sum((P - (s * Q @ R.T + t)) ** 2, axis=1))))
    out["mte"] = float(np.mean(np.linalg.norm(P - Q, axis=1)))
    out["n_points"] = len(P)
    pair = act[1:] & act[:-1]
    if not pair.any():
        return out
    vp, vq = (dp[1:] - dp[:-1])[pair], (dq[1:] - dq[:-1])[pair]
    out["tce"] = float(np.sqrt(np.mean(np.sum((vp - vq) ** 2, axis=1)))) / frame_dt
    out["n_pairs"] = len(vp)
    npn, nqn = np.linalg.norm(vp, axis=1), np.linalg.norm(vq, axis=1)
    moving = (npn > min_motion) & (nqn > min_motion)
    if moving.any():
        out["cosine_similarity"] = float(np.mean(np.sum(vp[moving] * vq[moving], axis=1) / (npn * nqn)[moving]))
        out["n_cosine_pairs"] = int(moving.sum())
    return out


# ----------------------------------------------------------------------------------------------- physics
def physical_figures(particle_J: np.ndarray, volumes: np.ndarray, strain: np.ndarray, reaction: np.ndarray,
                     applied: np.ndarray, feedback: np.ndarray, contact_ke_ie: np.ndarray, ke_ie_limit: float,
                     threshold_event: Mapping[str, Any] | None) -> tuple[dict[str, float], dict[str, np.ndarray],
                                                                         np.ndarray]:
    """Physical figures of one rollout: (scalars, per-finger arrays, volume_ratio (frame,)).

    volume_ratio[t] = sum v0 J[t] / sum v0; max_volume_change = max |volume_ratio - 1|; max_squeeze_strain =
    max strain; rebound_ratio = 1 - m[-1] / max m with m = max_k strain[:, k] (NaN if max m < 1e-6);
    max_ke_ie_in_contact = max of the quasi-static check's measure over the contacts it judged, ``contact_ke_ie``
    (contact,), and quasi_static_warned = 1 if one exceeded ``ke_ie_limit``, else 0 (both NaN when no contact was
    judged; a NaN ratio, kinetic energy without internal energy, exceeds it); threshold_time (s) =
    threshold_event["time"] if crossed else NaN.  Per finger (N): peak |reaction|, peak |applied| and peak feedback
    force.  Shapes: particle_J (frame, particle), volumes (particle,) m^3, strain and feedback (frame, finger),
    reaction and applied (frame, finger, xyz) N.
    """
    J = _checked("particle_J", particle_J, (None, None))
    T = J.shape[0]
    v0 = _checked("particle volumes", volumes, (J.shape[1],))
    eps = _checked("squeeze_strain", strain, (T, N_FINGERS))
    rf = _checked("reaction_force", reaction, (T, N_FINGERS, 3))
    af = _checked("applied_force", applied, (T, N_FINGERS, 3))
    fb = _checked("feedback_force", feedback, (T, N_FINGERS))
    measure = np.nan_to_num(_checked("contact KE/IE", contact_ke_ie, (None,)), nan=np.inf)  # NaN: KE without IE
    if T == 0 or v0.sum() <= 0:
        raise ValueError(f"particle_J needs >= 1 frame and the particle volumes a positive sum, got {J.shape}, "
                         f"{v0.sum()} m^3")
    volume_ratio = J @ v0 / v0.sum()
    m = eps.max(axis=1)
    peak = float(m.max())
    event = dict(threshold_event or {})
    scalars = {
        "max_volume_change": float(np.abs(volume_ratio - 1.0).max()),
        "max_squeeze_strain": float(eps.max()),
        "rebound_ratio": 1.0 - float(m[-1]) / peak if peak >= 1e-6 else math.nan,
        "max_ke_ie_in_contact": float(measure.max()) if measure.size and np.isfinite(measure.max()) else math.nan,
        "quasi_static_warned": float((measure > ke_ie_limit).any()) if measure.size else math.nan,
        "threshold_time": float(event["time"]) if event.get("crossed") else math.nan,
    }
    per_finger = {
        "peak_reaction_force": np.linalg.norm(rf, axis=-1).max(axis=0),
        "peak_applied_force": np.linalg.norm(af, axis=-1).max(axis=0),
        "peak_feedback_force": fb.max(axis=0),
    }
    return scalars, per_finger, volume_ratio


# ----------------------------------------------------------------------------------------------- all together
def _json_float(v: Any) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def deformation_metrics(rollout: Mapping[str, np.ndarray], rollout_attrs: Mapping[str, Any],
                        field: Mapping[str, np.ndarray], forces: Mapping[str, np.ndarray],
                        contacts: Mapping[str, np.ndarray], frames: Mapping[str, np.ndarray],
                        obj: Mapping[str, np.ndarray], params: Mapping[str, Any] | MetricsConfig | None = None,
                        scene: str = "this scene") -> tuple[dict[str, Array], dict[str, Any]]:
    """Every metric of :data:`DEFINITIONS` for one object and variant.

    Inputs are the artifacts' arrays (mappings name -> numpy): ``rollout`` (mpm_rollout) with its attrs
    ``rollout_attrs``, ``field`` (dirichlet_field), ``forces`` (force_coefficients), ``contacts``
    (contact_patches), ``frames`` (signal_smoothing), ``obj`` (mpm_particles); ``params`` the ``metrics`` config
    (:class:`conf.metrics_schema.MetricsConfig` values); ``scene`` names the object in the error raised for a value
    outside its documented range (:func:`tasks.evaluation.metric_ranges.check_metrics`: a bug, never a result).

    Returns the per-frame arrays ``bdc_s_iou``, ``miou_iou``, ``volume_ratio``, ``nonrigid_displacement_rms``,
    ``sensed_trajectory``, ``reconstructed_trajectory`` and the attrs ``{"metrics": name -> float or None (NaN),
    "per_finger": name -> 5 values, "counts": ..., "definitions": DEFINITIONS}`` (JSON-safe).
    """
    cfg = validate_metrics(params)
    time = _checked("frames time", frames["time"], (None,))
    T = time.shape[0]
    if T == 0:
        raise ValueError("frames time must hold at least one frame, got 0")
    frame_dt = float(np.median(np.diff(time))) if T > 1 else math.nan
    if T > 1 and not frame_dt > 0:
        raise ValueError(f"frames time must increase, got a median step of {frame_dt} s")
    S = _checked("field surface_points", field["surface_points"], (None, 3)).shape[0]
    x = _checked("rollout gaussian_positions", rollout["gaussian_positions"], (T, S, 3))
    finger = _checked("field finger", field["finger"], (T, S), np.int64)
    active = _checked("contacts patch_active", contacts["patch_active"], (T, N_FINGERS), bool)
    normals = _checked("contacts patch_normals", contacts["patch_normals"], (T, N_FINGERS, 3))
    predicted = _checked("rollout predicted_squeeze_strain", rollout["predicted_squeeze_strain"], (T, N_FINGERS))
    observed = _checked("rollout squeeze_strain", rollout["squeeze_strain"], (T, N_FINGERS))
    coeff = _checked("forces force_coefficients", forces["force_coefficients"], (T, N_FINGERS))
    constrained = _checked("field constrained", field["constrained"], (T, S), bool)
    prescribed = _checked("field displacement", field["displacement"], (T, S, 3))

    score_t, ccc = bdc_t(predicted, observed)
    touch = touching_fingers(predicted)
    score_c, coupling = sdc(coeff, observed, touching=touch)
    u_obs = nonrigid_displacement(x)
    score_s, iou_s = bdc_s(constrained, u_obs)
    score_m, iou_m = miou(prescribed, u_obs, cfg.region_fraction)
    region = finger_regions(finger, normals)[0][-1]  # (finger, point): the largest set each finger constrained
    tracked = active & region.any(axis=1)  # contact frames of fingers whose region is known
    dp, dq = finger_trajectories(frames["fingertip_positions"], x, region, tracked)
    traj = trajectory_metrics(dp, dq, tracked, frame_dt if T > 1 else 1.0, cfg.ate_with_scale, cfg.min_motion)

    J = _checked("rollout particle_J", rollout["particle_J"], (T, None))
    shell = _checked("object particle_volumes", obj["particle_volumes"], (None,))
    interior = _checked("object interior_volumes", obj["interior_volumes"], (None,))
    if J.shape[1] == shell.size:
        v0 = shell
    elif J.shape[1] == shell.size + interior.size:
        v0 = np.concatenate([shell, interior])
    else:
        raise ValueError(f"rollout particle_J has {J.shape[1]} particles, expected {shell.size} (shell) or "
                         f"{shell.size + interior.size} (shell + interior) from the object")
    phys, phys_finger, volume_ratio = physical_figures(
        J, v0, observed, rollout["reaction_force"], rollout["applied_force"], rollout["feedback_force"],
        np.array([math.nan if c["ke_ie"] is None else c["ke_ie"] for c in rollout_attrs["quasi_static"]["contacts"]],
                 float), float(rollout_attrs["quasi_static"]["limit"]), rollout_attrs.get("threshold_event"))

    metrics = {"bdc_t": score_t, "bdc_s": score_s, "sdc": score_c, "miou": score_m,
               **{k: traj[k] for k in ("ate", "mte", "tce", "cosine_similarity")}, **phys}
    per_finger = {"bdc_t": ccc, "sdc": coupling, **phys_finger}
    for values in (metrics, per_finger, {"bdc_s_iou": iou_s, "miou_iou": iou_m}):
        check_metrics(values, scene)
    rms = np.sqrt(np.mean(np.sum(u_obs ** 2, axis=-1), axis=1))
    attrs = {
        "metrics": {k: _json_float(v) for k, v in metrics.items()},
        "per_finger": {k: [_json_float(v) for v in vals] for k, vals in per_finger.items()},
        "counts": {"touching_fingers": int(touch.sum()), "contact_fingers": int(active.any(axis=0).sum()),
                   "bdc_s_frames": int(np.isfinite(iou_s).sum()), "miou_frames": int(np.isfinite(iou_m).sum()),
                   "trajectory_points": int(traj["n_points"]), "trajectory_pairs": int(traj["n_pairs"]),
                   "cosine_pairs": int(traj["n_cosine_pairs"])},
        "no_contact": not bool(active.any()),
        "boundary": rollout_attrs.get("boundary"),
        "config": {"region_fraction": cfg.region_fraction, "ate_with_scale": cfg.ate_with_scale,
                   "min_motion": cfg.min_motion},
        "definitions": dict(DEFINITIONS),
    }
    arrays = {
        "bdc_s_iou": Array(iou_s, ("frame",), "1", "IoU of the Dirichlet set and the most deformed points; NaN: none"),
        "miou_iou": Array(iou_m, ("frame",), "1", "IoU of prescribed and observed deformed regions; NaN: none"),
        "volume_ratio": Array(volume_ratio, ("frame",), "1", "sum v0 J / sum v0 over all particles"),
        "nonrigid_displacement_rms": Array(rms, ("frame",), "m", "RMS |u_obs| over the surface points"),
        "sensed_trajectory": Array(dp, ("frame", "finger", "xyz"), "m",
                                   "fingertip displacement since first contact; NaN outside contact"),
        "reconstructed_trajectory": Array(dq, ("frame", "finger", "xyz"), "m",
                                          "finger region centroid displacement since first contact; NaN outside"),
    }
    return arrays, attrs


# ----------------------------------------------------------------------------------------------- Prefect step

@artifact_step("deformation_metrics",
               inputs=("mpm_rollout", "dirichlet_field", "force_coefficients", "contact_patches", "signal_smoothing",
                       "mpm_particles"),
               reads=("metrics",),
               outputs=("bdc_s_iou", "miou_iou", "nonrigid_displacement_rms", "volume_ratio", "sensed_trajectory",
                        "reconstructed_trajectory"))
def deformation_metrics_step(inputs, params):
    """BDC-T, BDC-S, SDC, mIoU, trajectory and physical metrics of one rollout (Table 2; Supplementary Part 6)."""
    r = inputs["mpm_rollout"]
    return deformation_metrics(r.arrays, r.attrs, inputs["dirichlet_field"].arrays,
                               inputs["force_coefficients"].arrays, inputs["contact_patches"].arrays,
                               inputs["signal_smoothing"].arrays, inputs["mpm_particles"].arrays, params["metrics"],
                               scene=r.ref.scope)
