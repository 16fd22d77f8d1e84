"""Why a wall thinner than the grid crept under a steady load: the zero-energy velocity modes of its particle layers,
by linear algebra on the MLS-MPM transfers.  Pure numpy, no solver run.

The clamped strip of :mod:`tasks.verification.membrane_bending` in its x-z plane (plane strain in y): particles on an
in-plane lattice of spacing dx / 2 in ``layers`` layers across the thickness (two at its Gauss points), the mid-surface
``offset`` cells above a plane of nodes; the nodes their quadratic B-spline stencils touch carry the unknowns (vx, vz),
those at x <= 0 are clamped.  For node velocities v each particle moves at P v = sum_i w_ip v_i and deforms at the MLS
gradient C = 4 / dx^2 sum_i w_ip v_i (x_i - x_p)^T (``kernels.gather_apic``).  The rates that cost strain energy are
the in-plane C_xx and the transverse shear C_xz + C_zx, and the normal C_zz for a solid or a wall with a normal
stiffness (``mpm.wall_normal_stiffness`` > 0); a plane-stress wall without one carries no normal stress, so C_zz is
free.  A velocity field in the null space of those rates that moves particles (P v != 0) costs no strain energy:
nothing resists it, and where the weight does work on it (sum_p m_p g . (P v)_p != 0) the strip creeps.

Measured (10 cells of 8 mm, 3 mm thick, two Gauss layers): in plane stress 13 such modes at every alignment, driven by
the weight except with the mid-surface exactly on a node plane (symmetry), 26 on a plane of cell centres; a solid has
none except within a cell-centre plane's reach, where the two layers' own stencils spread over four node layers (4
modes); with a normal stiffness as the solid's and both layers on their mid-surface's stencil
(``mpm.wall_stencil=shared``) none at any alignment (``tests/physics/test_membrane.py``).
"""
from __future__ import annotations

import numpy as np

from tasks.physics.mpm.boundary import bspline_stencil


def wall_modes(offset: float, layers: int = 2, normal_stiffness: bool = False, shared_stencil: bool = False,
               dx: float = 0.008, thickness: float = 0.003, length: float = 0.08, embed: int = 2) -> dict:
    """The zero-energy modes of the strip of the module doc (SI lengths) with its mid-surface ``offset`` cells above a
    node plane: ``normal_stiffness`` False is a plane-stress wall (True: a solid, or a wall with a normal stiffness),
    ``shared_stencil`` both layers on the stencil of their mid-surface.  Returns ``nodes`` (free nodes touched),
    ``particles``, ``modes`` (dimension of the null space of the energy-bearing rates), ``moving`` (those that move
    particles) and ``driven`` (norm of the weight's work rate over an orthonormal basis of the modes, per unit
    particle mass and g; ~1e-13 is none)."""
    h = dx / 2
    xs = np.arange(h / 2 - embed * dx, length, h)
    if layers == 2:
        zs = np.array([-1.0, 1.0]) * thickness / (2 * np.sqrt(3))
    else:
        zs = ((np.arange(layers) + 0.5) / layers - 0.5) * thickness
    mid = (12 + offset) * dx
    pos = np.array([(x, mid + z) for x in xs for z in zs])  # (P, 2) m, x and z
    g = pos / dx
    base = np.floor(np.column_stack([g[:, 0], np.full(len(g), mid / dx)]) - 0.5) if shared_stencil else None
    base, w = bspline_stencil(g, base)
    nodes: dict[tuple[int, int], int] = {}
    entries = []
    for p in range(len(pos)):
        for i in range(3):
            for k in range(3):
                node = (int(base[p, 0]) + i, int(base[p, 1]) + k)
                weight = w[p, 0, i] * w[p, 1, k]
                if node[0] <= 0 or weight < 1e-14:  # clamped, or not touched
                    continue
                entries.append((p, nodes.setdefault(node, len(nodes)), weight, np.array(node) * dx - pos[p]))
    n, n_p = len(nodes), len(pos)
    move = np.zeros((2 * n_p, 2 * n))  # particle velocities
    grad = np.zeros((n_p, 2, 2, 2 * n))  # C[a, b] = d v_a / d x_b per particle
    for p, i, weight, d in entries:
        for a in range(2):
            move[2 * p + a, 2 * i + a] += weight
            grad[p, a, :, 2 * i + a] += 4.0 / dx ** 2 * weight * d
    rates = [grad[:, 0, 0], grad[:, 0, 1] + grad[:, 1, 0]] + ([grad[:, 1, 1]] if normal_stiffness else [])
    energy = np.concatenate(rates)
    sv, vt = np.linalg.svd(energy)[1:]
    null = vt[np.sum(sv > 1e-9 * sv[0]):]
    weight_rate = np.zeros(2 * n_p)
    weight_rate[1::2] = -1.0
    moving = np.linalg.norm(null @ move.T, axis=1) > 1e-6 if len(null) else np.zeros(0, bool)
    return {"nodes": n, "particles": n_p, "modes": len(null), "moving": int(moving.sum()),
            "driven": float(np.linalg.norm(null @ (move.T @ weight_rate))) if len(null) else 0.0}
