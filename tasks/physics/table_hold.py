"""The table's hold on the body (``mpm.table_hold``; docs/limits/table-contact.md, "The hold").

Under ``mpm.contact = surface`` the table is a plane collider that pushes the particles touching it and, sticky
(``mpm.floor_sticky``), keeps them from slipping while they touch; it never pulls, so a body pushed sideways at its
top rolls or tips over its edge (the plush toy toppled and the force-driven ball rolled away when the default was
flipped to it).  The grid-node table had held the body through a halo: it overwrote the velocity of every node at or
below it, gluing the lowest ~1.5 cells of material to it.  The recording's object does not roll away because the
hand holds it down onto the table; what the scene can take from that is an *adhesive footprint*:

``footprint``: the particles whose lowest surface point lies within one particle spacing of the table in the body's
given shape (paper sec. 3.2's start, the captured object on the table: its lowest particle layer and, on a curved
base, the cap within one spacing) are held where they rest, through the gravity preload and the rollout: each one's lowest surface
point (its centre minus its contact reach |F^T e_z| along -z, as the table's collider measures it,
:func:`tasks.physics.mpm.kernels.contact.contact_velocity`) is a :class:`ParticlePins` pin at its resting position
(m), driven back there over every frame, so it neither slips nor lifts; the pin is ``free`` along -z, so the point
may still be pressed down onto the table, whose collider then acts on it (the hold adds no support: the Hertz table
case reads +2 to +7 % of the unheld table's force at 1-4 mm, the grip of a bonded patch on a frictionless table;
pins that also held the points up read 1.5-3.6x).  The rest of the body still meets the table only where it touches
it.  The pins are reported as no finger (finger id -1); their work m du . v_new (J) joins the boundary work the
energy guard credits, and it is zero at rest (the pinned points do not move).  Measured (docs/limits/table-contact.md,
"The hold"): the force-driven rubber ball, duck and clay, which the bare surface table let roll or be knocked over,
stay upright (tilt <= 10 deg, footprint slide <= 0.01 mm).  The plush toy, then standing on its two feet with its
centre of mass behind them, fell back under its weight; seated on its seat and legs (2026-12-06) it settles in 12
damped frames and sways < 2 deg under the squeeze.  The pipeline's table since then (``conf/mpm/default.yaml``).

``none``: no hold (the table as it was).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from conf.mpm_schema import TABLE_HOLD_MODES
from tasks.physics.mpm import MPMSolver, ParticlePins

DOWN = np.array([0.0, 0.0, -1.0])
# the footprint's band: a particle is in it when its lowest surface point is within this many of its own spacings
# (cbrt V0) of the table: the body's lowest particle layer and, on a curved base, the cap within one spacing.  Four
# spacings (measured 2026-12-06) held the plush toy through its preload but glued the bases as the grid's halo had:
# the force-driven clay's window strain 0.024 against its target 0.19, the Hertz table case +40-60 %
HOLD_BAND = 1.0


def table_footprint(solver: MPMSolver) -> np.ndarray:
    """(n,) int: the body's particles (velocity field 0, not released material) whose lowest surface point (the
    centre minus the contact reach stretched by F, |F^T e_z|, as the table's collider measures it) lies within
    ``HOLD_BAND`` of their spacing above the table plane, or below it; empty without a table."""
    if solver.floor_height is None:
        return np.zeros(0, np.int64)
    F = solver.deformation_gradients().astype(np.float64)
    reach = solver.contact_radii() * np.linalg.norm(F[:, 2, :], axis=1)  # |F^T e_z|: row z of F
    gap = solver.positions()[:, 2].astype(np.float64) - reach - float(solver.floor_height)
    body = solver.mat_field.numpy()[solver.material_ids()] == 0
    return np.flatnonzero((gap <= HOLD_BAND * np.cbrt(solver.volumes().astype(np.float64))) & body)


def table_hold(solver: MPMSolver, mode: str) -> Optional[ParticlePins]:
    """The hold of ``mode`` (``conf.mpm_schema.TABLE_HOLD_MODES``; module doc) on the body in ``solver`` as it rests now (its
    given shape, before the gravity preload, which it then holds too): pins (finger -1) at the footprint particles' lowest surface points, or None
    (``none``, or nothing touches the table).  Raises ``ValueError`` for an unknown mode."""
    if mode not in TABLE_HOLD_MODES:
        raise ValueError(f"mpm.table_hold: '{mode}' is not one of {', '.join(TABLE_HOLD_MODES)}")
    idx = table_footprint(solver) if mode == "footprint" else np.zeros(0, np.int64)
    if not len(idx):
        return None
    # the pin acts where the table's collider touches: the contact reach, in half spacings (ParticlePins arms)
    half = 0.5 * np.cbrt(solver.volumes()[idx].astype(np.float64))
    arms = np.clip(solver.contact_radii()[idx] / half, 0.0, 1.0)
    normals = np.tile(DOWN, (len(idx), 1))
    return ParticlePins(idx, solver.surface_points(idx, normals, arms), normals, np.full(len(idx), -1, np.int32),
                        arms=arms, free=np.ones(len(idx), bool))


def join_pins(a: Optional[ParticlePins], b: Optional[ParticlePins]) -> Optional[ParticlePins]:
    """Two pin sets as one (either may be None); a particle in both keeps ``a``'s pin (the fingers' over the
    table's hold).  Both must be of one slip kind (the kernel's ``pin_slip`` is one flag): ``ValueError`` else."""
    if a is None or b is None:
        return b if a is None else a
    if a.slip != b.slip:
        raise ValueError("join_pins: a slip and a no-slip pin set cannot be joined (one pin_slip flag per frame)")
    keep = ~np.isin(np.asarray(b.indices).reshape(-1), np.asarray(a.indices).reshape(-1))

    def rows(p: ParticlePins, name: str, default: float, mask=slice(None)) -> np.ndarray:
        n = len(np.asarray(p.indices).reshape(-1))
        v = getattr(p, name)
        return (np.full(n, default) if v is None else np.asarray(v).reshape(n, -1).squeeze(-1))[mask]

    return ParticlePins(np.concatenate([np.asarray(a.indices).reshape(-1), np.asarray(b.indices).reshape(-1)[keep]]),
                        np.concatenate([np.asarray(a.targets).reshape(-1, 3), np.asarray(b.targets).reshape(-1, 3)[keep]]),
                        np.concatenate([np.asarray(a.normals).reshape(-1, 3), np.asarray(b.normals).reshape(-1, 3)[keep]]),
                        np.concatenate([rows(a, "finger_ids", -1), rows(b, "finger_ids", -1, keep)]).astype(np.int32),
                        slip=a.slip,
                        arms=np.concatenate([rows(a, "arms", 1.0), rows(b, "arms", 1.0, keep)]),
                        free=np.concatenate([rows(a, "free", False), rows(b, "free", False, keep)]).astype(bool))


def held_pins(hold: Optional[ParticlePins], solver: MPMSolver) -> Optional[ParticlePins]:
    """``hold`` without the particles that have since left the body's velocity field (material released by a
    rupture, which no longer rests on the table as the body's skin did)."""
    if hold is None:
        return None
    body = solver.mat_field.numpy()[solver.material_ids()[hold.indices]] == 0
    if body.all():
        return hold
    if not body.any():
        return None
    return ParticlePins(hold.indices[body], hold.targets[body], hold.normals[body], hold.finger_ids[body],
                        arms=hold.arms[body], free=hold.free[body])
