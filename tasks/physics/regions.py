"""Where each finger acts and how deep it pressed: the finger regions and the squeeze strain (paper sec. 3.2).

Shared by the rollout (its rupture threshold) and the deformation metrics (Table 2), so neither step imports the
other.  Pure numpy.
"""
from __future__ import annotations

import math

import numpy as np

from conf.hand import N_FINGERS


def support_half_extent(direction: np.ndarray, half: np.ndarray) -> np.ndarray:
    """h(d) = sum_i |d_i| half_i: half-width (m) of the object's bounding box along unit direction(s) d."""
    return np.abs(direction) @ half


def _region_frames(finger: np.ndarray) -> np.ndarray:
    """(frame, finger) index of the frame whose constrained set is finger k's region at frame f (-1: none yet).

    The region is the largest set of points finger k has constrained so far: a press grows it; a release,
    which shrinks the contact to the deepest points, does not replace it."""
    T = finger.shape[0]
    chosen = np.full((T, N_FINGERS), -1, np.int64)
    for k in range(N_FINGERS):
        last, size = -1, 0
        for f in range(T):
            n = int((finger[f] == k).sum())
            if n and n >= size:
                last, size = f, n
            chosen[f, k] = last
    return chosen


def finger_regions(finger: np.ndarray, patch_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The surface region and squeeze direction of each finger per frame, remembered after release.

    Returns ``region`` (frame, finger, point) bool — the largest set of points finger k has constrained so far
    (a press grows it; a release, which shrinks the contact to the deepest points, does not replace it) — and
    ``direction`` (frame, finger, xyz) the inward unit normal of
    that patch.  Both the prescribed and the observed squeeze strain are measured on these regions.
    """
    T, S = finger.shape
    chosen = _region_frames(finger)
    region = np.zeros((T, N_FINGERS, S), bool)
    direction = np.zeros((T, N_FINGERS, 3))
    for f in range(T):
        for k in range(N_FINGERS):
            c = chosen[f, k]
            if c >= 0:
                region[f, k], direction[f, k] = finger[c] == k, -patch_normals[c, k]
    return region, direction


def region_weights(finger: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(frame, finger, point) the contact weight phi (eq. 3, ``dirichlet_field``'s ``weight``) of each point of
    finger k's region (:func:`finger_regions`) in the frame that region was chosen; 0 outside the region."""
    T, S = finger.shape
    chosen = _region_frames(finger)
    out = np.zeros((T, N_FINGERS, S))
    for f in range(T):
        for k in range(N_FINGERS):
            c = chosen[f, k]
            if c >= 0:
                out[f, k] = np.where(finger[c] == k, weight[c], 0.0)
    return out


CONTACT_CORE_PHI = math.exp(-0.5)  # patch weight at one sigma: the finger's contact core


def squeeze_strain(displacement: np.ndarray, region: np.ndarray, direction: np.ndarray, half: np.ndarray,
                   weight: np.ndarray | None = None) -> np.ndarray:
    """eps_k = mean inward displacement under finger k / h(d_k) (finger,), 1.

    ``displacement`` (point, xyz) m of the surface points, ``region`` (finger, point), ``direction``
    (finger, xyz).  Without ``weight`` the mean is over finger k's whole region.  With ``weight`` (finger,
    point; the patch weight phi of :func:`region_weights`) it is over the region's contact core, the points with
    phi >= exp(-1/2) (the patch's one-sigma ellipse, under the fingertip): the indentation depth at the contact,
    which the mean over the whole 2.5-sigma support (whose rim barely moves) underestimates by ~3x.  A finger
    that has not touched yet has strain 0.
    """
    out = np.zeros(N_FINGERS)
    for k in range(N_FINGERS):
        sel = region[k]
        if weight is not None and (sel & (weight[k] >= CONTACT_CORE_PHI)).any():
            sel = sel & (weight[k] >= CONTACT_CORE_PHI)
        if sel.any():
            out[k] = (displacement[sel] @ direction[k]).mean() / max(support_half_extent(direction[k], half), 1e-9)
    return out
