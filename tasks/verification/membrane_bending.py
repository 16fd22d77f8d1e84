"""How much bending a wall thinner than the grid carries: a cantilever strip of membrane particles (plane stress,
``mpm.thin_walls=membrane``) sagging under its own weight, against Euler-Bernoulli's tip deflection q L^4 / (8 E I).

The strip (length L along x, width w, thickness t < dx) is sampled as the object model samples such walls: one layer
of particles at the mid-surface, or two at the thickness's Gauss points z = +-t / (2 sqrt 3) (each carrying half
the wall's volume), or three at z = 0, +-sqrt(3/5) t / 2 (8/18, 5/18, 5/18 of it), the layers at each point a normal
fibre whose outer and inner particles are held at their distance (``membrane_fibres``, as the rollout holds them), on
an in-plane lattice of spacing dx / 2.  Its root is clamped: the strip reaches ``embed``
cells into the grid nodes held at x <= 0 (a strip that only starts at the held plane is not clamped in rotation),
and it relaxes under gravity by kinetic damping (the velocities scaled by ``damping`` every ``frame`` s) until it has
settled (:func:`settled`: the tip's sag stays within 0.2 % over 50 frames).  nu = 0, so the plate and beam
stiffnesses coincide.  Pure solver use.

``offset`` places the mid-surface that many cells above a plane of grid nodes (0.5: on a plane of cell centres,
where the two layers' own stencils would straddle it).  With ``mpm.wall_normal_stiffness`` 0 and ``mpm.wall_stencil``
``own`` (the walls before 2026-12-04) the two-layer strip never settled: its ringing died out near the closed form
(1.10x by 0.12 s for the 10-cell strip of ``tests/physics/test_membrane.py``), then it crept (1.39x at 0.5 s, 2.5x at 1.5 s;
a 25-cell strip 2.9x at 0.8 s), at every alignment; now it settles (docs/limits/thin-walls.md).
"""
from __future__ import annotations

import time
from typing import Optional, Sequence

import numpy as np

from tasks.physics.mpm import DirichletNodes, MPMSolver
from tasks.physics.mpm.materials import Material
from tasks.physics.mpm.thin_walls import gauss_layers

GRAVITY = 9.81  # m/s^2
SETTLE_FRAMES = 50  # frames over which a settled tip's sag stays put
SETTLE_TOL = 2e-3  # how far it may move over them, relative to the sag


def settled(sag: Sequence[float], frames: int = SETTLE_FRAMES, tol: float = SETTLE_TOL) -> bool:
    """Whether the sag history ``sag`` (m, one value per frame) has settled: its last ``frames`` + 1 values all lie
    within ``tol`` x |last value| of one another.  Their range, not two instants ``frames`` apart, which a strip
    ringing with that period, or crossing the same sag on its way back, passes by coincidence (the 10-cell strip of
    ``tests/physics/test_membrane.py`` did at frame 123, and was called settled at 1.10x while it crept)."""
    if len(sag) <= frames:
        return False
    last = np.asarray(sag[-frames - 1:], np.float64)
    return bool(np.ptp(last) < tol * abs(last[-1]))


def beam_tip_deflection(length: float, width: float, thickness: float, youngs_modulus: float,
                        density: float) -> float:
    """m: Euler-Bernoulli cantilever under its weight, q L^4 / (8 E I), q = rho g w t (N/m), I = w t^3 / 12 (m^4)."""
    q = density * GRAVITY * width * thickness
    return q * length ** 4 / (8.0 * youngs_modulus * width * thickness ** 3 / 12.0)


def cantilever_under_weight(dx: float, layers: int = 2, length: float = 0.2, width: float = 0.024,
                            thickness: float = 0.003, youngs_modulus: float = 6.5e8, density: float = 1000.0,
                            damping: float = 0.95, frame: float = 2e-3, max_frames: int = 400,
                            embed: int = 2, fibres: bool = True, offset: float = 0.5,
                            config: Optional[dict] = None) -> dict:
    """The membrane strip of the module doc on a grid of spacing ``dx`` (m) with ``layers`` (1, 2 or 3) particle
    layers, its free length ``length`` (m) beyond the clamp's ``embed`` cells, its mid-surface ``offset`` cells above a
    plane of nodes; ``fibres`` False: the layers' distance left free (``mpm.wall_fibres``); ``config``: more
    solver settings (e.g. ``wall_normal_stiffness``, ``wall_stencil``).
    Returns ``tip`` (m, the tip's sag at the end), ``beam`` (m, the closed form), ``ratio`` = tip / beam (> 1: the
    wall bends more easily than a plate of its thickness), ``sag`` (m, the tip's sag after each frame), ``frames``,
    ``settled`` (:func:`settled`; else the run stopped at ``max_frames``) and ``seconds``."""
    if layers not in (1, 2, 3) or not 0 < thickness < dx:
        raise ValueError(f"need layers 1, 2 or 3 and 0 < thickness < dx; got {layers}, {thickness}, {dx}")
    h = dx / 2
    heights, w = gauss_layers(layers)  # each layer's height above the mid-surface / t and share of the volume
    z = [h * thickness for h in heights]
    xs, ys = np.arange(h / 2 - embed * dx, length, h), np.arange(h / 2, width, h)
    mid = (np.floor(0.1 / dx) + offset) * dx  # m: on the 8 mm grid offset 0.5 is 0.1 m
    X = np.array([[x, y, mid + dz] for x in xs for y in ys for dz in z])
    strip = Material(name="strip", model="fixed_corotated", youngs_modulus=youngs_modulus, poisson_ratio=0.0,
                     density=density)
    fibre = np.arange(len(X)).reshape(-1, layers) if layers > 1 and fibres else None  # the layers at each (x, y)
    s = MPMSolver(X, np.tile(h * h * thickness * np.array(w), len(xs) * len(ys)), strip,
                  membrane_normals=np.tile([0.0, 0.0, 1.0], (len(X), 1)), membrane_fibres=fibre,
                  config=dict(device="cpu", dx=dx, gravity=[0.0, 0.0, -GRAVITY], floor=False, courant=0.3,
                              domain_lo=[-0.05 - embed * dx, -0.03, 0.0],
                              domain_hi=[length + 0.05, width + 0.03, 0.2], **(config or {})))
    nodes = np.argwhere(np.ones(s.dims, bool)).astype(np.int32)
    root = nodes[s.node_position(nodes)[:, 0] <= 1e-9]
    clamp = DirichletNodes(root, np.zeros((len(root), 3), np.float32))
    tip = X[:, 0] > length - h
    sag: list[float] = []
    t0 = time.perf_counter()
    done = False
    for _ in range(max_frames):
        s.step_frame(frame, dirichlet=clamp)
        s.set_velocities((damping * s.velocities()).astype(np.float32))
        sag.append(float(X[tip, 2].mean() - s.positions()[tip, 2].mean()))
        if settled(sag):
            done = True
            break
    beam = beam_tip_deflection(length, width, thickness, youngs_modulus, density)
    return {"tip": sag[-1], "beam": beam, "ratio": sag[-1] / beam, "sag": np.array(sag), "frames": len(sag),
            "settled": done, "seconds": time.perf_counter() - t0}
