"""Content checks of a user's 3DGS PLY (``geometry.kind: ply``), beyond its form: enough Gaussians, some of them
visible, and Gaussians smaller than the object they make up (paper sec. 3.1: the object is given as 3D Gaussians).

A file can be a perfectly readable 3DGS PLY and still render nothing: opacities written as probabilities where the
Inria layout stores ``logit(opacity)`` the other way round (all near 0 after the sigmoid: every frame is empty
background), or log-scales written as standard deviations (each Gaussian metres wide: every frame is one solid
colour).  :func:`check_splat_content` refuses such a file with one line naming it and the fix; it runs in the
preflight (:func:`tasks.control.sources.by_kind.geometry_file_bounds`) and again where the object model reads the
file (:class:`tasks.control.sources.ply.PlySource`), so the two can never disagree.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from tasks.control.gaussian_ply import GaussianPlyError

__all__ = ["MIN_GAUSSIANS", "VISIBLE_OPACITY", "MIN_VISIBLE_FRACTION", "check_splat_content"]

MIN_GAUSSIANS = 8  # fewer Gaussians make no surface (their k-nearest-neighbour normals and areas need 8)
VISIBLE_OPACITY = 1.0 / 255.0  # the rasterisers skip a Gaussian fainter than this (tasks.render.splat_torch.ALPHA_MIN)
MIN_VISIBLE_FRACTION = 0.01  # fewer visible Gaussians than this share: the object renders as empty background


def check_splat_content(path: str | Path, means: np.ndarray, scales: np.ndarray, opacities: np.ndarray) -> None:
    """Refuse a 3DGS PLY that cannot make a visible object (:class:`GaussianPlyError`, one line naming ``path`` and
    the fix).  ``means`` (N, 3), ``scales`` (N, 3) standard deviations (``exp`` of the stored log-scales) in the
    file's units, ``opacities`` (N,) in (0, 1) (sigmoid of the stored logits), as :func:`read_gaussian_ply` returns
    them.  Refused:

    * fewer than :data:`MIN_GAUSSIANS` Gaussians;
    * fewer than :data:`MIN_VISIBLE_FRACTION` of them at least :data:`VISIBLE_OPACITY` opaque;
    * a median Gaussian (its largest standard deviation) larger than the largest extent of the Gaussians' centres.
    """
    n = len(means)
    if n < MIN_GAUSSIANS:
        raise GaussianPlyError(f"PLY {path} holds only {n} Gaussians: at least {MIN_GAUSSIANS} are needed to make a "
                               f"surface; export the whole trained splat")
    opacities = np.asarray(opacities, np.float64)
    visible = opacities >= VISIBLE_OPACITY
    if visible.mean() < MIN_VISIBLE_FRACTION:
        raise GaussianPlyError(
            f"PLY {path}: {int(visible.sum())} of {n} Gaussians have an opacity of at least 1/255 (median "
            f"{np.median(opacities):.3g}, the sigmoid of the stored 'opacity'): every frame would be empty "
            f"background; store opacity as logit(opacity) as the Inria layout does (4.6 for 0.99), or export the "
            f"trained splat again")
    extent = float(np.max(np.ptp(np.asarray(means, np.float64), axis=0)))
    size = float(np.median(np.max(np.asarray(scales, np.float64)[visible], axis=1)))
    if size > extent:
        raise GaussianPlyError(
            f"PLY {path}: the median Gaussian's largest standard deviation (exp of scale_0..2) is {size:.3g}, more "
            f"than the {extent:.3g} its centres span (file units): every frame would be one "
            f"solid colour; store scale_0..2 as log(standard deviation) in the units of x y z as the Inria layout "
            f"does, or export the trained splat again")
