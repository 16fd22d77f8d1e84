"""Released stuffing (plush fibrefill) drawn as fibrous strands: the weight-free stand-in for the diffusion backend
of paper sec. 3.3 (``generation=physics``) for a fibrous interior.

Each visible particle gets a few curly random-walk strands (anti-aliased polylines at 1/16 px precision) around its
projected centre, tinted cream-white with a per-particle shade, drawn far to near (painter's algorithm), over a soft
contact shadow from the blurred, offset strand coverage.  Every random number is a hash of (seed, particle index,
draw), so a particle keeps its strands from frame to frame and however many particles are released.
Units: metres, pixels (strand sizes in particle screen radii, so the look holds at any resolution), linear RGB.
Camera conventions: see :mod:`tasks.generation.impostors`.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from tasks.generation.impostors import EffectFrame, ProjectedParticles, check_frame_inputs, project_particles

_SHIFT = 4  # cv2 fixed-point bits: coordinates in 1/16 px
_START_SPREAD = 0.6  # strand roots lie within this fraction of the particle's screen radius


@dataclass(frozen=True)
class StuffingAppearance:
    """Look of released fibrefill.  Colour linear RGB in [0, 1]; lengths in particle screen radii."""

    colour: tuple[float, float, float] = (0.93, 0.89, 0.80)  # cream white
    shade_variation: float = 0.25  # per-particle brightness factor drawn from [1 - v, 1]
    strands_per_particle: int = 4
    segments_per_strand: int = 6
    strand_length_radii: float = 3.0  # polyline length, in particle screen radii
    curl_rad_per_segment: float = 0.7  # largest steady turning of a strand per segment, radians
    jitter_rad: float = 0.5  # random turning per segment, radians (uniform in +-jitter/2)
    line_width_px: int = 1
    shadow_strength: float = 0.5  # darkening of the background under full coverage
    shadow_blur_radii: float = 0.8  # Gaussian sigma of the shadow, in particle screen radii
    shadow_offset_radii: tuple[float, float] = (0.4, 0.6)  # shadow displacement (x, y), in particle screen radii


STUFFING = StuffingAppearance()


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """SplitMix64 finaliser (Steele, Lea & Flood, OOPSLA 2014) on a uint64 array (wrapping arithmetic)."""
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def hashed_uniforms(seed: int, particle_index: np.ndarray, count: int) -> np.ndarray:
    """(particle, count) uniforms in [0, 1), each a pure function of (seed, particle index, column): the same
    particle draws the same numbers in every frame, whichever other particles are present."""
    key = particle_index.astype(np.uint64)[:, None] * np.uint64(count) + np.arange(count, dtype=np.uint64)
    mixed = _splitmix64(key ^ _splitmix64(np.array([seed], np.uint64)))
    return (mixed >> np.uint64(11)).astype(np.float64) * 2.0 ** -53


def strand_polylines(particles: ProjectedParticles, appearance: StuffingAppearance, seed: int) -> np.ndarray:
    """Curly random-walk strands per particle: (particle, strand, point, xy) image coordinates in pixels (the
    module's pixel-centre convention, centre of pixel j at j + 0.5).

    A strand starts within 0.6 screen radii of the centre with a random heading, turns by a steady per-strand
    curl plus a per-segment jitter, and has ``strand_length_radii`` screen radii of length, so every point lies
    within (0.6 + strand_length_radii) screen radii of the projected centre.
    """
    n, strands, segments = len(particles.index), appearance.strands_per_particle, appearance.segments_per_strand
    draws = hashed_uniforms(seed, particles.index, strands * (4 + segments)).reshape(n, strands, 4 + segments)
    radius = particles.radius_px[:, None, None]
    root = _START_SPREAD * radius[..., 0] * np.sqrt(draws[..., 0])
    root_angle, heading = 2.0 * np.pi * draws[..., 1], 2.0 * np.pi * draws[..., 2]
    curl = appearance.curl_rad_per_segment * (2.0 * draws[..., 3] - 1.0)
    steps = np.arange(segments)
    turn = heading[..., None] + curl[..., None] * steps + appearance.jitter_rad * np.cumsum(draws[..., 4:] - 0.5, -1)
    step_px = appearance.strand_length_radii * radius / segments
    offsets = np.cumsum(step_px[..., None] * np.stack([np.cos(turn), np.sin(turn)], -1), axis=2)
    start = np.stack([root * np.cos(root_angle), root * np.sin(root_angle)], -1)[:, :, None]
    centre = np.stack([particles.u, particles.v], -1)[:, None, None]
    return centre + np.concatenate([start, start + offsets], axis=2)


def render_stuffing(positions: np.ndarray, radii: np.ndarray | float, viewmat: np.ndarray, K: np.ndarray,
                    background_rgb: np.ndarray, surface_depth: np.ndarray,
                    appearance: StuffingAppearance = STUFFING, seed: int = 0) -> EffectFrame:
    """One frame of released stuffing as fibrous strands with a contact shadow (module doc).

    positions: (particle, xyz) world metres; radii: (particle,) or scalar metres; viewmat (4, 4), K (3, 3): see
    :mod:`tasks.generation.impostors`; background_rgb: (y, x, 3) linear RGB in [0, 1]; surface_depth: (y, x)
    metres of the object's surface without the released material (+inf where none): a particle whose front is
    behind the surface at its centre pixel is hidden.  ``seed`` and the particle's index fix its strands.
    Returns an :class:`EffectFrame`: rgb is the background darkened by the shadow with the strands over it
    (equal to ``background_rgb`` where both are 0); coverage is the strands' anti-aliased opacity.
    """
    height, width = check_frame_inputs(background_rgb, surface_depth)
    background = background_rgb.astype(np.float32)
    particles = project_particles(positions, radii, viewmat, K)
    # 1. cull particles hidden behind the surface, order the rest far to near
    col = np.clip(np.floor(particles.u).astype(np.int64), 0, width - 1)
    row = np.clip(np.floor(particles.v).astype(np.int64), 0, height - 1)
    visible = np.flatnonzero(particles.z - particles.radius_m < surface_depth[row, col])
    order = visible[np.argsort(-particles.z[visible], kind="stable")]
    if order.size == 0:
        return EffectFrame(background, surface_depth.astype(np.float32), np.zeros((height, width), np.float32))
    # 2. strands with a per-particle shade, and the box they and their shadow can reach
    strands_px = strand_polylines(particles, appearance, seed)[order]
    shade = 1.0 - appearance.shade_variation * hashed_uniforms(seed + 1, particles.index[order], 1)[:, 0]
    colours = np.clip(np.asarray(appearance.colour) * shade[:, None], 0.0, 1.0) * 255.0
    radius_px = float(np.median(particles.radius_px[order]))
    dx, dy = (o * radius_px for o in appearance.shadow_offset_radii)
    blur_px = max(appearance.shadow_blur_radii * radius_px, 0.5)
    margin = int(np.ceil(appearance.line_width_px + 2 + max(abs(dx), abs(dy)) + 4 * blur_px))
    lo = np.floor(strands_px.reshape(-1, 2).min(axis=0)).astype(int) - margin
    hi = np.ceil(strands_px.reshape(-1, 2).max(axis=0)).astype(int) + margin + 1
    left, top = max(lo[0], 0), max(lo[1], 0)
    box = (slice(top, min(hi[1], height)), slice(left, min(hi[0], width)))
    box_h, box_w = box[0].stop - top, box[1].stop - left
    if box_h <= 0 or box_w <= 0:
        return EffectFrame(background, surface_depth.astype(np.float32), np.zeros((height, width), np.float32))
    # 3. painter's algorithm in the box, fixed point (cv2 puts the centre of pixel j at coordinate j):
    #    premultiplied colour and opacity (RGBA, anti-aliased), nearest depth (aliased)
    fixed = np.round((strands_px - 0.5 - np.array([left, top])) * (1 << _SHIFT)).astype(np.int32)
    layer = np.zeros((box_h, box_w, 4), np.uint8)
    depth = np.full((box_h, box_w), np.inf, np.float32)
    for strands, colour, z in zip(fixed, colours, particles.z[order]):
        cv2.polylines(layer, strands, False, (*colour.tolist(), 255.0), appearance.line_width_px, cv2.LINE_AA, _SHIFT)
        cv2.polylines(depth, strands, False, float(z), appearance.line_width_px, cv2.LINE_8, _SHIFT)
    coverage = layer[..., 3].astype(np.float32) / np.float32(255.0)
    fringe_depth = cv2.erode(depth, np.ones((3, 3), np.uint8))  # anti-aliased fringe: nearest neighbouring strand
    depth = np.where(np.isfinite(depth), depth, np.where(coverage > 0, fringe_depth, np.inf))
    # 4. contact shadow: the blurred coverage, offset, darkens the background under the strands
    shifted = cv2.warpAffine(coverage, np.float32([[1, 0, dx], [0, 1, dy]]), (box_w, box_h))
    shadow = appearance.shadow_strength * cv2.GaussianBlur(shifted, (0, 0), blur_px)
    rgb = background.copy()
    lit = background[box] * ((1.0 - shadow) * (1.0 - coverage))[..., None] + layer[..., :3] / np.float32(255.0)
    rgb[box] = np.clip(lit, 0.0, 1.0)
    full_coverage = np.zeros((height, width), np.float32)
    full_coverage[box] = coverage
    full_depth = surface_depth.astype(np.float32)
    full_depth[box] = np.where(np.isfinite(depth), depth, full_depth[box])
    return EffectFrame(rgb, full_depth, full_coverage)
