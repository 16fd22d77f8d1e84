"""Diagnostics of a run: the frame statistics (:class:`FrameStats`), the guards that stop a run leaving its valid
range (error flags raised by the kernels, the J range, the energy guard, :class:`EnergyBudget`) with one
:class:`SimulationError` line naming where and when, and the plastic work dissipated so far.

Energy guard (``config.energy_guard_tolerance``): after every frame the total energy E = kinetic + internal +
gravitational (-m_phys g . x) is compared with its value at the reference frame (construction, or the end of the
first frame after a state setter) plus the work the boundary put in since (per frame, the positive part of the
work of the Dirichlet nodes, impulse . new velocity = m (v_bc - v*) . v_bc per node and substep, and of the force
patches, impulse . node velocity).  Walls, floor, friction, plasticity and viscosity only remove energy, and
gravity only exchanges it with the potential term, so growth beyond tolerance x energy scale (see
:class:`EnergyBudget`; never below the loading's scale, :func:`loading_floor`) is a numerical instability:
:class:`SimulationError` naming object, frame, time and the
materials whose energy grew.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Optional

import numpy as np
import warp as wp

from .boundary import pin_finger_of
from .kernels.structs import N_FLAGS, NO_SUBSTEP
from .mass_scaling import (
    QUASI_STATIC_ONSET_FRAMES,
    close_quasi_static_contact,
    energy_ratio,
    quasi_static_materials,
    sway_kinetic_energy,
)
from .materials import COL_HARDENING, COL_YIELD, PLASTIC_MODELS

if TYPE_CHECKING:
    from .solver import MPMSolver


class SimulationError(RuntimeError):
    """The simulation left its valid range (non-finite state, particle out of the grid, extreme J, Courant)."""


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
    local_damping: float = 0.0  # local damping coefficient of the measured materials during the frame (:mod:`tasks.physics.mpm.mass_scaling`)
    plastic_dissipation: float = 0.0  # J, plastic work the measured materials dissipated so far (plastic_dissipation)

    def as_dict(self) -> dict:
        d = dict(self.__dict__)
        for k, v in d.items():
            if isinstance(v, np.ndarray):
                d[k] = v.tolist()
        return d


@dataclass
class EnergyBudget:
    """Energy guard bookkeeping from a reference frame on (J; see the module doc).

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


def reset_flags(solver: MPMSolver, flags: Optional[wp.array] = None) -> None:
    f = np.zeros(N_FLAGS, np.int32)
    f[4:8] = NO_SUBSTEP
    f[8:12] = -1
    (solver.flags if flags is None else flags).assign(f)


def frame_stats(solver: MPMSolver, nsub: int, dts: list[float], frame_dt: float, wall0: float,
                 quasi_static: bool) -> FrameStats:
    s = solver.sums.numpy()
    e = solver.ext.numpy()
    ke, ie = float(s[0]), float(s[1])
    per = solver.mat_energy.numpy()  # (material, [KE, IE, PE]) J
    work = float(solver.boundary_work.numpy()[0])
    measured = quasi_static_materials(solver)
    dissipated = measured_plastic_dissipation(solver, measured)
    ke_s, ie_s = float(per[measured, 0].sum()), float(per[measured, 1].sum()) + dissipated
    local_damping = float(solver._damping[measured].max(initial=0.0))
    ratio = energy_ratio(ke_s, ie_s)
    reaction = solver.finger_react.numpy().astype(np.float64) / frame_dt
    applied = solver.finger_applied.numpy().astype(np.float64) / frame_dt
    loaded = quasi_static and bool(np.any(reaction != 0) or np.any(applied != 0))
    solver._loaded_frames = solver._loaded_frames + 1 if loaded else 0
    checked = solver.mass_scale > 1.0 and solver._loaded_frames > QUASI_STATIC_ONSET_FRAMES
    qs_ok = checked or close_quasi_static_contact(solver)  # a contact ended before this frame: judged
    process = math.nan
    if checked:
        if solver._contact is None:  # the contact's first checked frame
            solver._contact = {"first_frame": solver.frame, "first_time": solver.time, "ke": 0.0, "ie": 0.0,
                             "ke_sway": 0.0}
        c = solver._contact
        c["ke"] += ke_s
        c["ie"] += ie_s
        c["ke_sway"] += sway_kinetic_energy(solver, measured)
        c["last_frame"], c["last_time"] = solver.frame, solver.time
        process = energy_ratio(c["ke"], c["ie"])
    return FrameStats(
        frame=solver.frame, time=solver.time, substeps=nsub, dt_min=min(dts), dt_max=max(dts),
        courant=solver.courant_number(max(dts)), max_speed=float(e[2]), j_min=float(e[0]), j_max=float(e[1]),
        kinetic_energy=ke, internal_energy=ie, ke_ie_ratio=ratio, momentum=s[2:5].copy(), mass=float(s[5]),
        reaction=reaction, applied_force=applied,
        mass_scale=solver.mass_scale, stiffness_scale=solver.stiffness_scale, quasi_static_ok=qs_ok,
        wall_seconds=time.perf_counter() - wall0, gravitational_energy=float(per[:, 2].sum()),
        boundary_work=work, quasi_static_checked=checked, ke_ie_contact=process, local_damping=local_damping,
        plastic_dissipation=dissipated,
    )


