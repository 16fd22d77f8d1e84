"""MLS-MPM driver: :class:`MPMSolver` owns the Warp arrays and runs frames of CFL-adaptive substeps.

Per substep (paper sec. "Squeezing-Driven Deformation"): P2G -> grid update (gravity, walls, floor, Dirichlet
nodes with reaction forces, external finger forces) -> G2P with F_E <- (I + dt grad v) F_E and the material's
return mapping.  See :mod:`tasks.physics.mpm.kernels` for the kernels and :mod:`tasks.physics.mpm.constitutive` for the models.

Boundary conditions (generic; the finger field is connected by the caller)
    * :class:`DirichletPoints`: constrained points (positions, target velocities, finger ids, optional slip
      normals).  Every substep they are projected onto the nodes their quadratic B-spline stencils touch; a
      node's prescribed velocity is the weight-averaged target of the points touching it, per constrained
      direction (sticky points: all three; slip points: their normal; constraints with different normals on one
      node each keep their own component, see :func:`tasks.physics.mpm.kernels.dirichlet_velocity`).  Before the
      overwrite the solver accumulates the reaction  F_k = sum_{i in nodes of k} m_i (v_bc - v*_i) / dt
      (a node shared by several fingers is split in proportion to their weights).  F_k is the force the
      constraint applies to the material (N); the finger feels -F_k.
    * :class:`DirichletNodes`: explicit node indices with prescribed velocities.
    * :class:`ForcePatch` ("force mode"): a total force vector per finger, distributed over the massive nodes
      that finger's points touch in proportion to the B-spline weight, so the total force per finger is exactly
      the given vector, independent of the particle count.
    * :class:`Collider` (surface contact): rigid planes, spheres and capsules with signed distances, acting on the
      particles whose surface touches them (:func:`tasks.physics.mpm.kernels.contact_velocity`); their impulses
      join the per-finger reactions.  ``mpm.contact = surface`` makes the floor such a plane (``grid``: for the
      released field only).
    * floor plane and domain walls (config).
Tracers (surface 3D Gaussians) are embedded in the material: each is bound at rest to its nearest particles
(:meth:`MPMSolver._bind_tracers`) and placed from their positions and deformation gradients when read
(``tracer_positions``, ``tracer_state``), so it cannot drift off the material; deform covariances with
:func:`deform_covariances` (F Sigma F^T) and rotate with :func:`polar_rotation`.
"""
from __future__ import annotations

import gc
import math
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Optional, Sequence, Union

import numpy as np
import warp as wp

from conf.mpm_schema import MPMConfig, mpm_config_from
from tasks.physics.wall_resolution import gauss_layer_face

from . import kernels as K
from .materials import (
    COL_DAMPING,
    COL_DENSITY,
    COL_HARDENING,
    COL_PHYSICAL_DENSITY,
    COL_YIELD,
    MODEL_CODES,
    N_COLS,
    PLASTIC_MODELS,
    Material,
    pack_table,
)

FIXED_COROTATED = MODEL_CODES["fixed_corotated"]
VON_MISES = MODEL_CODES["von_mises"]
# Loaded frames at the start of every contact that the quasi-static check skips: where a finger first touches, the
# material under it is brought to the finger's speed while its strain energy is still that of its weight, so the
# kinetic/internal ratio is large however slowly the finger moves (first frame: orange 0.33, tomato 1.5 at the
# default 30 frames/s; second frame of the gentle tomato poke at 20 frames/s: 0.12; then below 0.03).  Mass scaling
# ties the scaled dynamics to the frame (s ~ frame_dt^2), so the transient spans about the same frames at any rate.
QUASI_STATIC_ONSET_FRAMES = 2
# Particles each tracer (surface Gaussian) is embedded in (:meth:`MPMSolver._bind_tracers`): the 4 nearest span a
# volume around a surface point (3 could be collinear on a one-particle shell's lattice) and stay within ~1 spacing.
TRACER_ANCHORS = 4
# mpm.threads: the hand-over (pool, 4 chunk launches, 3 grid sums) costs ~170 us of CPU per substep (measured on 64
# particles under load) and a thread saves ~80 ns per particle of its share: break-even ~2000 particles, 2x margin
MIN_PARTICLES_PER_THREAD = 4096
CHUNKS_PER_THREAD = 2  # mpm.threads > 1: particle chunks per thread (each has its own P2G grid)

wp.config.quiet = True


class SimulationError(RuntimeError):
    """The simulation left its valid range (non-finite state, particle out of the grid, extreme J, Courant)."""


# ============================================================================================ inputs
@dataclass
class DirichletPoints:
    """Constrained points with prescribed velocities (m, m/s).

    ``normals`` (optional, per point): when given (non-zero), only the velocity component along the normal is
    prescribed (frictionless contact, e.g. a slip plate); otherwise the full vector (sticky finger pad).
    ``min_weight``: stencil nodes whose B-spline weight is below this are left free (0 = all 27).
    ``advect``: move the points by ``velocity * dt`` every substep (kinematic targets).
    """

    positions: np.ndarray
    velocities: np.ndarray
    finger_ids: Optional[np.ndarray] = None
    normals: Optional[np.ndarray] = None
    min_weight: float = 0.0
    advect: bool = True


@dataclass
class DirichletNodes:
    """Explicit Dirichlet nodes: integer grid indices (M, 3), prescribed velocities (M, 3), finger ids (M,)."""

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
    """A rigid collider of the surface contact (``mpm.contact``; see :func:`tasks.physics.mpm.kernels.contact_velocity`):
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
    """Particle-level Dirichlet conditions (the kernel: :func:`tasks.physics.mpm.kernels.pin_velocity`): the
    surface point of each particle ``indices`` (its centre + r n along the outward surface normal ``normals``, r
    half its spacing stretched by F) is driven in a straight line from where it is at the frame start to
    ``targets`` (m) at the frame's end, all of its velocity or, with ``slip``, its normal component.  The push acts
    on those particles only, at their surface points (no grid node is held: no rigid layer next to the boundary);
    its impulses are the reactions of ``finger_ids`` (< 0: not reported).  ``arms`` (default 1) scale r: 0 pins
    the particle's centre, for a particle that is a whole wall thinner than its spacing (one layer on the wall's
    mid-surface): such a wall has no through-thickness compliance the particle resolves, and a push at its
    fictitious surface half a spacing out crushes it against the wall's membrane stiffness (the hollow rubber
    duck's pinned wall particles at 3 mm spacing: det F 1 -> 0.30 -> failure; pinned at their centres >= 0.49)."""

    indices: np.ndarray
    targets: np.ndarray
    normals: np.ndarray
    finger_ids: Optional[np.ndarray] = None
    slip: bool = False
    arms: Optional[np.ndarray] = None  # (pin,) where along n the pin acts, in half spacings (default 1: the surface)


@dataclass
class GravityPreload:
    """What :meth:`MPMSolver.preload_gravity` did (SI).  ``moved``: m, the largest solid-particle displacement of
    each pass; its first is the ``sag`` (how far the body moves under its weight from the shape it was given), its
    last the ``residual`` (what the prestress leaves unbalanced); ``frames``: damped frames over all passes;
    ``converged``: the last pass came to rest within its frames."""

    moved: tuple[float, ...]
    frames: int
    converged: bool

    @property
    def passes(self) -> int:
        return len(self.moved)

    @property
    def sag(self) -> float:
        return self.moved[0]

    @property
    def residual(self) -> float:
        return self.moved[-1]

    def as_dict(self) -> dict:
        return {"passes": self.passes, "frames": self.frames, "sag": self.sag, "residual": self.residual,
                "converged": self.converged, "moved": list(self.moved)}


BoundarySpec = Union[DirichletPoints, DirichletNodes, Sequence[Union[DirichletPoints, DirichletNodes]], None,
                     Callable[[float, Optional[float]], Any]]


@dataclass
class FrameStats:
    """Statistics of one frame (SI).  Energies, momentum, speed and J are end-of-frame values; ``reaction`` and
    ``applied_force`` are frame means (impulse / frame_dt) per finger id."""

    frame: int
    time: float  # s, simulated time at the end of the frame
    substeps: int
    dt_min: float
    dt_max: float
    courant: float  # c_p dt_max / dx
    max_speed: float  # m/s, particles, end of frame
    j_min: float
    j_max: float
    kinetic_energy: float  # J
    internal_energy: float  # J (elastic stored energy)
    ke_ie_ratio: float  # KE / (IE + plastic dissipation) of the quasi-static check's materials (MPMSolver)
    momentum: np.ndarray  # kg m/s
    mass: float  # kg
    reaction: np.ndarray  # (n_fingers, 3) N, mean force the Dirichlet constraint of each finger applied
    applied_force: np.ndarray  # (n_fingers, 3) N, mean force applied in force mode
    mass_scale: float
    stiffness_scale: float
    quasi_static_ok: bool
    wall_seconds: float
    gravitational_energy: float  # J, -sum m_phys g . x (physical weights), end of frame
    boundary_work: float  # J, work the Dirichlet nodes and force patches did on the material during the frame
    quasi_static_checked: bool = False  # the quasi-static check applied to this frame (see MPMSolver)
    ke_ie_contact: float = math.nan  # checked frames: sum KE / sum (IE + plastic work) of the measured materials
    energy_growth: float = 0.0  # energy guard measure: unexplained energy growth / energy scale (EnergyBudget)
    local_damping: float = 0.0  # local damping coefficient of the measured materials during the frame (class doc)
    plastic_dissipation: float = 0.0  # J, plastic work the measured materials dissipated so far (plastic_dissipation)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        for k, v in d.items():
            if isinstance(v, np.ndarray):
                d[k] = v.tolist()
        return d


# ============================================================================================ helpers
def membrane_normals_checked(normals: Optional[np.ndarray], n: int) -> Optional[np.ndarray]:
    """The solver's ``membrane_normals`` as float32 (n, 3), or None; rows must be unit vectors (a membrane particle)
    or zero (a solid one).  A bad array is one ValueError line naming what is wrong."""
    if normals is None:
        return None
    a = np.asarray(normals, np.float32)
    if a.shape != (n, 3):
        raise ValueError(f"membrane_normals must have shape ({n}, 3), one row per particle; got {a.shape}")
    norm = np.linalg.norm(a, axis=1)
    bad = ~np.isfinite(norm) | ((norm > 0) & (np.abs(norm - 1.0) > 1e-3))
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"membrane_normals: {int(bad.sum())} rows are neither unit vectors nor zero (row {i}: "
                         f"{a[i].tolist()}); give the rest unit normal of a thin wall's particle, 0 elsewhere")
    return np.ascontiguousarray(a)


class WallFibres(NamedTuple):
    """A thin wall's normal fibres as the solver holds them (:func:`membrane_fibres_checked`): per fibre its outer
    and inner Gauss layers' particles (``first``, ``second``, int32), their rest distance (``rest``, m, float32) and,
    in a wall of three Gauss layers, its middle layer's particle (``middle``, int32; None in two layers)."""
    first: np.ndarray
    second: np.ndarray
    rest: np.ndarray
    middle: Optional[np.ndarray]


def membrane_fibres_checked(fibres: Optional[np.ndarray], membrane_rows: np.ndarray, x: np.ndarray
                            ) -> Optional[WallFibres]:
    """The solver's ``membrane_fibres`` ((P, 2) or (P, 3) particle indices: outer, inner and, in three Gauss layers,
    middle) as :class:`WallFibres`, or None; every fibre joins membrane particles of one thin wall, no particle is
    in two fibres, and its ends are apart.  A bad array is one ValueError line naming what is wrong."""
    if fibres is None or len(fibres) == 0:
        return None
    a = np.asarray(fibres)
    n = len(membrane_rows)
    if a.ndim != 2 or a.shape[1] not in (2, 3) or not np.issubdtype(a.dtype, np.integer):
        raise ValueError("membrane_fibres must be integer particle indices of shape (P, 2) or (P, 3) (outer, inner, "
                         f"middle Gauss layer); got {a.dtype} {a.shape}")
    if a.min() < 0 or a.max() >= n:
        raise ValueError(f"membrane_fibres: indices must lie in [0, {n}); got {int(a.min())}..{int(a.max())}")
    if len(np.unique(a)) != a.size:
        raise ValueError("membrane_fibres: a particle is in two fibres (or twice in one); each wall particle lies on "
                         "one fibre, with its wall's other Gauss layers")
    if not membrane_rows[a].all():
        raise ValueError(f"membrane_fibres: {int((~membrane_rows[a]).any(axis=1).sum())} fibres join a particle "
                         "without a membrane normal; join only the Gauss layers of a thin wall (membrane_normals)")
    rest = np.linalg.norm(x[a[:, 0]].astype(np.float64) - x[a[:, 1]], axis=1)
    if not rest.min() > 0:
        raise ValueError(f"membrane_fibres: fibre {int(np.argmin(rest))}'s outer and inner particles lie at the "
                         "same position")
    return WallFibres(np.ascontiguousarray(a[:, 0], np.int32), np.ascontiguousarray(a[:, 1], np.int32),
                      rest.astype(np.float32), np.ascontiguousarray(a[:, 2], np.int32) if a.shape[1] == 3 else None)


def wall_offsets(x: np.ndarray, normals: np.ndarray, fibres: WallFibres) -> np.ndarray:
    """(particle,) float32 m: each thin wall's outer and inner Gauss layer's signed rest distance from its wall's
    mid-surface along its normal, (x - midpoint of its fibre's ends) . normal, 0 for every other particle (a middle
    layer lies on the mid-surface): :func:`tasks.physics.mpm.kernels.particle_stencil` gives every layer of a wall
    the stencil of its mid-surface."""
    out = np.zeros(len(x), np.float64)
    mid = 0.5 * (x[fibres.first].astype(np.float64) + x[fibres.second])
    for idx in (fibres.first, fibres.second):
        out[idx] = np.einsum("pi,pi->p", x[idx] - mid, normals[idx])
    return out.astype(np.float32)


def contact_reach(volume: np.ndarray, fibres: Optional[WallFibres] = None) -> np.ndarray:
    """(particle,) float32 m: how far each particle's surface reaches a collider (surface contact,
    :func:`tasks.physics.mpm.kernels.contact_velocity`): half its undeformed spacing, cbrt(V0) / 2; for the outer and
    inner Gauss layers of a wall thinner than the grid (``fibres`` as from :func:`membrane_fibres_checked`) its
    distance to its own face (:func:`~tasks.physics.wall_resolution.gauss_layer_face` x their rest distance), for a
    middle layer half the wall's
    thickness.  With cbrt(V0) / 2 the ball's outer layer (V0 21 mm^3: 1.38 mm) touched a flat 0.74 mm outside the
    wall's face (0.63 mm), its inner layer never, and the ball between surface flats read 1.10-1.37x the FE at 1-6 mm
    on the default grid; at the face 1.09-1.21x."""
    reach = 0.5 * np.cbrt(np.asarray(volume, np.float64))
    if fibres is not None:
        face = gauss_layer_face(2 if fibres.middle is None else 3)
        reach[fibres.first] = face * fibres.rest
        reach[fibres.second] = face * fibres.rest
        if fibres.middle is not None:
            reach[fibres.middle] = (0.5 + face) * fibres.rest
    return reach.astype(np.float32)


@dataclass
class EnergyBudget:
    """Energy guard bookkeeping from a reference frame on (J; see :class:`MPMSolver`).

    The unexplained growth is E - E_ref - W_in: E the total energy (kinetic + internal + gravitational -m_phys g . x,
    so material falling under gravity, released juice included, converts potential into kinetic energy and gains
    nothing), W_in the work the boundary put in (per frame, max(W, 0): a finger or force patch that takes energy back
    later, e.g. a force-driven body oscillating under a constant push, whose discrete work is not exactly
    conservative, is not credited with it).  The energy scale is the largest of the kinetic + internal energy at the
    reference frames, W_in and the change of gravitational energy seen: it never contains the energy being checked,
    so a blow-up cannot raise its own tolerance, while every legitimate source (initial state, boundary work,
    gravity) is in it.  It is kept across re-bases (a rupture changes the state, not the run's energy scale)."""

    frame: Optional[int]  # reference frame (None: re-base at the end of the next frame)
    energy: np.ndarray  # (material,) J, total energy per material at the reference
    potential: float  # J, gravitational energy at the reference
    scale: float  # J, running energy scale
    work_in: float = 0.0  # J, boundary work put in since the reference

    @classmethod
    def start(cls, frame: int, energy: np.ndarray, potential: float, mechanical: float,
              previous: Optional["EnergyBudget"] = None) -> "EnergyBudget":
        """A reference at ``frame`` with kinetic + internal energy ``mechanical`` (J)."""
        scale = max(mechanical, previous.scale if previous is not None else 0.0)
        return cls(frame=frame, energy=np.asarray(energy, np.float64).copy(), potential=potential, scale=scale)

    @staticmethod
    def rebase(previous: Optional["EnergyBudget"]) -> "EnergyBudget":
        """Forget the reference (state changed from outside) but keep the scale."""
        return EnergyBudget(frame=None, energy=np.zeros(0), potential=0.0,
                            scale=previous.scale if previous is not None else 0.0)

    def update(self, energy: np.ndarray, potential: float, work: float) -> float:
        """Add one frame (per-material total energy, gravitational energy, boundary work, J); returns the unexplained
        growth E - E_ref - W_in (J)."""
        self.work_in += max(float(work), 0.0)
        self.scale = max(self.scale, self.work_in, abs(potential - self.potential))
        return float(np.sum(energy) - self.energy.sum()) - self.work_in


