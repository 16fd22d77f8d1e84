"""Squeezing control signals: SenseGlove-like recordings (CSV) and synthetic squeeze sessions.

Paper sec. "Squeezing Control Mapping" (sec. 3.1): the control signals are 1) the normalised flexion of the
five fingers, 2) the 3D fingertip positions and 3) the 6-DoF palm pose.  This module reads and writes them
as raw, sensor-rate arrays and synthesises realistic sessions around an object.  Resampling, EMA and
de-biasing happen later in :mod:`tasks.control.signal_smoothing`; force coefficients (eq. 1) in
:mod:`tasks.control.force_coefficients`.

The recording format and its reader live in :mod:`tasks.control.recording`.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from conf.hand import FINGERS
from tasks.control.recording import SignalError, read_recording
from tasks.control.session_kinds import SESSION_KINDS
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step


# ============================================================================================ synthesis
def _cfg(cfg: Any, key: str, default: Any = None) -> Any:
    if isinstance(cfg, Mapping):
        return cfg.get(key, default)
    return getattr(cfg, key, default)


def _normalise(v: np.ndarray, axis: int = -1) -> np.ndarray:
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return v / np.maximum(n, 1e-300)


def _check_surface(surface_points: Any, surface_normals: Any) -> tuple[np.ndarray, np.ndarray]:
    pts = np.asarray(surface_points, dtype=np.float64)
    nrm = np.asarray(surface_normals, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] < len(FINGERS) + 1:
        raise SignalError(f"surface_points must have shape (point, 3) with at least {len(FINGERS) + 1} points, "
                          f"got {pts.shape}")
    if nrm.shape != pts.shape:
        raise SignalError(f"surface_normals must match surface_points {pts.shape}, got {nrm.shape}")
    if not (np.isfinite(pts).all() and np.isfinite(nrm).all()):
        raise SignalError("surface_points/surface_normals contain NaN or inf; resample the object surface")
    lengths = np.linalg.norm(nrm, axis=1)
    if np.any(lengths < 1e-12):
        raise SignalError(f"surface_normals has {int(np.sum(lengths < 1e-12))} zero vector(s); every surface "
                          f"point needs a normal")
    nrm = nrm / lengths[:, None]
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    if np.mean(np.einsum("ij,ij->i", nrm, pts - centre)) < 0:
        raise SignalError("surface_normals point into the object on average; flip them (outward normals "
                          "are expected)")
    return pts, nrm


def grasp_targets(surface_points: Any, surface_normals: Any) -> dict[str, np.ndarray]:
    """Plausible grasp locations on an object surface (object frame: centred near the origin, z up).

    Layout (a wrap grasp seen from above): the palm faces the object from the -y side; the four fingers
    (index on top .. pinky at the bottom) contact the +x side, the thumb opposes them on the -x side at the
    height between index and middle.  Finger spacing along z is ``min(0.3 * half_height, 0.02 m)``.
    For every digit the ideal point ``q`` on the bounding box side is computed and the closest surface
    point whose outward normal faces that side (normal . side > 0.5) is taken.

    Returns ``points`` (finger, 3) m, ``normals`` (finger, 3) outward unit, ``palm_point`` (3,) m,
    ``palm_normal`` (3,) outward unit, ``centre`` (3,) m (bounding-box centre), ``half_size`` (3,) m.
    """
    pts, nrm = _check_surface(surface_points, surface_normals)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    spacing = min(0.3 * half[2], 0.02)
    finger_side = _normalise(np.array([1.0, 0.25, 0.0]))
    thumb_side = _normalise(np.array([-1.0, 0.25, 0.0]))
    palm_side = np.array([0.0, -1.0, 0.0])
    dz = {"thumb": 0.5, "index": 1.5, "middle": 0.5, "ring": -0.5, "pinky": -1.5}

    def pick(side: np.ndarray, z: float) -> int:
        q = centre + np.array([side[0] * half[0], side[1] * half[1], z])
        ok = nrm @ side > 0.5
        cand = np.flatnonzero(ok) if ok.any() else np.arange(len(pts))
        d2 = np.sum((pts[cand] - q) ** 2, axis=1)
        return int(cand[int(np.argmin(d2))])

    sel = [pick(thumb_side if f == "thumb" else finger_side, dz[f] * spacing) for f in FINGERS]
    palm = pick(palm_side, 0.0)
    return {
        "points": pts[sel].copy(),
        "normals": nrm[sel].copy(),
        "palm_point": pts[palm].copy(),
        "palm_normal": nrm[palm].copy(),
        "centre": centre,
        "half_size": half,
    }


def _min_jerk(s: np.ndarray) -> np.ndarray:
    """Minimum-jerk 0->1 transition (10 s^3 - 15 s^4 + 6 s^5), s clipped to [0, 1]: human reach profile."""
    s = np.clip(s, 0.0, 1.0)
    return s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)


def _session_profile(kind: str, t: np.ndarray, duration: float) -> np.ndarray:
    """Normalised squeeze profile in [0, 1] for one (delayed) finger timeline ``t`` (s).

    Nominal timings are for a 3 s session and shrink proportionally for shorter sessions; longer sessions
    hold longer (ramp_hold_release, crush) or space the pulses further apart.
    """
    k = min(1.0, duration / 3.0)
    onset = 0.35 * k  # s of rest at the start (the de-bias window must see the rest pose)
    if kind in ("ramp_hold_release", "poke"):
        ramp, release, tail = 0.8 * k, 0.6 * k, 0.3 * k
        release_start = duration - tail - release
        return _min_jerk((t - onset) / ramp) * (1.0 - _min_jerk((t - release_start) / release))
    if kind == "crush":
        return _min_jerk((t - onset) / (0.25 * k))
    if kind == "pulses":
        end = duration - 0.15 * k
        slot = (end - onset) / 3.0
        rise, hold, fall = 0.3 * slot, 0.15 * slot, 0.3 * slot
        out = np.zeros_like(t)
        for i, amp in enumerate((1.0, 0.85, 0.95)):
            start = onset + i * slot
            bump = _min_jerk((t - start) / rise) * (1.0 - _min_jerk((t - start - rise - hold) / fall))
            out = np.maximum(out, amp * bump)
        return out
    raise SignalError(f"unknown squeeze session {kind!r}; signal.session must be one of {', '.join(SESSION_KINDS)}")


# per-finger hand model (thumb, index, middle, ring, pinky)
_REST_FLEXION = np.array([0.06, 0.05, 0.07, 0.09, 0.11])  # 1, relaxed hand is not fully open
_BASE_DELAY = np.array([0.0, 0.0, 0.02, 0.04, 0.06])  # s, fingers close one after the other
_AMPLITUDE = {
    "ramp_hold_release": np.array([0.95, 1.0, 0.97, 0.9, 0.82]),
    "pulses": np.array([0.95, 1.0, 0.97, 0.9, 0.82]),
    "crush": np.array([0.98, 1.0, 1.0, 0.97, 0.95]),
    "poke": np.array([0.06, 1.0, 0.12, 0.06, 0.04]),  # index only; slight sympathetic co-activation
}


def synthesize_session(
    kind: str,
    surface_points: Any,
    surface_normals: Any,
    cfg: Any,
    *,
    standoff: float = 0.005,
    travel_fraction: float = 0.25,
    palm_standoff: float = 0.015,
) -> dict[str, np.ndarray]:
    """A realistic synthetic squeeze session around an object (paper sec. "Squeezing Control Mapping").

    Kinds (``SESSION_KINDS``): ``ramp_hold_release`` (rest, ~0.8 s minimum-jerk ramp to the peak, hold,
    ~0.6 s release, rest), ``pulses`` (three squeeze pulses of 100/85/95 % of the peak), ``poke`` (index
    finger only, the others stay near rest with slight sympathetic co-activation), ``crush`` (whole hand,
    ~0.25 s ramp to the peak, hold to the end).  Nominal timings are for 3 s and shrink for shorter sessions.

    Flexion (1) of finger k: ``rest_k + a_k (peak - rest_k) p(t - d_k) + tremor + noise``, clipped to
    [0, 1], where p is the session profile, ``rest_k`` the relaxed-hand flexion (~0.05-0.11), ``a_k`` a
    per-finger amplitude (the strongest finger reaches ``cfg.peak_flexion``), ``d_k`` a per-finger delay
    (0-90 ms); tremor is a per-finger 8-12 Hz sine of amplitude ``cfg.tremor_amplitude`` (70 % at rest,
    100 % at full squeeze) and noise white Gaussian ``cfg.noise_std``.

    Geometry (m): see :func:`grasp_targets`.  At rest fingertip k sits ``standoff`` outside its target
    point along the outward normal n_k; as flexion grows it moves along the inward normal -n_k (its
    physical squeeze ray) by ``travel * (u_k - rest_k) / (1 - rest_k)`` with
    ``travel = travel_fraction * min(half-width x, half-width y)`` (u_k without sensor noise, so the
    tremor moves the fingertip too).  The palm sits ``palm_standoff`` outside the -y side and moves in by
    30 % of the mean finger travel.  Palm orientation: z = -palm normal (toward the object), x = from the
    thumb toward the fingers, y = z x x.  Positions get white noise ``cfg.position_noise_std`` (m), the
    orientation a random rotation of std ``position_noise_std / 0.1 m`` (rad).

    ``cfg`` is a :class:`conf.schema.SignalConfig` or any object/mapping with ``duration`` (s),
    ``sensor_rate`` (Hz), ``tremor_amplitude`` (1), ``noise_std`` (1), ``position_noise_std`` (m),
    ``peak_flexion`` (1) and ``seed``.  Deterministic for a seed.

    Returns the same arrays as :func:`read_recording`.
    """
    if kind not in SESSION_KINDS:
        raise SignalError(f"unknown squeeze session {kind!r}; signal.session must be one of {', '.join(SESSION_KINDS)}")
    duration = float(_cfg(cfg, "duration", 3.0))
    rate = float(_cfg(cfg, "sensor_rate", 200.0))
    tremor = float(_cfg(cfg, "tremor_amplitude", 0.01))
    noise = float(_cfg(cfg, "noise_std", 0.005))
    pos_noise = float(_cfg(cfg, "position_noise_std", 0.0005))
    peak = float(_cfg(cfg, "peak_flexion", 0.85))
    seed = int(_cfg(cfg, "seed", 0))
    checks = [
        ("duration", duration, duration > 0, "> 0 s"),
        ("sensor_rate", rate, rate > 0, "> 0 Hz"),
        ("tremor_amplitude", tremor, tremor >= 0, ">= 0"),
        ("noise_std", noise, noise >= 0, ">= 0"),
        ("position_noise_std", pos_noise, pos_noise >= 0, ">= 0 m"),
        ("peak_flexion", peak, 0 < peak <= 1, "in (0, 1]"),
    ]
    for key, value, ok, rule in checks:
        if not (ok and math.isfinite(value)):
            raise ValueError(f"signal.{key} must be {rule}, got {value}")
    n = int(math.floor(duration * rate + 1e-9)) + 1
    if n < 2:
        raise ValueError(f"signal.duration {duration} s at signal.sensor_rate {rate} Hz gives {n} sample; "
                         f"need at least 2")

    targets = grasp_targets(surface_points, surface_normals)
    rng = np.random.default_rng(seed)
    nf = len(FINGERS)
    t = np.arange(n) / rate

    # --- flexion
    rest = np.minimum(_REST_FLEXION + rng.uniform(-0.02, 0.02, nf), 0.5 * peak)
    rest = np.maximum(rest, 0.0)
    delay = _BASE_DELAY + rng.uniform(0.0, 0.03, nf)
    amp = _AMPLITUDE[kind] * rng.uniform(0.97, 1.0, nf)
    amp = amp / amp.max()
    freq = rng.uniform(8.0, 12.0, nf)
    phase = rng.uniform(0.0, 2.0 * np.pi, nf)
    profile = np.stack([_session_profile(kind, t - delay[k], duration) for k in range(nf)], axis=1)
    clean = rest + amp * (peak - rest) * profile
    trem = tremor * (0.7 + 0.3 * profile) * np.sin(2.0 * np.pi * freq * t[:, None] + phase)
    motion = clean + trem  # what the hand does
    flexion = np.clip(motion + rng.normal(0.0, noise, (n, nf)), 0.0, 1.0)  # what the glove reports

    # --- fingertips: rest standoff outside the surface, pressed along the inward normal
    half = targets["half_size"]
    travel = travel_fraction * float(min(half[0], half[1]))
    depth = travel * (motion - rest) / (1.0 - rest)  # (n, finger) m
    p0, nk = targets["points"], targets["normals"]
    tips = p0[None] + nk[None] * (standoff - depth[:, :, None])
    tips = tips + rng.normal(0.0, pos_noise, tips.shape)

    # --- palm
    pn = targets["palm_normal"]
    palm_depth = 0.3 * depth.mean(axis=1)
    palm = targets["palm_point"][None] + pn[None] * (palm_standoff - palm_depth[:, None])
    palm = palm + rng.normal(0.0, pos_noise, palm.shape)
    z_axis = -pn
    x_dir = p0[1:].mean(axis=0) - p0[0]
    x_axis = x_dir - (x_dir @ z_axis) * z_axis
    if np.linalg.norm(x_axis) < 1e-9:  # degenerate object: any axis orthogonal to z
        x_axis = np.cross(z_axis, [0.0, 0.0, 1.0]) if abs(z_axis[2]) < 0.9 else np.cross(z_axis, [1.0, 0.0, 0.0])
    x_axis = _normalise(x_axis)
    y_axis = np.cross(z_axis, x_axis)
    q0 = _quat_from_matrix(np.stack([x_axis, y_axis, z_axis], axis=1))
    rot_noise = rng.normal(0.0, pos_noise / 0.1, (n, 3))  # rad, small rotation vectors
    quat = _quat_multiply(_quat_from_rotvec(rot_noise), np.broadcast_to(q0, (n, 4)))
    quat = _normalise(quat)
    return {
        "time": t,
        "flexion": flexion,
        "fingertip_positions": tips,
        "palm_position": palm,
        "palm_orientation": quat,
    }


# ============================================================================================ quaternions
def _quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternion wxyz of a 3x3 rotation matrix (Shepperd's method), w >= 0."""
    m = r
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q = q / np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def _quat_from_rotvec(v: np.ndarray) -> np.ndarray:
    """Unit quaternions wxyz of rotation vectors (..., 3) (axis * angle, rad)."""
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(half)/angle, with its limit 0.5 at angle -> 0
    k = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-300), 0.5)
    return np.concatenate([np.cos(half), k * v], axis=-1)


