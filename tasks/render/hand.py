"""The glove's hand drawn from the recorded control signals (paper sec. 3.1: flexion, fingertip positions, palm
pose), for the videos only: the G-buffer of eq. 6 and every metric stay the object's alone.

Geometry (:func:`hand_capsules`): every bone is a capsule (a segment swept by a sphere), so the whole hand is one
list of capsules:

* five fingers as articulated chains knuckle -> 3 phalanges -> the *recorded* fingertip (the thumb: its base ->
  metacarpal-free 3-bone chain).  The chain ends exactly at the recorded fingertip: where a patch tore in the
  simulation or a finger is lifted, the drawing follows the recording, not the simulation.  A finger's bone
  lengths are fixed over the clip (its longest knuckle-to-tip distance x ``SLACK``), so when the tip comes closer
  the finger bends: the recorded flexion decides how the bend is shared between the three joints (an open finger
  bends at the knuckle, a flexed one curls at the two distal joints as well), and the bend bulges away from the
  grasp centre (the fingers wrap around the object);
* a palm of four metacarpal capsules from the wrist to the four knuckles, side by side so that they fuse into a
  slab, a thumb metacarpal and a short forearm behind the wrist; the palm pose (position, orientation: z towards the object, x from the thumb towards
  the fingers) places the wrist and the knuckles, the knuckles lined up with their fingers' recorded tips.

Rasterisation (:func:`render_hand`): exact ray-capsule intersection per pixel (front depth, normal), z-buffered
across capsules, with an anti-aliased silhouette from the distance between the pixel's ray and the capsule's axis
(coverage = clip(0.5 + (r - distance) f / z, 0, 1): a one-pixel ramp).  Shading: Lambert + ambient in a neutral skin
colour with a soft Blinn-Phong sheen.  :func:`composite_hand` puts the hand into a rendered frame by depth: a finger
in front of the object occludes it, a finger behind it is hidden (the object's semi-transparent rim lets it show
through as much as the object's alpha allows).
:func:`draw_hand` does both for the display step in one kernel pass, without the hand layer.

Units: metres, pixels, linear RGB in [0, 1].  Cameras as in :mod:`tasks.render.cameras` (OpenCV: x right, y down,
z forward; pixel (x, y) covers [x, x + 1) x [y, y + 1)).
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import NamedTuple

import numpy as np

from conf.hand import FINGERS, N_FINGERS

from .hand_kernels import (
    CAPSULE_FIELDS,
    capsule_scalars,
    composite_hand_pixels,
    draw_capsules,
    shade_and_composite_pixels,
    shade_skin_pixels,
)

# m, capsule radii per finger (thumb .. pinky), proximal and distal phalanx
FINGER_RADII = np.array([[0.0100, 0.0090], [0.0085, 0.0075], [0.0088, 0.0078], [0.0083, 0.0073], [0.0075, 0.0065]])
PHALANX_SHARES = np.array([0.45, 0.30, 0.25])  # bone lengths as shares of the finger's length (proximal first)
SLACK = 1.06  # a finger's length = its longest knuckle-to-tip distance over the clip x this: never straight
METACARPAL_RADIUS = 0.0115  # m: four side by side fuse into the palm
WRIST_RADIUS = 0.017  # m, the forearm's
FOREARM_M = 0.06  # m of forearm drawn behind the wrist
PALM_LENGTH_M = (0.020, 0.065)  # wrist-to-knuckle length range, m (scaled to the recorded hand)


class Capsules(NamedTuple):
    """Capsules: segment ends a, b (n, 3) m and radius (n,) m, world coordinates."""

    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray


class HandLayer(NamedTuple):
    """The hand in one camera: rgb (y, x, 3) linear RGB (shaded, not premultiplied), depth (y, x) m (camera z of the
    nearest capsule; +inf where none), coverage (y, x) in [0, 1] (anti-aliased silhouette)."""

    rgb: np.ndarray
    depth: np.ndarray
    coverage: np.ndarray


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices of unit quaternions (..., 4) w, x, y, z (the recording's palm orientation)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], -2)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def joint_weights(flexion: float) -> np.ndarray:
    """How a finger's bend is shared by its three joints (knuckle, middle, distal; sum 1) at ``flexion`` in [0, 1]:
    an open finger bends mostly at the knuckle, a fully flexed one evenly."""
    f = float(np.clip(flexion, 0.0, 1.0))
    w = (1.0 - f) * np.array([0.7, 0.2, 0.1]) + f * np.array([1.0, 1.0, 1.0]) / 3.0
    return w / w.sum()


def _planar_chain(lengths: np.ndarray, weights: np.ndarray, bend: float) -> np.ndarray:
    """Joint positions (4, 2) of a planar chain starting at the origin along +x, turning by ``bend`` x weights at its
    joints (towards +y)."""
    heading = np.cumsum(bend * weights)
    steps = lengths[:, None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    return np.vstack([np.zeros(2), np.cumsum(steps, axis=0)])


def finger_chain(knuckle: np.ndarray, tip: np.ndarray, length: float, flexion: float,
                 bulge: np.ndarray) -> np.ndarray:
    """The four joints (knuckle, middle, distal, tip) (4, 3) m of a finger of total ``length`` m whose chain ends at
    the recorded ``tip``: the total bend is the one at which the chain's end lies |tip - knuckle| from the knuckle
    (bisection; the end distance falls monotonically with the bend for shares of ``joint_weights``), the joints turn
    in the plane of (tip - knuckle, ``bulge``), the chain's middle bulging towards ``bulge``.  A tip farther than
    ``length`` gets a straight finger stretched to reach it."""
    knuckle, tip = np.asarray(knuckle, np.float64), np.asarray(tip, np.float64)
    chord = tip - knuckle
    d = float(np.linalg.norm(chord))
    lengths = PHALANX_SHARES * length
    weights = joint_weights(flexion)
    if d < 1e-9:
        return np.stack([knuckle] * 4)
    if d >= length:
        return knuckle + np.outer(np.r_[0.0, np.cumsum(PHALANX_SHARES)], chord)
    lo, hi = 0.0, 5.0  # rad: the end distance falls from length (straight) towards 0 as the finger curls
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.linalg.norm(_planar_chain(lengths, weights, mid)[-1]) > d else (lo, mid)
    pts = _planar_chain(lengths, weights, 0.5 * (lo + hi))
    end = pts[-1]
    # rotate the plane so that the chain's end lies on +x: its joints then bulge to -y
    c, s = end / np.linalg.norm(end)
    pts = pts @ np.array([[c, -s], [s, c]])
    pts *= d / np.linalg.norm(pts[-1])
    e1 = chord / d
    e2 = bulge - e1 * float(bulge @ e1)
    if np.linalg.norm(e2) < 1e-9:
        e2 = np.cross(e1, [0.0, 0.0, 1.0]) if abs(e1[2]) < 0.9 else np.cross(e1, [1.0, 0.0, 0.0])
    e2 = _unit(e2)
    return knuckle + np.outer(pts[:, 0], e1) - np.outer(pts[:, 1], e2)


def hand_frame(palm_position: np.ndarray, palm_orientation: np.ndarray, fingertips: np.ndarray,
               rest_tips: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wrist (3,), the five finger bases (finger, 3) (the thumb's base first, then the four knuckles) and the
    palm's inward direction (3,), m, world: from the palm pose of one frame and the rest fingertips of the clip.

    The palm length (wrist to knuckles, along the palm's x axis) is 0.55 x the median reach of the four fingers'
    rest tips along x, within ``PALM_LENGTH_M``; each knuckle sits at the component of its rest tip across the palm
    (the palm's y axis, within +-4 cm), so every finger starts in line with its own tip; the palm's back is
    ``METACARPAL_RADIUS`` behind the palm position (which the recording puts on the palm's skin)."""
    rot = quaternion_matrix(palm_orientation)
    x, y, z = rot[:, 0], rot[:, 1], rot[:, 2]
    centre = np.asarray(palm_position, np.float64) - z * METACARPAL_RADIUS
    rel = np.asarray(rest_tips, np.float64) - centre
    reach = float(np.median(rel[1:] @ x))
    length = float(np.clip(0.55 * reach, *PALM_LENGTH_M))
    across = np.clip(rel @ y, -0.04, 0.04)
    knuckles = centre + x * (0.5 * length) + np.outer(across, y)
    wrist = centre - x * (0.5 * length)
    thumb = centre - x * (0.1 * length) + y * np.clip(across[0], -0.02, 0.02) + z * (0.4 * METACARPAL_RADIUS)
    knuckles[0] = thumb
    return wrist, knuckles, z