@contextmanager
def _young_objects_collected():
    """Inside, Python's cyclic garbage collector scans only the objects made inside (``gc.freeze`` /
    ``gc.unfreeze``): every substep's launches allocate a few Python objects, and the full collection they
    trigger every few hundred substeps scans every object of the process (a pipeline worker holds ~0.5 M).
    Measured on a 4913-particle cube in a process of 140 k objects: one full collection per 600 substeps, 134-212
    ms each under load (~0.2-0.35 ms per 1.2 ms substep); none inside.  Left alone when the caller already froze
    objects or disabled the collector."""
    if gc.get_freeze_count() or not gc.isenabled():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _num(x: float) -> str:
    """3 significant digits, keeping a decimal point (1 -> '1.0', 1.4 -> '1.4')."""
    s = f"{x:.3g}"
    return s if ("." in s or "e" in s or "inf" in s or "nan" in s) else s + ".0"


def _ratio(kinetic: float, internal: float) -> float:
    """KE / IE (inf: kinetic energy without internal energy, 0: neither)."""
    return kinetic / internal if internal > 1e-30 else (math.inf if kinetic > 0 else 0.0)


def plastic_dissipation(alpha: np.ndarray, volume: np.ndarray, yield_stress: np.ndarray,
                        hardening: np.ndarray) -> float:
    """The plastic work (J) dissipated so far by particles of the von Mises return mapping
    (:func:`tasks.physics.mpm.constitutive.hencky_return_principal`): with the equivalent plastic strain ``alpha``
    (1) that it accumulates, the yield stress ``tau_y + H alpha`` (Pa, uniaxial, linear hardening H) is the
    Kirchhoff stress conjugate to it, so the work per unit of reference volume is int (tau_y + H a) da =
    tau_y alpha + H alpha^2 / 2, times the particle's reference ``volume`` (m^3).  A foam's Perzyna overstress and
    volumetric crush dissipate more than this: for it the sum is a lower bound."""
    a = np.asarray(alpha, np.float64)
    return float(np.sum(np.asarray(volume, np.float64) * (np.asarray(yield_stress, np.float64) * a
                                                           + 0.5 * np.asarray(hardening, np.float64) * a * a)))


def kinetic_energy_split(x: np.ndarray, v: np.ndarray, m: np.ndarray,
                         up: Sequence[float] = (0.0, 0.0, 1.0)) -> tuple[float, float, float, float]:
    """The kinetic energy (J) of particles at positions ``x`` (N, 3) m with velocities ``v`` (N, 3) m/s and masses
    ``m`` (N,) kg, split by Koenig's theorem into (horizontal translation, vertical translation, rotation,
    deformation): 1/2 M v_c^2 of the centre of mass, its velocity v_c split across and along the unit vertical
    ``up``; 1/2 omega . L of the rigid rotation about the centre of mass (L the angular momentum there, omega = I^-1 L
    with I the inertia tensor there); the rest, the kinetic energy relative to that rigid motion (>= 0: the rigid
    part is the mass-weighted least-squares fit of the velocity field).  A body pressed down on the table moves its
    centre of mass vertically (a uniform squash of a block on a sticky floor: 3/4 of its kinetic energy), one that
    sways, rocks or is pushed over on its base moves it horizontally and rotates."""
    x, v, m = (np.asarray(a, np.float64) for a in (x, v, m))
    total = 0.5 * float(m @ (v * v).sum(axis=1))
    mass = float(m.sum())
    if not mass > 0.0:
        return 0.0, 0.0, 0.0, 0.0
    v_c = m @ v / mass
    r = x - m @ x / mass
    mr = m[:, None] * r
    moments = mr.T @ r  # sum m r r^T
    ang = np.cross(mr, v).sum(axis=0)  # about the centre of mass (sum m r = 0: the drift adds nothing)
    inertia = np.trace(moments) * np.eye(3) - moments
    omega = np.linalg.lstsq(inertia, ang, rcond=1e-12)[0]  # a collinear body has no rotation about its axis
    vertical = 0.5 * mass * float(v_c @ np.asarray(up, np.float64)) ** 2
    translation, rotation = 0.5 * mass * float(v_c @ v_c), 0.5 * float(omega @ ang)
    return translation - vertical, vertical, rotation, max(total - translation - rotation, 0.0)


def resolve_device(device: Optional[str]) -> str:
    """``auto`` -> ``cuda:0`` when a CUDA device is present, else ``cpu``."""
    if device is None or device == "auto":
        return "cuda:0" if wp.get_cuda_device_count() > 0 else "cpu"
    return device


def bspline_stencil(g: np.ndarray, base: Optional[np.ndarray] = None):
    """numpy twin of the kernel stencil: base (P,3) int, weights (P,3,3) per axis; with ``base`` given, the
    B-spline's polynomial pieces on the nodes from it (the kernels' ``stencil_on``)."""
    base = np.floor(g - 0.5).astype(np.int64) if base is None else np.asarray(base, np.int64)
    f = g - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)  # (P,3 axes,3)
    return base, w


@dataclass(frozen=True)
class QuasiStaticLoad:
    """The time scale of the boundary load, for the quasi-static bound of the mass scale (see :func:`mass_scale_for`).

    ``rise_time``: t_load in s, how fast the fingers load the body (the rollout: the ramp time of the total force
    coefficient, :func:`tasks.physics.mpm_rollout.load_rise_time`).  ``height``: H in m, the body's extent along
    gravity (it stands on the table, which holds its base)."""

    rise_time: float
    height: float


def lowest_period(materials: Sequence[Material], height: float, stiffness_scale: float = 1.0,
                  mass_scale: float = 1.0) -> float:
    """Estimated period T1 (s) of the slowest vibration mode of a body of height ``height`` (m) held at its base: the
    fundamental of a shear beam fixed at one end, T1 = 4 H / c_s (a quarter wave over H; for a 1-D bar fixed at one
    end and free at the other, exact with its wave speed), c_s = sqrt(mu / (s rho)) the slowest shear-wave speed of
    the solid ``materials`` (m/s, after stiffness scaling, densities x ``mass_scale``): the softest material sets
    the slowest mode.  Hollow bodies rock slower on their small base (shell bending: the force-driven rubber duck's
    contacts stay quasi-static from k = 1.5 in :func:`mass_scale_for`, the ball's from k = 2.5; a solid slab swings
    with T1 within 15 %).  inf without a solid."""
    speeds = [math.sqrt(m.mu * stiffness_scale / (m.density * mass_scale)) for m in materials if m.model != "fluid"]
    return 4.0 * height / min(speeds) if speeds else math.inf


def mass_scale_for(materials: Sequence[Material], dx: float, frame_dt: float | None, cfg: MPMConfig,
                   load: Optional[QuasiStaticLoad] = None) -> float:
    """The density factor s >= 1 that ``cfg.mass_scaling`` prescribes for the scaled materials (dimensionless).

    ``off``: 1.  ``manual``: ``cfg.mass_scale``.  ``global`` / ``selective``: the smallest s for which the elastic
    CFL of the scaled ``materials`` (``global``: every non-fluid one; ``selective``: those with
    ``Material.is_mass_scaled``) needs at most N = ``cfg.target_substeps_per_frame`` substeps per output frame:
    s_cfl = max(1, (c_p (frame_dt / N) / (C dx))^2), c_p the largest P-wave speed (m/s, after stiffness scaling) of
    those materials, C = ``cfg.courant``, ``dx`` the grid spacing (m), ``frame_dt`` the frame duration (s).
    Scaling rho by s slows every wave by sqrt(s).  Fluids do not drive s: a weakly compressible fluid's bulk
    modulus is an artificial choice that the caller sets for its Mach number (so its sound speed stays at its target).

    Quasi-static bound (``cfg.quasi_static_margin`` = k > 0 and a ``load``): the scaled body's slowest mode must be k
    times faster than the load rises, k T1(s) <= t_load, so s <= s_qs = (t_load / (k T1(1)))^2 with T1 from
    :func:`lowest_period` (T1(s) = sqrt(s) T1(1)); s = max(1, min(s_cfl, s_qs)).  A smaller s costs
    sqrt(s_cfl / s_qs) times the substeps.
    """
    if cfg.mass_scaling == "off":
        return 1.0
    if cfg.mass_scaling == "manual":
        return float(cfg.mass_scale)
    if frame_dt is None:
        raise ValueError(f"mass_scaling={cfg.mass_scaling} needs the frame duration")
    scaled = [m for m in materials if (m.is_mass_scaled if cfg.mass_scaling == "selective" else m.model != "fluid")]
    if not scaled:
        return 1.0
    c_p = max(m.p_wave_speed(cfg.stiffness_scaling) for m in scaled)
    s = (c_p * (frame_dt / cfg.target_substeps_per_frame) / (cfg.courant * dx)) ** 2
    return max(1.0, min(s, quasi_static_bound(scaled, cfg, load)))


def quasi_static_bound(materials: Sequence[Material], cfg: MPMConfig, load: Optional[QuasiStaticLoad]) -> float:
    """s_qs = (t_load / (k T1(1)))^2 of :func:`mass_scale_for` for a body of ``materials`` (inf: no bound, when
    ``cfg.quasi_static_margin`` is 0 or there is no ``load``)."""
    if not cfg.quasi_static_margin > 0 or load is None:
        return math.inf
    period = lowest_period(materials, load.height, cfg.stiffness_scaling)
    return (load.rise_time / (cfg.quasi_static_margin * period)) ** 2


def material_mass_scales(materials: Sequence[Material], present: Sequence[Material], dx: float,
                         frame_dt: float | None, cfg: MPMConfig, load: Optional[QuasiStaticLoad] = None) -> np.ndarray:
    """Per-material density factors (material,) under ``cfg.mass_scaling`` (dimensionless).

    ``selective``: each material with ``Material.is_mass_scaled`` gets its own smallest factor
    :func:`mass_scale_for` ``([material])`` (the stiffest gets the s of ``global``, a softer solid less, a torn skin
    softened 100x needs 100x less), the others 1 (physical inertia): mass is scaled only where it buys time, which
    keeps the mass ratio between released material and the solids it must push past small.  Every other mode: the
    one factor :func:`mass_scale_for` ``(present)`` of the materials ``present`` for every material.  ``load``: the
    quasi-static bound of :func:`mass_scale_for`; under ``selective`` each scaled material's own, s_m <= (t_load /
    (k T1_m(1)))^2, so that every material's shear-wave speed at its scale, c_m = sqrt(mu_m / (s_m rho_m)), is at
    least c = 4 H k / t_load.  That bounds the body's slowest mode as well: its Rayleigh quotient omega^2 =
    int mu |grad u|^2 / int s rho |u|^2 >= min_m c_m^2 int |grad u|^2 / int |u|^2, that of a uniform body with the
    slowest of those speeds, so the composite's T1 <= t_load / k.  (The former single cap, the softest material's,
    on every material slowed a pulp-cored fruit's stiff peel 8-22x more than its bound needs: 2.8x the substeps of
    the default orange at k = 1.5 instead of 1.1x.)
    """
    if cfg.mass_scaling != "selective":
        return np.full(len(materials), mass_scale_for(present, dx, frame_dt, cfg, load))
    return np.array([mass_scale_for([m], dx, frame_dt, cfg, load) if m.is_mass_scaled else 1.0 for m in materials],
                    np.float64)


