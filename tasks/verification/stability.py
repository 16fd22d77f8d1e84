"""Numerical stability suite (issue 5): stiff and extreme cases run through the production code path.

Every case returns one :class:`Row`: outcome, reason, max particle speed, J range, energy measure, Courant number,
substeps, substeps per simulated second, run time, and an accuracy figure where a reference exists.

Outcomes
    ``stable``    the run finished, the guards stayed quiet and the suite's own checks (below) found nothing;
    ``unstable``  a :class:`~tasks.physics.mpm.diagnostics.SimulationError` raised by the solver's guards after the run started
                  (non-finite state, particle out of the grid, extreme J, collapsing step), its message recorded;
                  or the suite's own checks found a failure the guards did NOT catch (reason starts ``UNCAUGHT``);
    ``refused``   a validation error raised before the step it concerns ran: config / material / boundary-input
                  validation, or the forced Courant check (reason = the error's message);
    ``flagged`` / ``resolved``  thin-wall cases (a resolution finding, no simulation; :mod:`tasks.physics.wall_resolution`);
    ``error``     any other exception type: a guard is missing (the message is recorded, the suite goes on).

Case kinds and their production path
    * ``compression`` (stiffness sweep, near-incompressible, acceleration knobs, Courant, boundary): a column
      W x W x L (W = 4 dx, L = 8 dx) of particles at the production spacing (``sampling.particle_spacing``, dx
      exactly as :func:`tasks.physics.mpm_rollout.mpm_rollout` chooses it) with the material the production oracle gives
      the named object, run by :class:`~tasks.physics.mpm.MPMSolver` with the production ``mpm`` config.  Changed for a
      closed form and a conservative system, and only these: gravity 0 and no floor; two frictionless plates
      (slip Dirichlet points) compress the column to the strain ``eps`` (below the yield strain), hold, then let
      go.  Phases: load (20% velocity ramp), hold, free (no boundary: the column rings in free space).
      Timing ``intrinsic``: load over 20 L / c (c = sqrt(E/rho), quasi-static in the material's own time, the
      "short simulated window" of the stiff cases), hold 4 L / c, free 3 periods of the axial mode (2 L / c each);
      ``human``: load over 0.2 s at the 30 Hz frame rate (the squeeze time scale the acceleration knobs are for),
      hold 0.1 s, free >= 3 periods (with the scaled wave speed).
    * ``squeeze``: the real pipeline functions (:func:`tasks.control.squeeze_signals.grasp_targets` -> crafted session ->
      :func:`~tasks.control.signal_smoothing.smooth_signals` -> :func:`~tasks.control.force_coefficients.force_coefficients` ->
      :func:`~tasks.control.contact_patches.contact_patches` -> :func:`~tasks.control.dirichlet_field.dirichlet_field` ->
      :func:`~tasks.physics.mpm_rollout.mpm_rollout`) on a real object (:func:`~tasks.control.object_model.build_object_model`,
      :func:`~tasks.physics.particle_fill.build_mpm_particles`)
      with the production config groups, called directly (no Prefect).
    * ``push_out`` / ``nan_state`` / ``nan_input``: the compression column driven into the domain boundary, or
      corrupted by a NaN in its state / in its boundary input, to exercise the guards.
    * ``thin_wall``: :func:`tasks.physics.wall_resolution.thin_wall_finding` on the real object model.

Measures (SI)
    max_speed       m/s, largest end-of-frame particle speed;
    j_min, j_max    range of det F_E over all frames (end-of-frame values);
    energy_drift    FREE phase of a compression case only: (KE + IE)(end) / (KE + IE)(release) - 1 (no gravity, no
                    boundary after the release, so a conservative system: < 0 is numerical dissipation, > 0 is
                    energy created by the integrator);
    ke_ie_max       DRIVEN phases: a compression case's loading/hold, the largest kinetic/internal energy ratio; a
                    rollout, the quasi-static check's measure (sum KE / sum IE over a contact) at its largest over
                    the contacts the solver judges (NaN: none checked);
    courant         largest c_p dt / dx over the frames (c_p after scaling);
    accuracy_error  compression: F_top / (E A eps_mid) - 1 over the second half of the loading (E the REAL modulus,
                    eps_mid the mean compressive strain F_zz - 1 of the middle third of the column, A = W^2): the
                    closed form of uniaxial stress between frictionless plates, so it shows inertia (mass scaling)
                    and the force factor of stiffness scaling; squeeze: observed / prescribed peak squeeze strain - 1
                    up to the rupture (afterwards the torn patch is no longer driven).

Checks the suite adds to the guards (an ``UNCAUGHT`` finding when they fail): the final state is finite; in the
free phase the energy never grows by more than ``ENERGY_GROWTH_LIMIT``; in a rollout the outputs are finite, the
surface Gaussians stay on the material (no more than ``DETACHED_LIMIT`` of them farther than 1 dx from every
particle) and a weakly compressible interior fluid keeps its volume (|mean J - 1| <= ``FLUID_VOLUME_LIMIT`` and at
most ``FLUID_FAR_LIMIT`` of its particles beyond |J - 1| > 20 %; the fluid is designed for ~1 %).
"""
from __future__ import annotations

import csv
import json
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from tasks.physics.wall_resolution import grid_spacing, thin_wall_finding

ENERGY_GROWTH_LIMIT = 0.05  # 1, free-phase energy growth above this is reported as UNCAUGHT
DETACHED_LIMIT = 0.01  # 1, fraction of surface Gaussians farther than 1 dx from every particle
FLUID_VOLUME_LIMIT = 0.05  # 1, |mean J - 1| of a weakly compressible interior fluid (designed for ~1 %)
FLUID_FAR_LIMIT = 0.05  # 1, fraction of its particles with |J - 1| > 20 %
FRAME_RATE_HUMAN = 30.0  # Hz, the production output frame rate (control.smoothing.frame_rate default)

OUTCOMES = ("stable", "unstable", "refused", "flagged", "resolved", "error")


# ============================================================================================ rows and cases
@dataclass
class Row:
    """One line of the stability table (SI units; NaN = not applicable)."""

    case: str
    category: str
    outcome: str = "stable"
    reason: str = ""
    max_speed: float = math.nan  # m/s
    j_min: float = math.nan
    j_max: float = math.nan
    energy_drift: float = math.nan  # free phase: (KE+IE)(end)/(KE+IE)(release) - 1
    ke_ie_max: float = math.nan  # driven phases: max KE/IE
    courant: float = math.nan
    substeps: int = 0
    substeps_per_simulated_second: float = math.nan  # 1/s
    simulated_seconds: float = 0.0  # s
    wall_seconds: float = 0.0  # s
    accuracy_error: float = math.nan  # relative
    accuracy_reference: str = ""
    error_vs_unaccelerated: float = math.nan  # (1 + accuracy_error) / (1 + that of the baseline case) - 1
    mass_scale: float = 1.0
    stiffness_scale: float = 1.0
    notes: str = ""

    def as_dict(self) -> dict:
        return asdict(self)