def hand_capsules(fingertips: np.ndarray, palm_position: np.ndarray, palm_orientation: np.ndarray,
                  flexion: np.ndarray, grasp_centre: np.ndarray, rest_tips: np.ndarray,
                  finger_lengths: np.ndarray) -> Capsules:
    """The capsules of the hand in one frame (module doc): per finger 3 phalanges (fingers thumb .. pinky), then four
    metacarpals (wrist -> index .. pinky knuckle), a thumb metacarpal and the forearm.

    fingertips (finger, 3) m, palm_position (3,) m, palm_orientation (4,) wxyz, flexion (finger,) in [0, 1],
    grasp_centre (3,) m (the bend bulges away from it), rest_tips (finger, 3) m (the clip's first frame, which
    places the knuckles), finger_lengths (finger,) m (:func:`finger_lengths`)."""
    wrist, bases, inward = hand_frame(palm_position, palm_orientation, fingertips, rest_tips)
    a, b, r = [], [], []
    for k in range(N_FINGERS):
        tip = np.asarray(fingertips[k], np.float64)
        bulge = 0.5 * (bases[k] + tip) - np.asarray(grasp_centre, np.float64)
        joints = finger_chain(bases[k], tip, float(finger_lengths[k]), float(flexion[k]), bulge - 0.3 * inward *
                              np.linalg.norm(bulge))
        radii = np.interp([0.0, 0.5, 1.0], [0.0, 1.0], FINGER_RADII[k])
        a += list(joints[:3])
        b += list(joints[1:])
        r += list(radii)
    for k in range(1, N_FINGERS):  # metacarpals: the palm
        a.append(wrist + 0.35 * (bases[k] - bases[1:].mean(axis=0)))
        b.append(bases[k])
        r.append(METACARPAL_RADIUS)
    a.append(wrist)  # thumb metacarpal
    b.append(bases[0])
    r.append(FINGER_RADII[0, 0])
    along = _unit(bases[1:].mean(axis=0) - wrist)  # the forearm leaves the wrist away from the fingers
    a.append(wrist - 0.3 * METACARPAL_RADIUS * along)
    b.append(wrist - FOREARM_M * along)
    r.append(WRIST_RADIUS)
    return Capsules(np.array(a), np.array(b), np.array(r))


