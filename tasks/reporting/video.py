"""Videos and image grids a researcher can watch in a browser (issue "Videos and the report").

* :func:`encode_video` writes H.264 MP4 (yuv420p, BT.601 matrix tagged with sRGB primaries and transfer,
  ``+faststart`` so playback starts before the download ends) through PyAV, whose wheels ship libav with libx264
  and libvpx; ``.webm`` gives VP9, ``.webp`` an animated WebP through Pillow, which is also the fallback when no
  H.264 encoder is available.  All three play in Debian's Chromium 156 (checked headless).
* :func:`decode_video` reads them back (tests, metrics).
* :func:`contact_sheet` and :func:`side_by_side` tile images or videos with labels drawn by ``cv2.putText``.

Colour convention: float input is linear RGB in [0, 1] and is encoded with the sRGB transfer function
(:func:`to_display`); uint8 input is taken as display-ready sRGB and passed through unchanged.  Outputs are
uint8 sRGB in RGB channel order (convert to BGR before ``cv2.imwrite``).
"""
from __future__ import annotations

import functools
import os
import tempfile
import time
import warnings
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np
from PIL import Image, ImageSequence

try:
    import av
    from av.video.reformatter import ColorRange, Colorspace
except ImportError:  # PyAV absent: animated WebP remains
    av = None

_ENCODERS = {".mp4": "libx264", ".webm": "libvpx-vp9"}


def _x264_instruction_sets() -> dict[str, str]:
    """libx264's ``asm`` parameter capped at AVX2 on a CPU with AVX-512, else empty (libx264 detects the CPU).

    libx264 165's AVX-512 functions read uninitialised memory: the same frames encoded twice in one process gave
    different bytes (the I frame's mean QP 13.07 against 16.93 on a 96 x 68 video), following the heap's contents
    (reproduced with glibc's ``MALLOC_PERTURB_``).  Its AVX2 functions give the same bytes whatever the heap holds,
    so a re-encoded video is byte-identical to the cached one.  "SSE2Fast,AVX2" is what libx264 itself detects on
    these CPUs less AVX512.  The features are numpy's run-time detection (CPUID and the OS's XSAVE state)."""
    try:
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:  # another numpy layout: leave libx264's own detection
        return {}
    return {"x264-params": "asm=SSE2Fast,AVX2"} if features.get("AVX512F") else {}


# One encoder thread: the report media are made on the task runner's workers, one core each, beside simulations.
_ENCODER_OPTIONS = {"libx264": {"crf": "18", "preset": "medium", "threads": "1", **_x264_instruction_sets()},
                    "libvpx-vp9": {"crf": "30", "b": "0", "deadline": "good", "cpu-used": "4", "threads": "1"}}
# Colour tags (libavutil/pixfmt.h).  The samples are sRGB-encoded, so primaries BT.709 (= sRGB's) and transfer
# IEC 61966-2-1; the matrix is BT.601 (SMPTE 170M): Debian's Chromium 156 (software compositing) shows BT.601 within
# 2 levels of the source on saturated primaries, BT.709 off by up to 12.
_PRIMARIES_BT709, _TRANSFER_SRGB, _MATRIX_SMPTE170M = 1, 13, 6
_WEBP_QUALITY = 90
_LABEL_BACKGROUND = (32, 32, 32)
_LABEL_TEXT = (235, 235, 235)


def _srgb_table(levels: int = 1 << 16) -> np.ndarray:
    """uint8 sRGB (IEC 61966-2-1) of ``levels`` evenly spaced linear values in [0, 1]: a lookup table within one
    uint8 step of the power law and several times faster on video-sized arrays."""
    linear = np.linspace(0.0, 1.0, levels)
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


_SRGB_TABLE = _srgb_table()


def to_display(images: np.ndarray) -> np.ndarray:
    """Images (..., channel=3) as uint8 sRGB: float linear RGB in [0, 1] through the sRGB transfer function
    (IEC 61966-2-1, values clipped to [0, 1]), uint8 unchanged."""
    images = np.asarray(images)
    if images.shape[-1:] != (3,):
        raise ValueError(f"images must end in an RGB channel axis of 3, got shape {images.shape}")
    if images.dtype == np.uint8:
        return images
    if not np.issubdtype(images.dtype, np.floating):
        raise ValueError(f"images must be float linear RGB in [0, 1] or uint8 sRGB, got {images.dtype}")
    scaled = np.fmax(images.astype(np.float32), np.float32(0.0))  # fmax also maps NaN to 0
    np.fmin(scaled, np.float32(1.0), out=scaled)
    scaled *= np.float32(_SRGB_TABLE.size - 1)
    scaled += np.float32(0.5)
    return _SRGB_TABLE[scaled.astype(np.uint16)]


@functools.lru_cache(maxsize=None)
def encoder_available(encoder: str) -> bool:
    """Whether PyAV is installed and its libav can open ``encoder`` (e.g. "libx264") for writing."""
    if av is None:
        return False
    try:
        av.codec.Codec(encoder, "w")
    except ValueError:  # av's UnknownCodecError
        return False
    return True


