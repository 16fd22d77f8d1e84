"""Squeezing control signals: SenseGlove-like recordings (CSV) and synthetic squeeze sessions.

Paper sec. "Squeezing Control Mapping" (sec. 3.1): the control signals are 1) the normalised flexion of the
five fingers, 2) the 3D fingertip positions and 3) the 6-DoF palm pose.  This module reads and writes them
as raw, sensor-rate arrays and synthesises realistic sessions around an object.  Resampling, EMA and
de-biasing happen later in :mod:`tasks.control.signal_smoothing`; force coefficients (eq. 1) in
:mod:`tasks.control.force_coefficients`.

Recording format (CSV, one row per sensor sample)
-------------------------------------------------
* A header row is required.  Column names are matched exactly (surrounding spaces are ignored), column
  order is free and any extra column (e.g. per-joint angles, a frame counter) is ignored.
* ``time`` - sample time in seconds (s), strictly increasing (no duplicates).  Any origin is accepted.
* ``flex_thumb, flex_index, flex_middle, flex_ring, flex_pinky`` - flexion of each finger, either
  normalised to 0..1 (0 = open hand, 1 = fully closed) or SenseGlove "percent bent" 0..10000 (the sum of a
  finger's flexion joint angles normalised between the glove's open and closed presets, see
  field-notes.md "Real data").  The scale is detected once per file: if the largest flexion value of all
  five columns is > 1.5 the whole file is read as percent-bent and divided by 10000.  (A percent-bent
  recording whose every value is <= 1.5, i.e. an open hand that never bends by more than 0.015 %, would be
  read as normalised; such a recording carries no squeeze.)  After scaling every value must lie in
  [-0.05, 1.05] (a small calibration overshoot is tolerated) and is then clipped to [0, 1].
* ``tip_<finger>_x, tip_<finger>_y, tip_<finger>_z`` for the five fingers (thumb, index, middle, ring,
  pinky) - fingertip positions in metres (m), in the object's frame (object centred at the origin, z up).
* ``palm_x, palm_y, palm_z`` - palm centre in metres (m), same frame.
* ``palm_qw, palm_qx, palm_qy, palm_qz`` - palm orientation as a quaternion (w first) rotating palm-frame
  vectors into the object frame.  Non-unit quaternions are normalised; an all-zero quaternion is an error.
  Palm frame used by the synthetic sessions: z = palm normal pointing at the object, x = from the thumb
  side toward the four fingers, y = z x x.
* Every value must be a finite number.  Empty cells, ``nan`` and ``inf`` are errors naming the row.  Every row
  must have as many fields as the header (a longer row, e.g. two rows merged by a lost newline, is an error).
* Reading uses pandas' C parser: 1e6 rows x 28 columns (360-560 MB) read in ~3-9 s on a 2-core machine, and
  needs about twice the file size in memory.  A file larger than ``MAX_RECORDING_BYTES`` (256 MiB, about
  450 000 rows = 7.5 min at 1 kHz, far longer than a squeeze session, whose simulation costs seconds per frame)
  is refused before it is read (and, through :func:`conf.schema.validate`, before the flow hashes it), with a
  message naming the file and the fix: cut the recording to the squeeze.  The limit is the ``max_bytes``
  argument of :func:`read_recording`.
* A last row with fewer fields than the header (an interrupted export or copy) is reported as a truncated file.

Rows are numbered from 1 = the first data row after the header, so "row r" is line r + 1 of the file
(when the file has no blank lines, which are skipped).

Errors are :class:`SignalError` (a ``ValueError``) with a one-line message naming the file, the column and
row, and what to change.

Arrays (all SI): ``time`` (sample,) s; ``flexion`` (sample, finger) 1 in [0, 1]; ``fingertip_positions``
(sample, finger, 3) m; ``palm_position`` (sample, 3) m; ``palm_orientation`` (sample, 4) unit quaternion wxyz.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd

from conf.hand import FINGERS
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step

log = logging.getLogger(__name__)

__all__ = [
    "SignalError",
    "SESSION_KINDS",
    "FLEX_COLUMNS",
    "TIP_COLUMNS",
    "PALM_POSITION_COLUMNS",
    "PALM_QUATERNION_COLUMNS",
    "REQUIRED_COLUMNS",
    "PERCENT_BENT_FULL_SCALE",
    "MAX_RECORDING_BYTES",
    "check_recording_size",
    "read_recording",
    "write_recording",
    "validate_signals",
    "grasp_targets",
    "synthesize_session",
    "quat_to_matrix",
]


class SignalError(ValueError):
    """A recording or a raw signal set is unusable; the message is one line naming the file/array and the fix."""


FLEX_COLUMNS: tuple[str, ...] = tuple(f"flex_{f}" for f in FINGERS)
TIP_COLUMNS: tuple[str, ...] = tuple(f"tip_{f}_{a}" for f in FINGERS for a in "xyz")
PALM_POSITION_COLUMNS: tuple[str, ...] = ("palm_x", "palm_y", "palm_z")
PALM_QUATERNION_COLUMNS: tuple[str, ...] = ("palm_qw", "palm_qx", "palm_qy", "palm_qz")
REQUIRED_COLUMNS: tuple[str, ...] = (
    ("time",) + FLEX_COLUMNS + TIP_COLUMNS + PALM_POSITION_COLUMNS + PALM_QUATERNION_COLUMNS
)
SESSION_KINDS: tuple[str, ...] = ("ramp_hold_release", "pulses", "poke", "crush")

PERCENT_BENT_FULL_SCALE = 10000.0  # SenseGlove percent-bent value of a fully closed finger
MAX_RECORDING_BYTES = 256 * 2**20  # largest recording read (see the module docstring)
_SCALE_DETECT = 1.5  # flexion max above this => percent-bent file
_FLEX_TOLERANCE = 0.05  # accepted overshoot outside [0, 1] after scaling
_ZERO_QUAT = 1e-9

_SIGNAL_NAMES = ("time", "flexion", "fingertip_positions", "palm_position", "palm_orientation")


# ============================================================================================ recordings
def _one_line(text: Any) -> str:
    return " ".join(str(text).split())


def check_recording_size(path: str | Path, max_bytes: int | None = MAX_RECORDING_BYTES) -> None:
    """Refuse a recording larger than ``max_bytes`` (None: no limit) before anything reads or hashes it."""
    p = Path(path)
    size = p.stat().st_size if p.is_file() else 0
    if max_bytes is not None and size > max_bytes:
        raise SignalError(f"recording {p} is {_mib(size)}, above the {_mib(max_bytes)} limit of one squeeze "
                          f"recording (MAX_RECORDING_BYTES in tasks/control/squeeze_signals.py); cut it to the squeeze "
                          f"you want to simulate (keep the header row and that time span)")


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB" if n < 2**30 else f"{n / 2**30:.2f} GiB"


def read_recording(path: str | Path, frame_rate: float | None = None,
                   max_bytes: int | None = MAX_RECORDING_BYTES) -> dict[str, np.ndarray]:
    """Read a SenseGlove-like CSV recording (format in the module docstring) into raw sensor-rate arrays.

    Paper sec. "Squeezing Control Mapping": the three signal groups (flexion, fingertips, palm pose) as
    captured, before alignment/EMA/de-biasing.

    Parameters
    ----------
    path:
        CSV file.
    frame_rate:
        Optional target frame rate (Hz) of the later resampling; the recording must then span at least one
        frame interval ``1 / frame_rate`` (s).
    max_bytes:
        Largest file read (bytes, default ``MAX_RECORDING_BYTES``; None = no limit).

    Returns
    -------
    dict with ``time`` (sample,) s, ``flexion`` (sample, finger) in [0, 1], ``fingertip_positions``
    (sample, finger, 3) m, ``palm_position`` (sample, 3) m, ``palm_orientation`` (sample, 4) unit wxyz.

    Raises
    ------
    SignalError
        Missing/empty file, missing columns, non-numeric or non-finite values, flexion out of range,
        non-increasing time, too few samples, zero quaternion.  One line, naming file, column/row and fix.
    """
    p = Path(path)
    name = str(p)
    if not p.exists():
        raise SignalError(f"recording {name} does not exist; check signal.path (a CSV recording, see "
                          f"tasks/control/squeeze_signals.py for the format)")
    if p.is_dir():
        raise SignalError(f"recording {name} is a directory; signal.path must name a CSV file")
    check_recording_size(p, max_bytes)
    if p.stat().st_size == 0:
        raise SignalError(f"recording {name} is empty (0 bytes); record again or point signal.path at a "
                          f"CSV with a header row and samples")

    # --- header: which required columns are present (extra columns are read but not used)
    try:
        header = pd.read_csv(p, nrows=0, skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise SignalError(f"recording {name} is empty (no header row); write a header row "
                          f"'{','.join(REQUIRED_COLUMNS[:3])},...' followed by samples") from None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise SignalError(f"recording {name} is not a readable CSV ({_one_line(exc)}); save it as "
                          f"comma-separated UTF-8 text with a header row") from None
    present: dict[str, Any] = {}
    for col in header.columns:
        key = str(col).strip()
        present.setdefault(key, col)
    missing = [c for c in REQUIRED_COLUMNS if c not in present]
    if len(missing) == len(REQUIRED_COLUMNS):
        first = ",".join(str(c) for c in list(header.columns)[:4])
        raise SignalError(f"recording {name} has none of the required columns (the header row seems to be "
                          f"missing; line 1 reads '{first},...'); add a header row time,flex_<finger>,"
                          f"tip_<finger>_x/y/z,palm_x/y/z,palm_qw/qx/qy/qz (format: tasks/control/squeeze_signals.py)")
    if missing:
        raise SignalError(f"recording {name} lacks column(s) {', '.join(missing)}; add them to the header "
                          f"(format: tasks/control/squeeze_signals.py)")
    original = [present[c] for c in REQUIRED_COLUMNS]

    # --- data: fast path parses straight to float64; on failure re-read as text to locate the bad cell.
    # All columns are tokenised (no usecols) so that a row with more fields than the header - e.g. two rows
    # merged by a lost newline - is an error instead of being silently truncated.
    read_kw = dict(skipinitialspace=True, engine="c", low_memory=False)
    try:
        df = pd.read_csv(p, dtype={c: np.float64 for c in original}, **read_kw)
    except (ValueError, TypeError, pd.errors.ParserError) as exc:
        df = _locate_bad_cell(p, name, original, read_kw, exc)
    df = df[original]
    data = df.to_numpy(dtype=np.float64, copy=False)
    n = data.shape[0]
    if n < 2:
        raise SignalError(f"recording {name} has {n} sample(s); at least 2 are needed (record longer)")

    bad = ~np.isfinite(data)
    if bad.any():
        row = int(np.flatnonzero(bad.any(axis=1))[0])
        col = int(np.flatnonzero(bad[row])[0])
        value = data[row, col]
        if row == n - 1:
            _refuse_truncated(p, name, row, len(header.columns))
        what = "empty or NaN" if np.isnan(value) else f"{float(value)}"
        raise SignalError(f"recording {name}: column {REQUIRED_COLUMNS[col]} row {row + 1} "
                          f"(line {row + 2}) is {what}; every value must be a finite number - fill or "
                          f"drop that row")

    idx = {c: i for i, c in enumerate(REQUIRED_COLUMNS)}
    time = np.ascontiguousarray(data[:, idx["time"]])
    flexion = np.ascontiguousarray(data[:, [idx[c] for c in FLEX_COLUMNS]])
    tips = np.ascontiguousarray(data[:, [idx[c] for c in TIP_COLUMNS]]).reshape(n, len(FINGERS), 3)
    palm = np.ascontiguousarray(data[:, [idx[c] for c in PALM_POSITION_COLUMNS]])
    quat = np.ascontiguousarray(data[:, [idx[c] for c in PALM_QUATERNION_COLUMNS]])

    # --- time
    dt = np.diff(time)
    nonpos = np.flatnonzero(dt <= 0)
    if nonpos.size:
        i = int(nonpos[0])
        if dt[i] == 0:
            raise SignalError(f"recording {name}: time {float(time[i])!r} s is duplicated at rows {i + 1} and "
                              f"{i + 2} (lines {i + 2}-{i + 3}); timestamps must strictly increase - drop "
                              f"the duplicate row")
        raise SignalError(f"recording {name}: time goes backwards at row {i + 2} (line {i + 3}: "
                          f"{float(time[i + 1])!r} s after {float(time[i])!r} s); timestamps must strictly "
                          f"increase - sort the rows by time")
    span = float(time[-1] - time[0])
    if frame_rate is not None:
        if not frame_rate > 0:
            raise ValueError(f"control.smoothing.frame_rate must be > 0, got {frame_rate}")
        if span < 1.0 / frame_rate:
            raise SignalError(f"recording {name} spans {span:.4g} s, shorter than one frame "
                              f"({1.0 / frame_rate:.4g} s at {frame_rate:g} Hz); record longer or raise "
                              f"control.smoothing.frame_rate")

    # --- flexion scale and range
    fmax = float(flexion.max())
    scale = "normalised 0..1"
    if fmax > _SCALE_DETECT:
        flexion = flexion / PERCENT_BENT_FULL_SCALE
        scale = "SenseGlove percent-bent 0..10000"
        log.info("recording %s: flexion max %.4g > %.1f, read as %s", name, fmax, _SCALE_DETECT, scale)
    lo, hi = -_FLEX_TOLERANCE, 1.0 + _FLEX_TOLERANCE
    out = (flexion < lo) | (flexion > hi)
    if out.any():
        row = int(np.flatnonzero(out.any(axis=1))[0])
        col = int(np.flatnonzero(out[row])[0])
        raw = float(data[row, idx[FLEX_COLUMNS[col]]])
        raise SignalError(f"recording {name}: {FLEX_COLUMNS[col]} row {row + 1} (line {row + 2}) is {raw!r}, "
                          f"read as {scale} that is {flexion[row, col]:.4g}, outside [{lo:g}, {hi:g}]; write "
                          f"flexion as 0..1 or as percent-bent 0..10000 consistently in all flex_ columns")
    flexion = np.clip(flexion, 0.0, 1.0)

    # --- quaternions
    norm = np.linalg.norm(quat, axis=1)
    zero = np.flatnonzero(norm < _ZERO_QUAT)
    if zero.size:
        row = int(zero[0])
        raise SignalError(f"recording {name}: palm quaternion (palm_qw..palm_qz) is zero at row {row + 1} "
                          f"(line {row + 2}); write a rotation quaternion (identity = 1,0,0,0) or drop the row")
    quat = quat / norm[:, None]

    return {
        "time": time,
        "flexion": flexion,
        "fingertip_positions": tips,
        "palm_position": palm,
        "palm_orientation": quat,
    }


def _refuse_truncated(p: Path, name: str, row: int, columns: int) -> None:
    """Raise if the last line of ``p`` (data row ``row``, 0-based) has fewer fields than the header."""
    with open(p, "rb") as fh:
        fh.seek(0, 2)
        fh.seek(max(0, fh.tell() - 65536))
        tail = fh.read().rstrip(b"\r\n \t")
    fields = tail.rsplit(b"\n", 1)[-1].count(b",") + 1
    if fields < columns:
        raise SignalError(f"recording {name}: the last row {row + 1} (line {row + 2}) has {fields} of {columns} "
                          f"fields - the file looks truncated (an interrupted export or copy); export or copy "
                          f"the recording again, or drop that row")


def _locate_bad_cell(p: Path, name: str, original: list, read_kw: dict, exc: Exception) -> pd.DataFrame:
    """Slow diagnostic path: re-read as text, report the first non-numeric cell (column, row)."""
    try:
        df = pd.read_csv(p, dtype=str, keep_default_na=True, **read_kw)
    except (ValueError, pd.errors.ParserError) as exc2:
        raise SignalError(f"recording {name} is not a readable CSV ({_one_line(exc2)}); every row must "
                          f"have as many comma-separated fields as the header") from None
    first: tuple[int, int, str] | None = None
    for j, col in enumerate(original):
        text = df[col]
        num = pd.to_numeric(text, errors="coerce")
        badmask = (num.isna() & text.notna()).to_numpy()
        hits = np.flatnonzero(badmask)
        if hits.size and (first is None or hits[0] < first[0]):
            first = (int(hits[0]), j, str(text.iloc[int(hits[0])]))
    if first is None:  # pandas refused for another reason
        raise SignalError(f"recording {name} could not be parsed as numbers ({_one_line(exc)}); every "
                          f"required column must hold plain numbers") from None
    row, j, value = first
    if row == len(df) - 1:
        _refuse_truncated(p, name, row, len(df.columns))
    raise SignalError(f"recording {name}: column {REQUIRED_COLUMNS[j]} row {row + 1} (line {row + 2}) holds "
                      f"non-numeric {value!r}; write a plain number (decimal point, no units)")


def validate_signals(signals: Mapping[str, Any], where: str = "signals") -> dict[str, np.ndarray]:
    """Check names, shapes and finiteness of a raw signal dict; return float64 arrays.

    ``where`` names the source in error messages.  Shapes: time (S,), flexion (S, 5),
    fingertip_positions (S, 5, 3), palm_position (S, 3), palm_orientation (S, 4); S >= 2.
    """
    missing = [k for k in _SIGNAL_NAMES if k not in signals]
    if missing:
        raise SignalError(f"{where} lacks array(s) {', '.join(missing)}; expected {', '.join(_SIGNAL_NAMES)}")
    out = {k: np.asarray(signals[k], dtype=np.float64) for k in _SIGNAL_NAMES}
    s = out["time"].shape[0] if out["time"].ndim == 1 else -1
    f = len(FINGERS)
    shapes = {"time": (s,), "flexion": (s, f), "fingertip_positions": (s, f, 3), "palm_position": (s, 3),
              "palm_orientation": (s, 4)}
    if s < 0:
        raise SignalError(f"{where}: time must be 1-D (sample,), got shape {out['time'].shape}")
    for k, shape in shapes.items():
        if out[k].shape != shape:
            raise SignalError(f"{where}: {k} has shape {out[k].shape}, expected {shape} (sample count {s})")
        if not np.isfinite(out[k]).all():
            row = int(np.flatnonzero(~np.isfinite(out[k].reshape(s, -1)).all(axis=1))[0])
            raise SignalError(f"{where}: {k} is not finite at sample {row}; clean the signal")
    if s < 2:
        raise SignalError(f"{where} has {s} sample(s); at least 2 are needed")
    if np.any(np.diff(out["time"]) <= 0):
        i = int(np.flatnonzero(np.diff(out["time"]) <= 0)[0])
        raise SignalError(f"{where}: time does not strictly increase at sample {i + 1}; sort and de-duplicate")
    return out


def write_recording(path: str | Path, signals: Mapping[str, Any], float_format: str | None = None) -> Path:
    """Write raw signals (names/shapes as returned by :func:`read_recording`) as a CSV recording.

    Flexion is written normalised 0..1; positions in m; quaternions wxyz; time in s.  By default every value
    is written as Python's shortest round-tripping repr, so :func:`read_recording` gives back the same
    numbers (quaternions are renormalised on reading); ``float_format`` (e.g. ``"%.6g"``) trades exactness
    for size.  The file is written under a temporary name and renamed into place; parent directories are
    created.  Speed: ~3 s per 1e5 rows on a 2-core machine (pure Python formatting; pandas' to_csv was
    slower).  Returns the path.
    """
    s = validate_signals(signals, where=f"signals for {path}")
    n = s["time"].shape[0]
    table = np.column_stack([
        s["time"][:, None],
        s["flexion"],
        s["fingertip_positions"].reshape(n, -1),
        s["palm_position"],
        s["palm_orientation"],
    ])
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.tmp")
    fmt = repr if float_format is None else (lambda v: float_format % v)
    try:
        with open(tmp, "w", newline="") as fh:
            fh.write(",".join(REQUIRED_COLUMNS) + "\n")
            for start in range(0, n, 65536):
                rows = table[start:start + 65536].tolist()
                fh.write("\n".join(",".join(map(fmt, row)) for row in rows))
                fh.write("\n")
        tmp.replace(p)
    finally:
        if tmp.exists():
            tmp.unlink()
    return p


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
