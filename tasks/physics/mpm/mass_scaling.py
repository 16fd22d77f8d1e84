"""Mass (time) scaling and its quasi-static check (below): the density factor each material gets (:func:`mass_scale_for`, :func:`material_mass_scales`, bounded by the load's rise time,
:class:`QuasiStaticLoad`), the local damping of quasi-static frames, and the kinetic/internal energy ratio of
the scaled materials judged per contact (:func:`close_quasi_static_contact`).

Mass (time) scaling (``config.mass_scaling``; s from :func:`mass_scale_for`, fixed once: at construction, or for
``global``/``selective`` at the first :meth:`~tasks.physics.mpm.solver.MPMSolver.step_frame`): the densities of the scaled materials (all of them by
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
the kinetic/internal energy ratio of the materials whose inertia is artificial (:func:`quasi_static_materials`:
the mass-scaled ones declared quasi-static; ``FrameStats.ke_ie_ratio`` per frame), judged as Abaqus/Explicit
judges a quasi-static analysis: "the kinetic energy of the deforming material should not exceed a small
fraction (typically 5 % to 10 %) of its internal energy throughout the majority of the process" (Getting
Started with Abaqus, "Quasi-static analysis with Abaqus/Explicit", energy balance; the limit is
``config.quasi_static_ke_ie_max``), with the internal energy as Abaqus counts it, ALLIE: the stored strain energy
plus the plastic work dissipated so far (:func:`~tasks.physics.mpm.diagnostics.plastic_dissipation`; before 2026-12-04 the strain energy
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
over the contact so far; the contact is judged when it ends (:func:`close_quasi_static_contact`: the fingers
let go, a rupture, or the caller ends the run), listed in ``quasi_static_contacts`` with the share of its KE in
the body's sway on its base (``sway_ke_share``: the horizontal motion of the measured materials' centre of mass
and their rigid rotation about it, :func:`kinetic_energy_split`; a body pressed straight down has ~none), and
above the limit warned about once, in one line naming object, frames, times, that share and knobs
(``FrameStats.quasi_static_ok`` False in the frame that closed it).  A body rocking on the table under a
force-driven push (the default ball and duck: 85-99 % of their KE in the lowest, sway mode) is what the check is
for: its lowest mode is slower than the load (see the solver's ``load``).  The force-driven plush toy's sway under its
fingers' unbalanced net push (87 % of its KE; ``simulation.force_balance=none``) is real dynamics: the same
contact reads KE/IE 0.18 unscaled (docs/limits/quasi-static.md), so it warns at every mass scale > 1; the push
balanced in force and moment (the default) reads 0.037.

Quasi-static damping (``config.quasi_static_damping`` = a, 0 = off): mass scaling slows a scaled body's
vibration modes by sqrt(s) to periods of a few output frames, so a body pushed by a force (or loaded next to a
finger) rings instead of following its load.  As in explicit quasi-static analyses by dynamic relaxation (FLAC's
and PFC's local damping, Cundall 1987), the materials the quasi-static check measures get local non-viscous
damping (:func:`tasks.physics.mpm.kernels.transfer.local_damping`: the net force on a particle becomes F - a |F| sign(v),
per component) in every frame the caller declares quasi-static (``step_frame(quasi_static=True)``) of a
mass-scaled run.  It removes a fixed fraction of the vibration energy per cycle at any frequency and vanishes at
equilibrium (a block pushed by a constant force settles on its static compression).  It is not a cure for a
load that rises as fast as the scaled body's slowest mode (measured in the squeezes: the response then lags, see
``conf/mpm/default.yaml``): there only less mass scaling helps.  Released material, fluids and every frame after
a rupture (``quasi_static=False``) keep their inertia undamped; an unscaled run is never damped.
``FrameStats.local_damping`` is the coefficient a the measured materials had in the frame.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional, Sequence

import numpy as np

from conf.mpm_schema import MPMConfig

from .materials import COL_DAMPING, Material
from .model import present_materials, upload_materials

if TYPE_CHECKING:
    from .solver import MPMSolver


# Loaded frames at the start of every contact that the quasi-static check skips: where a finger first touches, the
# material under it is brought to the finger's speed while its strain energy is still that of its weight, so the
# kinetic/internal ratio is large however slowly the finger moves (first frame: orange 0.33, tomato 1.5 at the
# default 30 frames/s; second frame of the gentle tomato poke at 20 frames/s: 0.12; then below 0.03).  Mass scaling
# ties the scaled dynamics to the frame (s ~ frame_dt^2), so the transient spans about the same frames at any rate.
QUASI_STATIC_ONSET_FRAMES = 2


def energy_ratio(kinetic: float, internal: float) -> float:
    """KE / IE (inf: kinetic energy without internal energy, 0: neither)."""
    return kinetic / internal if internal > 1e-30 else (math.inf if kinetic > 0 else 0.0)


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


@dataclass(frozen=True)
class QuasiStaticLoad:
    """The time scale of the boundary load, for the quasi-static bound of the mass scale (see :func:`mass_scale_for`).

    ``rise_time``: t_load in s, how fast the fingers load the body (the rollout: the ramp time of the total force
    coefficient, :func:`tasks.physics.rollout_scene.load_rise_time`).  ``height``: H in m, the body's extent along
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