ROW_FIELDS = [f.name for f in fields(Row)]


@dataclass
class Case:
    """A stability case: ``kind`` selects the runner, ``params`` its inputs, ``quick`` puts it in the quick subset."""

    name: str
    category: str
    kind: str
    description: str
    params: dict = field(default_factory=dict)
    quick: bool = False


@dataclass
class SuiteContext:
    """The production configuration groups (plain dicts): ``mpm``, ``sampling``, ``control`` (smoothing, force,
    contact, displacement), ``signal``, ``simulation``, ``oracle`` and the object ``catalog`` (name -> config)."""

    mpm: dict
    sampling: dict
    control: dict
    signal: dict
    simulation: dict
    oracle: dict
    catalog: dict

    @classmethod
    def from_config(cls, cfg: Any) -> SuiteContext:
        from omegaconf import OmegaConf

        def plain(node: Any) -> Any:
            return OmegaConf.to_container(node, resolve=True) if not isinstance(node, (dict, list)) else node

        return cls(mpm=plain(cfg.mpm), sampling=plain(cfg.sampling), control=plain(cfg.control),
                   signal=plain(cfg.signal), simulation=plain(cfg.simulation), oracle=plain(cfg.oracle),
                   catalog={k: plain(v) for k, v in cfg.catalog.items()})


def _gel() -> dict:
    return {"name": "very_soft_gel", "model": "fixed_corotated", "youngs_modulus": 1.0e3, "poisson_ratio": 0.3, "density": 1000.0}


def default_cases() -> list[Case]:
    """The suite (order = table order).  Materials ``oracle:<object>`` are the production oracle's shell material."""
    C = Case
    return [
        # ---- stiffness sweep, adaptive step, no acceleration (intrinsic time scale = short window for the stiff)
        C("soft_gel_1kPa", "stiffness", "compression", "very soft gel E 1 kPa, nu 0.3", {"material": _gel()}, True),
        C("plush_300kPa", "stiffness", "compression", "plush toy fabric (oracle)", {"material": "oracle:plush_toy"}),
        C("clay_4MPa", "stiffness", "compression", "modelling clay (oracle), below yield", {"material": "oracle:clay"}),
        C("paperboard_4GPa", "stiffness", "compression", "paper cup board (oracle), below yield",
          {"material": "oracle:paper_cup"}),
        C("aluminium_69GPa", "stiffness", "compression", "can aluminium (oracle) 69 GPa, below yield",
          {"material": "oracle:can"}, True),
        # ---- near-incompressible (rubber ball's rubber with nu replaced)
        C("rubber_nu0.45", "incompressible", "compression", "rubber E 2.5 MPa, nu 0.45",
          {"material": "oracle:rubber_ball", "poisson_ratio": 0.45}),
        C("rubber_nu0.49", "incompressible", "compression", "rubber E 2.5 MPa, nu 0.49 (oracle value)",
          {"material": "oracle:rubber_ball", "poisson_ratio": 0.49}),
        C("rubber_nu0.499", "incompressible", "compression", "rubber E 2.5 MPa, nu 0.499",
          {"material": "oracle:rubber_ball", "poisson_ratio": 0.499}),
        # ---- acceleration knobs at the human time scale (0.2 s squeeze at 30 Hz)
        C("aluminium_mass_auto", "knobs", "compression", "aluminium, mass scaling auto (production target)",
          {"material": "oracle:can", "timing": "human", "knob": "mass_auto", "baseline": "aluminium_69GPa"}, True),
        C("aluminium_mass_auto_x5", "knobs", "compression", "aluminium, mass scaling auto, target / 5",
          {"material": "oracle:can", "timing": "human", "knob": "mass_auto", "target_factor": 0.2,
           "baseline": "aluminium_69GPa"}),
        C("aluminium_stiffness_scaled", "knobs", "compression",
          "aluminium, stiffness scaling 1/s (same substeps as mass auto)",
          {"material": "oracle:can", "timing": "human", "knob": "stiffness", "baseline": "aluminium_69GPa"}),
        C("paperboard_mass_auto", "knobs", "compression", "paperboard, mass scaling auto",
          {"material": "oracle:paper_cup", "timing": "human", "knob": "mass_auto",
           "baseline": "paperboard_4GPa"}),
        C("rubber_nu0.499_mass_auto", "knobs", "compression", "rubber nu 0.499, mass scaling auto",
          {"material": "oracle:rubber_ball", "poisson_ratio": 0.499, "timing": "human", "knob": "mass_auto",
           "baseline": "rubber_nu0.499"}),
        # ---- Courant number forced above the limit
        C("courant_forced_1.5", "courant", "compression", "forced dt at Courant 1.5 (limit 0.8)",
          {"material": "oracle:clay", "forced_courant": 1.5}, True),
        C("courant_forced_1.0", "courant", "compression", "forced dt at Courant 1.0 (above the 0.8 limit)",
          {"material": "oracle:clay", "forced_courant": 1.0}),
        C("courant_adaptive_0.8_nu0.49", "courant", "compression",
          "adaptive step at the largest accepted mpm.courant 0.8, fixed-corotated E 4 MPa nu 0.49",
          {"material": {"model": "fixed_corotated", "youngs_modulus": 4.0e6,
                        "poisson_ratio": 0.49, "density": 1700.0}, "mpm": {"courant": 0.8}}),
        C("courant_adaptive_0.95_nu0.45", "courant", "compression",
          "courant_limit raised to 1 by the user, adaptive mpm.courant 0.95, fixed-corotated E 4 MPa nu 0.45",
          {"material": {"model": "fixed_corotated", "youngs_modulus": 4.0e6,
                        "poisson_ratio": 0.45, "density": 1700.0}, "mpm": {"courant": 0.95, "courant_limit": 1.0}},
          True),
        C("courant_unguarded_2.5", "courant", "compression", "limit raised to 3, forced dt at Courant 2.5",
          {"material": "oracle:clay", "forced_courant": 2.5, "mpm": {"courant_limit": 3.0}}),
        # ---- domain boundary
        C("touching_boundary", "boundary", "compression", "column flush with the domain box (x) while squeezed",
          {"material": "oracle:clay", "touching": True}),
        C("pushed_out", "boundary", "push_out", "a finger pushes the column through a tight domain box",
          {"material": "oracle:clay"}, True),
        # ---- non-finite
        C("nan_state", "nonfinite", "nan_state", "NaN written into one particle velocity mid-run",
          {"material": "oracle:clay"}, True),
        C("nan_boundary_input", "nonfinite", "nan_input", "NaN in one Dirichlet target velocity",
          {"material": "oracle:clay"}, True),
        # ---- extreme squeezes through the whole pipeline
        C("step_all_fingers", "squeeze", "squeeze",
          "all five fingers to full flexion within one frame (step), production smoothing; tomato",
          {"object": "tomato", "session": "step"}),
        C("step_all_fingers_raw", "squeeze", "squeeze",
          "the same step with the EMA off (ema_alpha 1): the step reaches the solver in one frame; tomato",
          {"object": "tomato", "session": "step", "smoothing": {"ema_alpha": 1.0}}),
        C("step_can", "squeeze", "squeeze", "step crush of the aluminium can (thin wall, cola)",
          {"object": "can", "session": "step"}),
        C("deep_poke", "squeeze", "squeeze", "index poke 1.6x deeper than the half-thickness; clay block",
          {"object": "clay", "session": "ramp", "fingers": [1], "depth_over_half": 1.6, "ramp": 0.4}),
        C("oscillation_sensor_rate", "squeeze", "squeeze",
          "full flexion on/off every sensor sample (Nyquist of the 200 Hz sensor); rubber ball",
          {"object": "rubber_ball", "session": "oscillation", "frequency": "nyquist"}),
        C("oscillation_12Hz", "squeeze", "squeeze",
          "full-amplitude 12 Hz squeeze (passes the 30 Hz anti-alias filter); rubber ball",
          {"object": "rubber_ball", "session": "oscillation", "frequency": 12.0}),
        # ---- thin walls
        *[C(f"thin_wall_{o}", "thin_wall", "thin_wall", f"wall vs grid spacing: {o}", {"object": o},
            o in ("can", "paper_cup", "rubber_ball"))
          for o in ("can", "paper_cup", "tomato", "rubber_duck", "plush_toy", "rubber_ball", "orange", "clay")],
    ]