def finger_lengths(fingertips: np.ndarray, palm_position: np.ndarray, palm_orientation: np.ndarray) -> np.ndarray:
    """(finger,) m: each finger's length for the whole clip, its longest base-to-tip distance x ``SLACK``.

    fingertips (frame, finger, 3) m, palm_position (frame, 3) m, palm_orientation (frame, 4) wxyz."""
    tips = np.asarray(fingertips, np.float64)
    longest = np.zeros(tips.shape[1])
    for f in range(len(tips)):
        _, bases, _ = hand_frame(palm_position[f], palm_orientation[f], tips[f], tips[0])
        longest = np.maximum(longest, np.linalg.norm(tips[f] - bases, axis=1))
    return SLACK * longest


def hand_sequence(signals: Mapping[str, np.ndarray], frames: np.ndarray) -> list[Capsules]:
    """The hand's capsules at the given signal frames (the rendered frames' indices; clipped to the recording).

    ``signals``: the ``signal_smoothing`` artifact (or any mapping with ``fingertip_positions`` (frame, finger, 3) m,
    ``palm_position`` (frame, 3) m, ``palm_orientation`` (frame, 4), ``flexion`` (frame, finger) and
    ``grasp_centre`` (frame, 3) m)."""
    tips, palm, quat = (np.asarray(signals[k], np.float64) for k in ("fingertip_positions", "palm_position",
                                                                        "palm_orientation"))
    flexion, centre = np.asarray(signals["flexion"], np.float64), np.asarray(signals["grasp_centre"], np.float64)
    if tips.shape[1:] != (len(FINGERS), 3):
        raise ValueError(f"fingertip_positions must be (frame, {len(FINGERS)}, 3) m, got {tips.shape}")
    lengths = finger_lengths(tips, palm, quat)
    index = np.clip(np.asarray(frames, int), 0, len(tips) - 1)
    return [hand_capsules(tips[f], palm[f], quat[f], flexion[f], centre[f], tips[0], lengths) for f in index]