def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of wxyz quaternions (..., 4)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], axis=-1)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of unit wxyz quaternions (..., 4)."""
    q = _normalise(np.asarray(q, dtype=np.float64))
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ], axis=-2)


# ----------------------------------------------------------------------------------------------- Prefect step
RAW_DIMS = {
    "time": (("sample",), "s"),
    "flexion": (("sample", "finger"), "1"),
    "fingertip_positions": (("sample", "finger", "xyz"), "m"),
    "palm_position": (("sample", "xyz"), "m"),
    "palm_orientation": (("sample", "quat"), "1"),
}


@artifact_step("squeeze_signals", inputs=("object_model",),
               reads=("signal", "object.session", "control.smoothing.frame_rate"), files=("signal.path",),
               outputs=tuple(RAW_DIMS))
def squeeze_signals_step(inputs, params):
    """Raw squeezing control signals: a SenseGlove CSV recording or a synthetic session around the object.

    ``signal.session`` None means the object's own session; the frame rate (Hz) refuses a recording shorter than
    one frame.  The object model's surface aims the synthetic hand.
    """
    sig = dict(params["signal"])
    sig["session"] = sig["session"] or params["object.session"]
    if sig["source"] == "csv":
        raw = read_recording(sig["path"], frame_rate=params["control.smoothing.frame_rate"])
    else:
        obj = inputs["object_model"]
        raw = synthesize_session(sig["session"], obj["surface_points"], obj["surface_normals"], sig)
    arrays = {name: Array(np.asarray(raw[name]), dims, units) for name, (dims, units) in RAW_DIMS.items()}
    return arrays, {"source": sig["source"], "session": sig["session"] if sig["source"] != "csv" else None,
                    "samples": int(len(raw["time"]))}