def select_cases(names: Sequence[str] = (), quick: bool = False, cases: list[Case] | None = None) -> list[Case]:
    """Cases by name or category (empty = all); ``quick`` keeps the quick subset.  Unknown names are an error."""
    cases = default_cases() if cases is None else cases
    known = {c.name for c in cases} | {c.category for c in cases}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"unknown stability case(s) {unknown}; known cases: {[c.name for c in cases]}; "
                         f"categories: {sorted({c.category for c in cases})}")
    sel = [c for c in cases if not names or c.name in names or c.category in names]
    return [c for c in sel if c.quick] if quick else sel


# ============================================================================================ shared helpers
def _material(spec: Any, ctx: SuiteContext, poisson_ratio: float | None = None):
    """A :class:`~tasks.physics.mpm.materials.Material` from a kwargs dict or ``oracle:<object>`` (production oracle)."""
    from tasks.physics.mpm.materials import material_from_dict

    if isinstance(spec, str) and spec.startswith("oracle:"):
        from tasks.physics.material_oracle import material_oracle, mpm_material_kwargs

        name = spec.split(":", 1)[1]
        obj = ctx.catalog[name]
        mats = material_oracle(obj["description"], obj["name"], obj.get("material"), obj.get("interior"), ctx.oracle)
        kw = mpm_material_kwargs(mats.shell, f"{name}_shell")
    else:
        kw = dict(spec)
    if poisson_ratio is not None:
        kw["poisson_ratio"] = poisson_ratio
    return material_from_dict(kw)


def _target_substeps(ctx: SuiteContext) -> int:
    """Production substeps per output frame of the auto mass scaling (``mpm.target_substeps_per_frame``)."""
    return int(ctx.mpm["target_substeps_per_frame"])