def _pixel_rays(K: np.ndarray, x0: int, x1: int, y0: int, y1: int) -> np.ndarray:
    """Unit ray directions (y, x, 3), camera coordinates, through the pixel centres of the box [x0, x1) x [y0, y1)."""
    u = (np.arange(x0, x1) + 0.5 - K[0, 2]) / K[0, 0]
    v = (np.arange(y0, y1) + 0.5 - K[1, 2]) / K[1, 1]
    d = np.stack(np.broadcast_arrays(u[None, :], v[:, None], np.ones((1, 1))), -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


SKIN_LIGHT = _unit(np.array([-0.4, -0.7, -0.6]))  # unit, camera coordinates, towards the light: upper left


def shade_skin(normal: np.ndarray, colour: np.ndarray, view: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """Lambert + ambient + a soft Blinn-Phong sheen, camera coordinates (light from the upper left, camera side):
    rgb = clip(colour (0.38 + 0.62 max(n.l, 0)) + 0.12 max(n.h, 0)^24, 0, 1), h = unit(l - v), at every pixel where
    ``coverage`` (y, x) > 0, zero elsewhere; normal, view (3, y, x) unit.  Returns (y, x, 3) float32.

    A Warp kernel (:func:`tasks.render.hand_kernels.shade_skin_pixels`); equal to the former numpy expression within
    float64 round-off (numpy's n.l is a BLAS product with fused multiply-adds, its power SVML's), float32 out."""
    return shade_skin_pixels(normal, view, coverage, colour, SKIN_LIGHT)


_RAYS: dict[tuple, np.ndarray] = {}


def _rasterise(capsules: Capsules, viewmat: np.ndarray, K: np.ndarray, width: int, height: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int], np.ndarray]:
    """Front depth (h, w) m, unit normal (3, h, w), coverage (h, w) over the union of the capsules' screen boxes and
    its origin (y, x) px (:func:`tasks.render.hand_kernels.draw_capsules`), and the pixel rays (3, y, x) of the
    whole image, for the hand's capsules in one camera (:func:`render_hand`)."""
    viewmat, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    focal = float(K[0, 0])
    key = (K.tobytes(), width, height)
    if key not in _RAYS:  # one camera's rays serve every frame
        if len(_RAYS) > 8:
            _RAYS.clear()
        _RAYS[key] = np.moveaxis(_pixel_rays(K, 0, width, 0, height), -1, 0).copy()
    rays = _RAYS[key]
    a_cam = capsules.a @ viewmat[:3, :3].T + viewmat[:3, 3]
    b_cam = capsules.b @ viewmat[:3, :3].T + viewmat[:3, 3]
    radius = np.asarray(capsules.radius, np.float64)
    near = np.minimum(a_cam[:, 2], b_cam[:, 2]) - radius
    ahead = np.flatnonzero(near > 1e-3)  # behind or through the camera: not drawn
    # screen boxes: the ends' pixels +- the radius at the nearest depth + 2 px, clipped to the image
    uv_a, uv_b = ((ends[ahead, :2] / ends[ahead, 2:] * [K[0, 0], K[1, 1]] + K[:2, 2]) for ends in (a_cam, b_cam))
    pad = (radius[ahead] * focal / near[ahead] + 2)[:, None]
    lo = np.maximum(np.floor(np.minimum(uv_a, uv_b) - pad).astype(int), 0)
    hi = np.minimum(np.ceil(np.maximum(uv_a, uv_b) + pad).astype(int) + 1, [width, height])
    seen = (lo < hi).all(axis=1)
    drawn = ahead[seen]
    scalars = [capsule_scalars(a_cam[n], b_cam[n], float(radius[n])) for n in drawn]
    boxes = np.column_stack([lo[seen, 0], hi[seen, 0], lo[seen, 1], hi[seen, 1]])
    depth, normal, coverage, origin = draw_capsules(np.array(scalars, np.float64).reshape(-1, CAPSULE_FIELDS), boxes,
                                                    rays, focal)
    return depth, normal, coverage, origin, rays


def render_hand(capsules: Capsules, viewmat: np.ndarray, K: np.ndarray, width: int, height: int,
                colour: np.ndarray) -> HandLayer:
    """The hand's capsules in one camera (module doc): world-to-camera ``viewmat`` (4, 4), intrinsics ``K`` (3, 3) px,
    ``colour`` (3,) linear RGB.  Each capsule is intersected over its projected bounding box only, z-buffered across
    capsules, in a Warp kernel (:mod:`tasks.render.hand_kernels`: Quilez's ray-capsule intersection per pixel)."""
    local_depth, local_normal, local_coverage, (oy, ox), rays = _rasterise(capsules, viewmat, K, width, height)
    depth, coverage, normal = np.full((height, width), np.inf), np.zeros((height, width)), np.zeros((3, height, width))
    normal[2] = -1.0
    box = np.s_[oy:oy + local_depth.shape[0], ox:ox + local_depth.shape[1]]
    depth[box], coverage[box], normal[(slice(None), *box)] = local_depth, local_coverage, local_normal
    rgb = shade_skin(normal, np.asarray(colour, np.float64), rays, coverage)
    return HandLayer(rgb, depth.astype(np.float32), coverage.astype(np.float32))


def draw_hand(capsules: Capsules, viewmat: np.ndarray, K: np.ndarray, colour: np.ndarray, scene_rgb: np.ndarray,
              scene_alpha: np.ndarray, scene_depth: np.ndarray, background: np.ndarray) -> np.ndarray:
    """``composite_hand(scene_rgb, scene_alpha, scene_depth, background, render_hand(capsules, viewmat, K, width,
    height, colour))`` (the frame's size) without the hand layer: the skin's shading and the depth compositing in one
    kernel pass over the rows and columns the hand covers
    (:func:`tasks.render.hand_kernels.shade_and_composite_pixels`), the same numbers."""
    height, width = scene_rgb.shape[:2]
    depth, normal, coverage, origin, rays = _rasterise(capsules, viewmat, K, width, height)
    return shade_and_composite_pixels(normal, rays, coverage, depth, origin, np.asarray(colour, np.float64),
                                      SKIN_LIGHT, scene_rgb, scene_alpha, scene_depth, background)


def composite_hand(scene_rgb: np.ndarray, scene_alpha: np.ndarray, scene_depth: np.ndarray,
                   background: np.ndarray, hand: HandLayer) -> np.ndarray:
    """The hand put into a rendered frame by depth (linear RGB (y, x, 3) in, out).

    scene_rgb: the frame composited over ``background`` (3,); scene_alpha (y, x): its opacity; scene_depth (y, x) m:
    depth of what the frame shows (+inf or 0 where nothing).  Where the hand is nearer (or nothing is drawn):
    ``cov hand + (1 - cov) scene``; where it is behind: it replaces the background only,
    ``scene + (1 - alpha) cov (hand - background)``.

    A Warp kernel over the rows and columns the hand covers (:func:`tasks.render.hand_kernels.composite_hand_pixels`),
    in float32 (other inputs are cast to float32 first): bit-identical to the former numpy expression on the display
    step's float32 inputs."""
    return composite_hand_pixels(scene_rgb, scene_alpha, scene_depth, background, *hand)