def measured_plastic_dissipation(solver: MPMSolver, measured: np.ndarray) -> float:
    """The plastic work (J) the particles of the ``measured`` materials (material,) bool have dissipated so far
    (:func:`plastic_dissipation`, at the material table's yield stress and hardening: scaled as the kernels use
    them); 0 without a plastic material."""
    if not solver.has_plastic:
        return 0.0
    rows = measured & np.isin(solver.mat_model.numpy(), PLASTIC_MODELS)
    on = rows[solver._mid_host]
    if not on.any():
        return 0.0
    par, mid = solver.mat_par.numpy(), solver._mid_host[on]
    return plastic_dissipation(solver.alpha.numpy()[on], solver.vol.numpy()[on], par[mid, COL_YIELD],
                               par[mid, COL_HARDENING])


def energy_baseline(solver: MPMSolver) -> None:
    """Before the first frame: the reference energy of the initial state (F_E = I, C = 0: no internal energy),
    per material: kinetic 1/2 m v^2 (scaled masses) + gravitational -m_phys g . x (J)."""
    if not solver._energy_initial:
        return
    solver._energy_initial = False
    m, m_phys = solver.masses().astype(np.float64), solver.physical_masses().astype(np.float64)
    x, v = solver.x.numpy().astype(np.float64), solver.v.numpy().astype(np.float64)
    ke = 0.5 * m * np.einsum("ij,ij->i", v, v)
    pe = -m_phys * (x @ np.asarray(solver.cfg.gravity, np.float64))
    per = np.bincount(solver._mid_host, weights=ke + pe, minlength=len(solver.materials))
    solver._energy_ref = EnergyBudget.start(solver.frame, per, float(pe.sum()), float(ke.sum()), solver._energy_ref)


def energy_state_changed(solver: MPMSolver) -> None:
    """A state setter changed the energy from outside: the guard re-bases at the end of the next frame (the
    initial state keeps its exact reference unless F_E was set); the energy scale reached so far is kept."""
    if solver.frame > 0:
        solver._energy_initial = False
        solver._energy_ref = EnergyBudget.rebase(solver._energy_ref)


def loading_floor(solver: MPMSolver, st: FrameStats) -> float:
    """The energy scale (J) below which the guard never stops a run, from the loading's scale: the energy of moving
    the largest load seen so far through one grid cell dx, where the discretisation resolves no change of shape.
    The loads are the body's weight (physical mass x |g|: a body settling on the floor exchanges micro-joules
    between gravity and strain) and the boundary's force, read from its impulses (the mean force of every finger's
    Dirichlet nodes, pins, colliders and force patches over the frame, summed over the fingers).  The floor is kept
    as a running maximum (``solver._loading_force``, N): a scripted squeeze that starts at rest, with a smooth ramp
    and no gravity, has a near-zero energy at its first frames, and a tolerance relative to it alone stopped it at
    frame 1 on 5e-8 J of round-off (issue 50).  An instability grows the energy by orders of magnitude within a few
    substeps (x28 in 5 substeps at Courant 0.95), far beyond any such floor."""
    weight = float(solver.physical_masses().astype(np.float64).sum()) * float(
        np.linalg.norm(np.asarray(solver.cfg.gravity, np.float64)))
    pushed = float(np.linalg.norm(np.asarray(st.reaction, np.float64), axis=-1).sum()
                   + np.linalg.norm(np.asarray(st.applied_force, np.float64), axis=-1).sum())
    solver._loading_force = max(solver._loading_force, pushed if math.isfinite(pushed) else 0.0)
    return max(weight, solver._loading_force) * solver.dx


