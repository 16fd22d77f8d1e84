"""What the interactive 4D viewer draws (``python -m flows.view``), as pure functions from cached artifacts' arrays.

One :class:`SqueezeScene` per object, variant and seed holds, per simulated frame, everything drawn: the object's
3D Gaussians as the MPM deformed them (paper sec. 3.2, drawn with the G-buffer's capped covariances,
:func:`tasks.render.scene.drawn_covariances`) and the released interior material from the rupture on (the
G-buffer's rule, :func:`tasks.render.scene.rollout_released_visibility`, and look, ``render.released``); the hand
of the recording (smoothed fingertips and palm, sec. 3.1); the contact patches of eq. 2; the constrained surface
points of eq. 3 with their prescribed displacement; the per-finger reaction (N) and feedback force; the flexion
and force-coefficient curves of eq. 1; the rig cameras of the report (``render``) and the table plane.

Positions are world metres (z up).  The splats are handed to the client in centimetres (:data:`SPLAT_UNIT`)
under a node scaled by 0.01: viser packs covariances as float16, whose smallest normal number (6.1e-5) would
flush a 1 mm Gaussian's 1e-6 m^2 to a subnormal; in cm^2 it is 0.01.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from tasks.render.cameras import orbit_rig
from tasks.render.colour import linear_to_srgb
from tasks.render.scene import (
    RELEASED_SCALE_FACTOR,
    drawn_covariances,
    released_appearance,
    rollout_particle_volumes,
    rollout_released_visibility,
    rupture_frame,
)

SPLAT_UNIT = 0.01  # m per unit of the splat buffers sent to the client (centimetres)
PATCH_SEGMENTS = 24  # line segments of one contact patch's outline ellipse
FORCE_ARROW_M_PER_N = 0.002  # m of arrow per N of reaction force (2 mm/N)
_IJ = ((0, 0, 0, 1, 1, 2), (0, 1, 2, 1, 2, 2))  # xx xy xz yy yz zz


def recording_name(scope: str, variant: str) -> str:
    """The file name of a squeeze's offline recording (``python -m flows.view record=true``), in
    ``<paths.reports>/viewer/``, where the run reports link it from: ``<scope>_<variant>.html``."""
    return f"{scope}_{variant}.html"


@dataclass(frozen=True)
class SqueezeScene:
    """One squeeze (object, variant, seed) as the viewer draws it; arrays are per simulated frame (leading axis).

    time (frame,) s.  gaussian_positions (frame, G, 3) m, gaussian_covariances (frame, G, 6) m^2 (drawn, capped),
    gaussian_colors (G, 3) linear RGB, gaussian_opacities (G,).  released_positions (frame, R, 3) m of the R
    particles ever released, released_visible (frame, R) bool, released_sigma (R,) m (isotropic splat size),
    released_color (3,), released_opacity.  fingertips (frame, finger, 3) m, palm_position (frame, 3) m,
    palm_orientation (frame, 4) wxyz; flexion and force_coefficients (frame, finger) 1 (eq. 1).  patch_* (frame,
    finger, ...) eq. 2 (centres m, normals, two tangent axes, two radii m, active).  surface_points (point, 3) m,
    displacement (frame, point, 3) m and constrained (frame, point) bool (eq. 3).  reaction_force (frame, finger,
    3) N, feedback_force (frame, finger) N.  rupture_frame: the frame of the rupture (None: none).  table_height m.
    rig_viewmats (view, 4, 4) world-to-camera (OpenCV) and rig_Ks (view, 3, 3) px: the report's cameras."""

    label: str
    time: np.ndarray
    gaussian_positions: np.ndarray
    gaussian_covariances: np.ndarray
    gaussian_colors: np.ndarray
    gaussian_opacities: np.ndarray
    released_positions: np.ndarray
    released_visible: np.ndarray
    released_sigma: np.ndarray
    released_color: np.ndarray
    released_opacity: float
    fingertips: np.ndarray
    palm_position: np.ndarray
    palm_orientation: np.ndarray
    flexion: np.ndarray
    force_coefficients: np.ndarray
    patch_centers: np.ndarray
    patch_normals: np.ndarray
    patch_axes: np.ndarray
    patch_radii: np.ndarray
    patch_active: np.ndarray
    surface_points: np.ndarray
    displacement: np.ndarray
    constrained: np.ndarray
    reaction_force: np.ndarray
    feedback_force: np.ndarray
    rupture_frame: int | None
    table_height: float
    rig_viewmats: np.ndarray
    rig_Ks: np.ndarray

    @property
    def n_frames(self) -> int:
        return len(self.time)

    @property
    def frame_rate(self) -> float:
        """Hz, of the simulated frames."""
        return float((len(self.time) - 1) / (self.time[-1] - self.time[0])) if len(self.time) > 1 else 30.0

    @property
    def center(self) -> np.ndarray:
        """(3,) m, the object's rest centre (centre of its Gaussians' box at frame 0)."""
        p = self.gaussian_positions[0]
        return 0.5 * (p.min(axis=0) + p.max(axis=0))