def deform_covariances(F: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariances of deformed Gaussians: F Sigma F^T (F: (N,3,3), cov: (N,3,3))."""
    return np.einsum("nij,njk,nlk->nil", F, cov, F)


def polar_rotation(F: np.ndarray) -> np.ndarray:
    """Rotation part R (det +1) of the polar decomposition F = R S, batched (N,3,3).

    Uses the SVD F = U S V^T with the sign of the smallest singular value flipped when det F < 0, so R is a proper
    rotation (the closest one to F).
    """
    F = np.asarray(F, dtype=np.float64)
    U, _, Vt = np.linalg.svd(F)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    D = np.ones(F.shape[:-1])
    D[..., -1] = d
    return (U * D[..., None, :]) @ Vt


def rotate_quaternions(R: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """Compose rotation matrices R (N,3,3) with Gaussian orientations q (N,4, w first): returns R*q (w first)."""
    from scipy.spatial.transform import Rotation

    r = Rotation.from_matrix(R)
    qx = np.concatenate([q_wxyz[:, 1:], q_wxyz[:, :1]], axis=1)
    out = (r * Rotation.from_quat(qx)).as_quat()
    return np.concatenate([out[:, 3:], out[:, :3]], axis=1)


# ============================================================================================ solver
class MPMSolver:
    """MLS-MPM solver (Warp, CPU or CUDA).

    Args:
        positions: (N, 3) particle positions, m.
        volumes: (N,) or scalar initial particle volumes, m^3 (mass = volume x material density, constant).
        materials: one :class:`Material` or a list; ``material_ids`` (N,) index into it (default all 0).
        velocities: (N, 3) initial velocities, m/s (default 0).
        config: :class:`conf.mpm_schema.MPMConfig`, a mapping or an OmegaConf node (default settings if None).
        tracers: (T, 3) tracer positions (surface Gaussians), embedded in the particles nearest to them at rest
            (:meth:`_bind_tracers`).
        tracer_anchors: (N,) bool, the particles tracers may be bound to (default all): a surface Gaussian belongs
            to the skin, not to the interior that a rupture releases.
        device: overrides ``config.device``.
        n_fingers: size of the per-finger reaction/force arrays (grows automatically with the finger ids seen).
        label: name of the simulated object, quoted by the energy guard's message.
        load: the time scale of the boundary load (:class:`QuasiStaticLoad`): with ``config.quasi_static_margin`` > 0
            it bounds the mass scale of ``global`` / ``selective`` scaling (:func:`mass_scale_for`).
        membrane_normals: (N, 3) rest unit normals of the particles of a wall thinner than the grid spacing (a
            shell the grid cannot resolve through its thickness), zero rows for the others: an elastic
            (fixed-corotated, neo-Hookean) membrane particle has no normal stress on its wall (plane stress,
            :func:`tasks.physics.mpm.constitutive.membrane_F`), so its wall thins as it stretches instead of
            locking its volume.  A von Mises membrane particle returns in plane stress
            (:func:`tasks.physics.mpm.constitutive.membrane_plastic_return`) and its row becomes the wall's current
            normal, carried by the flow every substep (plastic flow moves F_E's reference, so the rest normal no
            longer tells where the wall lies in it); :meth:`set_material_ids` converts a row between the two when a
            particle changes between an elastic and a von Mises material.  Whether a particle is a membrane is its
            row (non-zero), whatever its material's ``membrane`` flag.  Foam and fluid models ignore it.
        membrane_fibres: (P, 2) or (P, 3) particle indices, the Gauss layers of a thin wall at each point of it
            (membrane particles; outer, inner and, in three layers, middle; ``config.wall_fibres``): after every
            substep's advection each fibre's outer and inner particles are put back at their rest distance about
            their centre of mass (:func:`tasks.physics.mpm.kernels.k_wall_fibres`, Kirchhoff-Love's inextensible
            normal fibre), which nothing else holds on a grid coarser than the wall.  A middle particle moves with the
            grid: put back on its fibre's mid-point every substep, clamped strips 0.86 of a cell thick read 1.14x
            Euler-Bernoulli at dx 3.5 mm and 0.95x at dx 8 mm, free 1.03x and 1.09x, what the B-splines' clamp, a
            node plane behind the strip's root, makes of the closed form (1.04x and 1.08x).  A fibre whose outer and
            inner particles come to differ in material is left alone.

    Mass (time) scaling (``config.mass_scaling``; s from :func:`mass_scale_for`, fixed once: at construction, or for
    ``global``/``selective`` at the first :meth:`step_frame`): the densities of the scaled materials (all of them by
    s, or under ``selective`` those with ``Material.is_mass_scaled`` each by its own factor <= s, see
    :func:`material_mass_scales`; per material in ``material_mass_scale``) are multiplied, while every particle's
    weight stays physical, m_phys g: under a uniform scale the grid adds g / s (``self.gravity``, m/s^2) to every
    node's velocity; under mixed scales each particle's P2G adds the impulse dt m_phys g, so a node gains dt g sum_p
    w_ip m_phys,p divided by its (scaled) mass: a scaled solid feels g / s exactly as under uniform scaling and an
    unscaled blob falls at g.  Weights and every quasi-static state under gravity and boundary loads are unchanged,
    while a scaled material's wave speed, hence the stable dt it needs, scales by 1/sqrt(s) and sqrt(s); the stable
    step is the smallest over the materials present with their own scales.  For elastic materials driven only by
    gravity and static boundaries the uniformly scaled motion is exactly the unscaled one slowed down by sqrt(s):
    x_s(t) = x(t / sqrt(s)). Inertia-driven motion of a scaled material (impacts, rebounds, free flight) is slowed
    by that factor, so a boundary moving at a prescribed speed meets a material that responds sqrt(s) times slower.
    Quasi-static check: mass scaling assumes that the scaled material deforms quasi-statically, so its measure is
    the kinetic/internal energy ratio of the materials whose inertia is artificial (:meth:`_quasi_static_materials`:
    the mass-scaled ones declared quasi-static; ``FrameStats.ke_ie_ratio`` per frame), judged as Abaqus/Explicit
    judges a quasi-static analysis: "the kinetic energy of the deforming material should not exceed a small
    fraction (typically 5 % to 10 %) of its internal energy throughout the majority of the process" (Getting
    Started with Abaqus, "Quasi-static analysis with Abaqus/Explicit", energy balance; the limit is
    ``config.quasi_static_ke_ie_max``), with the internal energy as Abaqus counts it, ALLIE: the stored strain energy
    plus the plastic work dissipated so far (:func:`plastic_dissipation`; before 2026-12-04 the strain energy
    alone, which a yielding wall keeps small whatever it has absorbed: the default can warned at 0.47, 0.015 with
    its plastic work).  Exclusions, each for a physical reason: released material and fluids keep their physical mass
    (their motion is real dynamics, not a mass-scaling artefact); frames without boundary load (the start-up sag of a
    body under its suddenly applied weight, KE/IE ~ 1, and free flight are dynamic in any case, and nothing distorts a
    deformation that no finger imposes); the first ``QUASI_STATIC_ONSET_FRAMES`` loaded frames of every contact (the
    material under a finger is brought to its speed while its strain energy is still that of its weight); frames the
    caller declares dynamic (``step_frame(quasi_static=False)``: after a rupture the release is dynamic by design).  The
    remaining frames of one contact (``FrameStats.quasi_static_checked``) form the process, and the measure is its ratio
    of sums, sum KE / sum (IE + plastic work) over the contact: each frame counts with its energy, so a deformation that
    inertia distorts at full load shows, while the first frames of a load, where IE (~ load^2) is a few thousandths of
    its peak, weigh what they deform (the default paper cup pushed by a force: 1.28 in its first checked frame at 3 % of
    the load, 0.019 over the contact).  ``FrameStats.ke_ie_contact`` is that ratio
    over the contact so far; the contact is judged when it ends (:meth:`close_quasi_static_contact`: the fingers
    let go, a rupture, or the caller ends the run), listed in ``quasi_static_contacts`` with the share of its KE in
    the body's sway on its base (``sway_ke_share``: the horizontal motion of the measured materials' centre of mass
    and their rigid rotation about it, :func:`kinetic_energy_split`; a body pressed straight down has ~none), and
    above the limit warned about once, in one line naming object, frames, times, that share and knobs
    (``FrameStats.quasi_static_ok`` False in the frame that closed it).  A body rocking on the table under a
    force-driven push (the default ball and duck: 85-99 % of their KE in the lowest, sway mode) is what the check is
    for: its lowest mode is slower than the load (see ``load``).  The force-driven plush toy's sway under its
    fingers' unbalanced net push (87 % of its KE; ``simulation.force_balance=none``) is real dynamics: the same
    contact reads KE/IE 0.18 unscaled (README, known limits), so it warns at every mass scale > 1; the push
    balanced in force and moment (the default) reads 0.037.

    Quasi-static damping (``config.quasi_static_damping`` = a, 0 = off): mass scaling slows a scaled body's
    vibration modes by sqrt(s) to periods of a few output frames, so a body pushed by a force (or loaded next to a
    finger) rings instead of following its load.  As in explicit quasi-static analyses by dynamic relaxation (FLAC's
    and PFC's local damping, Cundall 1987), the materials the quasi-static check measures get local non-viscous
    damping (:func:`tasks.physics.mpm.kernels.local_damping`: the net force on a particle becomes F - a |F| sign(v),
    per component) in every frame the caller declares quasi-static (``step_frame(quasi_static=True)``) of a
    mass-scaled run.  It removes a fixed fraction of the vibration energy per cycle at any frequency and vanishes at
    equilibrium (a block pushed by a constant force settles on its static compression).  It is not a cure for a
    load that rises as fast as the scaled body's slowest mode (measured in the squeezes: the response then lags, see
    ``conf/mpm/default.yaml``): there only less mass scaling helps.  Released material, fluids and every frame after
    a rupture (``quasi_static=False``) keep their inertia undamped; an unscaled run is never damped.
    ``FrameStats.local_damping`` is the coefficient a the measured materials had in the frame.

    Energy guard (``config.energy_guard_tolerance``): after every frame the total energy E = kinetic + internal +
    gravitational (-m_phys g . x) is compared with its value at the reference frame (construction, or the end of the
    first frame after a state setter) plus the work the boundary put in since (per frame, the positive part of the
    work of the Dirichlet nodes, impulse . new velocity = m (v_bc - v*) . v_bc per node and substep, and of the force
    patches, impulse . node velocity).  Walls, floor, friction, plasticity and viscosity only remove energy, and
    gravity only exchanges it with the potential term, so growth beyond tolerance x energy scale (see
    :class:`EnergyBudget`) is a numerical instability: :class:`SimulationError` naming object, frame, time and the
    materials whose energy grew.
    """

    def __init__(
        self,
        positions: np.ndarray,
        volumes: Union[np.ndarray, float],
        materials: Union[Material, Sequence[Material]],
        material_ids: Optional[np.ndarray] = None,
        velocities: Optional[np.ndarray] = None,
        config: Any = None,
        tracers: Optional[np.ndarray] = None,
        tracer_anchors: Optional[np.ndarray] = None,
        device: Optional[str] = None,
        n_fingers: int = 5,
        label: str = "",
        load: Optional[QuasiStaticLoad] = None,
        membrane_normals: Optional[np.ndarray] = None,
        membrane_fibres: Optional[np.ndarray] = None,
    ) -> None:
        self.cfg: MPMConfig = mpm_config_from(config)
        self.label = str(label)
        self.load = load
        self.device = resolve_device(device or self.cfg.device)
        if self.cfg.debug:
            wp.set_module_options({"mode": "debug"}, K)
        self.materials: list[Material] = [materials] if isinstance(materials, Material) else list(materials)
        x = np.ascontiguousarray(np.asarray(positions, dtype=np.float32).reshape(-1, 3))
        n = x.shape[0]
        if n == 0:
            raise ValueError("MPMSolver needs at least one particle")
        if not np.all(np.isfinite(x)):
            raise SimulationError("initial particle positions contain NaN/inf")
        self.n_particles = n
        vol = np.broadcast_to(np.asarray(volumes, dtype=np.float32), (n,)).copy()
        if not np.all(vol > 0):
            raise ValueError("particle volumes must be > 0")
        mid = np.zeros(n, np.int32) if material_ids is None else np.asarray(material_ids, np.int32).reshape(n)
        if mid.min() < 0 or mid.max() >= len(self.materials):
            raise ValueError(f"material_ids must be in [0, {len(self.materials)})")
        v = np.zeros_like(x) if velocities is None else np.asarray(velocities, np.float32).reshape(n, 3)
        if not np.all(np.isfinite(v)):  # stability suite guard: bad input is refused, not reported as a blow-up
            raise SimulationError(f"initial particle velocities contain NaN/inf ({int((~np.isfinite(v)).any(1).sum())} "
                                  "particles): the caller's input is corrupt")
        normals = membrane_normals_checked(membrane_normals, n)
        self._membrane_rows = np.zeros(n, bool) if normals is None else normals.any(axis=1)
        self._check_membranes(mid)
        self._mid_host = mid
        self._warned_quasi_static = False
        self._loaded_frames = 0  # consecutive frames in which the boundary loaded the material (quasi-static check)
        self._contact: Optional[dict] = None  # the open contact of the quasi-static check: its frames, sums of KE, IE (J)
        self.quasi_static_contacts: list[dict] = []  # judged contacts: first and last checked frame, KE/IE (class doc)
        self._damping = np.zeros(len(self.materials))  # local damping coefficient per material (quasi-static damping)
        self._preload_damping = 0.0  # local damping of every material while the body settles (preload_gravity)
        self._tracer_F0_inv: Optional[np.ndarray] = None  # (T, 3, 3) the tracers' F after a preload, inverted
        present = sorted(set(int(i) for i in np.unique(mid)))
        self._present = present
        codes_present = {self.materials[i].code for i in present}
        self.n_fingers = int(n_fingers)

        # ---------------- grid geometry
        cfg = self.cfg
        tr = None if tracers is None else np.asarray(tracers, np.float32).reshape(-1, 3)
        pts = x if tr is None or len(tr) == 0 else np.concatenate([x, tr], axis=0)
        bb_lo, bb_hi = pts.min(axis=0).astype(np.float64), pts.max(axis=0).astype(np.float64)
        extent = float(np.max(bb_hi - bb_lo))
        if cfg.dx is not None:
            dx = float(cfg.dx)
        else:
            dx = max(extent, 1e-6) / cfg.cells_across
        self.floor_height: Optional[float] = None
        if cfg.floor:
            # default: the lowest particle (not tracer) rests on the floor: its centre (grid contact) or, with surface
            # contact, its surface (centre minus half its spacing, see Collider)
            low = x[:, 2] - (0.5 * np.cbrt(vol) if cfg.contact == "surface" else 0.0)
            self.floor_height = float(low.min() if cfg.floor_height is None else cfg.floor_height)
        if cfg.domain_lo is not None:
            box_lo = np.asarray(cfg.domain_lo, np.float64)
            box_hi = np.asarray(cfg.domain_hi, np.float64)
        else:
            box_lo = bb_lo - cfg.margin_cells * dx
            box_hi = bb_hi + cfg.margin_cells * dx
            if self.floor_height is not None:
                box_lo[2] = min(self.floor_height, bb_lo[2])
        pad = cfg.padding
        dims = np.ceil((box_hi - box_lo) / dx - 1e-9).astype(int) + 2 * pad + 1
        lo = box_lo - pad * dx
        self.dx = dx
        self.lo = lo
        self.dims = tuple(int(d) for d in dims)
        self.gi = K.GridInfo()
        self.gi.lo = wp.vec3(*lo.astype(np.float32))
        self.gi.dx = float(dx)
        self.gi.inv_dx = float(1.0 / dx)
        self.gi.safe_lo = wp.vec3(1.0, 1.0, 1.0)
        self.gi.safe_hi = wp.vec3(*(np.asarray(self.dims, np.float32) - 2.0))
        g0 = (x.astype(np.float64) - lo) / dx
        outside = np.any((g0 < pad - 0.5) | (g0 > np.asarray(self.dims) - pad - 0.5), axis=1)
        if np.any(outside):
            raise SimulationError(
                f"{int(outside.sum())} particles start inside the padding layer / outside the domain box "
                f"[{box_lo.round(4).tolist()}, {box_hi.round(4).tolist()}]: enlarge domain_lo/domain_hi"
            )
        self.floor_g = 0.0 if self.floor_height is None else float((self.floor_height - lo[2]) / dx)

        # ---------------- scaling and material table
        self.stiffness_scale = float(cfg.stiffness_scaling)
        # global / selective: fixed by the first step_frame's duration
        self._mass_scale_pending = cfg.mass_scaling in ("global", "selective")
        self.mass_scale = 1.0 if self._mass_scale_pending else mass_scale_for(self._present_materials(), dx, None, cfg)
        self.material_mass_scale = np.full(len(self.materials), self.mass_scale)
        d = self.device
        self.mat_model = wp.zeros(len(self.materials), dtype=wp.int32, device=d)
        self.mat_par = wp.zeros((len(self.materials), N_COLS), dtype=float, device=d)
        self.mat_table = K.MaterialTable()
        self.mat_table.model = self.mat_model
        self.mat_table.par = self.mat_par
        self.mat_field = wp.zeros(len(self.materials), dtype=wp.int32, device=d)
        self.mat_table.field = self.mat_field
        self._upload_materials()

        # ---------------- particle state (allocate only what the present models need)
        self.x = wp.array(x, dtype=wp.vec3, device=d)
        self.x_carry = wp.zeros(n, dtype=wp.vec3, device=d)  # the advection's round-off (kernels.round_off)
        self.v = wp.array(v, dtype=wp.vec3, device=d)
        self.C = wp.zeros(n, dtype=wp.mat33, device=d)
        self.F = wp.array(np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)), dtype=wp.mat33, device=d)
        self.F_carry = wp.zeros(n, dtype=wp.mat33, device=d)  # F_E's update's round-off (kernels.round_off)
        self.has_corotated = FIXED_COROTATED in codes_present
        self.has_plastic = any(m.code in PLASTIC_MODELS for m in self.materials)  # also one assigned mid-run
        qn = n if self.has_corotated or self.has_plastic else 1  # rotation / eigenbasis warm starts
        self.q = wp.array(np.tile(np.array([0, 0, 0, 1], np.float32), (qn, 1)), dtype=wp.quat, device=d)
        self.alpha = wp.zeros(n if self.has_plastic else 1, dtype=float, device=d)
        self.vol = wp.array(vol, dtype=float, device=d)
        self.mat_id = wp.array(mid, dtype=wp.int32, device=d)
        self.n_membrane = int(np.count_nonzero(self._membrane_rows))
        self.normal = wp.array(normals if self.n_membrane else np.zeros((1, 3), np.float32), dtype=wp.vec3, device=d)
        self.particles = K.Particles()
        fibres = membrane_fibres_checked(membrane_fibres, self._membrane_rows, x)
        self.reach = wp.array(contact_reach(vol, fibres), dtype=float, device=d)
        shared = fibres is not None and cfg.wall_stencil == "shared"
        self.wall_offset = wp.array(wall_offsets(x, normals, fibres) if shared else np.zeros(1, np.float32),
                                    dtype=float, device=d)
        for name in ("x", "v", "C", "F", "q", "alpha", "vol", "mat_id", "normal", "reach", "x_carry", "F_carry",
                     "wall_offset"):
            setattr(self.particles, name, getattr(self, name))
        fibres = fibres if cfg.wall_fibres else None
        self.n_fibres = 0 if fibres is None else len(fibres.rest)
        self._fibre_arrays = [] if fibres is None else [  # first, second, rest (a middle layer moves with the grid)
            wp.array(f, device=d) for f in (fibres.first, fibres.second, fibres.rest)]
        self._fibres = None if fibres is None else wp.launch(
            K.k_wall_fibres, dim=self.n_fibres, device=d, record_cmd=True,
            inputs=[self.x, self.vol, self.mat_id, *self._fibre_arrays])

        # ---------------- grid (two buffers: the fused G2P/P2G reads one and fills the other)
        self.grid_a = wp.zeros(self.dims, dtype=wp.vec4, device=d)
        self.grid_b = wp.zeros(self.dims, dtype=wp.vec4, device=d)
        self._bc_alloc = False
        dummy3 = wp.zeros((1, 1, 1), dtype=wp.vec4, device=d)
        # the released field's grid buffer paired with each body buffer (a one-node placeholder while unused)
        self._field2 = {id(self.grid_a): dummy3, id(self.grid_b): dummy3}
        self.two_fields = False
        self.field_cohesion = 0.0
        self._update_fields()
        self.bc_grid = K.DirichletGrid()
        self.bc_grid.target = self.bc_grid.reaction = dummy3
        self.bc_grid.proj = wp.zeros((1, 1, 1), dtype=wp.mat33, device=d)

        # ---------------- tracers
        self.n_tracers = 0 if tr is None else len(tr)
        self.tx = wp.array(tr if self.n_tracers else np.zeros((1, 3), np.float32), dtype=wp.vec3, device=d)
        self.tF = wp.array(np.tile(np.eye(3, dtype=np.float32), (max(self.n_tracers, 1), 1, 1)), dtype=wp.mat33,
                           device=d)
        self._bind_tracers(x, vol, tr, tracer_anchors)

        # ---------------- small buffers
        self.flags = wp.zeros(K.N_FLAGS, dtype=wp.int32, device=d)
        self._reset_flags()
        self.gstats = wp.zeros(1, dtype=float, device=d)
        big = 2**30
        self.bbox_init = wp.array(np.array([big, big, big, -big, -big, -big], np.int32), dtype=wp.int32, device=d)
        self.bbox = wp.zeros(6, dtype=wp.int32, device=d)
        self._last_box: Optional[tuple[np.ndarray, np.ndarray]] = None
        self.all_corotated = codes_present == {FIXED_COROTATED}
        # CPU: host views of the small per-substep buffers (zero-copy); CUDA: device ops + copies
        self._cpu = wp.get_device(d).is_cpu
        self._gstats_np = self.gstats.numpy() if self._cpu else None
        self._bbox_np = self.bbox.numpy() if self._cpu else None
        self._cmds: Optional[dict] = None
        self.sums = wp.zeros(6, dtype=wp.float64, device=d)
        self.ext = wp.zeros(3, dtype=float, device=d)
        self.ext_init = wp.array(np.array([np.inf, -np.inf, 0.0], np.float32), dtype=float, device=d)
        self.mat_energy = wp.zeros((len(self.materials), 3), dtype=wp.float64, device=d)
        self.boundary_work = wp.zeros(1, dtype=wp.float64, device=d)  # J, this frame (energy guard)
        self.col = K.Colliders()  # surface-contact colliders (count 0: none), see _upload_colliders
        self._col_version = 0  # bumped when self.col changes (the recorded launches re-read it)
        self._set_colliders([])
        self._set_pins(None)
        self._alloc_finger_arrays(self.n_fingers)
        # CPU threads of the fused G2P/P2G (mpm.threads): the particles are cut into CHUNKS_PER_THREAD x threads
        # chunks; chunk c > 0 scatters into its own P2G grid, error flags, stencil box and collider impulses
        # (``_shares``), summed in chunk order after every launch, whichever thread ran it
        self.threads = self._thread_count()
        self._shares: list[dict] = []
        self._pool: Optional[ThreadPoolExecutor] = None
        self._energy_ref: Optional[EnergyBudget] = None  # energy guard reference (see _check_energy)
        self._energy_initial = True  # the reference is the initial state (F = I, C = 0: no internal energy)

        self.time = 0.0
        self.frame = 0
        self.substep = 0
        self._vmax = float(np.max(np.linalg.norm(v, axis=1))) if n else 0.0
        self._times: list[tuple[int, float]] = []
        self.last_stats: Optional[FrameStats] = None

    # ------------------------------------------------------------------ setup helpers
    def _present_materials(self) -> list[Material]:
        return [self.materials[i] for i in self._present]

    def lowest_period(self) -> float:
        """Estimated period (s) of the slowest mode of the body as scaled (:func:`lowest_period` of the measured
        materials present, each with its own mass scale, the height from ``load``); inf without a load."""
        if self.load is None:
            return math.inf
        measured = self._quasi_static_materials()
        return max((lowest_period([self.materials[i]], self.load.height, self.stiffness_scale,
                                  float(self.material_mass_scale[i])) for i in self._present if measured[i]),
                   default=math.inf)

    def _upload_materials(self) -> None:
        """Material table with the per-material mass scales, wave speeds, and where gravity acts: uniform scale s
        among the materials present -> the grid adds g / s (``self.gravity``); mixed -> the P2G adds dt m_phys g."""
        models, params = pack_table(self.materials, self.stiffness_scale, self.material_mass_scale, self._damping)
        self._mat_params = params
        self.mat_model.assign(models)
        self.mat_par.assign(params)
        present = self._present
        self.wave_speeds = {self.materials[i].name: self.materials[i].p_wave_speed(
            self.stiffness_scale, float(self.material_mass_scale[i])) for i in present}  # m/s
        self.c_max = max(self.wave_speeds.values())
        self.gravity = [g / self.mass_scale for g in self.cfg.gravity]
        scales = {float(self.material_mass_scale[i]) for i in present}
        self._weight_in_p2g = len(scales) > 1
        uniform = max(scales)
        self._grid_gravity = [0.0, 0.0, 0.0] if self._weight_in_p2g else [g / uniform for g in self.cfg.gravity]
        self._cmds = None  # the recorded launches hold the gravity
        self.dt_visc = math.inf
        for i in present:
            m = self.materials[i]
            if m.model == "fluid" and m.viscosity > 0:
                rho = m.density * float(self.material_mass_scale[i])
                self.dt_visc = min(self.dt_visc, rho * self.dx ** 2 / (6.0 * m.viscosity))

    def released_field_materials(self) -> np.ndarray:
        """(material,) bool: the materials of the released velocity field (``mpm.multi_field`` under
        ``mpm.mass_scaling=selective``): those that keep their physical inertia while the body is scaled
        (``Material.is_mass_scaled`` False: released material, fluids).  Under the other modes every material has
        the same scale and one field is kept."""
        on = self.cfg.multi_field and self.cfg.mass_scaling == "selective"
        return np.array([on and not m.is_mass_scaled for m in self.materials])

    def _update_fields(self) -> None:
        """Velocity field of each material (kernels: ``MaterialTable.field``).  Two fields only while both the body
        (field 0) and the released field (field 1) have particles: otherwise everything is field 0 and the second
        grid is neither allocated nor launched (the single-field path, unchanged).  The second pair of grid buffers
        is allocated (zeroed) when the second field first appears."""
        released = self.released_field_materials()
        present = np.zeros(len(self.materials), bool)
        present[self._present] = True
        two = bool((released & present).any() and (~released & present).any())
        field = (released & two).astype(np.int32)
        # N/kg: the cohesion of the released field's contact with the body (kernels.k_field_contact), the largest
        # Material.cohesion / (2 rho dx) of its materials present
        cohesion = max([m.cohesion / (2.0 * m.density * self.dx)
                        for m, on in zip(self.materials, released & present & two) if on], default=0.0)
        if cohesion != self.field_cohesion:
            self._cmds = None  # the recorded launches hold the grid conditions
        self.field_cohesion = cohesion
        self.mat_field.assign(field)
        if two and self._field2[id(self.grid_a)].shape != self.grid_a.shape:
            self._field2 = {id(g): wp.zeros(self.dims, dtype=wp.vec4, device=self.device)
                            for g in (self.grid_a, self.grid_b)}
        if two != self.two_fields:
            self._cmds = None  # the recorded launches hold the grid buffers
            for g in self._field2.values():
                g.zero_()
        self.two_fields = two

    def stable_dt_per_material(self) -> dict[str, float]:
        """The stable substep (s) each material of the table needs alone, present or not yet (a ruptured skin, a
        released interior): C dx / c_p with its own (un)scaled P-wave speed, and for a viscous fluid also
        rho dx^2 / (6 mu) (explicit viscosity).  The solver steps with the smallest over the materials present."""
        out = {}
        for m, scale in zip(self.materials, self.material_mass_scale.tolist()):
            dt = self.cfg.courant * self.dx / m.p_wave_speed(self.stiffness_scale, scale)
            if m.model == "fluid" and m.viscosity > 0:
                dt = min(dt, m.density * scale * self.dx ** 2 / (6.0 * m.viscosity))
            out[m.name] = dt
        return out

    def _alloc_finger_arrays(self, k: int) -> None:
        d = self.device
        self.n_fingers = k
        self.finger_react = wp.zeros(k, dtype=wp.vec3, device=d)
        self.finger_applied = wp.zeros(k, dtype=wp.vec3, device=d)
        self.col.impulse = self.finger_react  # the colliders' impulses are the fingers' reactions
        self._col_version += 1

    def _ensure_bc_arrays(self) -> None:
        if not self._bc_alloc:
            d = self.device
            self.bc_grid.target = wp.zeros(self.dims, dtype=wp.vec4, device=d)
            self.bc_grid.proj = wp.zeros(self.dims, dtype=wp.mat33, device=d)
            self.bc_grid.reaction = wp.zeros(self.dims, dtype=wp.vec4, device=d)
            self._bc_alloc = True
            self._cmds = None  # recorded grid launches reference the boundary arrays

    def _reset_flags(self, flags: Optional[wp.array] = None) -> None:
        f = np.zeros(K.N_FLAGS, np.int32)
        f[4:8] = K.NO_SUBSTEP
        f[8:12] = -1
        (self.flags if flags is None else flags).assign(f)

    # ------------------------------------------------------------------ public geometry helpers
    def node_position(self, idx: np.ndarray) -> np.ndarray:
        """World positions (m) of integer grid indices (M, 3)."""
        return self.lo + np.asarray(idx, np.float64) * self.dx

    def project_points(self, positions: np.ndarray, velocities: np.ndarray, finger_ids: Optional[np.ndarray] = None,
                       min_weight: float = 0.0) -> DirichletNodes:
        """Project constrained points onto the grid nodes within their B-spline support (numpy).

        Returns the touched nodes with the weight-averaged target velocity and the finger with the largest weight
        share; the solver does the same projection on the device every substep for :class:`DirichletPoints`.
        """
        P = np.asarray(positions, np.float64).reshape(-1, 3)
        V = np.asarray(velocities, np.float64).reshape(-1, 3)
        fid = np.zeros(len(P), np.int64) if finger_ids is None else np.asarray(finger_ids, np.int64)
        g = (P - self.lo) / self.dx
        base, w = bspline_stencil(g)
        off = np.stack(np.meshgrid(range(3), range(3), range(3), indexing="ij"), -1).reshape(-1, 3)
        ww = w[:, 0, off[:, 0]] * w[:, 1, off[:, 1]] * w[:, 2, off[:, 2]]  # (P, 27)
        nodes = (base[:, None, :] + off[None]).reshape(-1, 3)
        ww = ww.reshape(-1)
        keep = ww > min_weight
        nodes, ww = nodes[keep], ww[keep]
        vv = np.repeat(V, 27, axis=0)[keep]
        ff = np.repeat(fid, 27)[keep]
        uniq, inv = np.unique(nodes, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        W = np.bincount(inv, weights=ww)
        vel = np.stack([np.bincount(inv, weights=ww * vv[:, c]) for c in range(3)], 1) / W[:, None]
        nf = int(ff.max()) + 1 if len(ff) else 1
        share = np.zeros((len(uniq), nf))
        np.add.at(share, (inv, ff), ww)
        return DirichletNodes(indices=uniq.astype(np.int32), velocities=vel.astype(np.float32),
                              finger_ids=share.argmax(axis=1).astype(np.int32))

    # ------------------------------------------------------------------ time step
    def courant_number(self, dt: float) -> float:
        return dt * self.c_max / self.dx

    def _stable_dt(self, vmax: float) -> float:
        cfg = self.cfg
        dt = cfg.courant * self.dx / self.c_max
        if vmax > 0:
            dt = min(dt, cfg.max_speed_cfl * self.dx / vmax)
        return min(dt, self.dt_visc)

    def _next_dt(self, remaining: float, vmax: float) -> float:
        cfg = self.cfg
        if cfg.dt is not None:
            dt = float(cfg.dt)
            cn = self.courant_number(dt)
            if cn > cfg.courant_limit:
                raise SimulationError(
                    f"Courant number {_num(cn)} > limit {_num(cfg.courant_limit)}: lower dt or E "
                    f"(forced dt={dt:.3g} s, c_p={self.c_max:.4g} m/s, dx={self.dx:.4g} m; "
                    f"at substep {self.substep}, t={self.time:.6g} s)"
                )
            adv = vmax * dt / self.dx
            if adv > cfg.courant_limit:
                raise SimulationError(
                    f"advective Courant number {_num(adv)} > limit {_num(cfg.courant_limit)}: lower dt "
                    f"(max speed {vmax:.4g} m/s at substep {self.substep}, t={self.time:.6g} s)"
                )
        else:
            dt = self._stable_dt(vmax)
        if dt >= remaining * (1.0 - 1e-6):
            return remaining
        n_left = math.ceil(remaining / dt - 1e-6)
        return remaining / n_left

    def _resolve_auto_mass_scale(self, frame_dt: float) -> None:
        if not self._mass_scale_pending:
            return
        self._mass_scale_pending = False
        self.mass_scale = mass_scale_for(self._present_materials(), self.dx, frame_dt, self.cfg, self.load)
        self.material_mass_scale = material_mass_scales(self.materials, self._present_materials(), self.dx, frame_dt,
                                                        self.cfg, self.load)
        self._upload_materials()

    # ------------------------------------------------------------------ boundary upload
    def _upload_dirichlet(self, spec: BoundarySpec) -> list[dict]:
        if spec is None:
            return []
        items = [spec] if isinstance(spec, (DirichletPoints, DirichletNodes)) else list(spec)
        out = []
        for it in items:
            if isinstance(it, DirichletNodes):
                idx = np.asarray(it.indices, np.float64).reshape(-1, 3)
                # the outermost node layer belongs to the domain walls and has no full stencil: skipped
                keep = np.all((idx >= 1) & (idx <= np.asarray(self.dims) - 2), axis=1)
                it = DirichletNodes(idx[keep], np.broadcast_to(np.asarray(it.velocities, np.float32).reshape(-1, 3),
                                                               (len(idx), 3))[keep],
                                    None if it.finger_ids is None else np.asarray(it.finger_ids).reshape(-1)[keep],
                                    None if it.normals is None else np.broadcast_to(
                                        np.asarray(it.normals, np.float32).reshape(-1, 3), (len(idx), 3))[keep])
                idx = idx[keep]
                # the point sits on its node, moved 1e-3 dx towards the grid centre: in float32 a node of layer 1
                # would otherwise round to grid coordinate 0.99999976, outside the band [1, dims - 2] every point
                # must lie in (the stencil, base floor(g - 0.5), is the same either way)
                centre = 0.5 * (np.asarray(self.dims, np.float64) - 1.0)
                pos = self.lo + (idx + 1e-3 * np.sign(centre - idx)) * self.dx
                # a point on a node has weight 0.75^3 = 0.42 there and <= 0.75^2 0.125 = 0.07 on the other stencil
                # nodes: min_weight 0.2 keeps exactly that node
                it = DirichletPoints(pos, it.velocities, it.finger_ids, it.normals, min_weight=0.2, advect=False)
            pos = np.asarray(it.positions, np.float32).reshape(-1, 3)
            m = len(pos)
            if m == 0:
                continue
            vel = np.broadcast_to(np.asarray(it.velocities, np.float32).reshape(-1, 3), (m, 3))
            fid = np.zeros(m, np.int32) if it.finger_ids is None else np.asarray(it.finger_ids, np.int32).reshape(m)
            nrm = np.zeros((m, 3), np.float32) if it.normals is None else np.broadcast_to(
                np.asarray(it.normals, np.float32).reshape(-1, 3), (m, 3))
            if nrm.any():
                ln = np.linalg.norm(nrm, axis=1, keepdims=True)
                nrm = np.where(ln > 0, nrm / np.maximum(ln, 1e-30), 0.0).astype(np.float32)
            if fid.min() < 0:
                raise ValueError("finger ids must be >= 0")
            bad = ~(np.isfinite(pos).all(1) & np.isfinite(vel).all(1) & np.isfinite(nrm).all(1))
            if bad.any():  # stability suite guard: a NaN target is an input error, not a numerical blow-up
                raise ValueError(
                    f"Dirichlet boundary input contains NaN/inf positions, velocities or normals: {int(bad.sum())} of "
                    f"{m} points (fingers {sorted(set(fid[bad].tolist()))}) at frame {self.frame}, t={self.time:.6g} s; "
                    "the finger field / targets passed to step_frame are corrupt")
            self._grow_fingers(int(fid.max()) + 1)
            d = self.device
            pts = K.DirichletPointSet()
            pts.x = wp.array(np.ascontiguousarray(pos), dtype=wp.vec3, device=d)
            pts.v = wp.array(np.ascontiguousarray(vel), dtype=wp.vec3, device=d)
            pts.n = wp.array(np.ascontiguousarray(nrm), dtype=wp.vec3, device=d)
            pts.finger = wp.array(fid, dtype=wp.int32, device=d)
            pts.min_w = float(it.min_weight)
            pts.advect = int(bool(it.advect))
            out.append(dict(pts=pts, count=m, speed=float(np.linalg.norm(vel, axis=1).max())))
        if out:
            self._ensure_bc_arrays()
        return out

    def _upload_forces(self, spec: Optional[Union[ForcePatch, Sequence[ForcePatch]]]) -> list[dict]:
        if spec is None:
            return []
        items = [spec] if isinstance(spec, ForcePatch) else list(spec)
        out = []
        for it in items:
            pos = np.asarray(it.positions, np.float32).reshape(-1, 3)
            fid = np.asarray(it.finger_ids, np.int32).reshape(-1)
            forces = np.asarray(it.forces, np.float32).reshape(-1, 3)
            if len(pos) == 0:
                continue
            if fid.max() >= len(forces) or fid.min() < 0:
                raise ValueError("ForcePatch.finger_ids must index ForcePatch.forces")
            if not (np.isfinite(pos).all() and np.isfinite(forces).all()):  # stability suite guard (input error)
                raise ValueError(f"ForcePatch input contains NaN/inf positions or forces at frame {self.frame}, "
                                 f"t={self.time:.6g} s; the finger forces passed to step_frame are corrupt")
            self._grow_fingers(len(forces))
            d = self.device
            ff = np.zeros((self.n_fingers, 3), np.float32)
            ff[: len(forces)] = forces
            x, follow = wp.array(pos, dtype=wp.vec3, device=d), it.tracers is not None
            if follow and it.particles is not None:
                raise ValueError("ForcePatch: give tracers or particles, not both")
            if follow:  # every tracer is a point; those not in the patch have finger -1 (no push)
                x, fid = self.tx, self._points_on(it.tracers, fid, self.n_tracers, len(self.tx), "tracers")
            elif it.particles is not None:  # every particle is a point, at its own position
                x, fid = self.x, self._points_on(it.particles, fid, self.n_particles, self.n_particles, "particles")
            out.append(dict(x=x, f=wp.array(fid, dtype=wp.int32, device=d), F=wp.array(ff, dtype=wp.vec3, device=d),
                            w=wp.zeros(len(ff), dtype=float, device=d), count=len(fid), follow=follow))
        return out

    @staticmethod
    def _points_on(index: np.ndarray, fid: np.ndarray, n: int, size: int, name: str) -> np.ndarray:
        """The finger id per entry of a solver array of ``size`` entries (-1: not pushed) for a patch whose points
        are its entries ``index`` (< n, one per point of finger ``fid``)."""
        index = np.asarray(index, np.int64).reshape(-1)
        if len(index) != len(fid) or index.min() < 0 or index.max() >= n:
            raise ValueError(f"ForcePatch.{name} must give one index (< {n}) per point")
        full = np.full(size, -1, np.int32)
        full[index] = fid
        return full

    def _set_colliders(self, rows: list[tuple[int, np.ndarray, np.ndarray, float, np.ndarray, float, int, int]]) -> None:
        """Upload collider rows (kind code, a, b, radius, velocity, friction, finger id, field) into ``self.col``."""
        d, n = self.device, len(rows)
        cols = list(zip(*rows)) if n else [[0], [np.zeros(3)], [np.zeros(3)], [0.0], [np.zeros(3)], [0.0], [-1], [-1]]
        self.col.count = n
        self.col.kind = wp.array(np.asarray(cols[0], np.int32), dtype=wp.int32, device=d)
        for name, vals in (("a", cols[1]), ("b", cols[2]), ("vel", cols[4])):
            setattr(self.col, name, wp.array(np.asarray(vals, np.float32).reshape(-1, 3), dtype=wp.vec3, device=d))
        self.col.radius = wp.array(np.asarray(cols[3], np.float32), dtype=float, device=d)
        self.col.mu = wp.array(np.asarray(cols[5], np.float32), dtype=float, device=d)
        self.col.finger = wp.array(np.asarray(cols[6], np.int32), dtype=wp.int32, device=d)
        self.col.field = wp.array(np.asarray(cols[7], np.int32), dtype=wp.int32, device=d)
        self.col.fields = int(np.bitwise_or.reduce([3 if f < 0 else 1 << f for f in cols[7]])) if n else 0
        self.col.work = self.boundary_work
        self._col_version += 1

    def _set_pins(self, pins: Optional[ParticlePins], frame_dt: float = 0.0) -> int:
        """Upload the frame's :class:`ParticlePins` into ``self.col`` (none: ``pins = 0``); returns their number.
        Each pin's path starts at its particle's surface point now and ends at its target at the frame's end,
        ``frame_dt`` (s) later."""
        d, col = self.device, self.col
        n = 0 if pins is None else len(np.asarray(pins.indices).reshape(-1))
        self._pin_speed = 0.0
        if n == 0:
            if col.pins or col.pin_slot is None:
                col.pins, col.pin_slip = 0, 0
                col.pin_slot = wp.full(1, -1, dtype=wp.int32, device=d)
                for name in ("pin_y", "pin_v", "pin_n"):
                    setattr(col, name, wp.zeros(1, dtype=wp.vec3, device=d))
                col.pin_arm = wp.zeros(1, dtype=float, device=d)
                col.pin_finger = wp.full(1, -1, dtype=wp.int32, device=d)
                self._col_version += 1
            return 0
        idx = np.asarray(pins.indices, np.int64).reshape(-1)
        target = np.asarray(pins.targets, np.float64).reshape(-1, 3)
        normal = np.asarray(pins.normals, np.float64).reshape(-1, 3)
        fid = (np.full(n, -1, np.int32) if pins.finger_ids is None
               else np.asarray(pins.finger_ids, np.int32).reshape(-1))
        arm = np.ones(n) if pins.arms is None else np.asarray(pins.arms, np.float64).reshape(-1)
        if not (len(target) == len(normal) == len(fid) == len(arm) == n):
            raise ValueError(f"ParticlePins: {n} indices but {len(target)} targets, {len(normal)} normals, "
                             f"{len(fid)} finger ids and {len(arm)} arms")
        if not ((arm >= 0) & (arm <= 1)).all():
            raise ValueError("ParticlePins: arms must lie in [0, 1] (0: the particle's centre, 1: its surface)")
        if idx.min() < 0 or idx.max() >= self.n_particles or len(np.unique(idx)) != n:
            raise ValueError(f"ParticlePins: indices must be distinct particles in [0, {self.n_particles})")
        length = np.linalg.norm(normal, axis=1)
        if not (np.isfinite(target).all() and np.isfinite(normal).all() and (length > 0).all()):
            raise ValueError(f"ParticlePins at frame {self.frame}: NaN/inf targets or zero normals")
        normal = normal / length[:, None]
        start = self.surface_points(idx, normal, arm)
        velocity = (target - start) / frame_dt
        slot = np.full(self.n_particles, -1, np.int32)
        slot[idx] = np.arange(n, dtype=np.int32)
        col.pins, col.pin_slip = n, int(bool(pins.slip))
        col.pin_slot = wp.array(slot, dtype=wp.int32, device=d)
        col.pin_y = wp.array(start.astype(np.float32), dtype=wp.vec3, device=d)
        col.pin_v = wp.array(velocity.astype(np.float32), dtype=wp.vec3, device=d)
        col.pin_n = wp.array(normal.astype(np.float32), dtype=wp.vec3, device=d)
        col.pin_arm = wp.array(arm.astype(np.float32), dtype=float, device=d)
        col.pin_finger = wp.array(fid, dtype=wp.int32, device=d)
        self._grow_fingers(int(fid.max()) + 1)
        self._pin_speed = float(np.linalg.norm(velocity, axis=1).max())
        self._col_version += 1
        return n

    def _pin_finger_of(self, particle: int) -> Optional[int]:
        """The finger id of ``particle``'s pin in the frame's uploaded :class:`ParticlePins` (None: not pinned)."""
        if not self.col.pins:
            return None
        slot = int(self.col.pin_slot.numpy()[particle])
        return None if slot < 0 else int(self.col.pin_finger.numpy()[slot])

    def surface_points(self, indices: np.ndarray, normals: np.ndarray, arms: Optional[np.ndarray] = None
                       ) -> np.ndarray:
        """(P, 3) m: the surface points of particles ``indices`` along the unit ``normals`` (P, 3), centre + r n
        with r = arm radius |F^T n| (radius half the particle's undeformed spacing; ``arms`` (P,) default 1, 0 the
        centre: :class:`ParticlePins`), as the contact and pin kernels measure them."""
        idx = np.asarray(indices, np.int64).reshape(-1)
        F = self.deformation_gradients()[idx].astype(np.float64)
        radius = 0.5 * np.cbrt(self.volumes()[idx].astype(np.float64))
        if arms is not None:
            radius = radius * np.asarray(arms, np.float64).reshape(-1)
        reach = radius * np.linalg.norm(np.einsum("pji,pj->pi", F, normals), axis=1)
        return self.positions()[idx].astype(np.float64) + reach[:, None] * normals

    def tracer_anchor_particles(self) -> np.ndarray:
        """(T, TRACER_ANCHORS) the particles each tracer is embedded in, nearest first."""
        return self._anchor[0].numpy().copy() if self._anchor is not None else np.zeros((0, TRACER_ANCHORS), np.int32)

    def table_plane_fields(self) -> Optional[int]:
        """Which particles the table (floor) acts on as a plane collider, where their surface touches it: every
        particle under ``mpm.contact = surface`` (-1), the released field's (1) under ``grid`` contact with two
        velocity fields (the body's field keeps the floor as a grid condition, :func:`tasks.physics.mpm.kernels.
        fixed_boundaries`), or none (None: no table, or one field under ``grid`` contact)."""
        if self.floor_height is None:
            return None
        if self.cfg.contact == "surface":
            return -1
        return 1 if self.two_fields else None

    def on_table_plane(self) -> np.ndarray:
        """(particle,) bool: the particles the table acts on as a plane collider (:meth:`table_plane_fields`)."""
        which = self.table_plane_fields()
        if which is None:
            return np.zeros(self.n_particles, bool)
        if which < 0:
            return np.ones(self.n_particles, bool)
        return self.mat_field.numpy()[self.material_ids()] == which

    def _upload_colliders(self, spec: Optional[Union[Collider, Sequence[Collider]]]) -> int:
        """The frame's colliders plus the table as a plane collider (:meth:`table_plane_fields`: for every particle
        under ``mpm.contact = surface``, for the released field under ``grid`` contact; friction ``floor_friction``,
        no slip if ``floor_sticky``); returns their number."""
        items = [] if spec is None else ([spec] if isinstance(spec, Collider) else list(spec))
        table = self.table_plane_fields()
        if table is not None:
            mu = -1.0 if self.cfg.floor_sticky else float(self.cfg.floor_friction)
            items = [Collider("plane", (0.0, 0.0, self.floor_height), (0.0, 0.0, 1.0), friction=mu,
                              field=table)] + items
        rows = []
        for i, c in enumerate(items):
            a, b, vel = (np.asarray(v, np.float64).reshape(3) for v in (c.a, c.b, c.velocity))
            if c.kind not in Collider.KINDS:
                raise ValueError(f"collider {i}: kind '{c.kind}' is not one of {', '.join(Collider.KINDS)}")
            if not (np.isfinite(a).all() and np.isfinite(b).all() and np.isfinite(vel).all()
                    and math.isfinite(c.radius) and math.isfinite(c.friction)):
                raise ValueError(f"collider {i} ({c.kind}) has NaN/inf position, velocity, radius or friction at "
                                 f"frame {self.frame}; the colliders passed to step_frame are corrupt")
            if c.kind == "plane":
                if not np.linalg.norm(b) > 0:
                    raise ValueError(f"collider {i} (plane): normal b must be non-zero")
                b = b / np.linalg.norm(b)
            elif not c.radius > 0:
                raise ValueError(f"collider {i} ({c.kind}): radius must be > 0 m (got {c.radius})")
            if c.field > 1:
                raise ValueError(f"collider {i} ({c.kind}): field {c.field} is not a velocity field; use 0 (the body), "
                                 f"1 (the released field) or -1 (every particle)")
            rows.append((Collider.KINDS.index(c.kind), a, b, float(c.radius), vel, float(c.friction),
                         int(c.finger_id), int(c.field)))
        self._grow_fingers(max([r[6] + 1 for r in rows], default=0))
        self._collider_speed = max([float(np.linalg.norm(r[4])) for r in rows], default=0.0)
        if rows or self.col.count:
            self._set_colliders(rows)
        return len(rows)

    def _grow_fingers(self, k: int) -> None:
        if k > self.n_fingers:
            self._alloc_finger_arrays(k)

    # ------------------------------------------------------------------ stepping
    def _step_params(self, dt_g2p: float, dt_p2g: float, restart: bool = False) -> K.StepParams:
        sp = K.StepParams()
        sp.dt_g2p = float(dt_g2p)
        sp.dt_p2g = float(dt_p2g)
        sp.substep = int(self.substep)
        sp.j_min = float(self.cfg.j_min)
        sp.j_max = float(self.cfg.j_max)
        sp.polar_iters = int(self.cfg.polar_restart_iterations if restart else self.cfg.polar_iterations)
        sp.polar_tol = float(self.cfg.polar_tol)
        sp.polar_newton = int(restart or self.cfg.polar_method == "newton")
        sp.weight_g = wp.vec3(*self.cfg.gravity)
        sp.weight_in_p2g = int(self._weight_in_p2g)
        sp.wall_k = float(self.cfg.wall_normal_stiffness)
        return sp

    def _grid_conditions(self, released: bool = False) -> K.GridConditions:
        """Gravity (m/s^2: g / s under a uniform mass scale s, else zero: the P2G adds the weight), domain walls
        and floor of the grid update of the body's field, or with ``released`` of the released field (no floor:
        the table acts on its particles as a plane collider, :meth:`table_plane_fields`; and the cohesion of its
        contact with the body, :attr:`field_cohesion`)."""
        cfg = self.cfg
        gc = K.GridConditions()
        gc.gravity = wp.vec3(*self._grid_gravity)
        gc.pad = int(cfg.padding)
        gc.wall_sticky = int(cfg.wall_sticky)
        # surface contact, or the released field: the table is a plane collider
        gc.floor_on = int(self.floor_height is not None and cfg.contact == "grid" and not released)
        gc.floor_g = float(self.floor_g)
        gc.floor_mu = float(cfg.floor_friction)
        gc.floor_sticky = int(cfg.floor_sticky)
        gc.field_cohesion = self.field_cohesion if released else 0.0
        return gc

    def _recorded(self) -> dict:
        """Recorded launches of the per-substep kernels (fused G2P/P2G, grid update, field contact; one set per grid-buffer
        parity): replaying them avoids re-packing the arguments per launch (a ``wp.launch`` costs ~0.1-0.3 ms of
        Python, which dominates small scenes).  A replay updates only the per-launch struct of each kernel: ``sp``
        (:class:`K.StepParams`) and ``gs`` (:class:`K.GridStep`).  The boundary points' launches are recorded per
        frame (:meth:`_record_bc`)."""
        if self._cmds is not None:
            return self._cmds
        d = self.device
        cmds: dict = {"sp": self._step_params(0.0, 0.0), "gs": K.GridStep()}
        fused_kernel = K.FUSED[self.all_corotated, self.two_fields]
        conditions = self._grid_conditions()
        conditions_free = self._grid_conditions(released=True)
        cmds["gs2"] = K.GridStep()  # the released field's grid update: no Dirichlet nodes
        shares = self._thread_shares()
        # one StepParams per chunk: a recorded launch holds its struct argument by reference
        cmds["sp_threads"] = [cmds["sp"]] + [self._step_params(0.0, 0.0) for _ in shares]
        for sp, (first, _) in zip(cmds["sp_threads"], self._ranges):
            sp.first = first
        for cur, other in ((self.grid_a, self.grid_b), (self.grid_b, self.grid_a)):
            cur2, other2 = self._field2[id(cur)], self._field2[id(other)]
            fused = [wp.launch(fused_kernel, dim=self.n_particles if not shares else self._ranges[0][1], device=d,
                               record_cmd=True, inputs=[self.gi, cmds["sp"], self.particles, self.mat_table, cur,
                                                        other, cur2, other2, self.flags, self.bbox, self.col])]
            accumulate = []
            for sh, sp, (_, count) in zip(shares, cmds["sp_threads"][1:], self._ranges[1:]):
                fused.append(wp.launch(fused_kernel, dim=count, device=d, record_cmd=True, inputs=[
                    self.gi, sp, self.particles, self.mat_table, cur, sh["grid"], cur2, sh["grid2"],
                    sh["flags"], sh["bbox"], sh["col"]]))
                accumulate.append([wp.launch(K.k_grid_accumulate, dim=(1, 1, 1), device=d, record_cmd=True,
                                             inputs=[wp.vec3i(0, 0, 0), out, part])
                                   for out, part in ((other, sh["grid"]), (other2, sh["grid2"]))[:1 + self.two_fields]])
            grid = wp.launch(K.k_grid_update, dim=(1, 1, 1), device=d, record_cmd=True, inputs=[
                cmds["gs"], conditions, cur, other, self.bc_grid, self.gstats, self.boundary_work])
            fields = None
            if self.two_fields:
                fields = (wp.launch(K.k_grid_update, dim=(1, 1, 1), device=d, record_cmd=True, inputs=[
                    cmds["gs2"], conditions_free, cur2, other2, self.bc_grid, self.gstats, self.boundary_work]),
                    wp.launch(K.k_field_contact, dim=(1, 1, 1), device=d, record_cmd=True, inputs=[
                        cmds["gs"], conditions, conditions_free, cur, cur2]))
            cmds[id(cur)] = (fused, grid, fields, accumulate)
        cmds["col_version"] = {id(self.grid_a): self._col_version, id(self.grid_b): self._col_version}
        self._cmds = cmds
        return cmds

    def _thread_count(self) -> int:
        """Threads of the fused kernel: ``mpm.threads`` on the CPU (1 on CUDA), at most one per
        ``MIN_PARTICLES_PER_THREAD`` particles (below, a thread's hand-over costs more than its share saves)."""
        if not self._cpu:
            return 1
        return max(1, min(int(self.cfg.threads), self.n_particles // MIN_PARTICLES_PER_THREAD))

    def _thread_shares(self) -> list[dict]:
        """The buffers of chunks 1.. of the fused kernel (allocated once, the released field's grid when it first
        appears) and the chunks' particle ranges ``_ranges`` [(first, count)] (contiguous, equal).  More chunks than
        threads: a thread that another process slows down leaves its next chunk to the others (each substep waits
        for the last chunk), while every chunk keeps its own buffers, so the sums do not depend on which thread ran
        which chunk (the run is reproducible)."""
        t = self.threads * CHUNKS_PER_THREAD if self.threads > 1 else 1
        bounds = np.linspace(0, self.n_particles, t + 1).round().astype(int)
        self._ranges = [(int(a), int(b - a)) for a, b in zip(bounds[:-1], bounds[1:])]
        d = self.device
        while len(self._shares) < t - 1:
            sh = dict(grid=wp.zeros(self.dims, dtype=wp.vec4, device=d), grid2=wp.zeros((1, 1, 1), dtype=wp.vec4,
                                                                                         device=d),
                      flags=wp.zeros(K.N_FLAGS, dtype=wp.int32, device=d), bbox=wp.clone(self.bbox_init),
                      react=wp.zeros(self.n_fingers, dtype=wp.vec3, device=d),
                      work=wp.zeros(1, dtype=wp.float64, device=d), col=K.Colliders())
            self._reset_flags(sh["flags"])
            sh["bbox_np"] = sh["bbox"].numpy()
            self._shares.append(sh)
        for sh in self._shares:
            if self.two_fields and sh["grid2"].shape != self.grid_a.shape:
                sh["grid2"] = wp.zeros(self.dims, dtype=wp.vec4, device=d)
            self._share_colliders(sh)
        if t > 1 and self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.threads - 1, thread_name_prefix="mpm")
        return self._shares

    def _share_colliders(self, sh: dict) -> None:
        """A thread's view of the colliders: the same ones, with its own impulse (N s per finger) and work (J)
        accumulators (summed into the fingers' reactions and the boundary work at the frame's end)."""
        if sh["react"].shape[0] != self.n_fingers:
            sh["react"] = wp.zeros(self.n_fingers, dtype=wp.vec3, device=self.device)
        for name in ("count", "fields", "kind", "a", "b", "radius", "vel", "mu", "finger", "field", "pins",
                     "pin_slip", "pin_slot", "pin_y", "pin_v", "pin_n", "pin_arm", "pin_finger"):
            setattr(sh["col"], name, getattr(self.col, name))
        sh["col"].impulse = sh["react"]
        sh["col"].work = sh["work"]

    def _gather_shares(self, accumulate: list) -> None:
        """After the threads' fused launches: add each thread's P2G grid into the shared one over the node box its
        particles touched (:func:`tasks.physics.mpm.kernels.k_grid_accumulate`) and merge its stencil box."""
        box = self._bbox_np
        for sh, launches in zip(self._shares, accumulate):
            b = sh["bbox_np"]
            if b[0] > b[3]:  # no particle
                continue
            lo, hi = self._clamp_box(b)
            dims = tuple(int(a) for a in hi - lo + 1)
            for launch in launches:
                launch.set_param_at_index(0, wp.vec3i(int(lo[0]), int(lo[1]), int(lo[2])))
                launch.set_dim(dims)
                launch.launch()
            box[:3] = np.minimum(box[:3], b[:3])
            box[3:] = np.maximum(box[3:], b[3:])

    def _reset_bbox(self) -> None:
        if self._cpu:
            for b in [self._bbox_np] + [sh["bbox_np"] for sh in self._shares]:
                b[:3] = 2**30
                b[3:] = -(2**30)
        else:
            wp.copy(self.bbox, self.bbox_init)

    def _record_bc(self, bcs: list[dict], fps: list[dict]) -> None:
        """Record the launches of each boundary point set (projection, reaction, clear + advance) into its dict under
        ``cmds``, and those of each force patch (weights, push, work; one set per grid-buffer parity, keyed by the
        buffer's id), after the frame's uploads (which may re-allocate the finger and boundary arrays)."""
        gs = self._recorded()["gs"]
        for bc in bcs:
            common = dict(dim=bc["count"], device=self.device, record_cmd=True)
            bc["cmds"] = (
                wp.launch(K.k_bc_scatter, **common, inputs=[self.gi, bc["pts"], self.bc_grid, self.flags, gs]),
                wp.launch(K.k_bc_reaction, **common, inputs=[self.gi, bc["pts"], gs, self.bc_grid, self.finger_react]),
                wp.launch(K.k_bc_clear_advance, **common, inputs=[self.gi, bc["pts"], gs, self.bc_grid]))
        for fp in fps:
            common = dict(dim=fp["count"], device=self.device, record_cmd=True)
            fp["cmds"] = {id(g): (
                wp.launch(K.k_force_weights, **common, inputs=[self.gi, fp["x"], fp["f"], g, fp["w"], self.flags, gs]),
                wp.launch(K.k_force_apply, **common, inputs=[
                    self.gi, fp["x"], fp["f"], fp["F"], fp["w"], gs, g, self.finger_applied]),
                wp.launch(K.k_force_work, **common, inputs=[
                    self.gi, fp["x"], fp["f"], fp["F"], fp["w"], gs, g, self.boundary_work]))
                for g in (self.grid_a, self.grid_b)}

    def _substep_params(self, dt: float, has_bc: int) -> K.GridStep:
        """The per-launch struct ``gs`` of this substep (dt in s, Dirichlet nodes on or off, substep counter)."""
        gs = self._recorded()["gs"]
        gs.dt = float(dt)
        gs.has_bc = int(has_bc)
        gs.substep = int(self.substep)
        return gs

    @staticmethod
    def _replay(cmd, gs: K.GridStep) -> None:
        """Launch a recorded command with this substep's ``gs``."""
        cmd.set_param_by_name("gs", gs)
        cmd.launch()

    def _launch_grid(self, cur, box_lo: np.ndarray, box_hi: np.ndarray, gs: K.GridStep) -> float:
        """Grid update over the node box [box_lo, box_hi] with the substep's ``gs`` (with two velocity fields: both
        fields' updates, then their contact, :func:`tasks.physics.mpm.kernels.k_field_contact`); returns the max
        grid speed (m/s)."""
        cmds = self._recorded()
        grid, fields = cmds[id(cur)][1], cmds[id(cur)][2]
        if self._cpu:
            self._gstats_np[0] = 0.0
        else:
            self.gstats.zero_()
        gs.origin = wp.vec3i(int(box_lo[0]), int(box_lo[1]), int(box_lo[2]))
        dims = tuple(int(a) for a in box_hi - box_lo + 1)
        grid.set_dim(dims)
        self._replay(grid, gs)
        if fields is not None:
            gs2 = cmds["gs2"]
            gs2.origin, gs2.dt, gs2.has_bc, gs2.substep = gs.origin, gs.dt, 0, gs.substep
            for launch, params in zip(fields, (gs2, gs)):
                launch.set_dim(dims)
                self._replay(launch, params)
        return float(self._gstats_np[0]) if self._cpu else float(self.gstats.numpy()[0])

    def _launch_fused(self, cur, dt: float, dt_next: float) -> None:
        cmds = self._recorded()
        fused = cmds[id(cur)][0]
        new_col = cmds["col_version"][id(cur)] != self._col_version
        if new_col:
            for sh in self._shares:
                self._share_colliders(sh)
            cmds["col_version"][id(cur)] = self._col_version
        for c, (launch, sp) in enumerate(zip(fused, cmds["sp_threads"])):
            sp.dt_g2p = float(dt)
            sp.dt_p2g = float(dt_next)
            sp.substep = int(self.substep)
            launch.set_param_by_name("sp", sp)
            if new_col:
                launch.set_param_by_name("col", self.col if c == 0 else self._shares[c - 1]["col"])
        if len(fused) == 1:
            fused[0].launch()
            return
        # Warp releases the GIL while a CPU kernel runs: every thread takes the next chunk until none is left
        chunks = iter(fused)

        def work() -> None:
            for launch in chunks:  # a shared iterator: each chunk is taken once (the GIL guards next())
                launch.launch()

        pending = [self._pool.submit(work) for _ in range(self.threads - 1)]
        work()
        for job in pending:
            job.result()
        self._gather_shares(cmds[id(cur)][3])

    def step_frame(self, frame_dt: float, dirichlet: BoundarySpec = None,
                   forces: Optional[Union[ForcePatch, Sequence[ForcePatch]]] = None,
                   quasi_static: bool = True,
                   colliders: Optional[Union[Collider, Sequence[Collider]]] = None,
                   probe: Optional[Callable[[float], None]] = None, probe_every: int = 1,
                   pins: Optional[ParticlePins] = None) -> FrameStats:
        """Advance by ``frame_dt`` seconds with CFL-adaptive substeps; returns the frame statistics.

        ``dirichlet``: DirichletPoints / DirichletNodes (or a list), constant targets over the frame (points are
        advected with their target velocity every substep), or a callable ``(t, dt) -> spec`` evaluated at every
        substep (t = time since the frame start; dt = the substep's size, None at the frame's first call, which
        only sizes the first substep).  ``forces``: ForcePatch (force mode, or a list, or such a callable),
        constant over the frame.  ``quasi_static``: whether the motion of this frame is meant to be quasi-static
        (False: dynamic by design, e.g. after a rupture; the quasi-static check skips it).  ``colliders``: rigid
        :class:`Collider` s (surface contact) at their positions at the frame start, moved with their velocities
        every substep; their reactions join ``FrameStats.reaction`` under their finger ids.  ``probe``: called
        with the time since the frame start (s) after every ``probe_every``-th substep's particle update inside the
        frame (the particles, e.g. :meth:`positions`, are then at that time; the frame's end is not probed).
        ``pins``: :class:`ParticlePins`, particles whose surface points reach their targets at the frame's end; their
        reactions join ``FrameStats.reaction`` under their finger ids.  Raises :class:`SimulationError` when a guard
        trips.
        """
        if not frame_dt > 0:
            raise ValueError("frame_dt must be > 0")
        with _young_objects_collected():
            return self._advance_frame(frame_dt, dirichlet, forces, quasi_static, colliders, probe, probe_every, pins)

    def _advance_frame(self, frame_dt: float, dirichlet: BoundarySpec,
                       forces: Optional[Union[ForcePatch, Sequence[ForcePatch]]], quasi_static: bool,
                       colliders: Optional[Union[Collider, Sequence[Collider]]],
                       probe: Optional[Callable[[float], None]], probe_every: int,
                       pins: Optional[ParticlePins]) -> FrameStats:
        """The body of :meth:`step_frame`."""
        wall0 = time.perf_counter()
        self._resolve_auto_mass_scale(frame_dt)
        self._set_damping(quasi_static)
        cfg = self.cfg
        d = self.device
        bc_fn = dirichlet if callable(dirichlet) else None
        f_fn = forces if callable(forces) else None
        bcs = self._upload_dirichlet(dirichlet(0.0, None) if bc_fn else dirichlet)
        fps = self._upload_forces(forces(0.0, None) if f_fn else forces)
        n_col = self._upload_colliders(colliders)
        n_pin = self._set_pins(pins, frame_dt)
        # m/s: a moving collider or pin bounds the step like a Dirichlet target's speed
        col_speed = max(self._collider_speed, self._pin_speed)
        self._record_bc(bcs, fps)
        col_advance = wp.launch(K.k_collider_advance, dim=n_col, device=d, record_cmd=True,
                                inputs=[self.col, self._recorded()["gs"]]) if n_col else None
        pin_advance = wp.launch(K.k_pin_advance, dim=n_pin, device=d, record_cmd=True,
                                inputs=[self.col, self._recorded()["gs"]]) if n_pin else None
        self.finger_react.zero_()
        self.finger_applied.zero_()
        self.boundary_work.zero_()
        for sh in self._shares:
            sh["react"].zero_()
            sh["work"].zero_()
        self._energy_baseline()
        has_bc = int(len(bcs) > 0)
        bc_speed = max([b["speed"] for b in bcs], default=0.0)
        check_every = 1 if cfg.debug else cfg.check_every
        n = self.n_particles

        t = 0.0
        nsub = 0
        dts: list[float] = []
        self._frame_dts = dts  # the substeps taken so far (the guard messages quote their Courant number)
        self._times = [(self.substep, self.time)]
        dt = self._next_dt(frame_dt, max(self._vmax, bc_speed, col_speed))
        cur, other = self.grid_b, self.grid_a
        # P2G of the frame's first substep (stress from the stored state)
        self._reset_bbox()
        wp.launch(K.k_p2g, dim=n, device=d, inputs=[
            self.gi, self._step_params(0.0, dt, restart=True), self.particles, self.mat_table, cur,
            self._field2[id(cur)], self.flags, self.bbox, self.col])
        box_cur = self._read_box()
        box_prev = self._last_box if self._last_box is not None else box_cur
        while True:
            if nsub > 0 and bc_fn is not None:  # time-varying constraints: re-evaluated every substep
                bcs = self._upload_dirichlet(bc_fn(t, dt))
                has_bc = int(len(bcs) > 0)
                bc_speed = max([b["speed"] for b in bcs], default=0.0)
            if nsub > 0 and f_fn is not None:
                fps = self._upload_forces(f_fn(t, dt))
            if nsub > 0 and (bc_fn is not None or f_fn is not None):  # new points, or re-allocated finger arrays
                self._record_bc(bcs, fps)
            gs = self._substep_params(dt, has_bc)
            if any(fp["follow"] for fp in fps):
                self._place_tracers()  # the points of a patch given by tracers follow the material
            for fp in fps:
                fp["w"].zero_()
                self._replay(fp["cmds"][id(cur)][0], gs)  # k_force_weights
                self._replay(fp["cmds"][id(cur)][1], gs)  # k_force_apply
            for fp in fps:  # the work, once every patch has pushed
                self._replay(fp["cmds"][id(cur)][2], gs)  # k_force_work
            for bc in bcs:
                self._replay(bc["cmds"][0], gs)  # k_bc_scatter
            vmax = self._launch_grid(cur, np.minimum(box_cur[0], box_prev[0]), np.maximum(box_cur[1], box_prev[1]), gs)
            for bc in bcs:
                self._replay(bc["cmds"][1], gs)  # k_bc_reaction
                self._replay(bc["cmds"][2], gs)  # k_bc_clear_advance
            t += dt
            nsub += 1
            dts.append(dt)
            remaining = frame_dt - t
            if remaining <= 1e-6 * frame_dt:
                self.sums.zero_()
                self.mat_energy.zero_()
                wp.copy(self.ext, self.ext_init)
                wp.launch(K.k_g2p, dim=n, device=d, inputs=[
                    self.gi, self._step_params(dt, 0.0, restart=True), self.particles, self.mat_table, cur,
                    self._field2[id(cur)], self.flags, self.sums, self.ext, wp.vec3(*self.cfg.gravity), self.mat_energy])
                if self._fibres is not None:
                    self._fibres.launch()
                self.substep += 1
                self._times.append((self.substep, self.time + t))
                self._last_box = box_cur
                break
            if not math.isfinite(vmax):
                self._vmax = vmax
                self._check_flags(force_nonfinite=True)
            dt_next = self._next_dt(remaining, max(vmax, bc_speed, col_speed))
            if col_advance is not None:  # the next P2G sees the colliders where they are at its time
                self._replay(col_advance, gs)
            if pin_advance is not None:  # and the pins' targets
                self._replay(pin_advance, gs)
            self._reset_bbox()
            self._launch_fused(cur, dt, dt_next)
            if self._fibres is not None:  # the next G2P advects the restored layers (their P2G is a substep behind)
                self._fibres.launch()
            box_prev, box_cur = box_cur, self._read_box()
            cur, other = other, cur
            dt = dt_next
            self.substep += 1
            self._times.append((self.substep, self.time + t))
            self._vmax = vmax
            if probe is not None and nsub % probe_every == 0:
                probe(t)
            if nsub % check_every == 0:
                self._check_flags()
            if nsub >= cfg.max_substeps_per_frame:
                raise SimulationError(
                    f"frame {self.frame} needs more than {cfg.max_substeps_per_frame} substeps "
                    f"(dt={dt:.3g} s, max speed {vmax:.4g} m/s at substep {self.substep}, "
                    f"t={self.time + t:.6g} s): the time step collapsed; likely cause: runaway velocities "
                    f"(unstable material or boundary velocities too large)")
        for sh in self._shares:  # the chunks' collider impulses (N s; fingers added this frame: none yet) and work (J)
            react, own = self.finger_react.numpy(), sh["react"].numpy()
            k = min(len(react), len(own))
            react[:k] += own[:k]
            self.boundary_work.numpy()[:] += sh["work"].numpy()
        # grid_a: last grid state (velocities + masses of the last P2G); grid_b: zeroed, the next frame's P2G target
        self.grid_a, self.grid_b = cur, other
        self.time += frame_dt
        self.frame += 1
        self._vmax = vmax
        stats = self._frame_stats(nsub, dts, frame_dt, wall0, quasi_static)
        self._check_flags()
        self._check_state(stats)
        self._check_energy(stats)
        self.last_stats = stats
        return stats

    def _set_damping(self, quasi_static: bool) -> None:
        """The frame's local damping coefficients (class doc, quasi-static damping): ``quasi_static_damping`` on the
        measured materials of a mass-scaled run in a quasi-static frame, else none."""
        a = float(self.cfg.quasi_static_damping)
        on = quasi_static and self.mass_scale > 1.0 and a > 0.0
        rates = np.where(self._quasi_static_materials(), a, 0.0) if on else np.zeros(len(self.materials))
        if self._preload_damping > 0.0:  # preload_gravity: everything settles
            rates = np.full(len(self.materials), self._preload_damping)
        if not np.array_equal(rates, self._damping):
            self._damping = rates
            self._mat_params[:, COL_DAMPING] = rates
            self.mat_par.assign(self._mat_params)

    def _read_box(self) -> tuple[np.ndarray, np.ndarray]:
        """Node box [lo, hi] (inclusive) touched by the last P2G (stencil bases + 2), clamped to the grid."""
        return self._clamp_box(self._bbox_np if self._cpu else self.bbox.numpy())

    def _clamp_box(self, bbox: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Node box [lo, hi] (inclusive) of the stencil bases [bbox[:3], bbox[3:]] (+ 2), clamped to the grid."""
        b = bbox.tolist()
        dims = self.dims
        lo = [min(max(b[i], 0), dims[i] - 1) for i in range(3)]
        hi = [max(min(b[3 + i] + 2, dims[i] - 1), lo[i]) for i in range(3)]
        return np.array(lo), np.array(hi)

    # ------------------------------------------------------------------ statistics and guards
    def _frame_stats(self, nsub: int, dts: list[float], frame_dt: float, wall0: float,
                     quasi_static: bool) -> FrameStats:
        s = self.sums.numpy()
        e = self.ext.numpy()
        ke, ie = float(s[0]), float(s[1])
        per = self.mat_energy.numpy()  # (material, [KE, IE, PE]) J
        work = float(self.boundary_work.numpy()[0])
        measured = self._quasi_static_materials()
        dissipated = self._plastic_dissipation(measured)
        ke_s, ie_s = float(per[measured, 0].sum()), float(per[measured, 1].sum()) + dissipated
        local_damping = float(self._damping[measured].max(initial=0.0))
        ratio = _ratio(ke_s, ie_s)
        reaction = self.finger_react.numpy().astype(np.float64) / frame_dt
        applied = self.finger_applied.numpy().astype(np.float64) / frame_dt
        loaded = quasi_static and bool(np.any(reaction != 0) or np.any(applied != 0))
        self._loaded_frames = self._loaded_frames + 1 if loaded else 0
        checked = self.mass_scale > 1.0 and self._loaded_frames > QUASI_STATIC_ONSET_FRAMES
        qs_ok = checked or self.close_quasi_static_contact()  # a contact ended before this frame: judged
        process = math.nan
        if checked:
            if self._contact is None:  # the contact's first checked frame
                self._contact = {"first_frame": self.frame, "first_time": self.time, "ke": 0.0, "ie": 0.0,
                                 "ke_sway": 0.0}
            c = self._contact
            c["ke"] += ke_s
            c["ie"] += ie_s
            c["ke_sway"] += self._sway_kinetic_energy(measured)
            c["last_frame"], c["last_time"] = self.frame, self.time
            process = _ratio(c["ke"], c["ie"])
        return FrameStats(
            frame=self.frame, time=self.time, substeps=nsub, dt_min=min(dts), dt_max=max(dts),
            courant=self.courant_number(max(dts)), max_speed=float(e[2]), j_min=float(e[0]), j_max=float(e[1]),
            kinetic_energy=ke, internal_energy=ie, ke_ie_ratio=ratio, momentum=s[2:5].copy(), mass=float(s[5]),
            reaction=reaction, applied_force=applied,
            mass_scale=self.mass_scale, stiffness_scale=self.stiffness_scale, quasi_static_ok=qs_ok,
            wall_seconds=time.perf_counter() - wall0, gravitational_energy=float(per[:, 2].sum()),
            boundary_work=work, quasi_static_checked=checked, ke_ie_contact=process, local_damping=local_damping,
            plastic_dissipation=dissipated,
        )

    def _plastic_dissipation(self, measured: np.ndarray) -> float:
        """The plastic work (J) the particles of the ``measured`` materials (material,) bool have dissipated so far
        (:func:`plastic_dissipation`, at the material table's yield stress and hardening: scaled as the kernels use
        them); 0 without a plastic material."""
        if not self.has_plastic:
            return 0.0
        rows = measured & np.isin(self.mat_model.numpy(), PLASTIC_MODELS)
        on = rows[self._mid_host]
        if not on.any():
            return 0.0
        par, mid = self.mat_par.numpy(), self._mid_host[on]
        return plastic_dissipation(self.alpha.numpy()[on], self.vol.numpy()[on], par[mid, COL_YIELD],
                                   par[mid, COL_HARDENING])

    def preload_gravity(self, frame_dt: float, max_frames: int, passes: int = 3, damping: float = 0.8,
                        tolerance: float = 0.01) -> GravityPreload:
        """Gravity preload (geostatic prestress): make the body's given shape (a captured object standing on the
        table) its equilibrium under its weight, so that the run starts at rest instead of sagging and swaying
        from the first frame (the plush toy, given gravity at t = 0: its top swung 4 cm forward before the
        fingers arrived).  Each pass (at most ``passes``):

        1. settles the body by dynamic relaxation (Cundall's local damping ``damping`` on every material, as FLAC's
           static solutions and LS-DYNA's dynamic-relaxation preload do; gravity, floor and walls only) until the
           fastest solid particle moves at most ``tolerance`` grid cells per ``frame_dt`` s after its motion
           peaked, or for ``max_frames`` frames;
        2. puts the particles back where they were given, at rest (v = 0, C = 0), keeping their deformation
           gradients: the stress that carried the weight in the settled shape now holds the given shape, whose
           stress-free shape is the given one less the sag (first order in the sag).  The next pass settles what
           that change of geometry left.  A body that leans under its weight (a soft toy rocking on its base) is
           over-held by the full settled strain, since its upright given shape has less overturning moment than
           the settled one, and its passes converge slowly (the plush toy's 36.6, 22, 16.5, 11 mm); from the
           second pass on each pass keeps omega times its strain, omega by Aitken's rule (Irons and Tuck 1969, as
           partitioned fluid-structure codes relax their coupling iterations), exact for a linear response (the
           plush toy: 36.6, 22, 0.2 mm).  A fluid (the can's cola) has no shape to hold: it stays where it settled,
           at rest, with the pressure it settled to.

        The tracers (surface Gaussians) are re-bound to stay on their given positions, and :meth:`tracer_state`
        reports their deformation from the preloaded state.  Time and frame count restart at 0.  Raises
        :class:`SimulationError` like :meth:`step_frame`."""
        if not (max_frames >= 1 and passes >= 1 and 0.0 < damping < 1.0 and tolerance > 0.0):
            raise ValueError(f"preload_gravity: need max_frames >= 1, passes >= 1, damping in (0, 1) and tolerance "
                             f"> 0, got {max_frames}, {passes}, {damping}, {tolerance}")
        x0 = self.positions()
        fluid = np.array([m.model == "fluid" for m in self.materials])[self._mid_host]  # no shape to hold: it settles
        zero_v, zero_c = np.zeros((self.n_particles, 3)), np.zeros((self.n_particles, 3, 3))
        frames, moved, rest = 0, [], False
        start, last, omega = self.F.numpy().astype(np.float64), None, 1.0
        self._preload_damping = damping
        try:
            for _ in range(passes):
                peak = -math.inf  # the pass starts at rest: it is over once its motion has peaked and died down
                for _ in range(max_frames):
                    self.step_frame(frame_dt, quasi_static=False)
                    frames += 1
                    speed = float(np.linalg.norm(self.velocities()[~fluid], axis=1).max(initial=0.0))
                    rest = speed * frame_dt <= tolerance * self.dx and speed < peak
                    if rest:
                        break
                    peak = max(peak, speed)
                x = self.positions()
                moved.append(float(np.linalg.norm(x - x0, axis=1)[~fluid].max(initial=0.0)))
                settled = self.F.numpy().astype(np.float64)
                update = np.where(fluid[:, None, None], 0.0, settled - start)  # the solids' settled strain
                if last is not None:  # Aitken relaxation of the passes (Irons and Tuck 1969)
                    change = update - last
                    size = float(np.vdot(change, change))
                    if size > 0.0:
                        omega = float(np.clip(-omega * np.vdot(last, change) / size, 0.1, 2.0))
                last, start = update, np.where(fluid[:, None, None], settled, start + omega * update)
                self.set_deformation_gradients(start)
                self.set_positions(np.where(fluid[:, None], x, x0))
                self.set_velocities(zero_v)
                self.set_affine_velocities(zero_c)
                if rest and moved[-1] <= tolerance * self.dx:
                    break
        finally:
            self._preload_damping = 0.0
        self._rebind_tracers_to_preload()
        self.time, self.frame, self.substep = 0.0, 0, 0
        return GravityPreload(moved=tuple(moved), frames=frames, converged=rest)

    def _rebind_tracers_to_preload(self) -> None:
        """After :meth:`preload_gravity`: each tracer's rest offsets become F0_k^-1 r_tk (F0_k its anchor's preloaded
        F), so it sits at its given position, and its reported F is relative to its preloaded F."""
        if not self.n_tracers:
            return
        anchor, weight, offset = self._anchor
        near, r = anchor.numpy(), offset.numpy().astype(np.float64)
        F0 = self.F.numpy().astype(np.float64)
        self._anchor = (anchor, weight, wp.array(np.einsum("tkij,tkj->tki", np.linalg.inv(F0[near]), r)
                                                 .astype(np.float32), dtype=wp.vec3, device=self.device))
        self._place_tracers()
        self._tracer_F0_inv = np.linalg.inv(self.tF.numpy()[: self.n_tracers].astype(np.float64))

    def close_quasi_static_contact(self) -> bool:
        """Judge the open contact of the quasi-static check (class doc): the solver calls it in the first frame after
        a contact (the fingers let go, or a rupture), the caller when it ends the run while a finger still loads the
        body.  The contact's KE/IE (sum KE / sum IE of the measured materials over its checked frames) is appended
        to ``quasi_static_contacts`` (first_frame, last_frame, ke_ie) and, above ``config.quasi_static_ke_ie_max``,
        warned about once per solver in one line naming object, frames, times, materials and knobs.  Returns
        whether it passed (True when no contact was open)."""
        c, self._contact = self._contact, None
        if c is None:
            return True
        ratio = _ratio(c["ke"], c["ie"])
        sway = c["ke_sway"] / c["ke"] if c["ke"] > 0 else 0.0
        self.quasi_static_contacts.append({"first_frame": c["first_frame"], "last_frame": c["last_frame"],
                                           "ke_ie": ratio, "sway_ke_share": sway})
        ok = not ratio > self.cfg.quasi_static_ke_ie_max
        if not ok and not self._warned_quasi_static:  # once per solver; every contact's value is in the list
            self._warned_quasi_static = True
            who = f"object '{self.label}': " if self.label else ""
            names = ", ".join(f"'{self.materials[i].name}' x{self.material_mass_scale[i]:.3g}"
                              for i in np.flatnonzero(self._quasi_static_materials()) if i in self._present)
            warnings.warn(
                f"{who}quasi-static check over frames {c['first_frame']}-{c['last_frame']} of a contact "
                f"(t={c['first_time']:.4g}-{c['last_time']:.4g} s): kinetic/internal energy ratio {ratio:.3g} of the "
                f"mass-scaled material ({names}; {100 * sway:.0f} % of its kinetic energy in the body's sway on "
                "its base: horizontal motion of its centre of mass and rotation about it) > "
                f"mpm.quasi_static_ke_ie_max={self.cfg.quasi_static_ke_ie_max:g} "
                "while the boundary loads it: the squeeze is dynamic in the scaled time and inertia distorts the "
                "deformation; scale less (mpm.quasi_static_margin, now "
                f"{self.cfg.quasi_static_margin:g}, bounds the scale by a force-driven load's rise time; "
                "mpm.mass_scaling=off, or a larger mpm.target_substeps_per_frame) or squeeze more slowly (a longer "
                "signal.duration)",
                RuntimeWarning, stacklevel=3)
        return ok

    def _sway_kinetic_energy(self, measured: np.ndarray) -> float:
        """Kinetic energy (J, scaled masses) of the sway of the particles of the ``measured`` (material,) materials on
        their base: the horizontal motion of their centre of mass and their rigid rotation about it
        (:func:`kinetic_energy_split`, vertical = against gravity)."""
        on = measured[self._mid_host]
        g = np.asarray(self.cfg.gravity, np.float64)
        up = -g / np.linalg.norm(g) if np.any(g) else np.array([0.0, 0.0, 1.0])
        horizontal, _, rotation, _ = kinetic_energy_split(self.positions()[on], self.velocities()[on],
                                                          self.masses()[on], up)
        return horizontal + rotation

    def _quasi_static_materials(self) -> np.ndarray:
        """(material,) bool: the materials the kinetic/internal energy ratio measures: the mass-scaled ones declared
        quasi-static (``Material.is_mass_scaled``; released or flying material and fluids are not, whatever the
        scaling mode); without scaling every declared one, else every material."""
        declared = np.array([m.is_mass_scaled for m in self.materials])
        for mask in (declared & (self.material_mass_scale > 1.0), declared):
            if mask.any():
                return mask
        return np.ones(len(self.materials), bool)

    # ------------------------------------------------------------------ energy guard
    def _energy_baseline(self) -> None:
        """Before the first frame: the reference energy of the initial state (F_E = I, C = 0: no internal energy),
        per material: kinetic 1/2 m v^2 (scaled masses) + gravitational -m_phys g . x (J)."""
        if not self._energy_initial:
            return
        self._energy_initial = False
        m, m_phys = self.masses().astype(np.float64), self.physical_masses().astype(np.float64)
        x, v = self.x.numpy().astype(np.float64), self.v.numpy().astype(np.float64)
        ke = 0.5 * m * np.einsum("ij,ij->i", v, v)
        pe = -m_phys * (x @ np.asarray(self.cfg.gravity, np.float64))
        per = np.bincount(self._mid_host, weights=ke + pe, minlength=len(self.materials))
        self._energy_ref = EnergyBudget.start(self.frame, per, float(pe.sum()), float(ke.sum()), self._energy_ref)

    def _energy_state_changed(self) -> None:
        """A state setter changed the energy from outside: the guard re-bases at the end of the next frame (the
        initial state keeps its exact reference unless F_E was set); the energy scale reached so far is kept."""
        if self.frame > 0:
            self._energy_initial = False
            self._energy_ref = EnergyBudget.rebase(self._energy_ref)

    def _check_energy(self, st: FrameStats) -> None:
        """Energy guard (see the class doc and :class:`EnergyBudget`): raise when the energy grew beyond the
        reference energy plus the boundary work put in by more than tolerance x energy scale."""
        rel = float(self.cfg.energy_guard_tolerance)
        per_split = self.mat_energy.numpy()
        per = per_split.sum(axis=1)
        ref = self._energy_ref
        if ref is None or ref.frame is None:
            self._energy_ref = EnergyBudget.start(self.frame, per, st.gravitational_energy,
                                                  st.kinetic_energy + st.internal_energy, ref)
            return
        growth = ref.update(per, st.gravitational_energy, st.boundary_work)
        # below the energy of lifting the whole body by one grid cell the discretisation resolves no change (a body
        # settling on the floor exchanges micro-joules between gravity and strain): never a reason to stop
        weight_cell = float(self.physical_masses().astype(np.float64).sum()) * float(
            np.linalg.norm(np.asarray(self.cfg.gravity, np.float64))) * self.dx
        scale = max(ref.scale, weight_cell)
        tol = rel * scale + 1e-9
        st.energy_growth = growth / max(scale, 1e-9)  # (1e-9 J: the absolute floor of the tolerance)
        if rel <= 0 or growth <= tol:
            return
        grew = np.argsort(-(per - ref.energy))
        names = ", ".join(f"'{self.materials[i].name}' +{per[i] - ref.energy[i]:.3g} J (kinetic "
                          f"{per_split[i, 0]:.3g}, internal {per_split[i, 1]:.3g})"
                          for i in grew[:3] if per[i] > ref.energy[i])
        who = f"object '{self.label}': " if self.label else ""
        raise SimulationError(
            f"{who}energy guard at frame {st.frame} (t={st.time:.6g} s): the total energy (kinetic + internal + "
            f"gravitational) grew by {growth + ref.work_in:.4g} J since frame {ref.frame}, {growth:.4g} J beyond the "
            f"boundary work put in {ref.work_in:.4g} J (tolerance {tol:.3g} J = {rel:g} x energy scale "
            f"{scale:.3g} J); grew: {names}. "
            f"Likely cause: numerical instability (Courant number {st.courant:.3g}, limit "
            f"{self.cfg.courant_limit:.3g}, c_p={self.c_max:.4g} m/s, dx={self.dx:.4g} m); lower mpm.courant or dt")

    def _substep_time(self, sub: int) -> float:
        best = self.time
        for s, t in self._times:
            if s <= sub:
                best = t
        return best

    def _material_name(self, p: int) -> str:
        return self.materials[int(self._mid_host[p])].name

    def _check_flags(self, force_nonfinite: bool = False) -> None:
        f = self.flags.numpy()
        for sh in self._shares:  # merge the chunks' flags (counts, first substep, an offending index)
            g = sh["flags"].numpy()
            if g[:4].any():
                f[:4] += g[:4]
                f[4:8] = np.minimum(f[4:8], g[4:8])
                f[8:] = np.maximum(f[8:], g[8:])
                self._reset_flags(sh["flags"])
        if not (f[0] or f[1] or f[2] or f[3]) and not force_nonfinite:
            return
        x = self.x.numpy()
        F = self.F.numpy()
        taken = getattr(self, "_frame_dts", None)  # the largest dt actually used this frame, not the post-blow-up one
        cn = self.courant_number(max(taken) if taken else (
            self._stable_dt(self._vmax) if self.cfg.dt is None else self.cfg.dt))
        hint_dt = (f"Courant number {cn:.3g} (limit {self.cfg.courant_limit:.3g}), c_p={self.c_max:.4g} m/s, "
                   f"dx={self.dx:.4g} m")
        if f[1] or force_nonfinite:  # non-finite first: it explains the others
            bad = ~(np.isfinite(x).all(1) & np.isfinite(F).reshape(len(F), -1).all(1))
            p = int(np.argmax(bad)) if bad.any() else int(max(f[9], 0))
            sub = int(f[5]) if f[5] != K.NO_SUBSTEP else self.substep
            raise SimulationError(
                f"non-finite particle state (NaN/inf position, velocity or F) at substep {sub} "
                f"(t={self._substep_time(sub):.6g} s, frame {self.frame}); {int(bad.sum())} particles non-finite now; "
                f"worst particle #{p} of material '{self._material_name(p)}'. Likely cause: numerical blow-up - "
                f"the time step is too large for the stiffness ({hint_dt}) or the input contains NaN; "
                "lower dt or E, or enable stiffness/mass scaling")
        if f[0]:
            g = (x.astype(np.float64) - self.lo) / self.dx
            lo_b, hi_b = 1.0, np.asarray(self.dims, np.float64) - 2.0
            out = np.maximum(lo_b - g, 0.0).max(1) + np.maximum(g - hi_b, 0.0).max(1)
            p = int(np.argmax(out)) if out.max() > 0 else int(max(f[8], 0))
            sub = int(f[4])
            hi = (self.lo + (np.asarray(self.dims) - 1) * self.dx).round(5).tolist()
            raise SimulationError(
                f"particle left the simulation grid (entered the padding layer / domain boundary) at substep {sub} "
                f"(t={self._substep_time(sub):.6g} s, frame {self.frame}); {int(f[0])} offences; worst particle #{p} "
                f"of material '{self._material_name(p)}' at {x[p].round(5).tolist()} m, grid "
                f"[{self.lo.round(5).tolist()}, {hi}]. "
                f"Likely cause: velocities too large (max speed {self._vmax:.4g} m/s; unstable material, "
                f"{hint_dt}) or boundary targets driving material out of the domain; enlarge the domain "
                "(margin_cells / domain_lo / domain_hi) or lower dt")
        if f[2]:
            J = np.linalg.det(F.astype(np.float64))
            dev = np.abs(np.log(np.clip(J, 1e-30, None)))
            dev[~np.isfinite(J) | (J <= 0)] = np.inf
            p = int(np.argmax(dev))
            sub = int(f[6])
            pinned = self._pin_finger_of(p)
            cause = ("element inversion or over-stretch - the load or boundary velocity is too large for the material "
                     f"stiffness, or the time step is too large ({hint_dt}); lower dt, raise E, or use a plastic/fluid "
                     "model for this material") if pinned is None else (
                f"it is pinned (ParticlePins, finger id {pinned}): the finger's whole push acts on the pinned "
                "particles' surfaces and crushes them where the prescribed displacement meets a stiff response; "
                "use grid-node Dirichlet fingers (mpm.fingers=dirichlet), which spread it over the grid")
            raise SimulationError(
                f"extreme volume change det(F)={J[p]:.4g} outside [{self.cfg.j_min}, {self.cfg.j_max}] at substep "
                f"{sub} (t={self._substep_time(sub):.6g} s, frame {self.frame}); {int(f[2])} offences; worst particle "
                f"#{p} of material '{self._material_name(p)}'. Likely cause: {cause}")
        if f[3]:
            sub = int(f[7])
            p = int(f[11])
            raise SimulationError(
                f"a boundary / force point left the simulation grid (entered the padding layer) at substep {sub} "
                f"(t={self._substep_time(sub):.6g} s, frame {self.frame}); point #{p}. Likely cause: constrained or "
                "force points lie outside the domain box, or targets move them out; enlarge the domain")

    def _check_state(self, st: FrameStats) -> None:
        """Per-frame cheap checks: finite energies/momentum and the J range."""
        vals = [st.kinetic_energy, st.internal_energy, st.j_min, st.j_max, st.max_speed, *st.momentum.tolist()]
        if not all(math.isfinite(v) for v in vals):
            self._check_flags(force_nonfinite=True)
        if st.j_min < self.cfg.j_min or st.j_max > self.cfg.j_max:
            self.flags.assign(np.array([0, 0, 1, 0, 0, 0, self.substep, 0, -1, -1, 0, -1], np.int32))
            self._check_flags()

    # ------------------------------------------------------------------ accessors
    def positions(self) -> np.ndarray:
        return self.x.numpy().copy()

    def velocities(self) -> np.ndarray:
        return self.v.numpy().copy()

    def deformation_gradients(self, plane_stress: bool = False) -> np.ndarray:
        """Elastic deformation gradients F_E (N, 3, 3) (fluid: J^(1/3) I), as stored; with ``plane_stress`` a thin
        wall's elastic particles as their plane-stress projection, the material's state (the stored F_E keeps the
        grid's normal stretch, which ``mpm.wall_normal_stiffness`` resists: under a finger's nodes its J left 1 as
        far as a locked solid wall's, 0.26)."""
        if not plane_stress or self.n_membrane == 0:
            return self.F.numpy().copy()
        out = wp.zeros(self.n_particles, dtype=wp.mat33, device=self.device)
        wp.launch(K.k_plane_stress_F, dim=self.n_particles, device=self.device,
                  inputs=[self.particles, self.mat_table, out])
        return out.numpy()

    def plastic_strain(self) -> np.ndarray:
        """Equivalent plastic strain alpha (N,) (zeros when no plastic material is present)."""
        if not self.has_plastic:
            return np.zeros(self.n_particles, np.float32)
        return self.alpha.numpy().copy()

    def set_plastic_strain(self, alpha: np.ndarray) -> None:
        """Set the equivalent plastic strain alpha (N,) (e.g. 0 for material released as a fresh mass); a solver
        without plastic materials holds none and accepts only zeros."""
        alpha = np.asarray(alpha, np.float32).reshape(self.n_particles)
        if not (np.isfinite(alpha).all() and alpha.min(initial=0.0) >= 0.0):
            raise ValueError("set_plastic_strain: alpha must be finite and >= 0 (an equivalent plastic strain)")
        if not self.has_plastic:
            if alpha.any():
                raise ValueError("set_plastic_strain: no plastic material in this solver, so no plastic strain")
            return
        self.alpha.assign(alpha)

    def volumes(self) -> np.ndarray:
        return self.vol.numpy().copy()

    def contact_radii(self) -> np.ndarray:
        """(particle,) m: the radius with which surface contact reaches a collider
        (:func:`tasks.physics.mpm.kernels.contact_velocity`, before its F^T n stretch; :func:`contact_reach`)."""
        return self.reach.numpy().astype(np.float64)

    def set_contact_radii(self, reach: np.ndarray) -> None:
        """Set each particle's contact radius (m; :meth:`contact_radii`), e.g. a wall sampled in Gauss layers but held
        as a 3D solid, whose layers touch at the wall's faces (:func:`contact_reach` with its fibres)."""
        r = np.asarray(reach, np.float64)
        if r.shape != (self.n_particles,) or not (np.all(np.isfinite(r)) and np.all(r >= 0)):
            raise ValueError(f"set_contact_radii: need {self.n_particles} finite radii >= 0 (m), one per particle; "
                             f"got shape {r.shape}")
        self.reach.assign(r.astype(np.float32))

    def masses(self) -> np.ndarray:
        """Particle masses (kg), including the material's current mass scale (the inertia)."""
        par = self.mat_par.numpy()
        return self.vol.numpy() * par[self._mid_host, COL_DENSITY]

    def physical_masses(self) -> np.ndarray:
        """Physical particle masses (kg), without mass scaling (the weight is m_phys g)."""
        par = self.mat_par.numpy()
        return self.vol.numpy() * par[self._mid_host, COL_PHYSICAL_DENSITY]

    def material_ids(self) -> np.ndarray:
        return self._mid_host.copy()

    def _bind_tracers(self, x: np.ndarray, vol: np.ndarray, tr: Optional[np.ndarray],
                      anchors: Optional[np.ndarray]) -> None:
        """Bind every tracer to its ``TRACER_ANCHORS`` nearest anchor particles at rest (see :func:`K.k_tracer_embed`):
        weights w_k proportional to 1 / (d_k + h / 2) (d_k its distance to particle k, h the mean particle spacing,
        m; sum 1) and the rest offsets X_t - X_k.  Several anchors average out a single particle's rotation noise;
        all of them lie within about a particle spacing of a surface Gaussian."""
        if not self.n_tracers:
            self._anchor = None
            return
        from scipy.spatial import cKDTree

        mask = np.ones(len(x), bool) if anchors is None else np.asarray(anchors, bool).reshape(len(x))
        if not mask.any():
            raise ValueError("tracer_anchors selects no particle: tracers need particles to be embedded in")
        idx = np.flatnonzero(mask)
        k = min(TRACER_ANCHORS, len(idx))
        dist, near = cKDTree(x[idx].astype(np.float64)).query(tr.astype(np.float64), k=k)
        dist, near = dist.reshape(len(tr), k), idx[near.reshape(len(tr), k)]
        h = float(np.cbrt(vol.astype(np.float64)).mean())
        w = 1.0 / (dist + 0.5 * h)
        w /= w.sum(axis=1, keepdims=True)
        d = self.device
        self._anchor = (wp.array(near.astype(np.int32), dtype=wp.int32, device=d),
                        wp.array(w.astype(np.float32), dtype=float, device=d),
                        wp.array((tr[:, None, :] - x[near]).astype(np.float32), dtype=wp.vec3, device=d))

    def _place_tracers(self) -> None:
        if self.n_tracers:
            wp.launch(K.k_tracer_embed, dim=self.n_tracers, device=self.device,
                      inputs=[self.x, self.F, *self._anchor, self.tx, self.tF])

    def tracer_positions(self) -> np.ndarray:
        """(T, 3) m, the tracers placed from their anchors' current state."""
        self._place_tracers()
        return self.tx.numpy()[: self.n_tracers].copy()

    def tracer_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The tracers placed once from their anchors' current state: positions (T, 3) m and deformation
        gradients (T, 3, 3), each the weighted mean of its anchors' F (after :meth:`preload_gravity`, relative to
        the preloaded state: I at its end)."""
        self._place_tracers()
        tF = self.tF.numpy()[: self.n_tracers].copy()
        if self._tracer_F0_inv is not None:
            tF = np.einsum("tij,tjk->tik", tF.astype(np.float64), self._tracer_F0_inv).astype(np.float32)
        return self.tx.numpy()[: self.n_tracers].copy(), tF

    def grid_mass(self) -> float:
        """Total mass (kg) on the grid from the last P2G (float64 sum of the nodal masses of both velocity
        fields)."""
        grids = [self.grid_a] + ([self._field2[id(self.grid_a)]] if self.two_fields else [])
        return float(sum(g.numpy()[..., 3].astype(np.float64).sum() for g in grids))

    def set_velocities(self, v: np.ndarray) -> None:
        self._energy_state_changed()
        self.v.assign(np.asarray(v, np.float32).reshape(-1, 3))
        self._vmax = max(self._vmax, float(np.max(np.linalg.norm(v, axis=1))))

    def set_positions(self, x: np.ndarray) -> None:
        self._energy_state_changed()
        self.x.assign(np.asarray(x, np.float32).reshape(-1, 3))
        self.x_carry.zero_()  # a round-off belongs to the positions it was lost from

    def set_material_ids(self, ids: np.ndarray) -> None:
        """Re-assign particle materials (e.g. a ruptured shell).  The new materials must use models whose state
        is already allocated and the same (physical) density: the physical mass, hence the weight, is conserved
        exactly; under selective mass scaling the inertia follows the new material's scale (burst pulp that
        becomes released juice gets its physical mass back).  The set of materials present, the stable time step
        (their wave speeds, fluid viscosity) and the fixed-corotated fast path are updated; the scale s stays as
        it was."""
        self._energy_state_changed()
        ids = np.asarray(ids, np.int32).reshape(self.n_particles)
        if ids.min() < 0 or ids.max() >= len(self.materials):
            raise ValueError(f"material ids must be in [0, {len(self.materials)})")
        changed = ids != self._mid_host
        for a, b in {(int(i), int(j)) for i, j in zip(self._mid_host[changed], ids[changed])}:
            ma, mb = self.materials[a], self.materials[b]
            if ma.density != mb.density:
                raise ValueError(f"material {mb.name} has another density than {ma.name}: mass would change")
            if (mb.code == FIXED_COROTATED and not self.has_corotated) or (mb.is_plastic and not self.has_plastic):
                raise ValueError(f"material {mb.name} needs solver state that was not allocated")
        self._check_membranes(ids)
        self._convert_membrane_normals(ids)
        self._mid_host = ids.copy()
        self.mat_id.assign(ids)
        self._present = sorted(set(int(i) for i in np.unique(ids)))
        self.all_corotated = {self.materials[i].code for i in self._present} == {FIXED_COROTATED}
        self._upload_materials()
        self._update_fields()

    def _convert_membrane_normals(self, ids: np.ndarray) -> None:
        """A membrane particle's normal row is its rest normal N under an elastic model and its current normal n
        under von Mises (``membrane_normals``); one changing between the two gets the other, through its stored F:
        n = cof(F) N / |cof(F) N| (Nanson), N = F^T n / |F^T n|."""
        codes = np.array([m.code for m in self.materials])
        was, now = codes[self._mid_host] == VON_MISES, codes[ids] == VON_MISES
        rows = np.flatnonzero(self._membrane_rows & (was != now))
        if not len(rows):
            return
        F = self.F.numpy()[rows].astype(np.float64)
        normals = self.normal.numpy()
        given = normals[rows].astype(np.float64)
        to_current = now[rows]
        c1, c2, c3 = F[:, :, 0], F[:, :, 1], F[:, :, 2]
        cof = np.stack([np.cross(c2, c3), np.cross(c3, c1), np.cross(c1, c2)], axis=2)  # columns: det(F) F^-T
        moved = np.where(to_current[:, None], np.einsum("nij,nj->ni", cof, given),
                         np.einsum("nji,nj->ni", F, given))
        size = np.linalg.norm(moved, axis=1, keepdims=True)
        normals[rows] = np.where(size > 1e-6, moved / np.maximum(size, 1e-12), given).astype(np.float32)
        self.normal.assign(normals)

    def _check_membranes(self, ids: np.ndarray) -> None:
        """Every particle of a ``membrane`` material needs a rest normal: its stable step is the plane-stress wave's,
        which a particle in 3D stress would exceed (ValueError naming the material)."""
        for i, m in enumerate(self.materials):
            missing = int(np.count_nonzero((ids == i) & ~self._membrane_rows)) if m.membrane else 0
            if missing:
                raise ValueError(f"material '{m.name}' is a membrane but {missing} of its particles have no rest "
                                 "normal (membrane_normals): give one per particle, or membrane=False")

    def affine_velocities(self) -> np.ndarray:
        """APIC affine velocity matrices C (N, 3, 3), 1/s (the particle's velocity gradient, stored at frame ends)."""
        return self.C.numpy().copy()

    def set_affine_velocities(self, C: np.ndarray) -> None:
        """Set the APIC affine velocity matrices C (N, 3, 3), 1/s, e.g. with :meth:`set_velocities` for an initial
        rigid spin v = w x (x - c): C = [w]x (the skew matrix of w), so the first P2G carries the spin's full
        angular momentum and kinetic energy (Jiang et al. 2015, APIC) instead of losing the part within each
        particle's stencil.  The velocity field is unchanged, so the energy guard's reference stays."""
        C = np.asarray(C, np.float32).reshape(self.n_particles, 3, 3)
        if not np.isfinite(C).all():
            raise ValueError("set_affine_velocities: C contains NaN/inf; pass finite velocity gradients (1/s)")
        self.C.assign(C)

    def set_deformation_gradients(self, F: np.ndarray) -> None:
        self._energy_initial = False
        self._energy_ref = EnergyBudget.rebase(self._energy_ref)
        self.F.assign(np.asarray(F, np.float32).reshape(-1, 3, 3))
        self.F_carry.zero_()

    def state_nbytes(self) -> dict[str, int]:
        """Bytes of the per-particle state arrays (allocated only for the models present)."""
        arrs = dict(x=self.x, x_carry=self.x_carry, v=self.v, C=self.C, F=self.F, F_carry=self.F_carry, q=self.q,
                    alpha=self.alpha, vol=self.vol, mat_id=self.mat_id, normal=self.normal,
                    wall_offset=self.wall_offset)
        return {k: int(a.size * wp.types.type_size_in_bytes(a.dtype)) for k, a in arrs.items()}

    def bytes_per_particle(self) -> float:
        return sum(self.state_nbytes().values()) / self.n_particles

    def grid_nbytes(self) -> int:
        """Bytes of the grid arrays: two vec4 buffers (four once a second velocity field was used), plus the
        Dirichlet target, reaction (vec4) and projector (mat33) arrays once a constraint was used, plus one vec4
        P2G buffer per field for every particle chunk after the first (``mpm.threads`` > 1)."""
        nodes = int(np.prod(self.dims))
        fields = 2 if self._field2[id(self.grid_a)].shape == self.grid_a.shape else 1
        chunks = sum(16 * nodes * (1 + (sh["grid2"].shape == self.grid_a.shape)) for sh in self._shares)
        return nodes * (2 * 16 * fields + ((16 + 16 + 36) if self._bc_alloc else 0)) + chunks