def _even(frames: np.ndarray) -> np.ndarray:
    """(frame, y, x, 3) padded by edge replication to even y and x (yuv420p halves both chroma axes)."""
    pad_y, pad_x = frames.shape[1] % 2, frames.shape[2] % 2
    return np.pad(frames, ((0, 0), (0, pad_y), (0, pad_x), (0, 0)), mode="edge") if pad_y or pad_x else frames


def _write_webp(frames: np.ndarray, path: Path, fps: float) -> Path:
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=max(int(round(1000.0 / fps)), 1),
                   loop=0, quality=_WEBP_QUALITY, method=4)
    return path


def _write_libav(frames: np.ndarray, path: Path, fps: float, encoder: str) -> Path:
    frames = _even(frames)
    options = {"movflags": "+faststart"} if path.suffix == ".mp4" else {}
    with av.open(str(path), "w", options=options) as container:
        stream = container.add_stream(encoder, rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        stream.options = _ENCODER_OPTIONS.get(encoder, {})
        context = stream.codec_context
        context.color_primaries, context.color_trc = _PRIMARIES_BT709, _TRANSFER_SRGB
        context.colorspace = _MATRIX_SMPTE170M
        context.color_range = ColorRange.MPEG
        for image in frames:
            frame = av.VideoFrame.from_ndarray(image, format="rgb24").reformat(
                format="yuv420p", dst_colorspace=Colorspace.ITU601, dst_color_range=ColorRange.MPEG)
            container.mux(stream.encode(frame))
        container.mux(stream.encode())
    return path


def encode_video(frames: np.ndarray, path: str | os.PathLike, fps: float = 30.0, encoder: str | None = None) -> Path:
    """Write a browser-playable video; the container follows the path's suffix.

    frames: (frame, y, x, channel=3), float linear RGB in [0, 1] or uint8 sRGB (see the module doc).
    path: ``.mp4`` (H.264, yuv420p, faststart), ``.webm`` (VP9) or ``.webp`` (animated WebP, Pillow).
    fps: frames per second.  encoder: a libav encoder name overriding the suffix's default (libx264, libvpx-vp9).
    Odd heights and widths are padded by one replicated row/column (yuv420p needs even sizes).
    When the encoder is not available (no PyAV, or a libav without it) the video is written as animated WebP
    beside ``path`` with a warning.  Returns the path written.
    """
    frames, path = to_display(frames), Path(path)
    if frames.ndim != 4 or len(frames) == 0:
        raise ValueError(f"frames must be (frame, y, x, 3) with at least one frame, got shape {frames.shape}")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    if path.suffix == ".webp":
        return _write_webp(frames, path, fps)
    if path.suffix not in _ENCODERS:
        raise ValueError(f"video path {path} must end in .mp4, .webm or .webp")
    encoder = encoder or _ENCODERS[path.suffix]
    if not encoder_available(encoder):
        warnings.warn(f"no {encoder} encoder (PyAV/libav): writing animated WebP instead of {path.name}",
                      stacklevel=2)
        return _write_webp(frames, path.with_suffix(".webp"), fps)
    return _write_libav(frames, path, fps, encoder)


def decode_video(path: str | os.PathLike) -> tuple[np.ndarray, float]:
    """Read a video written by :func:`encode_video`: ((frame, y, x, 3) uint8 sRGB, frames per second)."""
    path = Path(path)
    if path.suffix == ".webp":
        with Image.open(path) as image:
            frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(image)]
            duration_ms = image.info.get("duration", 0)
        return np.stack(frames), (1000.0 / duration_ms if duration_ms else 0.0)
    if av is None:
        raise ValueError(f"decoding {path.suffix} needs PyAV: pip install av")
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(stream)]
        return np.stack(frames), float(stream.average_rate)