def check_energy(solver: MPMSolver, st: FrameStats) -> None:
    """Energy guard (see the module doc and :class:`EnergyBudget`): raise when the energy grew beyond the
    reference energy plus the boundary work put in by more than tolerance x energy scale."""
    rel = float(solver.cfg.energy_guard_tolerance)
    per_split = solver.mat_energy.numpy()
    per = per_split.sum(axis=1)
    ref = solver._energy_ref
    if ref is None or ref.frame is None:
        solver._energy_ref = EnergyBudget.start(solver.frame, per, st.gravitational_energy,
                                                st.kinetic_energy + st.internal_energy, ref)
        return
    growth = ref.update(per, st.gravitational_energy, st.boundary_work)
    scale = max(ref.scale, loading_floor(solver, st))
    tol = rel * scale + 1e-9
    st.energy_growth = growth / max(scale, 1e-9)  # (1e-9 J: the absolute floor of the tolerance)
    if rel <= 0 or growth <= tol:
        return
    grew = np.argsort(-(per - ref.energy))
    names = ", ".join(f"'{solver.materials[i].name}' +{per[i] - ref.energy[i]:.3g} J (kinetic "
                      f"{per_split[i, 0]:.3g}, internal {per_split[i, 1]:.3g})"
                      for i in grew[:3] if per[i] > ref.energy[i])
    who = f"object '{solver.label}': " if solver.label else ""
    raise SimulationError(
        f"{who}energy guard at frame {st.frame} (t={st.time:.6g} s): the total energy (kinetic + internal + "
        f"gravitational) grew by {growth + ref.work_in:.4g} J since frame {ref.frame}, {growth:.4g} J beyond the "
        f"boundary work put in {ref.work_in:.4g} J (tolerance {tol:.3g} J = {rel:g} x energy scale "
        f"{scale:.3g} J); grew: {names}. "
        f"Likely cause: numerical instability (Courant number {st.courant:.3g}, limit "
        f"{solver.cfg.courant_limit:.3g}, c_p={solver.c_max:.4g} m/s, dx={solver.dx:.4g} m); lower mpm.courant or dt")


def substep_time(solver: MPMSolver, sub: int) -> float:
    best = solver.time
    for s, t in solver._times:
        if s <= sub:
            best = t
    return best


def material_name(solver: MPMSolver, p: int) -> str:
    return solver.materials[int(solver._mid_host[p])].name


