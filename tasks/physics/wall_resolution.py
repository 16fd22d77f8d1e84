"""Can the MPM grid resolve an object's wall?  A pure check of wall thickness against the grid spacing.

A hollow object whose wall is thinner than the grid spacing ``dx`` is sampled on the wall's mid-surface, the
particles carrying area x thickness of volume (:mod:`tasks.physics.particle_fill`), so its mass and membrane stiffness
E t are physical: by default in two layers at the thickness's Gauss points, which in plane stress
(``mpm.thin_walls: membrane``) carry its bending for the curvatures the grid's field represents (over half a cell
thick, three layers, ``sampling.thin_wall_layers: 3``, which the finding then advises: two leave the grid's strain
quadratic through the wall unresisted, docs/limits/thin-walls.md; from ``mpm.membrane_max_thickness``, 3/4 of a cell,
on it carries 3D stress in its layers, where plane stress softens as the grid refines); with
``sampling.thin_wall_layers: 1`` in ONE layer on the neutral surface, where bending strain is zero.  Either way the
quadratic B-spline grid smears the wall over ~3 dx, so a dent or buckle shorter than the grid can represent is not
what the wall would do.

Criterion (classical shell buckling; Timoshenko & Gere, Theory of Elastic Stability, ch. 11; Zoelly for the
sphere): a thin cylinder (axial load) or sphere (external pressure) of radius R and thickness t buckles with the
wavelength

    lambda = 2 pi sqrt(R t) / (12 (1 - nu^2))^(1/4)

and a finger's dent decays over the bending length l_b = sqrt(R t) / (3 (1 - nu^2))^(1/4) = sqrt(2) lambda / (2 pi)
(both are the shell's own length scale).  A grid of spacing dx represents no wave shorter than 2 dx (Nyquist), so a
wall with lambda < 2 dx is FLAGGED: its buckles and creases are under-resolved by the factor 2 dx / lambda and it
behaves like a membrane smeared over the grid (the "silently mushy" case).  R is half the smallest bounding-box
side (cans, cups, balls, fruit); the single-particle-layer sampling (t < s) is reported either way.

Values for the production sampling (s = 4 mm, dx = 8 mm, 2 dx = 16 mm): can (R 33 mm, t 0.1 mm, nu 0.33) lambda
6.3 mm, flagged x2.5; paper cup (R 40 mm, t 0.35 mm, nu 0.3) 12.9 mm, flagged x1.2; tomato skin (R 27.5 mm, t 1 mm)
18.7 mm, rubber duck 26.7 mm, plush fabric 25 mm, rubber ball (R 32.5 mm, t 3 mm) 35.7 mm: resolved (one particle
layer, but their buckle wavelength spans more than two cells).
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

from conf.mpm_schema import MPMConfig


@dataclass
class WallFinding:
    """Result of :func:`thin_wall_finding` (SI units)."""

    object: str
    flagged: bool
    message: str
    wall_thickness: float  # m
    particle_spacing: float  # m
    dx: float  # m, grid spacing
    particle_layers: float  # particle layers across the wall (a thin wall: sampling.thin_wall_layers, 1, 2 or 3)
    radius: float  # m, R used for the bending length
    bending_length: float  # m, l_b = sqrt(R t) / (3 (1 - nu^2))^(1/4), decay length of a dent
    buckle_wavelength: float  # m, lambda = 2 pi sqrt(R t) / (12 (1 - nu^2))^(1/4)
    under_resolution: float  # 2 dx / buckle_wavelength (> 1: flagged)
    bending_stiffness: float  # N m, D = E t^3 / (12 (1 - nu^2)) (nan when E is not given)
    advice: str = ""  # a wall over half a cell thick in two Gauss layers: take three (also in message)

    def as_dict(self) -> dict:
        return asdict(self)


def grid_spacing(mpm: Any, particle_spacing: float) -> float:
    """dx (m) exactly as the rollout chooses it: ``mpm.dx`` or ``particle_spacing x cbrt(mpm.particles_per_cell)``."""
    get = mpm.get if isinstance(mpm, Mapping) else (lambda k, d=None: getattr(mpm, k, d))
    dx = get("dx", None)
    return float(dx) if dx else float(particle_spacing) * float(get("particles_per_cell", 8)) ** (1.0 / 3.0)


def thin_wall_finding(attrs: Mapping[str, Any], dx: float, poisson_ratio: float = 0.3,
                      youngs_modulus: float | None = None, name: str | None = None,
                      membrane_max_thickness: float = MPMConfig.membrane_max_thickness) -> WallFinding:
    """Compare an object's wall with the grid spacing ``dx`` (m); see the module doc for the criterion.  A wall
    sampled in two Gauss layers that is over half a cell thick but held in plane stress (thinner than
    ``membrane_max_thickness`` x dx, ``mpm.membrane_max_thickness``; thicker ones carry 3D stress) is advised to
    take three.

    ``attrs``: the object model's attributes (``wall_thickness``, ``particle_spacing``, ``bbox_min``, ``bbox_max``,
    ``thin_wall``; a solid body has ``wall_thickness`` 0), ``poisson_ratio`` and optional ``youngs_modulus`` (Pa)
    of the wall material.  Returns a :class:`WallFinding` whose ``message`` is one line for a report.
    """
    if not (dx > 0 and math.isfinite(dx)):
        raise ValueError(f"thin_wall_finding: dx must be > 0 m, got {dx}")
    nu = float(poisson_ratio)
    if not 0.0 <= nu < 0.5:
        raise ValueError(f"thin_wall_finding: poisson_ratio must be in [0, 0.5), got {nu}")
    obj = str(name or attrs.get("name") or attrs.get("kind") or "object")
    t = float(attrs.get("wall_thickness", 0.0) or 0.0)
    s = float(attrs["particle_spacing"])
    lo, hi = attrs["bbox_min"], attrs["bbox_max"]
    R = 0.5 * min(float(h) - float(q) for q, h in zip(lo, hi))
    nan = float("nan")
    if t <= 0.0:
        return WallFinding(obj, False, f"{obj}: solid body (no wall), nothing to resolve", 0.0, s, dx, nan, R, nan,
                           nan, 0.0, nan)
    sampled_thin = bool(attrs.get("thin_wall", t < s))
    layers = float(attrs.get("thin_wall_layers", 1)) if sampled_thin else t / s
    l_b = math.sqrt(R * t) / (3.0 * (1.0 - nu * nu)) ** 0.25
    lam = 2.0 * math.pi * math.sqrt(R * t) / (12.0 * (1.0 - nu * nu)) ** 0.25
    ratio = 2.0 * dx / lam
    D = nan if youngs_modulus is None else float(youngs_modulus) * t ** 3 / (12.0 * (1.0 - nu * nu))
    if not sampled_thin:
        layer_txt = f"{layers:.1f} particle layers"
    elif layers == 1:
        layer_txt = "one particle layer (membrane-like: mid-surface particles carry no bending strain)"
    else:
        layer_txt = (f"{'two' if layers == 2 else 'three'} particle layers at the thickness's Gauss points (bending "
                     "from their difference)")
    head = (f"{obj} wall {_mm(t)} {'<' if t < dx else '>='} dx {_mm(dx)}: {layer_txt}; buckle wavelength "
            f"2 pi sqrt(R t)/(12(1-nu^2))^(1/4) = {_mm(lam)} (R {_mm(R)}, nu {nu:g})")
    if ratio > 1.0:
        msg = (f"FLAGGED {head} < 2 dx = {_mm(2 * dx)}: bending/creasing under-resolved by x{ratio:.2g}; the wall "
               f"behaves as a membrane smeared over ~3 cells (refine sampling.particle_spacing to <= "
               f"{_mm(s * lam / (2.0 * dx))} for dx <= lambda/2)")
    else:
        msg = f"resolved: {head} >= 2 dx = {_mm(2 * dx)} (x{1.0 / ratio:.2g} margin)"
    advice = ""
    if sampled_thin and layers == 2 and 0.5 * dx < t < membrane_max_thickness * dx:
        advice = (f"a wall over half a cell thick ({t / dx:.2g} dx) in two Gauss layers can leave the grid's strain "
                  "quadratic through it unresisted (a clamped strip 0.86 dx thick sagged 1.23-3.67x "
                  "Euler-Bernoulli): sample it in three, sampling.thin_wall_layers=3")
        msg += "; " + advice
    return WallFinding(obj, ratio > 1.0, msg, t, s, dx, layers, R, l_b, lam, ratio, D, advice)


def _mm(x: float) -> str:
    return f"{x * 1e3:.3g} mm"