def squeeze_scene(arts: Mapping[str, Any], render: Mapping[str, Any], label: str) -> SqueezeScene:
    """The scene of one squeeze from its loaded artifacts, keyed by step name: ``object_model``,
    ``signal_smoothing``, ``force_coefficients``, ``contact_patches``, ``dirichlet_field``, ``material_oracle``,
    ``mpm_rollout`` (and ``mpm_particles`` where the particle volumes live there); ``render`` the render config
    (the rig and the released material's look, as the G-buffer uses them)."""
    obj, frames, rollout = arts["object_model"], arts["signal_smoothing"], arts["mpm_rollout"]
    patches, field, coeffs = arts["contact_patches"], arts["dirichlet_field"], arts["force_coefficients"]
    n = len(rollout["time"])
    if len(frames["time"]) != n:
        raise ValueError(f"{label}: the rollout has {n} frames but the smoothed signals {len(frames['time'])}")
    event = rollout.attrs.get("threshold_event")
    visible = rollout_released_visibility(rollout, event, n)
    ever = visible.any(axis=0)
    particles = arts.get("mpm_particles") or obj  # the particle volumes' step
    volumes = rollout_particle_volumes(particles.arrays, len(rollout["particle_material"]))
    interior = ((arts["material_oracle"].attrs["materials"].get("interior")) or {}).get("name")
    look = released_appearance(render, interior)
    flight = rollout.attrs.get("released_free_fall") or {}
    floor = flight.get("floor_height")
    viewmats, Ks = orbit_rig(render, obj.attrs["bbox_min"], obj.attrs["bbox_max"])
    return SqueezeScene(
        label=label, time=np.asarray(rollout["time"], float),
        gaussian_positions=np.asarray(rollout["gaussian_positions"], np.float32),
        gaussian_covariances=drawn_covariances(rollout["gaussian_covariances"], obj["gaussian_scales"]),
        gaussian_colors=np.asarray(obj["gaussian_colors"], np.float32),
        gaussian_opacities=np.asarray(obj["gaussian_opacities"], np.float32),
        released_positions=np.asarray(rollout["particle_positions"][:, ever], np.float32),
        released_visible=visible[:, ever], released_sigma=RELEASED_SCALE_FACTOR * np.cbrt(volumes[ever]),
        released_color=np.asarray(look["color"], float), released_opacity=float(look["opacity"]),
        fingertips=np.asarray(frames["fingertip_positions"], float),
        palm_position=np.asarray(frames["palm_position"], float),
        palm_orientation=np.asarray(frames["palm_orientation"], float),
        flexion=np.asarray(frames["flexion"], float), force_coefficients=np.asarray(coeffs["force_coefficients"], float),
        patch_centers=patches["patch_centers"], patch_normals=patches["patch_normals"], patch_axes=patches["patch_axes"],
        patch_radii=patches["patch_radii"], patch_active=np.asarray(patches["patch_active"], bool),
        surface_points=np.asarray(field["surface_points"], float), displacement=np.asarray(field["displacement"], float),
        constrained=np.asarray(field["constrained"], bool),
        reaction_force=np.asarray(rollout["reaction_force"], float),
        feedback_force=np.asarray(rollout["feedback_force"], float),
        rupture_frame=rupture_frame(event),
        table_height=float(floor) if floor is not None else float(obj.attrs["bbox_min"][2]),
        rig_viewmats=viewmats, rig_Ks=Ks)


def full_covariances(packed: np.ndarray) -> np.ndarray:
    """(..., 6) xx xy xz yy yz zz -> (..., 3, 3) symmetric."""
    packed = np.asarray(packed)
    full = np.zeros(packed.shape[:-1] + (3, 3), packed.dtype)
    full[..., _IJ[0], _IJ[1]] = packed
    full[..., _IJ[1], _IJ[0]] = packed
    return full


@dataclass(frozen=True)
class FrameSplats:
    """The Gaussians of one frame as sent to the client, in :data:`SPLAT_UNIT` (cm): centers (N, 3),
    covariances (N, 3, 3) cm^2, rgbs (N, 3) in [0, 1] (display colour), opacities (N, 1); the surface's first,
    then every particle the squeeze ever releases, transparent (opacity 0) where not drawn in this frame (a
    constant count: each frame is one same-sized buffer, which viser updates in place and its recordings replay);
    ``n_released`` of them are drawn."""

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray
    n_released: int