def check_flags(solver: MPMSolver, force_nonfinite: bool = False) -> None:
    f = solver.flags.numpy()
    for sh in solver._shares:  # merge the chunks' flags (counts, first substep, an offending index)
        g = sh["flags"].numpy()
        if g[:4].any():
            f[:4] += g[:4]
            f[4:8] = np.minimum(f[4:8], g[4:8])
            f[8:] = np.maximum(f[8:], g[8:])
            reset_flags(solver, sh["flags"])
    if not (f[0] or f[1] or f[2] or f[3]) and not force_nonfinite:
        return
    x = solver.x.numpy()
    F = solver.F.numpy()
    taken = getattr(solver, "_frame_dts", None)  # the largest dt actually used this frame, not the post-blow-up one
    cn = solver.courant_number(max(taken) if taken else (
        solver._stable_dt(solver._vmax) if solver.cfg.dt is None else solver.cfg.dt))
    hint_dt = (f"Courant number {cn:.3g} (limit {solver.cfg.courant_limit:.3g}), c_p={solver.c_max:.4g} m/s, "
               f"dx={solver.dx:.4g} m")
    if f[1] or force_nonfinite:  # non-finite first: it explains the others
        bad = ~(np.isfinite(x).all(1) & np.isfinite(F).reshape(len(F), -1).all(1))
        p = int(np.argmax(bad)) if bad.any() else int(max(f[9], 0))
        sub = int(f[5]) if f[5] != NO_SUBSTEP else solver.substep
        raise SimulationError(
            f"non-finite particle state (NaN/inf position, velocity or F) at substep {sub} "
            f"(t={substep_time(solver, sub):.6g} s, frame {solver.frame}); {int(bad.sum())} particles non-finite now; "
            f"worst particle #{p} of material '{material_name(solver, p)}'. Likely cause: numerical blow-up - "
            f"the time step is too large for the stiffness ({hint_dt}) or the input contains NaN; "
            "lower dt or E, or enable stiffness/mass scaling")
    if f[0]:
        g = (x.astype(np.float64) - solver.lo) / solver.dx
        lo_b, hi_b = 1.0, np.asarray(solver.dims, np.float64) - 2.0
        out = np.maximum(lo_b - g, 0.0).max(1) + np.maximum(g - hi_b, 0.0).max(1)
        p = int(np.argmax(out)) if out.max() > 0 else int(max(f[8], 0))
        sub = int(f[4])
        hi = (solver.lo + (np.asarray(solver.dims) - 1) * solver.dx).round(5).tolist()
        raise SimulationError(
            f"particle left the simulation grid (entered the padding layer / domain boundary) at substep {sub} "
            f"(t={substep_time(solver, sub):.6g} s, frame {solver.frame}); {int(f[0])} offences; worst particle #{p} "
            f"of material '{material_name(solver, p)}' at {x[p].round(5).tolist()} m, grid "
            f"[{solver.lo.round(5).tolist()}, {hi}]. "
            f"Likely cause: velocities too large (max speed {solver._vmax:.4g} m/s; unstable material, "
            f"{hint_dt}) or boundary targets driving material out of the domain; enlarge the domain "
            "(margin_cells / domain_lo / domain_hi) or lower dt")
    if f[2]:
        J = np.linalg.det(F.astype(np.float64))
        dev = np.abs(np.log(np.clip(J, 1e-30, None)))
        dev[~np.isfinite(J) | (J <= 0)] = np.inf
        p = int(np.argmax(dev))
        sub = int(f[6])
        pinned = pin_finger_of(solver, p)
        cause = ("element inversion or over-stretch - the load or boundary velocity is too large for the material "
                 f"stiffness, or the time step is too large ({hint_dt}); lower dt, raise E, or use a plastic/fluid "
                 "model for this material") if pinned is None else (
            f"it is pinned (ParticlePins, finger id {pinned}): the finger's whole push acts on the pinned "
            "particles' surfaces and crushes them where the prescribed displacement meets a stiff response; "
            "use grid-node Dirichlet fingers (mpm.fingers=dirichlet), which spread it over the grid")
        raise SimulationError(
            f"extreme volume change det(F)={J[p]:.4g} outside [{solver.cfg.j_min}, {solver.cfg.j_max}] at substep "
            f"{sub} (t={substep_time(solver, sub):.6g} s, frame {solver.frame}); {int(f[2])} offences; worst particle "
            f"#{p} of material '{material_name(solver, p)}'. Likely cause: {cause}")
    if f[3]:
        sub = int(f[7])
        p = int(f[11])
        raise SimulationError(
            f"a boundary / force point left the simulation grid (entered the padding layer) at substep {sub} "
            f"(t={substep_time(solver, sub):.6g} s, frame {solver.frame}); point #{p}. Likely cause: constrained or "
            "force points lie outside the domain box, or targets move them out; enlarge the domain")


def check_state(solver: MPMSolver, st: FrameStats) -> None:
    """Per-frame cheap checks: finite energies/momentum and the J range."""
    vals = [st.kinetic_energy, st.internal_energy, st.j_min, st.j_max, st.max_speed, *st.momentum.tolist()]
    if not all(math.isfinite(v) for v in vals):
        check_flags(solver, force_nonfinite=True)
    if st.j_min < solver.cfg.j_min or st.j_max > solver.cfg.j_max:
        solver.flags.assign(np.array([0, 0, 1, 0, 0, 0, solver.substep, 0, -1, -1, 0, -1], np.int32))
        check_flags(solver)
