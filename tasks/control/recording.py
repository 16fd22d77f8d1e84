"""SenseGlove-like recordings: the CSV format of the squeezing control signals, read, validated and written.

Paper sec. 3.1: the control signals are 1) the normalised flexion of the five fingers, 2) the 3D fingertip
positions and 3) the 6-DoF palm pose.  This module is the file format (a library of the ``squeeze_signals``
step, and of the pre-flight check that reads a recording before the flow starts).

Recording format (CSV, one row per sensor sample)
-------------------------------------------------
* Fields are separated by commas and numbers use a decimal point: a file separated by semicolons or tabs, or with
  decimal commas (as spreadsheets export in a decimal-comma locale), is refused naming the separator and the fix.
* A header row is required.  Column names are matched exactly (surrounding spaces are ignored), column
  order is free and any extra column (e.g. per-joint angles, a frame counter) is ignored.
* ``time`` - sample time in seconds (s), strictly increasing (no duplicates).  Any origin is accepted.  A median
  sample interval of 0.5 or more (a sensor below 2 Hz) is refused as milliseconds, with the fix.
* ``flex_thumb, flex_index, flex_middle, flex_ring, flex_pinky`` - flexion of each finger, either
  normalised to 0..1 (0 = open hand, 1 = fully closed) or SenseGlove "percent bent" 0..10000 (the sum of a
  finger's flexion joint angles normalised between the glove's open and closed presets, see
  field-notes.md "Real data").  The scale is detected once per file: if the largest flexion value of all
  five columns is > 1.5 the whole file is read as percent-bent and divided by 10000.  (A percent-bent
  recording whose every value is <= 1.5, i.e. an open hand that never bends by more than 0.015 %, would be
  read as normalised; such a recording carries no squeeze.)  A largest value in (1.5, 105] is refused: it is
  flexion written as percent 0..100, which on the 0..10000 scale would be read as at most 1 % bent (nothing would be
  squeezed); the message gives both fixes (the two scales cannot be told apart there, so nothing is guessed).
  After scaling every value must lie in
  [-0.05, 1.05] (a small calibration overshoot is tolerated) and is then clipped to [0, 1].
* ``tip_<finger>_x, tip_<finger>_y, tip_<finger>_z`` for the five fingers (thumb, index, middle, ring,
  pinky) - fingertip positions in metres (m), in the object's frame (object centred at the origin, z up).  A
  fingertip more than 1 m from the palm is refused as millimetres (or centimetres), with the fix.
* ``palm_x, palm_y, palm_z`` - palm centre in metres (m), same frame.
* ``palm_qw, palm_qx, palm_qy, palm_qz`` - palm orientation as a quaternion (w first) rotating palm-frame
  vectors into the object frame.  Non-unit quaternions are normalised; an all-zero quaternion is an error.
  Palm frame used by the synthetic sessions: z = palm normal pointing at the object, x = from the thumb
  side toward the four fingers, y = z x x.
* Messages quote at most ``tasks.core.excerpt.EXCERPT_CHARS`` (80) characters of the file (a zero-filled tail is not echoed).
* Every value must be a finite number.  Empty cells, ``nan`` and ``inf`` are errors naming the row.  Every row
  must have as many fields as the header (a longer row, e.g. two rows merged by a lost newline, is an error).
* Reading uses pandas' C parser: 1e6 rows x 28 columns (360-560 MB) read in ~3-9 s on a 2-core machine, and
  needs about twice the file size in memory.  A file larger than ``MAX_RECORDING_BYTES`` (256 MiB, about
  450 000 rows = 7.5 min at 1 kHz, far longer than a squeeze session, whose simulation costs seconds per frame)
  is refused before it is read (and, through :mod:`flows.preflight`, before the flow starts), with a
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

import csv
import logging
import re
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd

from conf.hand import FINGERS
from tasks.core.excerpt import excerpt, one_line

log = logging.getLogger(__name__)


class SignalError(ValueError):
    """A recording or a raw signal set is unusable; the message is one line naming the file/array and the fix."""


FLEX_COLUMNS: tuple[str, ...] = tuple(f"flex_{f}" for f in FINGERS)
TIP_COLUMNS: tuple[str, ...] = tuple(f"tip_{f}_{a}" for f in FINGERS for a in "xyz")
PALM_POSITION_COLUMNS: tuple[str, ...] = ("palm_x", "palm_y", "palm_z")
PALM_QUATERNION_COLUMNS: tuple[str, ...] = ("palm_qw", "palm_qx", "palm_qy", "palm_qz")
REQUIRED_COLUMNS: tuple[str, ...] = (
    ("time",) + FLEX_COLUMNS + TIP_COLUMNS + PALM_POSITION_COLUMNS + PALM_QUATERNION_COLUMNS
)

PERCENT_BENT_FULL_SCALE = 10000.0  # SenseGlove percent-bent value of a fully closed finger
MAX_RECORDING_BYTES = 256 * 2**20  # largest recording read (see the module docstring)
_SCALE_DETECT = 1.5  # flexion max above this => percent-bent file
_FLEX_TOLERANCE = 0.05  # accepted overshoot outside [0, 1] after scaling
_ZERO_QUAT = 1e-9
_MAX_SAMPLE_INTERVAL = 0.5  # s; a median sample interval this long means the time column is not in seconds
_MAX_REACH = 1.0  # m; fingertips farther than this from the palm mean the positions are not in metres
_DECIMAL_COMMA = re.compile(r"\d,\d")  # 0,5: a number written with a decimal comma (or two fields)

_SIGNAL_NAMES = ("time", "flexion", "fingertip_positions", "palm_position", "palm_orientation")


# ============================================================================================ recordings
def check_recording_size(path: str | Path, max_bytes: int | None = MAX_RECORDING_BYTES) -> None:
    """Refuse a recording larger than ``max_bytes`` (None: no limit) before anything reads or hashes it."""
    p = Path(path)
    size = p.stat().st_size if p.is_file() else 0
    if max_bytes is not None and size > max_bytes:
        raise SignalError(f"recording {p} is {_mib(size)}, above the {_mib(max_bytes)} limit of one squeeze "
                          f"recording (MAX_RECORDING_BYTES in tasks/control/recording.py); cut it to the squeeze "
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
                          f"tasks/control/recording.py for the format)")
    if p.is_dir():
        raise SignalError(f"recording {name} is a directory; signal.path must name a CSV file")
    check_recording_size(p, max_bytes)
    if p.stat().st_size == 0:
        raise SignalError(f"recording {name} is empty (0 bytes); record again or point signal.path at a "
                          f"CSV with a header row and samples")

    _refuse_separators(p, name)
    # --- header: which required columns are present (extra columns are read but not used)
    try:
        header = pd.read_csv(p, nrows=0, skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise SignalError(f"recording {name} is empty (no header row); write a header row "
                          f"'{','.join(REQUIRED_COLUMNS[:3])},...' followed by samples") from None
    except (pd.errors.ParserError, UnicodeDecodeError, ValueError) as exc:
        raise SignalError(f"recording {name} is not a readable CSV ({one_line(exc)}); save it as "
                          f"comma-separated UTF-8 text with a header row") from None
    present: dict[str, Any] = {}
    for col in header.columns:
        key = str(col).strip()
        present.setdefault(key, col)
    missing = [c for c in REQUIRED_COLUMNS if c not in present]
    if len(missing) == len(REQUIRED_COLUMNS):
        first = one_line(",".join(str(c) for c in list(header.columns)[:4]))
        raise SignalError(f"recording {name} has none of the required columns (the header row seems to be "
                          f"missing; line 1 reads '{first},...'); add a header row time,flex_<finger>,"
                          f"tip_<finger>_x/y/z,palm_x/y/z,palm_qw/qx/qy/qz (format: tasks/control/recording.py)")
    if missing:
        raise SignalError(f"recording {name} lacks column(s) {', '.join(missing)}; add them to the header "
                          f"(format: tasks/control/recording.py)")
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
    step = float(np.median(dt))
    if step >= _MAX_SAMPLE_INTERVAL:
        raise SignalError(f"recording {name}: time steps by {step:g} per sample (median; {span:g} in all), a "
                          f"{1 / step:.3g} Hz sensor where SenseGlove streams at 100-1000 Hz; the time column "
                          f"looks like milliseconds: divide it by 1000 (seconds are expected)")
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
    if _SCALE_DETECT < fmax <= 100 * (1 + _FLEX_TOLERANCE):
        raise SignalError(f"recording {name}: flexion peaks at {fmax:.4g}, which on SenseGlove's percent-bent scale "
                          f"0..10000 is {fmax / 100:.2g} % bent (nothing would be squeezed); the flex_ columns look "
                          f"like percent 0..100: divide them by 100 (0..1) or multiply them by 100 (0..10000)")
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

    # --- positions: a hand's fingertips stay within ~0.25 m of its palm
    reach = float(np.linalg.norm(tips - palm[:, None, :], axis=-1).max())
    if reach > _MAX_REACH:
        unit, factor = ("millimetres", 1000) if reach > 30 else ("centimetres", 100)  # a hand: 8-20 cm, 80-200 mm
        raise SignalError(f"recording {name}: fingertip positions reach {reach:.4g} m from the palm (a hand spans "
                          f"~0.2 m); the CSV looks like {unit}: divide the tip_ and palm_x/y/z columns by {factor}")

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


def _refuse_separators(p: Path, name: str) -> None:
    """Raise if the file's first lines show another field separator than the comma (``;`` or a tab, as a spreadsheet
    in a decimal-comma locale exports) or decimal commas (a first data row with more comma-separated fields than the
    header and no decimal point): the header would otherwise look missing, or the numbers shift columns."""
    with open(p, "rb") as fh:
        lines = fh.read(65536).decode("utf-8-sig", errors="replace").splitlines()
    header = lines[0] if lines else ""
    data = next((line for line in lines[1:] if line.strip()), "")
    for sep, what in ((";", "semicolons (';')"), ("\t", "tabs")):
        if "time" in (c.strip().strip('"') for c in header.split(sep)):
            decimal = bool(_DECIMAL_COMMA.search(data))
            raise SignalError(
                f"recording {name} separates its columns with {what}"
                + (f" and writes decimal commas (line 2 reads {excerpt(data)})" if decimal else "")
                + ": save it as comma-separated text" + (" with decimal points" if decimal else "")
                + " (e.g. pandas df.to_csv(path), or a spreadsheet's CSV export with field separator ','"
                + (" and decimal separator '.'" if decimal else "") + ")")
    fields, columns = (len(next(csv.reader([line]), [])) for line in (data, header))
    if "." not in data and columns < fields <= 2 * columns and _DECIMAL_COMMA.search(data):
        raise SignalError(f"recording {name}: line 2 has {fields} comma-separated fields where the header has "
                          f"{columns}, and no decimal point: the numbers look written with decimal commas "
                          f"({excerpt(data)}); write decimal points (0.5, not 0,5)")


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
        raise SignalError(f"recording {name} is not a readable CSV ({one_line(exc2)}); every row must "
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
        raise SignalError(f"recording {name} could not be parsed as numbers ({one_line(exc)}); every "
                          f"required column must hold plain numbers") from None
    row, j, value = first
    if row == len(df) - 1:
        _refuse_truncated(p, name, row, len(df.columns))
    if re.fullmatch(r"\s*[-+]?\d+,\d+\s*", value):
        raise SignalError(f"recording {name}: column {REQUIRED_COLUMNS[j]} row {row + 1} (line {row + 2}) holds "
                          f"{excerpt(value)}, a decimal comma; write decimal points ({value.strip().replace(',', '.')})")
    raise SignalError(f"recording {name}: column {REQUIRED_COLUMNS[j]} row {row + 1} (line {row + 2}) holds "
                      f"non-numeric {excerpt(value)}; write a plain number (decimal point, no units)")


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