def frame_splats(scene: SqueezeScene, frame: int, offset: np.ndarray | None = None,
                 released: bool = True) -> FrameSplats:
    """The splats of ``frame`` (surface, then the released particles, drawn where visible and ``released``),
    shifted by ``offset`` (3,) m (the side-by-side comparison).  Colours go from linear RGB to the display's sRGB
    (the client blends in sRGB)."""
    shift = np.zeros(3) if offset is None else np.asarray(offset, float)
    shown = scene.released_visible[frame] & released
    n = len(shown)
    centers = np.concatenate([scene.gaussian_positions[frame], scene.released_positions[frame]]) + shift
    sigma2 = (scene.released_sigma ** 2)[:, None, None] * np.eye(3)
    cov = np.concatenate([full_covariances(scene.gaussian_covariances[frame]), sigma2])
    rgbs = np.concatenate([scene.gaussian_colors, np.broadcast_to(scene.released_color, (n, 3))])
    opacities = np.concatenate([scene.gaussian_opacities, np.where(shown, scene.released_opacity, 0.0)])
    return FrameSplats((centers / SPLAT_UNIT).astype(np.float32), (cov / SPLAT_UNIT**2).astype(np.float32),
                       linear_to_srgb(rgbs), opacities.astype(np.float32)[:, None], int(shown.sum()))


def hand_segments(scene: SqueezeScene, frame: int) -> np.ndarray:
    """(finger, 2, 3) m: each finger drawn from the palm to its fingertip at ``frame``."""
    tips = scene.fingertips[frame]
    return np.stack([np.broadcast_to(scene.palm_position[frame], tips.shape), tips], axis=1)


def patch_outlines(scene: SqueezeScene, frame: int, segments: int = PATCH_SEGMENTS) -> np.ndarray:
    """(active patch x segments, 2, 3) m: the outline ellipse of every active contact patch (eq. 2) at ``frame``,
    centre + r1 cos(a) t1 + r2 sin(a) t2 in the patch's tangent plane."""
    active = scene.patch_active[frame]
    centers, axes, radii = (a[frame][active] for a in (scene.patch_centers, scene.patch_axes, scene.patch_radii))
    angle = np.linspace(0.0, 2 * np.pi, segments + 1)
    ring = (centers[:, None] + radii[:, None, :1] * np.cos(angle)[None, :, None] * axes[:, None, 0]
            + radii[:, None, 1:] * np.sin(angle)[None, :, None] * axes[:, None, 1])
    return np.stack([ring[:, :-1], ring[:, 1:]], axis=2).reshape(-1, 2, 3)


def constrained_points(scene: SqueezeScene, frame: int) -> tuple[np.ndarray, np.ndarray]:
    """The surface points constrained by eq. 3 at ``frame``, at their prescribed place (rest + displacement),
    (point, 3) m, and their colour (point, 3) by the displacement's magnitude over the squeeze's peak (blue 0 ->
    red peak)."""
    on = scene.constrained[frame]
    u = scene.displacement[frame][on]
    peak = float(np.linalg.norm(scene.displacement, axis=-1).max(initial=0.0)) or 1.0
    t = np.clip(np.linalg.norm(u, axis=-1) / peak, 0.0, 1.0)[:, None]
    colors = (1 - t) * np.array([0.1, 0.3, 1.0]) + t * np.array([1.0, 0.1, 0.05])
    return scene.surface_points[on] + u, colors


def force_arrows(scene: SqueezeScene, frame: int, m_per_newton: float = FORCE_ARROW_M_PER_N) -> np.ndarray:
    """(finger, 2, 3) m: each finger's reaction force at ``frame`` as an arrow from its fingertip,
    ``m_per_newton`` m per N."""
    tips = scene.fingertips[frame]
    return np.stack([tips, tips + m_per_newton * scene.reaction_force[frame]], axis=1)


def rig_camera_poses(viewmats: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(position m, look-at point m, up) of each rig camera from its world-to-camera matrix (OpenCV: x right,
    y down, z forward), the look-at point one metre ahead."""
    poses = []
    for v in np.asarray(viewmats, float):
        rot, t = v[:3, :3], v[:3, 3]
        position = -rot.T @ t
        poses.append((position, position + rot.T @ np.array([0.0, 0.0, 1.0]), -rot.T @ np.array([0.0, 1.0, 0.0])))
    return poses


def side_offset(scene: SqueezeScene, gap: float = 0.4) -> np.ndarray:
    """(3,) m, where a compared squeeze is drawn: beside this one as rig camera 0 sees them (along its horizontal
    right-hand axis), its rest extent plus ``gap`` of it apart."""
    right = np.asarray(scene.rig_viewmats[0], float)[0, :3] * [1.0, 1.0, 0.0]  # camera x axis in world, level
    right /= np.linalg.norm(right)
    width = float(np.ptp(scene.gaussian_positions[0] @ right))
    return (1.0 + gap) * width * right
