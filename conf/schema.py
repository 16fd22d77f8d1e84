"""Structured (dataclass) schemas for every config group.

Hydra merges the YAML files under ``conf/`` into these schemas, so an unknown key or a value of the wrong
type is an error naming the key.  All physical quantities are SI: metres, seconds, pascals, kilograms.
Range checks that the type system cannot express live in :func:`validate` and run before any task.
"""
from __future__ import annotations

import difflib
import math
from dataclasses import dataclass, field, fields, is_dataclass
from typing import Any, Optional

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf

from conf.generation_schema import GenerationConfig, RefinementConfig, VideoMetricsConfig, validate_generation
from conf.hand import FINGERS
from conf.judge_schema import LLMJudgeConfig
from conf.metrics_schema import MetricsConfig, PaperMetricsConfig, validate_metrics, validate_paper_metrics
from conf.mpm_schema import MPMConfig
from conf.oracle_schema import OracleConfig
from conf.render_schema import RenderConfig, validate_render


# ----------------------------------------------------------------------------------------------- object
@dataclass
class GeometryConfig:
    """Shape of an object.

    ``kind`` selects a procedural signed-distance shape (``can``, ``cup``, ``sphere``, ``ellipsoid``, ``duck``,
    ``plush``, ``block``) or a user file (``ply`` = 3DGS PLY in the Inria layout, ``mesh`` = OBJ/PLY/STL/GLB).
    ``size`` is the shape's bounding box in metres (x, y, z); z is up.  ``wall_thickness`` is the real shell
    thickness in metres (0 = solid body).
    """

    kind: str = MISSING
    size: list[float] = field(default_factory=lambda: [0.05, 0.05, 0.05])
    wall_thickness: float = 0.0
    path: Optional[str] = None


@dataclass
class AppearanceConfig:
    """Colours (linear RGB in [0, 1]) and a procedural pattern for the surface Gaussians."""

    base_color: list[float] = field(default_factory=lambda: [0.8, 0.8, 0.8])
    accent_color: list[float] = field(default_factory=lambda: [0.2, 0.2, 0.2])
    pattern: str = "solid"  # solid | bands | label | speckle | dimples | stripes | fur
    opacity: float = 0.98


@dataclass
class MaterialOverrides:
    """Explicit material values; any value given here wins over the material oracle (SI units)."""

    model: Optional[str] = None
    youngs_modulus: Optional[float] = None  # Pa
    poisson_ratio: Optional[float] = None  # 1
    density: Optional[float] = None  # kg/m^3
    yield_stress: Optional[float] = None  # Pa (uniaxial)
    squeeze_threshold: Optional[float] = None  # 1 (compressive engineering strain at the contact)


@dataclass
class ObjectConfig:
    """One squeezable object: geometry, look, what it is made of, and its default squeeze session."""

    name: str = MISSING
    display_name: str = MISSING
    description: str = MISSING  # free text read by the material oracle
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    appearance: AppearanceConfig = field(default_factory=AppearanceConfig)
    filled: bool = False  # True: the shell material fills the whole body (clay, rubber ball core)
    interior: Optional[str] = None  # interior material (juice, cola, stuffing, pulp ...) or None
    material: MaterialOverrides = field(default_factory=MaterialOverrides)
    session: str = "ramp_hold_release"  # default synthetic squeeze session (see SignalConfig.session)
    eta: Optional[float] = None  # m per unit force coefficient: this object's eq. 3 scaling (None: control.displacement.eta)
    # N per unit force coefficient: the first guess of the force-matched calibration (variant.force_match), this
    # object's calibrated constant on the default grid, seed 0 (None: simulation.force_per_coefficient)
    force_per_coefficient: Optional[float] = None


# ----------------------------------------------------------------------------------------------- signal
@dataclass
class SignalConfig:
    """Where the squeezing control signals come from and how they are sampled.

    ``source``: ``synthetic`` (generator below) or ``csv`` (a SenseGlove recording at ``path``).
    """

    source: str = "synthetic"
    path: Optional[str] = None
    session: Optional[str] = None  # None: the object's own default session
    duration: float = 3.0  # s, synthetic sessions
    sensor_rate: float = 200.0  # Hz, synthetic sessions (SenseGlove streams at 100-1000 Hz)
    tremor_amplitude: float = 0.01  # flexion units (physiological tremor, 8-12 Hz)
    noise_std: float = 0.005  # flexion units (sensor noise)
    position_noise_std: float = 0.0005  # m
    peak_flexion: float = 0.85  # 1, maximum normalised flexion reached in the session
    seed: int = 0


# ----------------------------------------------------------------------------------------------- control
@dataclass
class SmoothingConfig:
    """Preprocessing (paper sec. 3.1): resampling, EMA, de-biasing."""

    frame_rate: float = 30.0  # Hz, the simulation's output frame rate
    ema_alpha: float = 0.35  # 1, EMA weight of the newest sample at the frame rate
    rest_window: float = 0.2  # s, leading window whose mean flexion is the rest pose (de-bias)


