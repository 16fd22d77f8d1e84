"""Browser videos: encode/decode round trips (frame count, size, PSNR), WebP fallback, labelled grids."""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tasks.reporting.video import (
    contact_sheet,
    decode_video,
    encode_video,
    encoder_available,
    side_by_side,
    to_display,
)

FRAMES, HEIGHT, WIDTH = 24, 64, 96


def _smooth_clip(frames: int = FRAMES, height: int = HEIGHT, width: int = WIDTH) -> np.ndarray:
    """(frame, y, x, 3) uint8 sRGB: smooth, saturated gradients drifting over time."""
    t = np.arange(frames)[:, None, None]
    yy, xx = np.mgrid[0:height, 0:width][:, None] / max(height, width)
    clip = np.stack([0.5 + 0.45 * np.sin(6 * xx + 0.2 * t), 0.5 + 0.45 * np.cos(5 * yy - 0.15 * t),
                     0.5 + 0.45 * np.sin(4 * (xx + yy) + 0.1 * t)], -1)
    return np.round(255 * clip).astype(np.uint8)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0 ** 2 / mse))


@pytest.mark.parametrize("suffix, encoder", [(".mp4", "libx264"), (".webm", "libvpx-vp9"), (".webp", None)])
def test_video_round_trip_keeps_frames_size_and_pixels(tmp_path, suffix, encoder):
    if encoder is not None and not encoder_available(encoder):
        pytest.skip(f"{encoder} is not in this libav")  # the fallback test below covers its absence
    clip = _smooth_clip()
    written = encode_video(clip, tmp_path / f"clip{suffix}", fps=24)
    assert written == tmp_path / f"clip{suffix}" and written.stat().st_size > 0
    frames, fps = decode_video(written)
    assert frames.shape == clip.shape and frames.dtype == np.uint8
    assert fps == pytest.approx(24, rel=0.05)
    assert _psnr(frames, clip) > 30
    assert _psnr(frames[5], clip[5]) > _psnr(frames[5], clip[15]) + 5  # frames stay in order


