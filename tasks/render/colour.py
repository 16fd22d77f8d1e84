"""Colour encodings shared by the render, generation, metric and report stages.

The renderer composites linear RGB in [0, 1]; images stored in artifacts, fed to the generators and shown in
videos are 8-bit sRGB (IEC 61966-2-1 transfer function: s = 12.92 c for c <= 0.0031308, else
1.055 c^(1/2.4) - 0.055).  Conversions happen once, here.
"""
from __future__ import annotations

import numpy as np

_ENCODE_STEPS = 4096  # linear -> sRGB lookup resolution: max error below half an 8-bit level


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """sRGB-encoded float32 in [0, 1] of linear RGB (clipped to [0, 1] first; NaN -> 0)."""
    c = np.fmin(np.fmax(np.asarray(linear, dtype=np.float32), np.float32(0.0)), np.float32(1.0))
    return np.where(c <= 0.0031308, np.float32(12.92) * c,
                    np.float32(1.055) * np.power(c, np.float32(1.0 / 2.4)) - np.float32(0.055)).astype(np.float32)


_SRGB_TABLE = np.rint(linear_to_srgb(np.linspace(0.0, 1.0, _ENCODE_STEPS, dtype=np.float32)) * 255.0).astype(
    np.uint8)


def to_srgb_uint8(images: np.ndarray) -> np.ndarray:
    """8-bit sRGB of ``images`` (..., channel): uint8 passes through unchanged (already sRGB); float is linear RGB
    in [0, 1], clipped (NaN -> 0) and encoded through a 4096-entry table (error < 0.5 level)."""
    images = np.asarray(images)
    if images.dtype == np.uint8:
        return images
    if not np.issubdtype(images.dtype, np.floating):
        raise ValueError(f"images must be float linear RGB in [0, 1] or uint8 sRGB, got {images.dtype}")
    scaled = np.fmin(np.fmax(images.astype(np.float32), np.float32(0.0)), np.float32(1.0))
    return _SRGB_TABLE[(scaled * np.float32(_ENCODE_STEPS - 1) + np.float32(0.5)).astype(np.uint16)]


_LINEAR_TABLE = np.where(np.arange(256) / 255.0 <= 0.04045, np.arange(256) / 255.0 / 12.92,
                         ((np.arange(256) / 255.0 + 0.055) / 1.055) ** 2.4).astype(np.float32)


def srgb_uint8_to_linear(images: np.ndarray) -> np.ndarray:
    """Linear RGB float32 in [0, 1] of 8-bit sRGB ``images`` (the exact inverse transfer function per level)."""
    images = np.asarray(images)
    if images.dtype != np.uint8:
        raise ValueError(f"images must be uint8 sRGB, got {images.dtype}")
    return _LINEAR_TABLE[images]