def _lattice(lo: Sequence[float], hi: Sequence[float], h: float) -> np.ndarray:
    lo_a, hi_a = np.asarray(lo, float), np.asarray(hi, float)
    n = np.maximum(np.round((hi_a - lo_a) / h).astype(int), 1)
    axes = [lo_a[i] + (np.arange(n[i]) + 0.5) * (hi_a[i] - lo_a[i]) / n[i] for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def _classify(exc: BaseException, started: bool) -> tuple[str, str]:
    """(outcome, reason) of an exception raised by a case."""
    from conf.mpm_schema import MPMConfigError
    from tasks.physics.mpm import SimulationError
    from tasks.physics.mpm.materials import MaterialError

    msg = _one_line(exc)
    if isinstance(exc, SimulationError):
        return ("unstable" if started else "refused"), msg
    if isinstance(exc, (MPMConfigError, MaterialError, ValueError)):
        return "refused", f"{type(exc).__name__}: {msg}"
    return "error", f"{type(exc).__name__} (no guard caught it): {msg}"


class _Progress:
    """Whether the solver has taken a substep (an error before it is a refusal), and the frames so far."""

    def __init__(self) -> None:
        self.solver = None
        self.stats: list = []
        self.notes: list[str] = []  # what a runner knew before the error (kept in the row)

    @property
    def started(self) -> bool:
        return self.solver is not None and self.solver.substep > 0


def _fill_from_stats(row: Row, stats: list, sim_time: float) -> None:
    if not stats:
        return
    row.max_speed = max(s.max_speed for s in stats)
    row.j_min = min(s.j_min for s in stats)
    row.j_max = max(s.j_max for s in stats)
    row.courant = max(s.courant for s in stats)
    row.substeps = int(sum(s.substeps for s in stats))
    row.simulated_seconds = float(sim_time)
    row.substeps_per_simulated_second = row.substeps / sim_time if sim_time > 0 else math.nan
    row.mass_scale = float(stats[-1].mass_scale)
    row.stiffness_scale = float(stats[-1].stiffness_scale)


def _judged(case: Case, progress: _Progress, sim_time: float, outcome: str, reason: str) -> Row:
    """The row of a case that ran to its end without a guard stopping it, judged by the suite itself: the
    statistics of its frames, ``outcome`` and ``reason``."""
    row = Row(case.name, case.category)
    _fill_from_stats(row, progress.stats, sim_time)
    row.outcome, row.reason = outcome, reason
    return row


# ============================================================================================ compression cases
@dataclass
class _Column:
    W: float
    L: float
    X: np.ndarray
    vol: float
    dx: float


def _column(ctx: SuiteContext, mpm: dict) -> _Column:
    s = float(ctx.sampling["particle_spacing"])
    dx = grid_spacing(mpm, s)
    W, L = 4 * dx, 8 * dx
    return _Column(W, L, _lattice([0, 0, 0], [W, W, L], s), s ** 3, dx)


def _plates(col: _Column) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    dx = col.dx
    pg = _lattice([-dx, -dx, 0], [col.W + dx, col.W + dx, 0], dx / 2)[:, :2]
    top = np.c_[pg, np.full(len(pg), col.L)]
    bot = np.c_[pg, np.zeros(len(pg))]
    return top, bot, np.tile([0.0, 0.0, 1.0], (len(pg), 1))


def _compression_config(case: Case, ctx: SuiteContext, mat) -> tuple[dict, float]:
    """The production ``mpm`` config for a compression case: gravity 0, no floor, plus the case's knobs.
    Returns (config dict, frame_dt of the human timing or 0)."""
    p = case.params
    mpm = dict(ctx.mpm)
    mpm.update(gravity=[0.0, 0.0, 0.0], floor=False, mass_scaling="off", stiffness_scaling=1.0)
    mpm.update(p.get("mpm", {}))
    col_dx = grid_spacing(mpm, float(ctx.sampling["particle_spacing"]))
    mpm["dx"] = col_dx
    knob = p.get("knob")
    if knob == "mass_auto":
        mpm.update(mass_scaling="auto",
                   target_substeps_per_frame=max(1, round(_target_substeps(ctx) * p.get("target_factor", 1.0))))
    elif knob == "stiffness":
        # the stiffness factor that gives the same P-wave speed (same substeps) as the auto mass scale: k = 1 / s
        from conf.mpm_schema import mpm_config_from
        from tasks.physics.mpm import mass_scale_for

        auto = mpm_config_from({**mpm, "mass_scaling": "auto", "target_substeps_per_frame": _target_substeps(ctx)})
        mpm["stiffness_scaling"] = 1.0 / mass_scale_for([mat], col_dx, 1.0 / FRAME_RATE_HUMAN, auto)
    if "forced_courant" in p:
        c_p = mat.p_wave_speed(float(mpm["stiffness_scaling"]))
        mpm["dt"] = float(p["forced_courant"]) * col_dx / c_p
    return mpm, (1.0 / FRAME_RATE_HUMAN if p.get("timing") == "human" else 0.0)


def _strain_target(mat, p: Mapping[str, Any]) -> float:
    eps = float(p.get("strain", 0.01))
    if mat.yield_stress > 0:
        eps = min(eps, 0.5 * mat.yield_stress / mat.youngs_modulus)  # stay elastic: the closed form holds
    return eps


def run_compression(case: Case, ctx: SuiteContext, progress: _Progress | None = None) -> Row:
    """Load / hold / free run of the plate-compressed column (module doc); raises on guard errors."""
    from tasks.physics.mpm import DirichletPoints, MPMSolver

    p = case.params
    progress = progress or _Progress()
    mat = _material(p["material"], ctx, p.get("poisson_ratio"))
    mpm, human_fdt = _compression_config(case, ctx, mat)
    col = _column(ctx, mpm)
    if p.get("touching"):  # explicit domain box whose x-lo face is the column's face (x = 0)
        m = int(mpm.get("margin_cells", 8)) * col.dx
        mpm["domain_lo"] = [0.0, -m, -m]
        mpm["domain_hi"] = [col.W + m, col.W + m, col.L + m]
    solver = MPMSolver(col.X, col.vol, mat, config=mpm)
    progress.solver = solver
    eps = _strain_target(mat, p)
    top, bot, nrm = _plates(col)
    mid = np.abs(col.X[:, 2] - col.L / 2) < col.L / 6
    area = col.W * col.W
    rows: list[dict] = []

    def c_bar_eff() -> float:
        return math.sqrt(mat.youngs_modulus * solver.stiffness_scale / (mat.density * solver.mass_scale))

    if human_fdt:
        fdt, n_load, n_hold = human_fdt, 6, 3
    else:
        tau = col.L / c_bar_eff()
        fdt, n_load, n_hold = 2.0 * tau, 10, 2
    T_load = n_load * fdt
    ramp = 0.2
    V = eps * col.L / (T_load * (1 - ramp / 2))
    z_top = col.L
    for f in range(n_load + n_hold):
        tm = (f + 0.5) * fdt
        vz = -V * min(1.0, tm / (ramp * T_load)) if f < n_load else 0.0
        bcs = [DirichletPoints(bot, np.zeros_like(bot), np.zeros(len(bot), int), normals=nrm, advect=False),
               DirichletPoints(top, np.tile([0.0, 0.0, vz], (len(top), 1)), np.ones(len(top), int), normals=nrm)]
        st = solver.step_frame(fdt, dirichlet=bcs)
        progress.stats.append(st)
        z_top += vz * fdt
        top[:, 2] = z_top
        F = solver.deformation_gradients()
        rows.append({"phase": "load" if f < n_load else "hold", "strain": (col.L - z_top) / col.L,
                         "top": -float(st.reaction[1, 2]), "eps_mid": -float(F[mid, 2, 2].mean() - 1.0), "st": st})
    # free phase: no boundary, no gravity, no floor -> KE + IE conserved by the exact dynamics
    period = 2.0 * col.L / c_bar_eff()
    n_free = max(3, math.ceil(3 * period / fdt))
    fdt_free = 3 * period / n_free if not human_fdt else fdt
    e0 = rows[-1]["st"].kinetic_energy + rows[-1]["st"].internal_energy
    energies = []
    for _ in range(n_free):
        st = solver.step_frame(fdt_free)
        progress.stats.append(st)
        energies.append(st.kinetic_energy + st.internal_energy)

    row = Row(case.name, case.category)
    _fill_from_stats(row, progress.stats, solver.time)
    row.ke_ie_max = max(r["st"].ke_ie_ratio for r in rows)
    row.energy_drift = energies[-1] / e0 - 1.0 if e0 > 0 else math.nan
    late = [r for r in rows if r["phase"] == "load" and r["strain"] > 0.5 * eps]
    f_sim = np.mean([r["top"] for r in late])
    f_ref = np.mean([mat.youngs_modulus * area * r["eps_mid"] for r in late])
    row.accuracy_error = float(f_sim / f_ref - 1.0)
    row.accuracy_reference = "F_top vs E A eps_mid (uniaxial stress)"
    notes = [(f"eps {eps:.3g}, E {mat.youngs_modulus:.3g} Pa, nu {mat.poisson_ratio:g}, rho {mat.density:g}, "
             f"c_p {mat.p_wave_speed():.4g} m/s, dx {col.dx * 1e3:.3g} mm, {len(col.X)} particles")]
    if row.stiffness_scale != 1.0:
        notes.append(f"force / stiffness_scale - 1 = {f_sim / row.stiffness_scale / f_ref - 1.0:+.3g} "
                     f"(the kinematics; the reaction force itself is x{row.stiffness_scale:.3g}, the yield strain "
                     f"x{1 / row.stiffness_scale:.3g})")
    growth = max(energies) / e0 - 1.0 if e0 > 0 else 0.0
    if growth > ENERGY_GROWTH_LIMIT:
        row.outcome = "unstable"
        row.reason = (f"UNCAUGHT by the solver guards: free-phase energy grew by {growth:+.1%} (limit "
                      f"{ENERGY_GROWTH_LIMIT:.0%}) at Courant {row.courant:.3g}")
    x, v = solver.positions(), solver.velocities()
    if not (np.isfinite(x).all() and np.isfinite(v).all()):
        row.outcome, row.reason = "unstable", "UNCAUGHT by the solver guards: non-finite final state"
    if p.get("touching"):
        notes.append(f"column face on the domain box face x = 0; particle x min at the end "
                     f"{x[:, 0].min() * 1e3:.3g} mm (slip wall on the padding nodes)")
    row.notes = "; ".join(notes)
    return row


# ============================================================================================ guard cases
def _column_solver(case: Case, ctx: SuiteContext, progress: _Progress, **mpm_overrides: Any):
    """The case's material on the suite's column, in an MPMSolver configured as production (``ctx.mpm``) plus
    ``mpm_overrides``, dx chosen as the rollout chooses it; the solver is registered with ``progress``."""
    from tasks.physics.mpm import MPMSolver

    mat = _material(case.params["material"], ctx)
    mpm = {**ctx.mpm, **mpm_overrides}
    mpm["dx"] = grid_spacing(mpm, float(ctx.sampling["particle_spacing"]))
    col = _column(ctx, mpm)
    solver = MPMSolver(col.X, col.vol, mat, config=mpm)
    progress.solver = solver
    return col, solver


def run_push_out(case: Case, ctx: SuiteContext, progress: _Progress | None = None) -> Row:
    """A finger (sticky Dirichlet points on the +x face) pushes the column at 0.5 m/s toward -x inside a tight
    automatic box (``margin_cells`` 1): Dirichlet nodes override the slip walls, so material is driven into the
    padding layer until the out-of-grid guard stops the run."""
    from tasks.physics.mpm import DirichletPoints

    progress = progress or _Progress()
    col, solver = _column_solver(case, ctx, progress, gravity=[0.0, 0.0, 0.0], floor=False, margin_cells=1)
    face = col.X[col.X[:, 0] > col.W - col.dx / 2].copy()
    speed, fdt = 0.5, 1.0 / FRAME_RATE_HUMAN
    for _ in range(6):  # up to 0.1 m of travel: far past the 1-cell margin
        st = solver.step_frame(fdt, dirichlet=DirichletPoints(face, np.tile([-speed, 0, 0], (len(face), 1))))
        progress.stats.append(st)
        face[:, 0] -= speed * fdt
    return _judged(case, progress, solver.time, "unstable",
                   "UNCAUGHT by the solver guards: material pushed 0.1 m through a 1-cell margin")


def run_nan_state(case: Case, ctx: SuiteContext, progress: _Progress | None = None) -> Row:
    """Two frames of a free column, then a NaN written into one particle's velocity (a corrupted state)."""
    progress = progress or _Progress()
    _, solver = _column_solver(case, ctx, progress)  # production as is (gravity, sticky floor, mass scaling)
    for _ in range(2):
        progress.stats.append(solver.step_frame(1.0 / FRAME_RATE_HUMAN))
    v = solver.velocities()
    v[len(v) // 2, 0] = np.nan
    solver.set_velocities(v)
    for _ in range(3):
        progress.stats.append(solver.step_frame(1.0 / FRAME_RATE_HUMAN))
    return _judged(case, progress, solver.time, "unstable", "UNCAUGHT by the solver guards: NaN velocity was not detected")


def run_nan_input(case: Case, ctx: SuiteContext, progress: _Progress | None = None) -> Row:
    """A finger (Dirichlet points on the top face) whose target velocity of one point is NaN, from the 2nd frame."""
    from tasks.physics.mpm import DirichletPoints

    progress = progress or _Progress()
    col, solver = _column_solver(case, ctx, progress)  # production as is
    pts = col.X[col.X[:, 2] > col.L - col.dx / 2].copy()
    for f in range(3):
        vel = np.tile([0.0, 0.0, -0.01], (len(pts), 1))
        if f >= 1:
            vel[len(vel) // 2, 2] = np.nan
        progress.stats.append(solver.step_frame(1.0 / FRAME_RATE_HUMAN, dirichlet=DirichletPoints(pts, vel)))
    return _judged(case, progress, solver.time, "error", "no guard refused the NaN boundary input")


# ============================================================================================ squeeze cases
def crafted_session(kind: str, surface_points: np.ndarray, surface_normals: np.ndarray, *, duration: float,
                    sensor_rate: float, fingers: Sequence[int] = (0, 1, 2, 3, 4), onset: float = 0.3,
                    ramp: float = 0.4, frequency: Any = None, peak: float = 1.0, rest: float = 0.05,
                    travel: float | None = None, standoff: float = 0.005, travel_fraction: float = 0.25,
                    palm_standoff: float = 0.015) -> dict[str, np.ndarray]:
    """Raw sensor-rate signals of an extreme squeeze (same layout and geometry as
    :func:`tasks.control.squeeze_signals.synthesize_session`, no noise, no tremor, static palm).

    Profile p(t) in [0, 1] of the active ``fingers`` (the others stay at ``rest``), flexion = rest + (peak - rest) p,
    fingertip k at ``standoff - travel p`` along its target's outward normal:
      * ``step``: p = 0 before ``onset``, 1 from the next sensor sample on (full flexion within one sample);
      * ``ramp``: minimum-jerk 0 -> 1 over ``ramp`` seconds from ``onset``, then hold;
      * ``oscillation``: p = (1 - cos(2 pi f (t - onset))) / 2 after ``onset``; ``frequency="nyquist"`` is half the
        sensor rate, i.e. full flexion on every other sample.
    """
    from tasks.control.squeeze_signals import grasp_targets, synthesize_session

    n = math.floor(duration * sensor_rate + 1e-9) + 1
    t = np.arange(n) / sensor_rate
    if kind == "step":
        p = (t >= onset).astype(float)
    elif kind == "ramp":
        s = np.clip((t - onset) / ramp, 0.0, 1.0)
        p = s ** 3 * (10 - 15 * s + 6 * s * s)
    elif kind == "oscillation":
        f = 0.5 * sensor_rate if frequency == "nyquist" else float(frequency)
        p = np.where(t >= onset, 0.5 * (1.0 - np.cos(2.0 * np.pi * f * (t - onset))), 0.0)
        p = np.clip(np.round(p, 12), 0.0, 1.0)
    else:
        raise ValueError(f"crafted_session: unknown kind {kind!r}: use step, ramp or oscillation")
    tg = grasp_targets(surface_points, surface_normals)
    half = tg["half_size"]
    travel = travel_fraction * float(min(half[0], half[1])) if travel is None else float(travel)
    active = np.zeros(5, bool)
    active[list(fingers)] = True
    prof = np.where(active[None], p[:, None], 0.0)
    flexion = rest + (peak - rest) * prof
    tips = tg["points"][None] + tg["normals"][None] * (standoff - travel * prof)[:, :, None]
    base = synthesize_session("crush", surface_points, surface_normals,
                              {"duration": duration, "sensor_rate": sensor_rate, "tremor_amplitude": 0.0, "noise_std": 0.0,
                                   "position_noise_std": 0.0, "peak_flexion": peak, "seed": 0})
    palm = np.broadcast_to(tg["palm_point"] + tg["palm_normal"] * palm_standoff, (n, 3)).copy()
    quat = np.broadcast_to(base["palm_orientation"][0], (n, 4)).copy()
    return {"time": t, "flexion": flexion, "fingertip_positions": tips, "palm_position": palm,
            "palm_orientation": quat}


def _plain_arrays(d: Mapping[str, Any]) -> dict[str, np.ndarray]:
    return {k: (v.data if hasattr(v, "data") else np.asarray(v)) for k, v in d.items()}


def run_squeeze(case: Case, ctx: SuiteContext, progress: _Progress | None = None) -> Row:
    """The whole pipeline on a real object with a crafted session (module doc); rollout errors propagate."""
    from tasks.control.contact_patches import contact_patches
    from tasks.control.dirichlet_field import dirichlet_field
    from tasks.control.force_coefficients import force_coefficients
    from tasks.control.object_model import build_object_model
    from tasks.control.signal_smoothing import smooth_signals
    from tasks.physics.material_oracle import material_oracle, materials_to_dict
    from tasks.physics.mpm_rollout import mpm_rollout
    from tasks.physics.particle_fill import build_mpm_particles

    p = case.params
    obj = dict(ctx.catalog[p["object"]])
    o_arr, o_attrs = build_object_model(_Attr(obj), _Attr(ctx.sampling))
    p_arr, p_attrs = build_mpm_particles(_Attr(obj), _Attr(ctx.sampling),
                                         grid_spacing(ctx.mpm, float(ctx.sampling["particle_spacing"])))
    o, o_attrs = _plain_arrays({**o_arr, **p_arr}), {**o_attrs, **p_attrs}
    half = 0.5 * (np.asarray(o_attrs["bbox_max"]) - np.asarray(o_attrs["bbox_min"]))
    sig = ctx.signal
    duration = float(p.get("duration", 0.9))
    travel = None
    disp_cfg = dict(ctx.control["displacement"])
    force_cfg = ctx.control["force"]
    if "depth_over_half" in p:  # eta so that the peak prescribed displacement reaches depth_over_half x h(d)
        k = int(p["fingers"][0])
        w = float(force_cfg["weights"][k])
        c_peak = w * max(1.0 - 0.05 - float(force_cfg["beta"]), 0.0) ** float(force_cfg["gamma"])
        h_d = float(np.abs(_finger_direction(o)[k]) @ half)
        obj["eta"] = float(p["depth_over_half"]) * h_d / c_peak
        travel = float(p["depth_over_half"]) * h_d
    if obj.get("eta") is not None:
        disp_cfg["eta"] = obj["eta"]
    raw = crafted_session(p["session"], o["surface_points"], o["surface_normals"], duration=duration,
                          sensor_rate=float(sig["sensor_rate"]), fingers=p.get("fingers", (0, 1, 2, 3, 4)),
                          ramp=float(p.get("ramp", 0.4)), frequency=p.get("frequency"), travel=travel)
    sm = dict(ctx.control["smoothing"])
    sm.update(p.get("smoothing", {}))
    fr = _plain_arrays(smooth_signals(raw, sm["frame_rate"], sm["ema_alpha"], sm["rest_window"]))
    fc = _plain_arrays(force_coefficients(fr["flexion"], sm["frame_rate"], force_cfg["weights"], force_cfg["beta"],
                                          force_cfg["gamma"], force_cfg["release_gamma"],
                                          force_cfg["release_rate_threshold"]))
    cp = _plain_arrays(contact_patches(o["surface_points"], o["surface_normals"], o["surface_curvature"],
                                       o["surface_principal_dirs"], o["surface_area"], fr["fingertip_positions"],
                                       fr["squeeze_directions"], fc["force_coefficients"], ctx.control["contact"]))
    df = _plain_arrays(dirichlet_field(o["surface_points"], cp["patch_centers"], cp["patch_normals"],
                                       cp["patch_axes"], cp["patch_radii"], cp["patch_active"],
                                       fc["force_coefficients"], disp_cfg, surface_normals=o["surface_normals"]))
    mats = material_oracle(obj["description"], obj["name"], obj.get("material"), obj.get("interior"), ctx.oracle)
    peak_disp = float(np.linalg.norm(df["displacement"], axis=-1).max(initial=0.0))
    notes = [(f"{o_attrs['n_particles']} + {o_attrs['n_interior']} particles, {len(fr['time'])} frames, "
             f"peak prescribed displacement {peak_disp * 1e3:.3g} mm (half extent {half.round(4).tolist()} m), "
             f"peak force coefficient {fc['force_coefficients'].max():.3g}")]
    if p["session"] == "oscillation":
        u = fr["flexion"][fr["time"] - fr["time"][0] > 0.3 + 3 / sm["frame_rate"]]
        notes.append(f"smoothed flexion after the onset: mean {u.mean():.3g}, peak-to-peak "
                     f"{np.ptp(u, axis=0).max():.3g} (raw 0.95)")
    progress = progress or _Progress()
    progress.notes = notes
    progress.solver = _StartedMarker()  # the rollout builds its own solver: an error inside it is a run error
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        arrays, attrs = mpm_rollout(o, o_attrs, df, fc["force_coefficients"], cp, fr["time"], materials_to_dict(mats),
                                    ctx.mpm, ctx.simulation, "dirichlet")
    a = _plain_arrays(arrays)
    row = Row(case.name, case.category)
    frames = slice(1, None)
    row.max_speed = float(a["max_speed"][frames].max())
    row.j_min, row.j_max = float(a["j_min"][frames].min()), float(a["j_max"][frames].max())
    row.courant = float(a["courant"][frames].max())
    row.substeps = int(a["substeps"].sum())
    row.simulated_seconds = float(fr["time"][-1] - fr["time"][0])
    row.substeps_per_simulated_second = row.substeps / row.simulated_seconds
    row.mass_scale = float(attrs["mass_scale"])
    qs = attrs["quasi_static"]
    row.ke_ie_max = float(qs["max_ke_ie_in_contact"]) if qs["frames_checked"] else math.nan  # NaN: no frame checked
    # up to the rupture: afterwards a torn patch is no longer driven, so the prescribed strain is not a reference
    last = int(attrs["threshold_event"]["frame"]) + 1 if attrs["threshold_event"].get("crossed") else None
    pred, obs = a["predicted_squeeze_strain"][:last].max(), a["squeeze_strain"][:last].max()
    row.accuracy_error = float(obs / pred - 1.0) if pred > 0 else math.nan
    row.accuracy_reference = "peak squeeze strain vs prescribed (eq. 3), up to the rupture"
    dx = float(attrs["dx"])
    ev = attrs["threshold_event"]
    if ev.get("crossed"):
        notes.append(f"ruptured at frame {ev['frame']}, {ev['released_particles']} particles released")
    J, mat_of = a["particle_J"][frames], a["particle_material"]
    names = _labels(arrays["particle_material"].description)
    notes.append("J range per particle label: " + ", ".join(
        f"{names.get(int(k), str(k))} [{J[:, mat_of == k].min():.3g}, {J[:, mat_of == k].max():.3g}]"
        for k in np.unique(mat_of)))
    fluid_msg = ""
    # label 1 = the interior fluid (equal particle volumes).  Labels are the FINAL ones: with a solid core, the
    # fluid is made from core particles at the rupture, so only the frames after it are fluid frames.
    first = 0
    if getattr(mats, "core", None) is not None:
        first = int(ev["frame"]) if ev.get("crossed") else len(J)  # J[k] is frame k + 1
    if mats.interior is not None and getattr(mats.interior, "model", "") == "fluid" and (mat_of == 1).any() \
            and first < len(J):
        Jf = J[first:, mat_of == 1].astype(np.float64)
        vol_err = Jf.mean(axis=1) - 1.0
        far = np.mean(np.abs(Jf - 1.0) > 0.2, axis=1)
        f_v, f_far = int(np.argmax(np.abs(vol_err))), int(np.argmax(far))
        fr_v, fr_far = first + f_v + 1, first + f_far + 1
        notes.append(f"interior fluid (frames {first + 1}-{len(J)}): total volume error max {vol_err[f_v]:+.1%} "
                     f"(frame {fr_v}), at the end {vol_err[-1]:+.1%}; particles with |J-1| > 20 %: max "
                     f"{far[f_far]:.1%} (frame {fr_far}); designed for ~1 % (Mach 0.1)")
        if abs(vol_err[f_v]) > FLUID_VOLUME_LIMIT or far[f_far] > FLUID_FAR_LIMIT:
            fluid_msg = (f"UNCAUGHT by the solver guards: the weakly compressible interior fluid is off its volume "
                         f"(total {vol_err[f_v]:+.1%} at frame {fr_v}, {vol_err[-1]:+.1%} at the end; "
                         f"{far[f_far]:.0%} of its particles beyond |J-1| > 20 % at frame {fr_far}; designed for "
                         "~1 %), while J stays inside the [j_min, j_max] guard")
    track = a["dirichlet_tracking_error"]
    notes.append(f"max Dirichlet tracking error {track.max() * 1e3:.3g} mm ({track.max() / dx:.2g} dx)")
    bad = [k for k, v in a.items() if np.issubdtype(v.dtype, np.floating) and not np.isfinite(v).all()]
    detached = _detached_fraction(a["gaussian_positions"], a["particle_positions"], dx)
    notes.append(f"surface Gaussians > 1 dx from every particle: {detached.max():.2%} (worst frame)")
    if bad:
        row.outcome, row.reason = "unstable", f"UNCAUGHT by the solver guards: non-finite outputs {bad}"
    elif fluid_msg:
        row.outcome, row.reason = "unstable", fluid_msg
    elif detached.max() > DETACHED_LIMIT:
        f = int(np.argmax(detached))
        row.outcome = "unstable"
        row.reason = (f"UNCAUGHT by the solver guards: {detached[f]:.1%} of the surface Gaussians lie farther than "
                      f"1 dx from every particle at frame {f} (the rendered surface left the material)")
    for w in caught:
        if issubclass(w.category, RuntimeWarning):
            notes.append(f"warning: {_one_line(w.message)}")
            break
    row.notes = "; ".join(notes)
    return row


def _labels(description: str) -> dict[int, str]:
    """Particle label names from the rollout's ``particle_material`` description ("0 shell, 1 interior (...), ...")."""
    import re

    return {int(k): v.strip() for k, v in re.findall(r"(\d+) ([a-z ]+?)(?= \(|,|$)", description)}


class _StartedMarker:
    substep = 1


class _Attr(dict):
    """A dict readable by attribute (the object model reads configs by attribute or key)."""

    def __getattr__(self, key: str) -> Any:
        try:
            v = self[key]
        except KeyError:
            raise AttributeError(key) from None
        return _Attr(v) if isinstance(v, dict) else v


def _finger_direction(o: Mapping[str, np.ndarray]) -> np.ndarray:
    from tasks.control.squeeze_signals import grasp_targets

    return -grasp_targets(o["surface_points"], o["surface_normals"])["normals"]


def _detached_fraction(gauss: np.ndarray, parts: np.ndarray, dx: float, every: int = 3) -> np.ndarray:
    """Per frame: fraction of surface Gaussians farther than ``dx`` from every particle (checked every ``every``
    frames and at the last frame; others 0)."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(gauss))
    frames = sorted(set(range(0, len(gauss), every)) | {len(gauss) - 1})
    for f in frames:
        d, _ = cKDTree(parts[f]).query(gauss[f], k=1)
        out[f] = float(np.mean(d > dx))
    return out


# ============================================================================================ thin walls
def run_thin_wall(case: Case, ctx: SuiteContext, progress: _Progress | None = None) -> Row:
    """:func:`tasks.physics.wall_resolution.thin_wall_finding` on the real object model with the production dx."""
    from tasks.control.object_model import build_object_model
    from tasks.physics.particle_fill import build_mpm_particles

    name = case.params["object"]
    obj = ctx.catalog[name]
    dx = grid_spacing(ctx.mpm, float(ctx.sampling["particle_spacing"]))
    attrs = {**build_object_model(_Attr(obj), _Attr(ctx.sampling))[1],
             **build_mpm_particles(_Attr(obj), _Attr(ctx.sampling), dx)[1]}
    mat = _material(f"oracle:{name}", ctx)
    fnd = thin_wall_finding(attrs, dx, mat.poisson_ratio, mat.youngs_modulus, name=name,
                            membrane_max_thickness=float(ctx.mpm["membrane_max_thickness"]))
    row = Row(case.name, case.category, outcome="flagged" if fnd.flagged else "resolved", reason=fnd.message)
    row.notes = (f"{attrs['n_particles']} wall particles; bending length {fnd.bending_length * 1e3:.3g} mm; "
                 f"D = E t^3/(12(1-nu^2)) = {fnd.bending_stiffness:.3g} N m")
    return row


# ============================================================================================ suite
RUNNERS: dict[str, Callable[..., Row]] = {
    "compression": run_compression,
    "push_out": run_push_out,
    "nan_state": run_nan_state,
    "nan_input": run_nan_input,
    "squeeze": run_squeeze,
    "thin_wall": run_thin_wall,
}


def run_case(case: Case, ctx: SuiteContext) -> Row:
    """Run one case; every exception becomes the row's outcome and reason (the process always continues)."""
    progress = _Progress()
    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # quasi-static warnings: the KE/IE column reports them
            row = RUNNERS[case.kind](case, ctx, progress)
    except Exception as exc:  # noqa: BLE001 - the suite records every failure as an outcome
        outcome, reason = _classify(exc, progress.started)
        row = Row(case.name, case.category, outcome=outcome, reason=reason)
        solver = progress.solver if not isinstance(progress.solver, _StartedMarker) else None
        _fill_from_stats(row, progress.stats, solver.time if solver is not None else 0.0)
        if solver is not None:
            row.substeps = int(solver.substep)
            cfg = solver.cfg
            row.courant = solver.courant_number(cfg.dt) if cfg.dt is not None else max(
                float(cfg.courant), row.courant if math.isfinite(row.courant) else 0.0)
            row.notes = (f"{len(progress.stats)} frames, {solver.substep} substeps completed before the error; "
                         f"courant = {'the forced dt' if cfg.dt is not None else 'mpm.courant (adaptive)'}")
        if progress.notes:
            row.notes = "; ".join([*progress.notes, row.notes] if row.notes else progress.notes)
    row.wall_seconds = time.perf_counter() - t0
    return row


def run_suite(ctx: SuiteContext, cases: Sequence[Case], log: Callable[[str], None] | None = None) -> list[Row]:
    """Run ``cases`` in order; a case with a ``baseline`` (the unaccelerated case of the same material) gets
    ``error_vs_unaccelerated`` when that case ran too."""
    rows = []
    for c in cases:
        row = run_case(c, ctx)
        rows.append(row)
        if log:
            log(f"{c.name:28s} {row.outcome:9s} {row.wall_seconds:7.1f} s  {row.reason[:110]}")
    by_name = {r.case: r for r in rows}
    for c, r in zip(cases, rows):
        base = by_name.get(c.params.get("baseline", ""))
        if base is not None and math.isfinite(base.accuracy_error) and math.isfinite(r.accuracy_error):
            r.error_vs_unaccelerated = (1.0 + r.accuracy_error) / (1.0 + base.accuracy_error) - 1.0
    return rows


# ============================================================================================ report
def _fmt(v: Any) -> str:
    if isinstance(v, float):
        if math.isnan(v):
            return ""
        return f"{v:.3g}"
    return str(v)


TABLE_COLUMNS = ("case", "category", "outcome", "max_speed", "j_min", "j_max", "energy_drift", "ke_ie_max", "courant",
                 "substeps", "substeps_per_simulated_second", "wall_seconds", "accuracy_error",
                 "error_vs_unaccelerated", "mass_scale",
                 "stiffness_scale")


def table_text(rows: Sequence[Row]) -> str:
    """Fixed-width text table (printed at the end of a run)."""
    head = list(TABLE_COLUMNS)
    body = [[_fmt(getattr(r, c)) for c in head] for r in rows]
    width = [max(len(h), *(len(b[i]) for b in body)) if body else len(h) for i, h in enumerate(head)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(head, width))]
    lines += ["  ".join(x.ljust(w) for x, w in zip(b, width)) for b in body]
    lines += ["", "reasons:"] + [f"  {r.case}: {r.reason}" for r in rows if r.reason]
    return "\n".join(lines)


def write_report(rows: Sequence[Row], out_dir: str | Path, config: Mapping[str, Any] | None = None,
                 title: str = "Numerical stability suite") -> Path:
    """``stability.csv`` (one row per case, all fields) and ``stability.md`` (table, definitions, findings)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "stability.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=ROW_FIELDS)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.as_dict().items()})
    md = [f"# {title}", "", f"{len(rows)} cases; outcomes: " + ", ".join(
        f"{o} {sum(r.outcome == o for r in rows)}" for o in OUTCOMES if any(r.outcome == o for r in rows)), ""]
    md += ["| " + " | ".join(TABLE_COLUMNS) + " | reason |", "|" + "---|" * (len(TABLE_COLUMNS) + 1)]
    for r in rows:
        md.append("| " + " | ".join(_fmt(getattr(r, c)) for c in TABLE_COLUMNS) + f" | {r.reason.replace('|', '/')} |")
    uncaught = [r for r in rows if r.reason.startswith("UNCAUGHT") or r.outcome == "error"]
    md += ["", "## Failures the solver guards did not catch", ""]
    md += [f"- **{r.case}**: {r.reason}" for r in uncaught] or ["- none"]
    walls = [r for r in rows if r.category == "thin_wall"]
    if walls:
        md += ["", "## Thin walls (tasks.physics.wall_resolution.thin_wall_finding)", ""]
        md += [f"- **{r.case}** ({r.outcome}): {r.reason}; {r.notes}" for r in walls]
    md += ["", "## Notes per case", ""] + [f"- **{r.case}**: {r.notes}" for r in rows if r.notes]
    md += ["", "## Definitions", "",
           ("- outcome: `stable` finished with quiet guards and passed the suite's checks; `unstable` a solver guard "
           "(SimulationError) stopped the run, or the suite found a failure the guards missed (reason `UNCAUGHT`); "
           "`refused` a validation error: config, material, boundary input or the forced-Courant check, raised "
           "before the step it concerns ran; `flagged`/`resolved` thin-wall "
           "finding; `error` an exception no guard translated."),
           ("- max_speed (m/s), j_min/j_max (det F_E) over end-of-frame states; courant = max c_p dt / dx (c_p after "
           "scaling); substeps_per_simulated_second = substeps / simulated time."),
           ("- energy_drift: compression cases only, free phase (no gravity, no boundary, conservative): "
           "(KE+IE)(end)/(KE+IE)(release) - 1.  Negative = numerical dissipation of the MPM transfers."),
           ("- ke_ie_max: driven phases: plate loading/hold, the largest kinetic / internal energy ratio; a rollout, "
           "the largest value of the solver's quasi-static check (sum KE / sum IE over a contact) over the contacts "
           "it judges (mass scaling assumes it small; its limit is mpm.quasi_static_ke_ie_max)."),
           ("- accuracy_error: compression: F_top / (E A eps_mid) - 1 over the second half of the loading, E the real "
           "modulus (uniaxial stress between frictionless plates; shows inertia from mass scaling and the force factor "
           "of stiffness scaling); squeeze: observed / prescribed peak squeeze strain - 1."),
           ("- Compression cases use the production mpm config, dx rule, particle spacing and oracle materials; only "
           "gravity (0) and the floor (off) differ, for a closed form and a conservative free phase.  Squeeze cases "
           "run the real pipeline functions on the real object with the production config groups.")]
    if config is not None:
        (out / "config.json").write_text(json.dumps(config, indent=1, default=str))
    (out / "stability.md").write_text("\n".join(md) + "\n")
    return out / "stability.md"


__all__ = [
    "ROW_FIELDS",
    "Case",
    "Row",
    "SuiteContext",
    "crafted_session",
    "default_cases",
    "run_case",
    "run_compression",
    "run_squeeze",
    "run_suite",
    "run_thin_wall",
    "select_cases",
    "table_text",
    "write_report",
]