_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _text_box(text: str, height: int, width: int, align_left: bool = False, scale: float | None = None) -> np.ndarray:
    """(height, width, 3) uint8 label: ``text`` in white on dark grey, vertically centred; at OpenCV font ``scale``
    (default: sized to ``height``), shrunk to fit ``width``."""
    box = np.full((height, width, 3), _LABEL_BACKGROUND, np.uint8)
    scale = 0.6 * height / 24.0 if scale is None else scale
    (text_w, text_h), _ = cv2.getTextSize(text, _FONT, scale, 1)
    if text_w > width - 6:
        scale *= (width - 6) / text_w
        (text_w, text_h), _ = cv2.getTextSize(text, _FONT, scale, 1)
    x = 3 if align_left else max((width - text_w) // 2, 0)
    y = (height + text_h) // 2
    cv2.putText(box, text, (x, y), _FONT, scale, _LABEL_TEXT, 1, cv2.LINE_AA)
    return box


def _row_label_scale(labels: Sequence[str], width: int, label_px: int) -> float:
    """One font scale for every row label of a sheet: the column labels' size, up to twice it, at which the
    longest label still fits ``width`` (a short label is not drawn larger than the rest)."""
    scale = 2 * 0.6 * label_px / 24.0
    for label in labels:
        text_w = cv2.getTextSize(label, _FONT, scale, 1)[0][0]
        if text_w > width - 6:
            scale *= (width - 6) / text_w
    return scale


def contact_sheet(images: np.ndarray, row_labels: Sequence[str], column_labels: Sequence[str],
                  label_px: int = 20, row_label_px: int = 96) -> np.ndarray:
    """A labelled grid of images for the report (e.g. rows = views, columns = rest, peak squeeze, release).

    images: (row, column, y, x, channel=3), float linear RGB in [0, 1] or uint8 sRGB; row_labels: one per row,
    drawn in a left margin ``row_label_px`` wide; column_labels: one per column, drawn in a top band
    ``label_px`` high.  Returns (label_px + row * y, row_label_px + column * x, 3) uint8 sRGB, RGB order.
    """
    images = to_display(images)
    if images.ndim != 5:
        raise ValueError(f"images must be (row, column, y, x, 3), got shape {images.shape}")
    rows, columns, height, width = images.shape[:4]
    if len(row_labels) != rows or len(column_labels) != columns:
        raise ValueError(f"{len(row_labels)} row and {len(column_labels)} column labels for a {rows} x {columns} "
                         "grid: give one label per row and per column")
    header = np.concatenate([_text_box("", label_px, row_label_px)]
                            + [_text_box(label, label_px, width) for label in column_labels], axis=1)
    scale = _row_label_scale(row_labels, row_label_px, label_px)
    body = [np.concatenate([_text_box(label, height, row_label_px, align_left=True, scale=scale), *images[r]], axis=1)
            for r, label in enumerate(row_labels)]
    return np.concatenate([header, *body], axis=0)


def side_by_side(videos: Sequence[np.ndarray], labels: Sequence[str], columns: int | None = None,
                 label_px: int = 20) -> np.ndarray:
    """Tile several videos (views, stages) into one, each under its label, ``columns`` per row (default: all).

    videos: each (frame, y, x, channel=3) with equal shapes, float linear RGB in [0, 1] or uint8 sRGB; labels:
    one per video.  Empty grid cells are dark.  Returns (frame, rows * (label_px + y), columns * x, 3) uint8 sRGB.
    """
    if len(videos) == 0 or len(videos) != len(labels):
        raise ValueError(f"{len(videos)} videos and {len(labels)} labels: give one label per video (at least one)")
    tiles = [to_display(v) for v in videos]
    if any(t.ndim != 4 or t.shape != tiles[0].shape for t in tiles):
        raise ValueError(f"videos must all be (frame, y, x, 3) of one shape, got {[t.shape for t in tiles]}")
    frames, height, width = tiles[0].shape[:3]
    columns = columns or len(tiles)
    cells = []
    for k in range(-(-len(tiles) // columns) * columns):
        label = _text_box(labels[k] if k < len(tiles) else "", label_px, width)
        tile = tiles[k] if k < len(tiles) else np.full_like(tiles[0], _LABEL_BACKGROUND[0])
        cells.append(np.concatenate([np.broadcast_to(label, (frames, label_px, width, 3)), tile], axis=1))
    rows = [np.concatenate(cells[r:r + columns], axis=2) for r in range(0, len(cells), columns)]
    return np.concatenate(rows, axis=1)


def benchmark(frames: int = 90, size_px: int = 256, fps: float = 30.0) -> dict[str, float]:
    """Prints and returns, per container, the wall and CPU seconds (all threads) to encode and decode a smooth
    moving clip of float frames, and its kilobytes.  CPU time is the better figure on a shared machine."""
    t = np.arange(frames)[:, None, None]
    yy, xx = np.mgrid[0:size_px, 0:size_px][:, None] / size_px
    clip = np.stack([0.5 + 0.4 * np.sin(6 * xx + 0.1 * t), 0.5 + 0.4 * np.cos(5 * yy - 0.07 * t),
                     0.5 + 0.3 * np.sin(4 * (xx + yy) + 0.05 * t)], -1).astype(np.float32)
    figures = {}
    with tempfile.TemporaryDirectory() as folder:
        for suffix in (".mp4", ".webm", ".webp"):
            wall, cpu = time.perf_counter(), time.process_time()
            written = encode_video(clip, Path(folder) / f"clip{suffix}", fps)
            encode_wall, encode_cpu = time.perf_counter() - wall, time.process_time() - cpu
            wall, cpu = time.perf_counter(), time.process_time()
            decode_video(written)
            decode_wall, decode_cpu = time.perf_counter() - wall, time.process_time() - cpu
            name, kilobytes = suffix[1:], written.stat().st_size / 1e3
            figures.update({f"{name}_encode_s": encode_wall, f"{name}_encode_cpu_s": encode_cpu,
                            f"{name}_decode_s": decode_wall, f"{name}_decode_cpu_s": decode_cpu,
                            f"{name}_kb": kilobytes})
            print(f"{name}: {frames} frames {size_px}x{size_px}: encode {encode_wall:.2f} s wall / {encode_cpu:.2f} s "
                  f"CPU, decode {decode_wall:.2f} s / {decode_cpu:.2f} s, {kilobytes:.0f} kB")
    return figures


if __name__ == "__main__":
    benchmark()