@dataclass
class ForceConfig:
    """Force coefficients, eq. 1: c = w_k max(u - beta, 0)^gamma, with bidirectional activation."""

    weights: list[float] = field(default_factory=lambda: [1.2, 1.1, 1.0, 0.8, 0.6])  # thumb..pinky
    beta: float = 0.05  # 1, activation threshold on de-biased flexion
    gamma: float = 1.5  # 1, nonlinearity index
    release_gamma: float = 2.0  # 1, nonlinearity on the release phase (bidirectional activation)
    release_rate_threshold: float = 0.05  # 1/s, flexion rate below -this counts as releasing


@dataclass
class ContactConfig:
    """SC-CAE contact estimation, eq. 2 (weights of the composite objective)."""

    lambda_area: float = 1.0
    lambda_align: float = 0.2
    lambda_curvature: float = 0.05
    lambda_scale: float = 1.0
    lambda_overlap: float = 2.0
    sigma_min: float = 0.004  # m, patch radius at zero force
    sigma_max: float = 0.015  # m, patch radius at force coefficient 1
    candidates: int = 64  # surface candidates searched per finger and frame
    activation: float = 1e-3  # force coefficient above which a patch is active


@dataclass
class DisplacementConfig:
    """Displacement field, eq. 3: dx = sum_k eta c_k phi_k(x) n_k."""

    eta: float = 0.01  # m per unit force coefficient (global scaling factor)
    support: float = 2.5  # patch support in units of sigma (phi_k = 0 beyond)
    min_weight: float = 0.05  # surface points with phi below this are not constrained


