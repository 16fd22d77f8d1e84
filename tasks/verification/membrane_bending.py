"""How much bending a wall thinner than the grid carries: a cantilever strip of membrane particles (plane stress,
``mpm.thin_walls=membrane``) sagging under its own weight, against Euler-Bernoulli's tip deflection q L^4 / (8 E I).

The strip (length L along x, width w, thickness t < dx) is sampled as the object model samples such walls: one layer
of particles at the mid-surface, or two at the thickness's Gauss points z = +-t / (2 sqrt 3) (each carrying half
the wall's volume, the two at each point a normal fibre held at its length, ``membrane_pairs``, as the rollout
holds them), on an in-plane lattice of spacing dx / 2.  Its root is clamped: the strip reaches ``embed``
cells into the grid nodes held at x <= 0 (a strip that only starts at the held plane is not clamped in rotation:
on the 8 mm grid a 25-cell strip sagged 1.53x the closed form, embedded two cells 1.43x), and it relaxes
under gravity by kinetic damping (the velocities scaled by ``damping`` every ``frame`` s) until the tip moves less
than 0.2 % over 50 frames.  nu = 0, so the plate and beam stiffnesses coincide.  Pure solver use.
"""
from __future__ import annotations

import time

import numpy as np

from tasks.physics.mpm.materials import Material
from tasks.physics.mpm.solver import DirichletNodes, MPMSolver

GRAVITY = 9.81  # m/s^2


def beam_tip_deflection(length: float, width: float, thickness: float, youngs_modulus: float,
                        density: float) -> float:
    """m: Euler-Bernoulli cantilever under its weight, q L^4 / (8 E I), q = rho g w t (N/m), I = w t^3 / 12 (m^4)."""
    q = density * GRAVITY * width * thickness
    return q * length ** 4 / (8.0 * youngs_modulus * width * thickness ** 3 / 12.0)


def cantilever_under_weight(dx: float, layers: int = 2, length: float = 0.2, width: float = 0.024,
                            thickness: float = 0.003, youngs_modulus: float = 6.5e8, density: float = 1000.0,
                            damping: float = 0.95, frame: float = 2e-3, max_frames: int = 400,
                            embed: int = 2, fibres: bool = True) -> dict:
    """The membrane strip of the module doc on a grid of spacing ``dx`` (m) with ``layers`` (1 or 2) particle layers,
    its free length ``length`` (m) beyond the clamp's ``embed`` cells; ``fibres`` False: the two layers' distance
    left free (``mpm.wall_fibres``).
    Returns ``tip`` (m, the tip's settled sag), ``beam`` (m, the closed form), ``ratio`` = tip / beam (> 1: the wall
    bends more easily than a plate of its thickness), ``frames``, ``settled`` and ``seconds``."""
    if layers not in (1, 2) or not 0 < thickness < dx:
        raise ValueError(f"need layers 1 or 2 and 0 < thickness < dx; got {layers}, {thickness}, {dx}")
    h = dx / 2
    z = [-thickness / (2 * np.sqrt(3)), thickness / (2 * np.sqrt(3))] if layers == 2 else [0.0]
    xs, ys = np.arange(h / 2 - embed * dx, length, h), np.arange(h / 2, width, h)
    X = np.array([[x, y, 0.1 + dz] for x in xs for y in ys for dz in z])
    strip = Material(name="strip", model="fixed_corotated", youngs_modulus=youngs_modulus, poisson_ratio=0.0,
                     density=density)
    pairs = np.arange(len(X)).reshape(-1, 2) if layers == 2 and fibres else None  # the layers at each (x, y)
    s = MPMSolver(X, h * h * thickness / len(z), strip, membrane_normals=np.tile([0.0, 0.0, 1.0], (len(X), 1)),
                  membrane_pairs=pairs,
                  config=dict(device="cpu", dx=dx, gravity=[0.0, 0.0, -GRAVITY], floor=False, courant=0.3,
                              domain_lo=[-0.05 - embed * dx, -0.03, 0.0],
                              domain_hi=[length + 0.05, width + 0.03, 0.2]))
    nodes = np.argwhere(np.ones(s.dims, bool)).astype(np.int32)
    root = nodes[s.node_position(nodes)[:, 0] <= 1e-9]
    clamp = DirichletNodes(root, np.zeros((len(root), 3), np.float32))
    tip = X[:, 0] > length - h
    sag: list[float] = []
    t0 = time.perf_counter()
    settled = False
    for _ in range(max_frames):
        s.step_frame(frame, dirichlet=clamp)
        s.set_velocities((damping * s.velocities()).astype(np.float32))
        sag.append(float(X[tip, 2].mean() - s.positions()[tip, 2].mean()))
        if len(sag) > 100 and abs(sag[-1] - sag[-51]) < 2e-3 * abs(sag[-1]):
            settled = True
            break
    beam = beam_tip_deflection(length, width, thickness, youngs_modulus, density)
    return {"tip": sag[-1], "beam": beam, "ratio": sag[-1] / beam, "frames": len(sag), "settled": settled,
            "seconds": time.perf_counter() - t0}
