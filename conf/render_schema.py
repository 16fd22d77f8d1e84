"""Structured schema of the ``render`` config group: the multi-view G-buffer (paper sec. 3.2, last paragraph) and
the conditions of eq. 6 (sec. 3.3).  Accuracy knobs: ``width``/``height`` and ``frame_stride``."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ReleasedAppearance:
    """How released interior material looks as 3D Gaussians before the effect stage (linear RGB in [0, 1])."""

    color: list[float] = field(default_factory=lambda: [0.8, 0.5, 0.1])
    opacity: float = 0.8
    effect: str = "liquid"  # liquid | stuffing: which weight-free renderer draws it (generation=physics)


@dataclass
class RenderConfig:
    """The orbit rig and the G-buffer.

    views: cameras evenly spaced in azimuth around the object (VR: several views of one squeeze).
    elevation_deg: camera height above the object's centre, degrees.  azimuth0_deg: azimuth of view 0 (from +x).
    fov_deg: horizontal field of view.  fill: fraction of the image width the object's bounding sphere spans at
    rest (the camera distance follows from it and the object's size).
    width, height: pixels.  frame_stride: render every n-th simulated frame (1 = all, 30 fps at the default
    frame rate).  background: linear RGB behind the object.  device: where the rasteriser runs.
    mask_min_component_px, mask_closing_radius_px: R(.) of eq. 6 at 256 px width (scaled with the width):
    connected components of the released-material mask below this area are dropped, the boundary is closed
    with an elliptical kernel of this radius, holes are filled.  mask_threshold: composited weight above which a
    pixel belongs to the released material.
    depth_normalisation: ``sequence`` (inverse depth scaled to [0, 1] over the whole clip: no brightness flicker)
    or ``frame`` (per frame, as the MiDaS annotator).
    hand: draw the glove's hand (capsules from the recorded fingertips, palm pose and flexion) in the videos;
    hand_colour: its linear RGB (a neutral skin tone).  video_width, video_height: pixels of the watched videos
    (every orbit view plus, with ``closeup``, one view framing the fingers' contact region so that its four
    fingertips span ``closeup_fill`` of the width).
    released: appearance of released interior material, keyed by a word of the oracle's interior material name
    (``regular cola`` -> ``cola``, ``tomato juice / locular pulp`` -> ``tomato``, ``loose polyester fibrefill``
    -> ``fibrefill``); the first key contained in the name wins, others use ``released_default``.
    """

    views: int = 4
    elevation_deg: float = 20.0
    azimuth0_deg: float = -60.0
    fov_deg: float = 40.0
    fill: float = 0.6
    width: int = 192
    height: int = 192
    frame_stride: int = 2
    background: list[float] = field(default_factory=lambda: [0.92, 0.92, 0.90])
    near_plane: float = 0.01
    device: str = "auto"  # auto (CUDA when present, else CPU) | cpu | cuda
    mask_threshold: float = 0.5
    mask_min_component_px: int = 12
    mask_closing_radius_px: int = 2
    depth_normalisation: str = "sequence"
    released: dict[str, ReleasedAppearance] = field(default_factory=lambda: {
        "tomato": ReleasedAppearance(color=[0.75, 0.08, 0.03], opacity=0.85, effect="liquid"),
        "orange": ReleasedAppearance(color=[0.95, 0.55, 0.05], opacity=0.85, effect="liquid"),
        "cola": ReleasedAppearance(color=[0.12, 0.04, 0.02], opacity=0.9, effect="liquid"),
        "water": ReleasedAppearance(color=[0.75, 0.85, 0.95], opacity=0.5, effect="liquid"),
        "fibrefill": ReleasedAppearance(color=[0.93, 0.91, 0.86], opacity=0.95, effect="stuffing"),
        "stuffing": ReleasedAppearance(color=[0.93, 0.91, 0.86], opacity=0.95, effect="stuffing"),
    })
    released_default: ReleasedAppearance = field(default_factory=ReleasedAppearance)
    # the watched videos (step display_video; the G-buffer above, eq. 6 and every metric never see these)
    hand: bool = True
    hand_colour: list[float] = field(default_factory=lambda: [0.75, 0.46, 0.33])
    video_width: int = 384
    video_height: int = 384
    closeup: bool = True
    closeup_fill: float = 0.8


def validate_render(cfg) -> None:
    """Range checks of ``render``; raises ValueError naming the key."""
    r = cfg
    checks = [
        (r.views >= 1, "render.views", f"must be >= 1, got {r.views}"),
        (-90 < r.elevation_deg < 90, "render.elevation_deg", f"must be in (-90, 90), got {r.elevation_deg}"),
        (0 < r.fov_deg < 180, "render.fov_deg", f"must be in (0, 180), got {r.fov_deg}"),
        (0 < r.fill <= 1, "render.fill", f"must be in (0, 1], got {r.fill}"),
        (16 <= r.width <= 4096 and 16 <= r.height <= 4096, "render.width/height",
         f"must be in [16, 4096] px, got {r.width} x {r.height}"),
        (r.frame_stride >= 1, "render.frame_stride", f"must be >= 1, got {r.frame_stride}"),
        (16 <= r.video_width <= 4096 and 16 <= r.video_height <= 4096, "render.video_width/video_height",
         f"must be in [16, 4096] px, got {r.video_width} x {r.video_height}"),
        (len(r.hand_colour) == 3 and all(0 <= c <= 1 for c in r.hand_colour), "render.hand_colour",
         f"must be three linear RGB values in [0, 1], got {list(r.hand_colour)}"),
        (0 < r.closeup_fill <= 1, "render.closeup_fill", f"must be in (0, 1], got {r.closeup_fill}"),
        (len(r.background) == 3, "render.background", f"must be three linear RGB values, got {list(r.background)}"),
        (0 < r.mask_threshold < 1, "render.mask_threshold", f"must be in (0, 1), got {r.mask_threshold}"),
        (r.depth_normalisation in ("sequence", "frame"), "render.depth_normalisation",
         f"must be sequence or frame, got {r.depth_normalisation!r}"),
        (r.device in ("auto", "cpu", "cuda"), "render.device", f"must be auto, cpu or cuda, got {r.device!r}"),
    ]
    for ok, key, msg in checks:
        if not ok:
            raise ValueError(f"{key} {msg}")
