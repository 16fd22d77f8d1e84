"""Orbit camera rig for the multi-view G-buffer (paper sec. 3.2-3.3: views v = 1..V around the squeezed object).

Conventions (gsplat / OpenCV): world z is up; a camera looks along its +z axis with +x to the right of the image and
+y down; ``viewmats`` map world to camera coordinates; ``Ks`` are pinhole intrinsics in pixels with the principal
point at the image centre, pixel (x, y) covering [x, x + 1) x [y, y + 1).
"""

from collections.abc import Mapping
from typing import Any

import numpy as np

WORLD_UP = np.array([0.0, 0.0, 1.0])


def orbit_cameras(center: np.ndarray, radius_m: float, n_views: int, elevation_deg: float, fov_deg: float,
                  width: int, height: int, azimuth0_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """n_views cameras evenly spaced in azimuth on a circle around ``center``, all looking at it.

    center: (3,) m, world; radius_m m, camera-to-centre distance; elevation_deg: angle of the cameras above the
    horizontal plane through the centre, in (-90, 90); fov_deg: horizontal field of view in (0, 180); width, height
    px; azimuth0_deg: azimuth of view 0 about world z, measured from +x towards +y (view k is at
    azimuth0 + 360 k / n_views). Square pixels (fx = fy = width / (2 tan(fov / 2))).
    Returns viewmats (view, 4, 4) world-to-camera and Ks (view, 3, 3) px, float64.
    """
    center = np.asarray(center, dtype=np.float64)
    if center.shape != (3,):
        raise ValueError(f"center must be (3,) m, got shape {center.shape}")
    if not radius_m > 0 or n_views < 1 or not -90.0 < elevation_deg < 90.0 or not 0.0 < fov_deg < 180.0:
        raise ValueError(f"need radius_m > 0, n_views >= 1, elevation_deg in (-90, 90), fov_deg in (0, 180); got "
                         f"{radius_m}, {n_views}, {elevation_deg}, {fov_deg}")
    if width < 1 or height < 1:
        raise ValueError(f"width and height must be >= 1 px, got {width} x {height}")
    azimuth = np.radians(azimuth0_deg + 360.0 * np.arange(n_views) / n_views)
    elevation = np.radians(elevation_deg)
    direction = np.stack([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                          np.full(n_views, np.sin(elevation))], axis=1)           # centre -> camera, unit
    viewmats = np.stack([look_at(center + radius_m * d, center) for d in direction])
    focal = 0.5 * width / np.tan(0.5 * np.radians(fov_deg))
    K = np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])
    return viewmats, np.repeat(K[None], n_views, axis=0)


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """World-to-camera (4, 4) of a camera at ``eye`` (3,) m looking at ``target`` (3,) m with world z up in the
    image: rows of the rotation are the camera's right, down and forward axes in world coordinates."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, WORLD_UP)
    norm = np.linalg.norm(right)
    if norm < 1e-9:
        raise ValueError("look_at: the view direction is vertical; give an elevation strictly between -90 and 90")
    right = right / norm
    down = np.cross(forward, right)
    rot = np.stack([right, down, forward])
    viewmat = np.eye(4)
    viewmat[:3, :3] = rot
    viewmat[:3, 3] = -rot @ eye
    return viewmat


def distance_for_object(bbox_half_extent: np.ndarray, fov_deg: float, fill: float = 0.7) -> float:
    """Camera distance (m) at which the object's bounding sphere spans ``fill`` of the image width.

    bbox_half_extent: (3,) m, half the axis-aligned bounding box; its bounding sphere has radius
    R = |bbox_half_extent|. A sphere at distance d subtends the half angle asin(R / d); its silhouette's image
    radius is f tan(asin(R / d)), the half width is f tan(fov / 2), so fill = tan(asin(R / d)) / tan(fov / 2) and
    d = R / sin(atan(fill tan(fov / 2))). fov_deg: horizontal field of view; fill in (0, 1].
    """
    radius = float(np.linalg.norm(np.asarray(bbox_half_extent, dtype=np.float64)))
    if not radius > 0 or not 0.0 < fill <= 1.0 or not 0.0 < fov_deg < 180.0:
        raise ValueError(f"need a non-zero bbox_half_extent, fill in (0, 1] and fov_deg in (0, 180); got "
                         f"{bbox_half_extent}, {fill}, {fov_deg}")
    half_angle = np.arctan(fill * np.tan(0.5 * np.radians(fov_deg)))
    return radius / float(np.sin(half_angle))


def project_points(points: np.ndarray, viewmat: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection of world points into one camera.

    points: (point, 3) m, world; viewmat: (4, 4) world-to-camera; K: (3, 3) px.
    Returns uv (point, 2) px (continuous image coordinates; pixel (x, y) centre at (x + 0.5, y + 0.5)) and
    depth (point,) m, the camera-space z (points behind the camera have depth <= 0 and meaningless uv).
    """
    cam = np.asarray(points, dtype=np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    depth = cam[:, 2]
    uv = (cam @ K[:2, :].T) / depth[:, None]
    return uv, depth


def orbit_rig(render: Mapping[str, Any], bbox_min: np.ndarray, bbox_max: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """viewmats (view, 4, 4) and Ks (view, 3, 3) of ``render.views`` cameras around the object's rest box, at the
    distance where its bounding sphere spans ``render.fill`` of the image width."""
    lo, hi = np.asarray(bbox_min, float), np.asarray(bbox_max, float)
    radius = distance_for_object(0.5 * (hi - lo), render["fov_deg"], render["fill"])
    return orbit_cameras(0.5 * (lo + hi), radius, render["views"], render["elevation_deg"], render["fov_deg"],
                         render["width"], render["height"], render["azimuth0_deg"])
