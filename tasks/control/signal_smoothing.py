"""Preprocessing of the squeezing control signals (paper sec. "Squeezing Control Mapping", sec. 3.1).

The paper synchronises flexion, fingertip positions and palm pose "along a unified timeline", applies "an
exponential moving average ... to suppress noise induced by hand jitter" and uses the "de-biased flexion"
u~ in eq. 1.  :func:`smooth_signals` does these three steps on raw sensor-rate arrays (as produced by
:func:`tasks.control.recording.read_recording` / ``synthesize_session``) and returns frame-rate
:class:`tasks.core.artifacts.Array` objects.  Pure numpy/scipy; all units SI.

1. Timeline.  Frames ``t_f = t0 + f / frame_rate`` (s) for every f with ``t_f <= t_end``; t0 and t_end are the
   first and last sample times.
2. Anti-aliased resampling.  The raw signal (piecewise linear between samples) is averaged with a triangular
   (tent) kernel of half-width ``1 / frame_rate`` centred on each frame time.  The tent is a one-frame box
   average applied twice: its response sinc^2(f / frame_rate) is 0 at every multiple of the frame rate and
   below 5 % beyond 1.5x the frame rate, so high-rate content (sensor noise, SenseGlove's 100-1000 Hz
   stream) does not alias into the frame-rate signal, while the squeeze itself (< 3 Hz) passes with < 3 %
   loss at 30 Hz frames.  The average is computed exactly from the double integral of the piecewise-linear
   signal (second difference), so non-uniform sample times are fine and a linear ramp is reproduced exactly.
   Near the ends the kernel shrinks symmetrically to fit inside the data (still exact for ramps); when less
   than a quarter frame is left (only the first and possibly the last frame) the plain linear interpolant is
   used, so those edge frames are not anti-aliased.
   Quaternions are first made sign-continuous (q and -q are the same rotation), then averaged component-wise
   with the same kernel and renormalised (the normalised-lerp generalisation; accurate for the small
   rotations within one frame).
3. EMA at the frame rate: ``y_0 = x_0``, ``y_f = alpha x_f + (1 - alpha) y_{f-1}`` on flexion, fingertip and
   palm positions and the palm quaternion (renormalised).  Time constant ``-1 / (frame_rate ln(1 - alpha))``
   (about 77 ms at 30 Hz, alpha 0.35); it lags the signal by about ``(1 - alpha) / (alpha frame_rate)``.
4. De-bias: ``rest_k`` = mean of finger k's resampled flexion over frames with ``t_f - t0 < rest_window``;
   ``u~ = clip(y - rest_k, 0, 1)``.  The user must hold the rest pose during that window.
   ``rest_window = 0`` disables de-biasing.
5. Squeeze directions ``a_k,t = normalise(g_t - P_k,t)`` with the grasp centre ``g_t`` = mean of the five
   smoothed fingertip positions and the smoothed palm position (6 points).  Optionally
   (``direction_reference="grasp_axis"``) the component of ``g_t - P_k,t`` along the finger-spread axis
   (pinky -> index fingertip) is removed first, so that fingers spread along a tall object squeeze
   perpendicular to the spread instead of converging on one point.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np
from scipy.signal import lfilter

from conf.hand import FINGERS
from tasks.control.recording import SignalError, validate_signals
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step

__all__ = ["smooth_signals", "frame_times", "resample_antialiased", "ema", "DIRECTION_REFERENCES"]

DIRECTION_REFERENCES = ("grasp_centre", "grasp_axis")
_EDGE_FRACTION = 0.25  # below this fraction of a frame of room, edge frames use the linear interpolant


def frame_times(t0: float, t_end: float, frame_rate: float) -> np.ndarray:
    """Uniform frame timeline ``t0 + f / frame_rate`` (s) covering ``[t0, t_end]``."""
    n = int(math.floor((t_end - t0) * frame_rate + 1e-9)) + 1
    return t0 + np.arange(n) / frame_rate


def resample_antialiased(t: np.ndarray, x: np.ndarray, tf: np.ndarray, half_width: float) -> np.ndarray:
    """Tent-kernel average (half-width ``half_width`` s) of the piecewise-linear signal (t, x) at times ``tf``.

    ``t`` (S,) strictly increasing s, ``x`` (S, ...) any unit, ``tf`` (F,) inside ``[t[0], t[-1]]``.
    Exact for piecewise-linear input: uses the double integral J2 of the signal and
    ``avg = (J2(tf + h) - 2 J2(tf) + J2(tf - h)) / h^2`` with ``h = min(half_width, room to either end)``.
    Frames with ``h < 0.25 half_width`` get the linear interpolant.  Returns (F, ...) float64.
    """
    t = np.asarray(t, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    shape = x.shape[1:]
    x = x.reshape(len(t), -1)
    tf = np.asarray(tf, dtype=np.float64)
    origin = t[0]
    t = t - origin
    tf = tf - origin
    t_end = t[-1]
    mean = x.mean(axis=0)
    xc = x - mean  # keeps the double integral small (precision of the second difference)
    h = np.diff(t)
    slope = np.diff(xc, axis=0) / h[:, None]
    j1 = np.concatenate([np.zeros((1, xc.shape[1])), np.cumsum(0.5 * (xc[:-1] + xc[1:]) * h[:, None], axis=0)])
    seg2 = (j1[:-1] * h[:, None] + xc[:-1] * (h**2 / 2)[:, None] + slope * (h**3 / 6)[:, None])
    j2 = np.concatenate([np.zeros((1, xc.shape[1])), np.cumsum(seg2, axis=0)])

    def locate(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        tau = np.clip(tau, 0.0, t_end)
        i = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, len(t) - 2)
        return i, (tau - t[i])[:, None]

    def j2_at(tau: np.ndarray) -> np.ndarray:
        i, d = locate(tau)
        return j2[i] + j1[i] * d + xc[i] * d**2 / 2 + slope[i] * d**3 / 6

    i, d = locate(tf)
    lin = xc[i] + slope[i] * d
    hw = np.minimum(half_width, np.minimum(tf, t_end - tf))
    use = hw >= _EDGE_FRACTION * half_width
    out = lin.copy()
    if use.any():
        tu, hu = tf[use], hw[use][:, None]
        out[use] = (j2_at(tu + hu[:, 0]) - 2.0 * j2_at(tu) + j2_at(tu - hu[:, 0])) / hu**2
    return (out + mean).reshape((len(tf),) + shape)


def ema(x: np.ndarray, alpha: float) -> np.ndarray:
    """Exponential moving average along axis 0: ``y_0 = x_0``, ``y_f = alpha x_f + (1 - alpha) y_{f-1}``."""
    x = np.asarray(x, dtype=np.float64)
    flat = x.reshape(len(x), -1)
    zi = (1.0 - alpha) * flat[:1]
    y, _ = lfilter([alpha], [1.0, -(1.0 - alpha)], flat, axis=0, zi=zi)
    return y.reshape(x.shape)


def _sign_continuous(q: np.ndarray) -> np.ndarray:
    """Flip quaternions so consecutive ones lie in the same hemisphere (q ~ -q); first has w >= 0."""
    q = np.array(q, dtype=np.float64)
    if q[0, 0] < 0:
        q[0] = -q[0]
    flips = np.einsum("ij,ij->i", q[1:], q[:-1]) < 0
    sign = np.concatenate([[1.0], np.cumprod(np.where(flips, -1.0, 1.0))])
    return q * sign[:, None]


def _unit(v: np.ndarray, what: str) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        raise SignalError(f"{what} averaged to a zero quaternion; the palm orientation flips within one frame")
    return v / n


def _check_params(frame_rate: float, ema_alpha: float, rest_window: float) -> None:
    if not (math.isfinite(frame_rate) and frame_rate > 0):
        raise ValueError(f"control.smoothing.frame_rate must be > 0, got {frame_rate}")
    if not (math.isfinite(ema_alpha) and 0 < ema_alpha <= 1):
        raise ValueError(f"control.smoothing.ema_alpha must be in (0, 1], got {ema_alpha}")
    if not (math.isfinite(rest_window) and rest_window >= 0):
        raise ValueError(f"control.smoothing.rest_window must be >= 0 s, got {rest_window}")


def _squeeze_directions(tips: np.ndarray, palm: np.ndarray, reference: str) -> tuple[np.ndarray, np.ndarray]:
    """Unit squeeze directions (F, 5, 3) and grasp centres (F, 3); see module docstring step 5."""
    centre = (tips.sum(axis=1) + palm) / (tips.shape[1] + 1)
    v = centre[:, None, :] - tips
    if reference == "grasp_axis":
        spread = tips[:, FINGERS.index("index")] - tips[:, FINGERS.index("pinky")]
        length = np.linalg.norm(spread, axis=-1, keepdims=True)
        ok = length[:, 0] > 1e-6
        s = np.where(ok[:, None], spread / np.maximum(length, 1e-300), 0.0)
        v = v - np.einsum("fkc,fc->fk", v, s)[..., None] * s[:, None, :]
    norm = np.linalg.norm(v, axis=-1)
    valid = norm > 1e-9
    a = np.where(valid[..., None], v / np.maximum(norm, 1e-300)[..., None], np.nan)
    if not valid.all():  # fingertip exactly at the grasp centre: carry the neighbouring direction
        for k in range(a.shape[1]):
            good = np.flatnonzero(valid[:, k])
            if good.size == 0:
                raise SignalError(f"squeeze direction of the {FINGERS[k]} is undefined in every frame (fingertip "
                                  f"at the grasp centre); check the fingertip/palm positions")
            idx = np.maximum.accumulate(np.where(valid[:, k], np.arange(len(a)), 0))
            idx = np.where(np.arange(len(a)) < good[0], good[0], idx)
            a[:, k] = a[idx, k]
    return a, centre


def smooth_signals(
    raw: Mapping[str, Any],
    frame_rate: float,
    ema_alpha: float,
    rest_window: float,
    *,
    direction_reference: str = "grasp_centre",
) -> dict[str, Array]:
    """Align, anti-alias, EMA-smooth and de-bias raw squeezing control signals (paper sec. 3.1).

    Parameters
    ----------
    raw:
        Raw sensor-rate arrays (``time`` s, ``flexion`` 1, ``fingertip_positions`` m, ``palm_position`` m,
        ``palm_orientation`` wxyz), as from :func:`tasks.control.recording.read_recording`.
    frame_rate:
        Output frame rate (Hz), ``control.smoothing.frame_rate``.
    ema_alpha:
        EMA weight of the newest frame, in (0, 1] (1 = no smoothing), ``control.smoothing.ema_alpha``.
    rest_window:
        Leading window (s) whose mean flexion is the rest pose, ``control.smoothing.rest_window``; 0 disables
        de-biasing.
    direction_reference:
        ``"grasp_centre"`` (default, a = normalise(g - P)) or ``"grasp_axis"`` (component along the
        pinky->index spread axis removed); see the module docstring.

    Returns
    -------
    dict of :class:`Array`:
        ``time`` (frame,) s; ``flexion`` (frame, finger) 1, de-biased EMA flexion u~ in [0, 1];
        ``flexion_raw`` (frame, finger) 1, anti-aliased resampled flexion before EMA/de-bias;
        ``rest_flexion`` (finger,) 1, the subtracted rest pose; ``fingertip_positions`` (frame, finger, xyz) m,
        EMA-smoothed; ``squeeze_directions`` (frame, finger, xyz) 1, unit a_k,t; ``grasp_centre`` (frame, xyz)
        m; ``palm_position`` (frame, xyz) m, EMA-smoothed; ``palm_orientation`` (frame, quat) 1, unit wxyz,
        EMA-smoothed, sign-continuous.
    """
    _check_params(float(frame_rate), float(ema_alpha), float(rest_window))
    if direction_reference not in DIRECTION_REFERENCES:
        raise ValueError(f"direction_reference must be one of {', '.join(DIRECTION_REFERENCES)}, "
                         f"got {direction_reference!r}")
    s = validate_signals(raw, where="raw signals")
    t = s["time"]
    span = float(t[-1] - t[0])
    dt_frame = 1.0 / frame_rate
    if span < dt_frame:
        raise SignalError(f"raw signals span {span:.4g} s, shorter than one frame ({dt_frame:.4g} s at "
                          f"{frame_rate:g} Hz); record longer or raise control.smoothing.frame_rate")
    if rest_window > span:
        raise ValueError(f"control.smoothing.rest_window ({rest_window:g} s) is longer than the recording "
                         f"({span:.4g} s); shorten it")
    tf = frame_times(float(t[0]), float(t[-1]), float(frame_rate))

    def rs(x: np.ndarray) -> np.ndarray:
        return resample_antialiased(t, x, tf, dt_frame)

    flex_rs = rs(s["flexion"])
    tips_rs = rs(s["fingertip_positions"])
    palm_rs = rs(s["palm_position"])
    quat_rs = _unit(rs(_sign_continuous(s["palm_orientation"])), "palm orientation")

    flex_ema = ema(flex_rs, ema_alpha)
    tips = ema(tips_rs, ema_alpha)
    palm = ema(palm_rs, ema_alpha)
    quat = _unit(ema(_sign_continuous(quat_rs), ema_alpha), "smoothed palm orientation")

    if rest_window > 0:
        in_rest = (tf - tf[0]) < rest_window
        rest = flex_rs[in_rest].mean(axis=0)
    else:
        rest = np.zeros(len(FINGERS))
    flexion = np.clip(flex_ema - rest, 0.0, 1.0)

    directions, centre = _squeeze_directions(tips, palm, direction_reference)
    return {
        "time": Array(tf, ("frame",), "s", "frame times t0 + f / frame_rate"),
        "flexion": Array(flexion, ("frame", "finger"), "1",
                         "de-biased EMA flexion u~ in [0, 1] (paper eq. 1 input)"),
        "flexion_raw": Array(flex_rs, ("frame", "finger"), "1",
                             "flexion resampled to frames with a tent anti-alias kernel, before EMA and de-bias"),
        "rest_flexion": Array(rest, ("finger",), "1", "rest-pose flexion subtracted in the de-bias step"),
        "fingertip_positions": Array(tips, ("frame", "finger", "xyz"), "m", "EMA-smoothed fingertip positions P_k,t"),
        "squeeze_directions": Array(directions, ("frame", "finger", "xyz"), "1",
                                    f"unit squeeze directions a_k,t ({direction_reference})"),
        "grasp_centre": Array(centre, ("frame", "xyz"), "m", "mean of the five fingertips and the palm position"),
        "palm_position": Array(palm, ("frame", "xyz"), "m", "EMA-smoothed palm position"),
        "palm_orientation": Array(quat, ("frame", "quat"), "1", "EMA-smoothed palm orientation, unit wxyz"),
    }


# ----------------------------------------------------------------------------------------------- Prefect step


SMOOTHED_OUTPUTS = ("time", "flexion", "flexion_raw", "rest_flexion", "fingertip_positions", "palm_position",
                    "palm_orientation", "squeeze_directions", "grasp_centre")


@artifact_step("signal_smoothing", inputs=("squeeze_signals",), reads=("control.smoothing",),
               outputs=SMOOTHED_OUTPUTS)
def signal_smoothing_step(inputs, params):
    """Frame-rate control signals (sec. 3.1): resampled, EMA-smoothed, de-biased."""
    s = params["control.smoothing"]
    frames = smooth_signals(inputs["squeeze_signals"].arrays, s["frame_rate"], s["ema_alpha"], s["rest_window"])
    return frames, {"frame_rate": s["frame_rate"], "frames": int(len(frames["time"].data))}