def test_mp4_is_tagged_h264_yuv420p_with_faststart(tmp_path):
    av = pytest.importorskip("av")
    written = encode_video(_smooth_clip(), tmp_path / "clip.mp4", fps=30)
    with av.open(str(written)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        assert stream.codec_context.colorspace == 6  # BT.601 (SMPTE 170M) matrix
        assert stream.codec_context.color_trc == 13  # sRGB transfer
    head = written.read_bytes()[:4096]
    assert head.find(b"moov") < head.find(b"mdat") or b"mdat" not in head  # index before the data


def test_an_mp4_s_bytes_do_not_depend_on_what_the_heap_held(tmp_path):
    """Two processes whose freed and fresh heap memory hold different bytes (glibc's MALLOC_PERTURB_) encode the same
    clip to the same bytes, so a report video made again is the cached one (libx264's AVX-512 functions read
    uninitialised memory: on an AVX-512 CPU, without the cap in tasks.reporting.video, the three files differ)."""
    if not encoder_available("libx264"):
        pytest.skip("libx264 is not in this libav")
    np.save(tmp_path / "clip.npy", _smooth_clip(frames=12, height=200, width=330))
    script = ("import sys, numpy as np; from tasks.reporting.video import encode_video; "
              "encode_video(np.load(sys.argv[1]), sys.argv[2], fps=24)")
    for perturb in (0, 1, 85):
        env = {**os.environ, "MALLOC_PERTURB_": str(perturb)}
        subprocess.run([sys.executable, "-c", script, str(tmp_path / "clip.npy"), str(tmp_path / f"{perturb}.mp4")],
                       env=env, check=True, cwd=Path(__file__).resolve().parents[2])
    assert (tmp_path / "0.mp4").read_bytes() == (tmp_path / "1.mp4").read_bytes() == (tmp_path / "85.mp4").read_bytes()


def test_missing_encoder_falls_back_to_animated_webp(tmp_path):
    clip = _smooth_clip(frames=6)
    with pytest.warns(UserWarning, match="WebP"):
        written = encode_video(clip, tmp_path / "clip.mp4", fps=12, encoder="no-such-encoder")
    assert written == tmp_path / "clip.webp"
    frames, fps = decode_video(written)
    assert frames.shape == clip.shape and fps == pytest.approx(12, rel=0.05)
    assert _psnr(frames, clip) > 30


def test_odd_sizes_are_padded_to_even_for_yuv420p(tmp_path):
    if not encoder_available("libx264"):
        pytest.skip("libx264 is not in this libav")
    clip = _smooth_clip(frames=4, height=33, width=47)
    frames, _ = decode_video(encode_video(clip, tmp_path / "odd.mp4"))
    assert frames.shape == (4, 34, 48, 3)
    assert _psnr(frames[:, :33, :47], clip) > 30


def test_linear_float_frames_are_encoded_with_the_srgb_curve():
    linear = np.array([[0.0, 0.0031308, 0.18, 0.5, 1.0, 1.5]]).T.repeat(3, 1)  # mid grey 0.18 -> sRGB 118
    np.testing.assert_array_equal(to_display(linear)[:, 0], [0, 10, 118, 188, 255, 255])
    with pytest.raises(ValueError, match="channel"):
        to_display(np.zeros((4, 4)))


def test_bad_video_inputs_are_value_errors(tmp_path):
    with pytest.raises(ValueError, match="mp4"):
        encode_video(_smooth_clip(frames=2), tmp_path / "clip.avi")
    with pytest.raises(ValueError, match="frame"):
        encode_video(_smooth_clip()[0], tmp_path / "clip.webp")


def test_contact_sheet_row_labels_share_one_size():
    """A short row label ("can") is drawn no larger than a long one ("cream sauce"): one size for the column, the
    longest label fitting its margin, at most twice the column labels' size."""
    images = np.zeros((3, 1, 192, 192, 3), np.uint8)
    sheet = contact_sheet(images, ["can", "rubber_duck", "cream sauce"], ["peak"], label_px=20, row_label_px=96)

    def text_rows(r):  # the rows of row label r's cell that hold text
        cell = sheet[20 + 192 * r:20 + 192 * (r + 1), :96]
        return np.flatnonzero((cell > 128).any(axis=(1, 2)))

    heights = [len(text_rows(r)) for r in range(3)]
    assert all(h > 0 for h in heights)
    assert max(heights) <= 2 * 20  # at most twice the column labels' 20 px band ("can" alone: 3x that before)
    assert abs(heights[2] - heights[0]) <= 1  # "cream sauce" and "can": lower case without ascenders alike


def test_contact_sheet_layout_and_labels():
    images = np.zeros((2, 3, 40, 50, 3), np.uint8)
    images[1, 2] = 200
    sheet = contact_sheet(images, ["view 0", "view 1"], ["rest", "peak", "release"], label_px=16, row_label_px=60)
    assert sheet.shape == (16 + 2 * 40, 60 + 3 * 50, 3)
    np.testing.assert_array_equal(sheet[16 + 40:, 60 + 100:], 200)  # image (1, 2) lands in its cell
    assert (sheet[:16, 60:110] > 128).any() and (sheet[16:56, :60] > 128).any()  # label text is drawn
    with pytest.raises(ValueError, match="label"):
        contact_sheet(images, ["view 0"], ["rest", "peak", "release"])


def test_side_by_side_tiles_videos_under_their_labels():
    a, b, c = (np.full((5, 20, 30, 3), v, np.uint8) for v in (10, 100, 250))
    tiled = side_by_side([a, b, c], ["simulated", "conditions", "composite"], columns=2, label_px=12)
    assert tiled.shape == (5, 2 * (12 + 20), 2 * 30, 3)
    np.testing.assert_array_equal(tiled[:, 12:32, :30], 10)
    np.testing.assert_array_equal(tiled[:, 12:32, 30:], 100)
    np.testing.assert_array_equal(tiled[:, 44:, :30], 250)
    assert (tiled[0, :12, :30] > 128).any()  # the first label
    assert np.array_equal(tiled[0, :12], tiled[4, :12])  # labels do not change over time
    with pytest.raises(ValueError, match="shape"):
        side_by_side([a, b[:, :10]], ["a", "b"])