def resolve_auto_mass_scale(solver: MPMSolver, frame_dt: float) -> None:
    if not solver._mass_scale_pending:
        return
    solver._mass_scale_pending = False
    solver.mass_scale = mass_scale_for(present_materials(solver), solver.dx, frame_dt, solver.cfg, solver.load)
    solver.material_mass_scale = material_mass_scales(solver.materials, present_materials(solver), solver.dx, frame_dt,
                                                      solver.cfg, solver.load)
    upload_materials(solver)


def resume_load(solver: MPMSolver, load: Optional[QuasiStaticLoad]) -> None:
    """Give ``solver`` back the boundary ``load`` its gravity preload ran without (None: none): the squeeze's mass
    scale, bounded by that load, is then resolved at its first frame."""
    if load is not None:
        solver.load = load
        solver._mass_scale_pending = solver.cfg.mass_scaling in ("global", "selective")


def set_damping(solver: MPMSolver, quasi_static: bool) -> None:
    """The frame's local damping coefficients (module doc, quasi-static damping): ``quasi_static_damping`` on the
    measured materials of a mass-scaled run in a quasi-static frame, else none."""
    a = float(solver.cfg.quasi_static_damping)
    on = quasi_static and solver.mass_scale > 1.0 and a > 0.0
    rates = np.where(quasi_static_materials(solver), a, 0.0) if on else np.zeros(len(solver.materials))
    if solver._preload_damping > 0.0:  # preload_gravity: everything settles
        rates = np.full(len(solver.materials), solver._preload_damping)
    if not np.array_equal(rates, solver._damping):
        solver._damping = rates
        solver._mat_params[:, COL_DAMPING] = rates
        solver.mat_par.assign(solver._mat_params)


def close_quasi_static_contact(solver: MPMSolver) -> bool:
    """Judge the open contact of the quasi-static check (module doc): the solver calls it in the first frame after
    a contact (the fingers let go, or a rupture), the caller when it ends the run while a finger still loads the
    body.  The contact's KE/IE (sum KE / sum IE of the measured materials over its checked frames) is appended
    to ``quasi_static_contacts`` (first_frame, last_frame, ke_ie) and, above ``config.quasi_static_ke_ie_max``,
    warned about once per solver in one line naming object, frames, times, materials and knobs.  Returns
    whether it passed (True when no contact was open)."""
    c, solver._contact = solver._contact, None
    if c is None:
        return True
    ratio = energy_ratio(c["ke"], c["ie"])
    sway = c["ke_sway"] / c["ke"] if c["ke"] > 0 else 0.0
    solver.quasi_static_contacts.append({"first_frame": c["first_frame"], "last_frame": c["last_frame"],
                                       "ke_ie": ratio, "sway_ke_share": sway})
    ok = not ratio > solver.cfg.quasi_static_ke_ie_max
    if not ok and not solver._warned_quasi_static:  # once per solver; every contact's value is in the list
        solver._warned_quasi_static = True
        who = f"object '{solver.label}': " if solver.label else ""
        names = ", ".join(f"'{solver.materials[i].name}' x{solver.material_mass_scale[i]:.3g}"
                          for i in np.flatnonzero(quasi_static_materials(solver)) if i in solver._present)
        warnings.warn(
            f"{who}quasi-static check over frames {c['first_frame']}-{c['last_frame']} of a contact "
            f"(t={c['first_time']:.4g}-{c['last_time']:.4g} s): kinetic/internal energy ratio {ratio:.3g} of the "
            f"mass-scaled material ({names}; {100 * sway:.0f} % of its kinetic energy in the body's sway on "
            "its base: horizontal motion of its centre of mass and rotation about it) > "
            f"mpm.quasi_static_ke_ie_max={solver.cfg.quasi_static_ke_ie_max:g} "
            "while the boundary loads it: the squeeze is dynamic in the scaled time and inertia distorts the "
            "deformation; scale less (mpm.quasi_static_margin, now "
            f"{solver.cfg.quasi_static_margin:g}, bounds the scale by a force-driven load's rise time; "
            "mpm.mass_scaling=off, or a larger mpm.target_substeps_per_frame) or squeeze more slowly (a longer "
            "signal.duration)",
            RuntimeWarning, stacklevel=3)
    return ok


def sway_kinetic_energy(solver: MPMSolver, measured: np.ndarray) -> float:
    """Kinetic energy (J, scaled masses) of the sway of the particles of the ``measured`` (material,) materials on
    their base: the horizontal motion of their centre of mass and their rigid rotation about it
    (:func:`kinetic_energy_split`, vertical = against gravity)."""
    on = measured[solver._mid_host]
    g = np.asarray(solver.cfg.gravity, np.float64)
    up = -g / np.linalg.norm(g) if np.any(g) else np.array([0.0, 0.0, 1.0])
    horizontal, _, rotation, _ = kinetic_energy_split(solver.positions()[on], solver.velocities()[on],
                                                      solver.masses()[on], up)
    return horizontal + rotation


def quasi_static_materials(solver: MPMSolver) -> np.ndarray:
    """(material,) bool: the materials the kinetic/internal energy ratio measures: the mass-scaled ones declared
    quasi-static (``Material.is_mass_scaled``; released or flying material and fluids are not, whatever the
    scaling mode); without scaling every declared one, else every material."""
    declared = np.array([m.is_mass_scaled for m in solver.materials])
    for mask in (declared & (solver.material_mass_scale > 1.0), declared):
        if mask.any():
            return mask
    return np.ones(len(solver.materials), bool)