@dataclass
class ControlConfig:
    smoothing: SmoothingConfig = field(default_factory=SmoothingConfig)
    force: ForceConfig = field(default_factory=ForceConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    displacement: DisplacementConfig = field(default_factory=DisplacementConfig)


# ----------------------------------------------------------------------------------------------- object sampling
@dataclass
class SamplingConfig:
    """How an object is discretised: surface Gaussians for rendering/contact, volume particles for MPM."""

    surface_points: int = 3000  # surface samples = 3D Gaussians
    particle_spacing: float = 0.004  # m, volume particle spacing (MPM issue derives it from the grid)
    seed: int = 0
    # a hollow wall thinner than the spacing: 1 = one particle layer on its mid-surface; 2 (default) = two layers at
    # the thickness's Gauss points +-t / (2 sqrt 3), half the volume each, so that with mpm.thin_walls=membrane the
    # wall carries bending; 3 = three layers at 0, +-sqrt(3/5) t / 2 with 8/18, 5/18, 5/18 of the volume, which
    # also integrate a strain quadratic through the wall (a wall near a cell's thickness; docs/limits/thin-walls.md)
    # (tasks/physics/particle_fill.py)
    thin_wall_layers: int = 2


# ----------------------------------------------------------------------------------------------- simulation
@dataclass
class VariantConfig:
    """A method variant (paper Table 2): ``full`` imposes the displacement field as Dirichlet boundary
    conditions; ``no_dirichlet`` ("VirSqueezer w/o Dirichlet Boundary Constraint", PhysGaussian-style) pushes
    with a per-finger force estimated from the flexion instead (balanced so the fingers' forces sum to zero:
    ``simulation.force_balance``), its one constant calibrated per object (``force_match``) so that it pushes as
    hard as the full method; ``no_dirichlet_uncalibrated`` pushes with ``simulation.force_per_coefficient``."""

    name: str = "full"
    label: str = ""  # how the report names the variant (Table 2's "Method" column); default: name
    boundary: str = "dirichlet"  # dirichlet | force
    # force variants only: how the push's one constant K (N per unit eq. 1 coefficient) is set per object
    # (tasks/physics/force_match.py): indentation = calibrated so that the force-driven peak indentation under
    # the patches equals the eq. 3 field's prescribed one (within force_match_rtol, in at most force_match_runs
    # calibration runs from object.force_per_coefficient; a rejected run stops at the prescribed peak's frame, the
    # accepted one is the rollout); none = simulation.force_per_coefficient as given
    force_match: str = "none"
    force_match_rtol: float = 0.1
    force_match_runs: int = 8


@dataclass
class SimulationConfig:
    """How the squeeze drives the MPM (paper sec. "Squeezing-Driven Deformation").

    fluid_reference_speed: m/s; the least flow speed the interior fluid's compressibility is sized for.  The fluid
        gets the bulk modulus whose sound speed is v / ``fluid_mach`` with v = max(this speed, sqrt(
        max_release_speed^2 + 2 g H)), the speed of a release followed by a fall over the object's height H to the
        table (K = s_f rho (v / Mach)^2, s_f the mass scale the solver gives the fluid: 1 under
        ``mpm.mass_scaling=selective``), instead of water's 2.2 GPa.  At the defaults: c = 6.1 m/s (tomato, 55 mm
        tall) to 7.1 m/s (can, 115 mm), below the solids' scaled P-wave speed at 100 substeps per 1/30 s frame on the
        8 mm grid (7.2 m/s): the fluid costs no extra substeps; the hydrostatic compression g H / c^2 is < 3 %.  At
        max_release_speed 4: c = 13.8-14.2 m/s, ~190-200 substeps per frame while the fluid is present (a can's
        cola from the start, juice after the release).
    fluid_mach: Mach number of the interior fluid at that speed (0.3: density error ~ Mach^2 / 2 = 4.5 %, the
        usual weakly compressible limit).
    fluid_tait_exponent: gamma of the interior fluid's Tait equation of state p = K / gamma (J^-gamma - 1); 1
        keeps the sound speed constant under compression (water's gamma = 7 doubles it at J = 0.8, which an
        explicit step sized for the rest state does not survive in a squeezed, sealed can).
    force_per_coefficient: N per unit force coefficient c (force mode): the push of ``no_dirichlet_uncalibrated``
        and the first guess of the force-matched calibration of ``no_dirichlet`` (``variant.force_match``) for an
        object without its own ``object.force_per_coefficient``.
    force_balance: how the force mode's finger forces (N) are balanced: ``wrench`` (default) takes their net force
        off the fingers in proportion to their magnitudes, so they sum to 0 N, then their net moment about the
        centres of their patches by the least change of the same weights (each as far as the grip's friction
        allows; a poke, no two fingers pushing against each other, is left to the table); ``fingers`` the net
        force alone; ``none`` pushes each finger along its inward patch normal unchanged
        (``tasks.physics.rollout_fingers.balanced_push``).  A hand squeezing an object is a closed force loop (the
        table carries only the object's weight); unbalanced, the fingers' net push (1.8 N at the force-driven plush
        toy's contact, 4.7x its weight) swayed the toy on the table, made its squeeze dynamic (KE/IE 0.133 > 0.1: a
        quasi-static warning) and tipped it over; with the force alone balanced, the moment left (0.028 N m two
        frames before its rupture) swayed it once its force points followed the skin (KE/IE 0.123; ``wrench``: 0.037).
    force_balance_friction: Coulomb coefficient (1) of the fingertips' grip under ``force_balance=fingers`` or
        ``wrench``: the net force and moment are removed only as far as no finger's tangential force exceeds this
        times its normal push (the rest is left for the table).  1: a fingertip on rubber or fabric; the default
        grasps' force balance needs <= 0.74.
    torn_finger_push: where the force mode puts the share of a finger's force whose patch tore (its torn /
        constrained points; ``tasks.physics.mpm_rollout.force_patch``): ``beneath`` (default) on the core (stuffing,
        pulp) chosen at the rupture within 2 grid cells of its opening (its torn skin and the interior released under
        it) and still within ``release_radius`` + 2 cells of it, as much of the share as closes the grip (the least
        net force of the fingers' push; the crushable stuffing offers only that reaction), the finger pressing on
        through the hole; ``none`` drops it (the released material offers no support; a hollow can's cola, a fluid,
        never carries it).  Dropped, the force-driven plush toy's torn thumb left its four fingers side by side,
        unable to close the grip within their friction cones, and they shoved the toy over in two of three sampling
        seeds; pushed beneath, all three end upright (README, "Balanced force-driven push").
    release_radius: m; interior particles this close to a finger's patch centre are released at the
        threshold crossing (for an object with a solid core: the core particles there, which become the interior
        material), and shell particles this close rupture (become ``ruptured_softening`` x softer).  Keep it
        >= 2.5 grid cells (8 mm at the default sampling): MPM shares one velocity field per grid node, so
        released material within ~1.5 cells of the material that stays is dragged back with it.
    ruptured_softening: factor on the torn shell's E and yield stress.  1e-2 (default, global mass scaling): it no
        longer holds the interior in, yet keeps enough volumetric stiffness that torn skin carried off by the spray
        does not invert.  Under ``mpm.mass_scaling=selective`` the released fluid has its physical inertia
        (kinetic energy ~1 kJ/m^3 at 1.5 m/s), which does not open a skin softened only 100x; use 1e-4 there: 21 %
        (tomato crush) and 20 % (orange) of the released juice then ends > 2 mm outside the rest surface (but the
        force-driven ablation inverts the torn skins of the tomato, orange and plush toy).
    release_margin_cells: free grid cells around a scene with releasable material (at least ``mpm.margin_cells``
        on every side, not below the table): room for the spray to fly before a domain wall stops it.  8 (the
        default, = ``mpm.margin_cells``).  Measured (docs/limits/released-material.md; under load; default grid alignment): at
        3 m/s the tomato's juice flies free for 10.2 ms until a wall's reach; 16 all round: 14.1 ms (then the
        table's reach) at 1.8x the rollout's CPU time (the juice spreads over the larger floor, the active grid box
        with it); 8 more cells along the release direction only (``mpm.domain_hi``): the same 14.1 ms at +5 %.
    max_release_speed: m/s cap of the release speed.  Released material leaves at the Bernoulli speed
        sqrt(2 p / rho) of the finger's local pressure p = |reaction| / patch area (rho the interior's density; a
        liquid pressed out at 20 kPa leaves at ~6 m/s).  The cap binds in every default scene: the fingers'
        pressures on the mass-scaled shells at the release read 0.18 MPa (tomato), 0.49 MPa (orange) and 28-53 MPa
        (the can's aluminium), the shells' stress rather than the liquid's (19-320 m/s).  1.5: at 1 most of the
        released orange juice and plush stuffing was dragged back by the grid coupling to what stays (one velocity
        field then); under the former global mass scaling 2 squeezed the torn skin at the walls to det F ~ 0.06-0.09
        and 3 tore a 4 mm orange peel past det F 20.  Under selective scaling 4 stays within the guards (orange,
        tomato, can).  Faster releases were measured (docs/limits/released-material.md; under load): 3 / 4 m/s cost 1.31x /
        1.60x the substeps (tomato), 1.38x / 1.72x (orange), 1.56x / 1.98x (can: its cola is there from the start;
        the fluid's sound speed follows this cap, ``fluid_reference_speed``) and let only the tomato's whole juice fly
        free (-9.810 for 10.2 / 6.9 ms) and only at the default grid alignment (none half a cell off); Table 2 in
        bands overlapping the grid-offset noise.
    release_mach_max: the release speed is also capped at this fraction of the released material's sound speed
        after its mass scaling (a weakly compressible fluid or the torn skin pushed faster than ~0.3 of its wave speed
        shocks and inverts: with 10 substeps per 1/15 s frame, c = 0.36 m/s and a 1.5 m/s release tore the can's,
        orange's and tomato's skins past the J guard).  At the default settings c >= 6 m/s: no effect.
    stuffing_packing: volume ratio (1) of the plush toy's stuffing packed in the toy to the same fibres relaxed (the
        oracle's ``foam`` interior, loose fibrefill): released stuffing leaves at this J (F = J^(1/3) I) and expands
        out of the opening as a cohesive bulge (a fluid interior, juice and cola, is released at its rest volume
        whatever this is).  0.5 (default; the oracle's loose fibrefill is the packed stuffing's modulus and yield x
        0.5^3, van Wyk's cube law): the full plush toy's stuffing (seed 0, whose tear is 2.4 cm above the table) ends
        41 % outside the rest surface with a free contact (max 11.6 mm, spread over the toy's foot), 3 % (max 3.3
        mm, in the opening) with the default ``stuffing_cohesion``, in one piece (99 %); measured at E = yield = 1 kPa
        with the free contact: 0.6 29 %, max 10 mm, 1 (no packing) 24 %, max 6 mm.  A fluid stuffing released at 0.5
        flew apart (43 pieces).
    seam_opening: where the interior is packed stuffing, the torn fabric opens at the release as a hole of this
        fraction of ``release_radius`` (the fabric folded into the ring around it,
        ``tasks.physics.rupture_release.seam_opening``) instead of the torn patch staying as a lid over the opening
        (fruit skins keep the peel-back alone).  0.6 (default, 12 mm at release_radius 20 mm; 0.7 and 0.8 moved the
        stuffing's outward reach by < 1 mm).  0: the torn patch, one continuum in the grid, stays a lid over the opening and the stuffing stops
        under it within ~8 ms (5 mm).  The full plush toy's substeps 10,403 -> 9,004 with both (the loose foam's
        stable step is longer than the former viscous fluid's); Table 2 within 0.02.
    stuffing_cohesion: the released stuffing's entanglement with the stuffing it tore from, as a fraction of the
        loose stuffing's own yield stress (dimensionless): the tensile strength (Pa) of the contact between the
        released velocity field and the body (``Material.cohesion``; the tangential contact stays frictionless).
        Released stuffing has its own field (its physical inertia against the mass-scaled toy) and met the toy only
        through a frictionless, non-sticking contact: pushed out of the tear it slid off (seeds 1-2 and every
        force-driven seed: on the table 4-7 cm from the toy).  1 (default: the fibre mass holds across the tear's
        inner face what it holds within itself, 125 Pa for the oracle's loose fibrefill; its bulge's weight is
        ~7 Pa of that face): in all six plush runs (seeds 0-2, both variants) the stuffing stays on the toy (median
        2-5 mm from it, none > 3 cells), in one piece per opening, at the same substeps; outside the rest surface at
        the end, full variant, seeds 0 / 1 / 2: 3 / 29 / 14 % (max 3.3 / 13.2 / 10.3 mm).  0.25 (31 Pa) holds it
        too and lets it bulge further (seeds 1 / 2 full: 45 / 31 %, max 17 / 13 mm).  0: the former free contact.
    feedback_max_force: N, the glove's per-finger force-feedback range (resistive force is clipped to it).
    feedback_rule: the resistive force per finger (sec. 3.2), clipped to ``feedback_max_force``: ``yield_area``
        (the paper's rule: the shell's yield stress tau_y (Pa) x the contact patch area A_k (m^2); the simulated
        |reaction| for a shell without a yield stress), ``reaction`` (the simulated |reaction| of the finger, N) or
        ``auto`` (default: ``reaction`` with ``mpm.fingers=collider``, whose reactions come from the fingertip
        impulses at the surface, ``yield_area`` with the Dirichlet fingers, on grid nodes or on particles, whose
        reactions are not converged).
    gravity_preload_frames: the given shape (the captured object standing on the table) is the body's equilibrium
        under its weight: before the first frame the body settles under gravity by dynamic relaxation, then is put
        back where it was given, keeping the stress that carried its weight
        (:meth:`tasks.physics.mpm.solver.MPMSolver.preload_gravity`), in at most ``gravity_preload_passes``
        passes of at most this many damped frames each.  0: no preload; gravity then acts from the first frame
        on a stress-free body, which sags and sways from there (the plush toy's top swung 41 mm forward over the
        18 frames before the fingers arrived, and the fingers' eq. 3 targets, set on the given shape, pulled it
        back 34 mm within two frames).  The other seven objects settle by < 0.2 mm.
    gravity_preload_passes: passes of the preload (>= 1; each settles what the last one's change of geometry left).
    gravity_preload_tolerance: a pass ends at its crest (the body's kinetic energy peaked once it moved half a cell:
        its equilibrium) or when the fastest solid particle moves at most this many grid cells per frame after its
        motion peaked; the preload ends after a pass that moved no particle farther.
    """

    fluid_reference_speed: float = 1.5
    fluid_mach: float = 0.3
    fluid_tait_exponent: float = 1.0
    force_per_coefficient: float = 8.0
    force_balance: str = "wrench"
    force_balance_friction: float = 1.0
    torn_finger_push: str = "beneath"
    release_radius: float = 0.02
    release_margin_cells: int = 8
    max_release_speed: float = 1.5
    release_mach_max: float = 0.3
    ruptured_softening: float = 1.0e-2
    stuffing_packing: float = 0.5
    seam_opening: float = 0.6
    stuffing_cohesion: float = 1.0
    feedback_max_force: float = 20.0
    feedback_rule: str = "auto"
    gravity_preload_frames: int = 60
    gravity_preload_passes: int = 3
    gravity_preload_tolerance: float = 0.01


# ----------------------------------------------------------------------------------------------- runner
RUNNER_KINDS = ("sequential", "threads", "dask")
FORCE_BALANCES = ("wrench", "fingers", "none")  # simulation.force_balance
TORN_FINGER_PUSHES = ("beneath", "none")  # simulation.torn_finger_push


@dataclass
class RunnerConfig:
    """Prefect task runner: ``sequential``, ``threads`` or ``dask`` (local cluster or ``address``)."""

    kind: str = "threads"
    max_workers: int = 2
    address: Optional[str] = None  # dask scheduler address, e.g. tcp://10.0.0.5:8786
    n_workers: Optional[int] = None  # dask local cluster: worker processes (None: one per core)
    threads_per_worker: int = 1


@dataclass
class PathsConfig:
    artifacts: str = "artifacts"  # zarr artifacts and Prefect's cache records
    reports: str = "reports"
    export: Optional[str] = None  # python -m flows.export: PLY folder (None: reports/ply/<object>_<variant>)


@dataclass
class GridConfig:
    """The evaluation grid: objects x variants evaluated when no single ``object`` / ``variant`` is selected.

    Names refer to ``catalog`` (objects) and ``variants`` (method variants, e.g. Table 2's two rows)."""

    objects: list[str] = field(
        default_factory=lambda: [
            "can", "plush_toy", "rubber_duck", "clay", "tomato", "orange", "rubber_ball", "paper_cup"]
    )
    variants: list[str] = field(default_factory=lambda: ["full", "no_dirichlet"])
    backends: Optional[list[str]] = None  # effect backends run per variant (None: [generation.backend]); Table 1
    # sampling.seed values run per object and variant (None: [sampling.seed], one run); each seed is its own scope,
    # <object> for seed 0 and <object>@seed<k> otherwise, and the report gives each metric as mean +- std over them
    seeds: Optional[list[int]] = None


@dataclass
class LimitsConfig:
    """Bounds on a run's work, checked against the estimate of :func:`flows.preflight.estimate_work` before the
    flow starts (a run beyond one is refused with the estimate and this knob).  The defaults pass the default grid
    (91 frames, 1.6e9 particle-substeps, a 130 MB artifact at most, a 41x37x38 grid of 7 MB, ~7 min) with a wide
    margin; ``grid.seeds=[0,...,20]`` (21 grids, ~2.3 h) passes too."""

    max_frames: int = 9000  # output frames of one squeeze (5 min at 30 Hz)
    max_particle_steps: float = 1e11  # particles x substeps x frames summed over the objects x variants x seeds
    max_artifact_bytes: float = 8 * 2**30  # bytes of the largest artifact (the MPM rollout or the render g-buffer)
    max_grid_bytes: float = 8 * 2**30  # bytes of one scene's MPM background grid (nodes from mpm.dx and the object's box)
    max_wall_hours: float = 12.0  # expected wall time of the run (flows.preflight_settings: measured throughput)


@dataclass
class Config:
    object: Optional[ObjectConfig] = None
    catalog: dict[str, ObjectConfig] = field(default_factory=dict)
    grid: GridConfig = field(default_factory=GridConfig)
    signal: SignalConfig = field(default_factory=SignalConfig)
    control: ControlConfig = field(default_factory=ControlConfig)
    sampling: SamplingConfig = field(default_factory=SamplingConfig)
    runner: RunnerConfig = field(default_factory=RunnerConfig)
    paths: PathsConfig = field(default_factory=PathsConfig)
    oracle: OracleConfig = field(default_factory=OracleConfig)
    mpm: MPMConfig = field(default_factory=MPMConfig)
    simulation: SimulationConfig = field(default_factory=SimulationConfig)
    variant: Optional[VariantConfig] = None
    variants: dict[str, VariantConfig] = field(default_factory=dict)
    metrics: MetricsConfig = field(default_factory=MetricsConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    generation: GenerationConfig = field(default_factory=GenerationConfig)
    refinement: RefinementConfig = field(default_factory=RefinementConfig)
    video_metrics: VideoMetricsConfig = field(default_factory=VideoMetricsConfig)
    paper_metrics: PaperMetricsConfig = field(default_factory=PaperMetricsConfig)
    llm_judge: LLMJudgeConfig = field(default_factory=LLMJudgeConfig)
    run_name: Optional[str] = None  # report folder name; default: flow name + time stamp
    accuracy: dict[str, str] = field(default_factory=dict)  # the preset's measured error (conf/preset/), reported
    limits: LimitsConfig = field(default_factory=LimitsConfig)


def register_configs() -> None:
    """Register the root schema with Hydra's ConfigStore (``config_schema`` in the defaults lists)."""
    from hydra.core.config_store import ConfigStore

    ConfigStore.instance().store(name="config_schema", node=Config)


class ConfigError(ValueError):
    """A config value is out of its valid range; the message names the key and the fix."""


def _need(ok: bool, key: str, msg: str) -> None:
    if not ok:
        raise ConfigError(f"{key} {msg}")


def validate(cfg: Any) -> None:
    """Range checks the type system cannot express.  Raises :class:`ConfigError` naming the key."""
    validate_simulation(cfg, [("object", cfg.object)] if cfg.object is not None else
                        [(f"catalog.{n}", cfg.catalog[n]) for n in cfg.grid.objects if n in cfg.catalog])
    _validate_pipeline(cfg)


def validate_simulation(cfg: Any, objects: list[tuple[str, Any]]) -> None:
    """The checks of what a simulation reads, shared by the pipeline and the stability suite
    (:func:`conf.study.stability_schema.validate_stability`): no unknown key and no non-finite number anywhere in
    ``cfg``; the ``signal``, ``control``, ``sampling``, ``simulation``, ``mpm`` and ``oracle`` groups; the geometry
    and material of ``objects`` ((config key, object) pairs).  Raises :class:`ConfigError` naming the key."""
    need = _need
    _refuse_unknown_keys(cfg)
    _refuse_non_finite(cfg)
    s, c = cfg.signal, cfg.control
    need(s.source in ("synthetic", "csv"), "signal.source", f"must be synthetic or csv, got {s.source!r}")
    need(s.source != "csv" or bool(s.path), "signal.path", "is required with signal=csv: signal.path=/abs/rec.csv")
    need(s.duration > 0, "signal.duration", f"must be > 0 s, got {s.duration}")
    need(s.sensor_rate > 0, "signal.sensor_rate", f"must be > 0 Hz, got {s.sensor_rate}")
    need(0 < s.peak_flexion <= 1, "signal.peak_flexion", f"must be in (0, 1], got {s.peak_flexion}")
    need(c.smoothing.frame_rate > 0, "control.smoothing.frame_rate", f"must be > 0 Hz, got {c.smoothing.frame_rate}")
    need(0 < c.smoothing.ema_alpha <= 1, "control.smoothing.ema_alpha", f"must be in (0, 1], got {c.smoothing.ema_alpha}")
    need(len(c.force.weights) == len(FINGERS), "control.force.weights",
         f"needs one weight per finger {list(FINGERS)}, got {len(c.force.weights)}")
    need(0 <= c.force.beta < 1, "control.force.beta", f"must be in [0, 1), got {c.force.beta}")
    need(c.force.gamma > 0, "control.force.gamma", f"must be > 0, got {c.force.gamma}")
    need(c.force.release_gamma > 0, "control.force.release_gamma", f"must be > 0, got {c.force.release_gamma}")
    need(0 < c.contact.sigma_min <= c.contact.sigma_max, "control.contact.sigma_min",
         f"must satisfy 0 < sigma_min <= sigma_max, got {c.contact.sigma_min}, {c.contact.sigma_max}")
    need(c.contact.candidates >= 1, "control.contact.candidates", f"must be >= 1, got {c.contact.candidates}")
    need(c.displacement.eta >= 0, "control.displacement.eta", f"must be >= 0 m, got {c.displacement.eta}")
    need(cfg.sampling.surface_points >= 100, "sampling.surface_points", f"must be >= 100, got {cfg.sampling.surface_points}")
    need(cfg.sampling.seed >= 0, "sampling.seed", f"must be >= 0, got {cfg.sampling.seed}")
    need(cfg.sampling.particle_spacing > 0, "sampling.particle_spacing", f"must be > 0 m, got {cfg.sampling.particle_spacing}")
    need(cfg.sampling.thin_wall_layers in (1, 2, 3), "sampling.thin_wall_layers",
         f"must be 1, 2 or 3, got {cfg.sampling.thin_wall_layers}")
    sim = cfg.simulation
    need(sim.fluid_tait_exponent >= 1, "simulation.fluid_tait_exponent", f"must be >= 1, got {sim.fluid_tait_exponent}")
    need(sim.release_radius > 0, "simulation.release_radius", f"must be > 0 m, got {sim.release_radius}")
    need(sim.release_margin_cells >= 0, "simulation.release_margin_cells",
         f"must be >= 0 grid cells, got {sim.release_margin_cells}")
    need(0 < sim.fluid_mach <= 1, "simulation.fluid_mach", f"must be in (0, 1] (weakly compressible), got {sim.fluid_mach}")
    need(0 < sim.release_mach_max <= 1, "simulation.release_mach_max",
         f"must be in (0, 1] (a fraction of the released material's sound speed), got {sim.release_mach_max}")
    need(0 < sim.ruptured_softening <= 1, "simulation.ruptured_softening",
         f"must be in (0, 1], got {sim.ruptured_softening}")
    need(0.2 <= sim.stuffing_packing <= 1, "simulation.stuffing_packing",
         f"must be in [0.2, 1] (packed / relaxed volume of the stuffing; 1 = not packed), got {sim.stuffing_packing}")
    need(0 <= sim.seam_opening < 1, "simulation.seam_opening",
         f"must be in [0, 1) (the hole's radius over release_radius; 0 = no opening), got {sim.seam_opening}")
    need(sim.stuffing_cohesion >= 0, "simulation.stuffing_cohesion",
         f"must be >= 0 (a fraction of the loose stuffing's yield stress; 0 = no cohesion), got {sim.stuffing_cohesion}")
    need(sim.force_balance in FORCE_BALANCES, "simulation.force_balance",
         f"must be wrench (the fingers' forces and moments sum to zero), fingers (their forces) or none, "
         f"got {sim.force_balance!r}")
    need(sim.torn_finger_push in TORN_FINGER_PUSHES, "simulation.torn_finger_push",
         f"must be beneath (a torn finger presses on the core under its opening) or none, "
         f"got {sim.torn_finger_push!r}")
    need(sim.force_balance_friction > 0, "simulation.force_balance_friction",
         f"must be > 0 (a Coulomb coefficient, e.g. 1), got {sim.force_balance_friction}")
    need(sim.feedback_rule in ("auto", "reaction", "yield_area"), "simulation.feedback_rule",
         f"must be auto, reaction or yield_area, got {sim.feedback_rule!r}")
    need(sim.gravity_preload_frames >= 0, "simulation.gravity_preload_frames",
         f"must be >= 0 frames (0 = no preload), got {sim.gravity_preload_frames}")
    need(sim.gravity_preload_passes >= 1, "simulation.gravity_preload_passes",
         f"must be >= 1, got {sim.gravity_preload_passes}")
    need(sim.gravity_preload_tolerance > 0, "simulation.gravity_preload_tolerance",
         f"must be > 0 grid cells per frame, got {sim.gravity_preload_tolerance}")
    _validate_inputs(cfg, objects, need)


def _validate_pipeline(cfg: Any) -> None:
    """The grid, limits, variants and the metric, render and generation groups of a pipeline run."""
    need = _need
    if cfg.grid.seeds is not None:
        seeds = list(cfg.grid.seeds)
        need(len(seeds) > 0, "grid.seeds", "is empty: give at least one seed, e.g. grid.seeds=[0,1,2], or leave it unset")
        need(len(set(seeds)) == len(seeds), "grid.seeds", f"lists a seed twice: {seeds}")
        need(min(seeds) >= 0, "grid.seeds", f"must be >= 0, got {seeds}")
    if "runner" in cfg:
        need(cfg.runner.kind in RUNNER_KINDS, "runner.kind",
             f"must be one of {', '.join(RUNNER_KINDS)}, got {cfg.runner.kind!r}")
    lim = cfg.limits
    for key in ("max_frames", "max_particle_steps", "max_artifact_bytes", "max_grid_bytes", "max_wall_hours"):
        need(lim[key] > 0, f"limits.{key}", f"must be > 0, got {lim[key]}")
    need(cfg.object is not None or len(cfg.grid.objects) > 0, "grid.objects",
         f"is empty: name at least one object, e.g. [rubber_ball] (known {sorted(cfg.catalog)})")
    for name in cfg.grid.objects:
        need(name in cfg.catalog or (cfg.object is not None and cfg.object.name == name) or not cfg.catalog,
             "grid.objects", f"names unknown object {name!r}: known {sorted(cfg.catalog)}")
    if cfg.variant is None:
        need(len(cfg.grid.variants) > 0, "grid.variants", "is empty: name at least one variant, e.g. [full]")
        for name in cfg.grid.variants:
            need(name in cfg.variants, "grid.variants",
                 f"names unknown variant {name!r}: known {sorted(cfg.variants)} (add conf/variant/{name}.yaml "
                 f"and +variant@variants.{name}={name})")
    for variant in ([cfg.variant] if cfg.variant is not None else [cfg.variants[n] for n in cfg.grid.variants]):
        need(variant.boundary in ("dirichlet", "force"), f"variant {variant.name!r} boundary",
             f"must be dirichlet or force, got {variant.boundary!r}")
        need(variant.force_match in ("indentation", "none"), f"variant {variant.name!r} force_match",
             f"must be indentation or none, got {variant.force_match!r}")
        need(variant.force_match == "none" or variant.boundary == "force", f"variant {variant.name!r} force_match",
             f"calibrates a force-driven push: set boundary=force or force_match=none (got boundary="
             f"{variant.boundary!r})")
        need(variant.force_match_rtol > 0 and variant.force_match_runs >= 1, f"variant {variant.name!r} force_match",
             f"needs force_match_rtol > 0 and force_match_runs >= 1, got {variant.force_match_rtol}, "
             f"{variant.force_match_runs}")
    try:
        validate_metrics(cfg.metrics)
        validate_render(cfg.render)
        validate_generation(cfg.generation, cfg.refinement, cfg.video_metrics)
        validate_paper_metrics(cfg.paper_metrics)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _validate_inputs(cfg: Any, objects: list[tuple[str, Any]], need: Any) -> None:
    """What a run reads besides the method's knobs: the selected objects' geometry and material overrides, the
    MPM grid and the material oracle.  Each error names the key to change.  (Input *files* - existence, size,
    format - are checked by :mod:`flows.preflight` before the flow starts.)"""
    import math

    from conf.mpm_schema import MPMConfigError, mpm_config_from
    from conf.oracle_schema import ORACLE_BACKENDS

    def positive(value: Any) -> bool:
        return value is not None and math.isfinite(float(value)) and float(value) > 0

    for key, obj in objects:
        g, m = obj.geometry, obj.material
        need(len(g.size) == 3 and all(positive(v) for v in g.size), f"{key}.geometry.size",
             f"must be three lengths > 0 m (x, y, z), got {list(g.size)}")
        need(g.wall_thickness >= 0, f"{key}.geometry.wall_thickness", f"must be >= 0 m, got {g.wall_thickness}")
        need(g.kind not in ("ply", "mesh") or bool(g.path), f"{key}.geometry.path",
             f"is required with geometry.kind={g.kind}: give the file's path")
        if m.youngs_modulus is not None:
            need(positive(m.youngs_modulus), f"{key}.material.youngs_modulus",
                 f"must be > 0 Pa (Young's modulus in pascals, e.g. rubber 2e6), got {m.youngs_modulus}")
        if m.poisson_ratio is not None:
            need(0 <= m.poisson_ratio < 0.5, f"{key}.material.poisson_ratio",
                 f"must be in [0, 0.5), got {m.poisson_ratio}: 0.5 is incompressible (infinite Lame lambda); "
                 f"use at most 0.49 (rubber)")
        if m.density is not None:
            need(positive(m.density), f"{key}.material.density", f"must be > 0 kg/m^3, got {m.density}")
        if m.yield_stress is not None:
            need(positive(m.yield_stress), f"{key}.material.yield_stress", f"must be > 0 Pa, got {m.yield_stress}")
        if m.squeeze_threshold is not None:
            need(0 < m.squeeze_threshold < 1, f"{key}.material.squeeze_threshold",
                 f"must be in (0, 1) (the compressive strain where rupture starts), got {m.squeeze_threshold}")

    need(cfg.mpm.particles_per_cell >= 1, "mpm.particles_per_cell",
         f"must be >= 1 (grid spacing = particle spacing x cbrt of it), got {cfg.mpm.particles_per_cell}")
    try:
        mpm_config_from(cfg.mpm)
    except MPMConfigError as exc:  # mpm.dx = 0, mpm.cells_across = 0, ... (message names the key)
        raise ConfigError(str(exc)) from None

    o = cfg.oracle
    need(o.backend in ORACLE_BACKENDS, "oracle.backend", f"must be one of {', '.join(ORACLE_BACKENDS)}, got {o.backend!r}")
    need(positive(o.timeout_s), "oracle.timeout_s", f"must be > 0 s, got {o.timeout_s}")
    if o.backend == "llm":
        need(bool(o.llm_url) and str(o.llm_url).startswith(("http://", "https://")), "oracle.llm_url",
             "must be the http(s) base URL of an OpenAI-compatible API with oracle.backend=llm "
             "(e.g. http://127.0.0.1:8000/v1), or use oracle.backend=table")
        need(bool(o.api_key_env), "oracle.api_key_env", "must name the environment variable that holds the API key")


def _nodes(node: Any, key: str = ""):
    """Every (full key, node) of a composed config, depth first (None-valued groups are leaves)."""
    yield key, node
    if isinstance(node, (DictConfig, ListConfig)) and not node._is_none() and not node._is_missing():
        items = node.items_ex(resolve=False) if isinstance(node, DictConfig) else enumerate(node._content)
        for k, _ in items:
            child = node._get_node(k)
            yield from _nodes(child, f"{key}.{k}" if key and isinstance(node, DictConfig) else
                              (f"{key}[{k}]" if key else str(k)))


def _refuse_unknown_keys(cfg: Any) -> None:
    """A key added with ``+`` to a structured group (``+control.force.gama=2``, which Hydra's own typo hint
    suggests) would be stored and ignored: refuse it, naming the closest known key."""
    for key, node in _nodes(cfg):
        if not isinstance(node, DictConfig) or node._is_none():
            continue
        schema = OmegaConf.get_type(node)
        if not (isinstance(schema, type) and is_dataclass(schema)):
            continue
        known = [f.name for f in fields(schema)]
        for name in node.keys():
            if name not in known:
                full = f"{key}.{name}" if key else str(name)
                close = difflib.get_close_matches(str(name), known, n=1)
                hint = f"did you mean {(key + '.' if key else '') + close[0]}?" if close else f"known: {', '.join(known)}"
                raise ConfigError(f"{full} is not a key of {schema.__name__} (it would be ignored): {hint}")


def _refuse_non_finite(cfg: Any) -> None:
    """``inf`` and ``nan`` pass every ``> 0`` check and reach the method as NaN fields: refuse any non-finite
    number anywhere in the config, naming its key."""
    for key, node in _nodes(cfg):
        if isinstance(node, (DictConfig, ListConfig)):
            continue
        try:
            value = node._dereference_node()._value() if node._is_interpolation() else node._value()
        except Exception:  # noqa: BLE001 - an interpolation only Hydra's runtime resolves (e.g. ${now:...})
            continue
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{key} must be a finite number, got {value}")
