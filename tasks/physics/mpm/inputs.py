"""What the caller gives :meth:`~tasks.physics.mpm.solver.MPMSolver.step_frame` (SI units): constrained points and nodes
(Dirichlet conditions on the grid), force patches, rigid colliders of the surface contact and particle pins.
The solver uploads them every frame (:mod:`tasks.physics.mpm.boundary`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional, Sequence, Union

import numpy as np


@dataclass
class DirichletPoints:
    """Constrained points with prescribed velocities (m, m/s).

    ``normals`` (optional, per point): when given (non-zero), only the velocity component along the normal is
    prescribed (frictionless contact, e.g. a slip plate); otherwise the full vector (sticky finger pad).
    ``min_weight``: stencil nodes whose B-spline weight is below this are left free (0 = all 27).
    ``advect``: move the points by ``velocity * dt`` every substep (kinematic targets).

    What they hold (issue 50): a grid-node constraint, not a contact at the material's surface.  Every point sets the
    velocity of the grid nodes its quadratic B-spline stencil touches (27 nodes, 3 per axis), and every particle
    within that stencil's reach, ~1.5 cells of the point, takes its velocity from those nodes: a layer of material
    about one cell thick beside a plate moves rigidly with it.  A cube between two grid-node slip plates reads
    +31 to +57 % of E A eps at nu 0-0.49 with 8 cells across (+10 / +35 / +46 % plate-travel strain at nu 0.3 / 0.45
    / 0.49 on a 10 mm grid), and the reactions include the force that layer's rigid motion takes.  For a boundary at
    the surface use :class:`ParticlePins` (prescribed motion, E A eps within 5 %) or :class:`Collider` (contact);
    the pipeline states it in the rollout's notes when ``mpm.fingers=dirichlet`` drives the squeeze with them.
    """

    positions: np.ndarray
    velocities: np.ndarray
    finger_ids: Optional[np.ndarray] = None
    normals: Optional[np.ndarray] = None
    min_weight: float = 0.0
    advect: bool = True


@dataclass
class DirichletNodes:
    """Explicit Dirichlet nodes: integer grid indices (M, 3), prescribed velocities (M, 3), finger ids (M,).  The
    nodes themselves are held, so every particle whose stencil reaches them (within ~1.5 cells) moves with them: see
    :class:`DirichletPoints` for what such a constraint holds."""

    indices: np.ndarray
    velocities: np.ndarray
    finger_ids: Optional[np.ndarray] = None
    normals: Optional[np.ndarray] = None

    @classmethod
    def from_mask(cls, mask: np.ndarray, velocity, finger_id: int = 0) -> "DirichletNodes":
        """Nodes where the boolean grid-shaped ``mask`` is True, all with one velocity (3,) and finger id."""
        idx = np.argwhere(np.asarray(mask, bool)).astype(np.int32)
        vel = np.broadcast_to(np.asarray(velocity, np.float32).reshape(-1, 3), (len(idx), 3)).copy()
        return cls(idx, vel, np.full(len(idx), int(finger_id), np.int32))


@dataclass
class ForcePatch:
    """Force mode: finger k pushes with the total force ``forces[k]`` (N) through its points ``positions`` (m).

    ``tracers``: the solver's tracer indices the points are (``positions`` then only their place at the frame
    start): they are re-placed from their anchors every substep, so the push follows the material it acts on.
    Points fixed in space for a frame are left behind by material moving more than a cell in it (3 m/s for
    33 ms: 10 cm); the finger's whole force then goes to the little mass still under them, F / W without bound
    (the torn plush toy's finger 4: 2.3 N on 4e-5 kg, dt 3e-5 s and falling).  ``particles``: instead, the solver's
    particle indices the points are (each substep at the particles' own positions), e.g. the stuffing beneath a
    finger that tore through the skin (at most one of ``tracers`` and ``particles``)."""

    positions: np.ndarray
    finger_ids: np.ndarray
    forces: np.ndarray
    tracers: Optional[np.ndarray] = None
    particles: Optional[np.ndarray] = None


@dataclass
class Collider:
    """A rigid collider of the surface contact (``mpm.contact``; see :func:`tasks.physics.mpm.kernels.contact.contact_velocity`):
    it acts on the particles whose surface (centre +- half their spacing) it touches, not on grid nodes.

    ``kind``: ``plane`` (``a`` a point on it, ``b`` its normal towards the material), ``sphere`` (centre ``a``,
    ``radius``) or ``capsule`` (segment ``a``-``b``, ``radius``; e.g. a fingertip); positions in m.  ``velocity``:
    rigid translation (m/s; the solver moves it every substep).  ``friction``: Coulomb coefficient (0 frictionless,
    < 0 no slip while touching).  ``finger_id``: the reaction array entry that receives its force (< 0: none).
    ``field``: the velocity field whose particles it acts on (0 the body, 1 the released field; < 0: every
    particle)."""

    kind: str
    a: Sequence[float]
    b: Sequence[float] = (0.0, 0.0, 1.0)
    radius: float = 0.0
    velocity: Sequence[float] = (0.0, 0.0, 0.0)
    friction: float = 0.0
    finger_id: int = -1
    field: int = -1

    KINDS = ("plane", "sphere", "capsule")


@dataclass
class ParticlePins:
    """Particle-level Dirichlet conditions (the kernel: :func:`tasks.physics.mpm.kernels.contact.pin_velocity`): the
    surface point of each particle ``indices`` (its centre + r n along the outward surface normal ``normals``, r
    half its spacing stretched by F) is driven in a straight line from where it is at the frame start to
    ``targets`` (m) at the frame's end, all of its velocity or, with ``slip``, its normal component.  The push acts
    on those particles only, at their surface points (no grid node is held: no rigid layer next to the boundary);
    its impulses are the reactions of ``finger_ids`` (< 0: not reported).  ``arms`` (default 1) scale r: 0 pins
    the particle's centre, for a particle that is a whole wall thinner than its spacing (one layer on the wall's
    mid-surface): such a wall has no through-thickness compliance the particle resolves, and a push at its
    fictitious surface half a spacing out crushes it against the wall's membrane stiffness (the hollow rubber
    duck's pinned wall particles at 3 mm spacing: det F 1 -> 0.30 -> failure; pinned at their centres >= 0.49).
    ``free`` (default none): a pin that does not hold its point back when it moves out along n faster than its path
    (the table's hold, :mod:`tasks.physics.table_hold`: held from slipping and lifting, free to be pressed down)."""

    indices: np.ndarray
    targets: np.ndarray
    normals: np.ndarray
    finger_ids: Optional[np.ndarray] = None
    slip: bool = False
    arms: Optional[np.ndarray] = None  # (pin,) where along n the pin acts, in half spacings (default 1: the surface)
    free: Optional[np.ndarray] = None  # (pin,) bool: the point may move out along n faster than its path (default no)


BoundarySpec = Union[DirichletPoints, DirichletNodes, Sequence[Union[DirichletPoints, DirichletNodes]], None,
                     Callable[[float, Optional[float]], Any]]
