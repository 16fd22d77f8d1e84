"""Structured schema of the ``mpm`` config group (MLS-MPM solver, :mod:`tasks.physics.mpm`).

All physical quantities are SI (metres, seconds, pascals, kilograms).  The grid spacing is ``dx`` when given,
otherwise the object's largest extent divided by ``cells_across``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping, Optional


@dataclass
class MPMConfig:
    """MLS-MPM solver settings.

    Device and grid
        device: ``auto`` (CUDA when present, else CPU), ``cpu``, ``cuda`` or ``cuda:N``.
        dx: grid spacing in m; ``None`` = largest object extent / ``cells_across``.
        cells_across: cells across the object's largest extent when ``dx`` is None.
        particles_per_cell: volume particles per cell for samplers (8 = 2 x 2 x 2); the solver itself takes
            the particle volumes it is given.
        margin_cells: free cells around the particles' bounding box on every side (not below a floor).
        domain_lo / domain_hi: explicit world box (m) of the simulated region; overrides the automatic box.
        padding: boundary layer thickness in nodes; domain walls act on these nodes.  A particle entering the
            outermost cell (where its B-spline stencil would leave the grid) is an error (SimulationError).
    Time step (explicit; CFL-adaptive every substep)
        courant: C in dt <= C dx / c_p (c_p = P-wave speed of the stiffest material present, after scaling).
        max_speed_cfl: advective bound dt <= max_speed_cfl dx / max |v|.
        dt: forced substep size in s (disables the adaptive choice); checked against ``courant_limit``.
        courant_limit: largest Courant number dt c_p / dx accepted, for ``courant`` and for a forced ``dt``.
            0.8: ``python -m flows.studies.stability`` measured explicit MLS-MPM (8 cells, plate release) unstable
            at 0.95 for nu = 0.45 and at 0.9 for nu = 0.49, with J in range and no NaN (energy x120): no guard
            catches that, so the config refuses it.
        max_substeps_per_frame: safety cap (a collapsing dt is an error, not an endless loop).
    Body force and boundaries
        gravity: m/s^2 (z up).
        floor: enable the floor plane z = ``floor_height`` (None = lowest particle at construction).
        floor_friction: Coulomb coefficient of the floor (0 = frictionless slip).
        floor_sticky: the floor holds the material (no slip, no separation).
        wall_sticky: domain walls are sticky instead of slip.
        contact: how the floor and rigid colliders (``Collider``: plane, sphere, capsule) act.  ``grid`` (the
            floor acts on the body's grid nodes at or below it, so on material within its B-spline stencil, ~1.5 dx
            above it; the floor height defaults to the lowest particle's centre; with two velocity fields,
            ``multi_field``, the released field meets it as ``surface``'s plane collider, where its particles touch
            it, friction ``floor_friction`` or no slip while touching if ``floor_sticky``); ``surface`` (the floor is a plane
            collider: colliders act on the particles whose surface, centre -+ half the particle spacing, touches
            them, through the P2G momentum; the floor height defaults to the lowest particle's contact surface,
            its centre minus its contact reach: half its spacing, a thin wall's face; ``floor_sticky`` then means no
            slip while touching).  ``Collider`` s passed to ``step_frame`` act at
            the surface in both modes; ``DirichletPoints``/``DirichletNodes`` always act on grid nodes.  A sphere
            pressed on the table reads 2.1-5.8x Hertz at 1-4 mm on grid nodes, 1.23-1.44x at the surface
            (docs/limits/table-contact.md).  This class's default stays ``grid`` (the scripting API's, as
            before); the pipeline's table is ``surface`` with ``table_hold: footprint`` since 2026-12-06
            (``conf/mpm/default.yaml``; alone, without the hold, it toppled the plush toy and let the force-driven
            ball and duck roll: docs/limits/table-contact.md, "The flip").
        table_hold: what holds the body on a ``contact: surface`` table besides its contact
            (:mod:`tasks.physics.table_hold`).  ``none`` (this class's default; the pipeline's is ``footprint``): the table pushes the particles touching it and,
            sticky, keeps them from slipping, but never pulls: a body pushed sideways at its top can tip over its
            edge or roll (flipped to the surface table on 2026-12-06, the plush toy toppled and the force-driven ball
            rolled away).  ``footprint``: the particles within one particle spacing of the table in the body's given
            shape are held where they rest through the gravity preload and the rollout, no slip and no lift (particle pins at
            their lowest surface points, finger -1, that may still be pressed onto the table: no support is added,
            the Hertz table case reads +2 to +7 %; their work is credited to the energy guard and is zero at rest),
            as a hand pressing the object onto the table holds it; the rest of the body meets the table where it
            touches it.  Needs ``contact: surface`` (the grid-node table already glues ~1.5 cells of the body to it);
            with no table (``floor: false``) there is nothing to hold against and the hold is left out (a note says so).
            The force-driven ball, duck and clay then stay upright, and the plush toy, seated on its seat and
            legs, settles in 12 damped frames and sways < 2 deg under the squeeze: docs/limits/table-contact.md,
            "The hold" and "The flip, with the hold".
        fingers: how the squeeze's fingers drive the material (``variant.boundary=dirichlet`` in
            :mod:`tasks.physics.mpm_rollout`; the force-driven ablation is unaffected).  ``particles`` (default):
            every surface point the eq. 3 field constrains is driven to its target on the particles it is embedded in
            (``ParticlePins``): their surface points are driven by the displacement the point still needs, and the
            constraint reaches the grid through the P2G momentum, with no node held (a cube between two pinned layers
            reads E A eps within 5 % at nu = 0.3-0.49); on a wall thinner than the particle spacing the particles are
            pinned at their centres.  ``dirichlet``: the same targets as ``DirichletPoints`` on the grid nodes of
            each point's B-spline stencil (a ~1.5 dx halo: grid-node plates +30 % and more on the cube).  Default
            grid, all eight objects (2026-12-05): the pins hold the constrained points 1.03-3.7x closer to their
            targets and cut the rubber ball's preset errors (standard: position 0.46 -> 0.35 %, reaction 34 -> 26 %);
            on Table 2 they gain on BDC-T and SDC and lose 0.052 on BDC-S and 0.018 on mIoU, what the halo had held
            around each patch (docs/limits/fingers-and-contact.md).
            ``collider``: each active finger is a rigid sphere ``Collider`` of the fingertip pad radius (10 mm, the
            pad of the contact patches), its lowest point at the patch centre displaced by the eq. 3 amplitude
            eta c_k,t, moved there every frame: it pushes the particles it touches and never pulls; its impulses
            are the finger's reaction (N).  Meant for
            ``contact: surface`` (both act where the material touches).  Not the default: it lost Table 2 on the
            rubber ball, clay and rubber duck (docs/limits/fingers-and-contact.md; ``python -m flows.studies.fingers``).
        thin_walls: how a hollow object's wall thinner than the grid spacing ``dx`` (sampled on its mid-surface in
            ``sampling.thin_wall_layers`` Gauss layers, :mod:`tasks.physics.particle_fill`) carries stress.
            ``membrane`` (default; up to ``membrane_max_thickness`` of a cell): its elastic particles
            (fixed-corotated, neo-Hookean) have no normal stress on the wall, as a thin shell (plane stress;
            :func:`tasks.physics.mpm.constitutive.membrane_F`), and its von Mises particles return-map in plane
            stress (:func:`tasks.physics.mpm.constitutive.membrane_plastic_return`; can 6,900 -> 1,600 N, paper cup
            950 -> 350 N per finger): the wall thins as it stretches, and its in-plane wave
            speed sets its stable step; in two layers at the thickness's Gauss points it also carries its bending
            (ball 50 N per finger, rubber springs back with 20 % of its dent left).  ``solid``: full 3D stress; the
            grid, which cannot resolve the thickness, holds it where a finger's nodes reach through the wall, and
            the wall's volume locks as nu -> 0.5 (the rubber ball and duck, nu = 0.49: 570 and 3,100 N per finger;
            docs/limits/thin-walls.md); its Gauss layers touch colliders at the wall's faces (since 2026-12-04; before,
            half a particle spacing out).
        membrane_max_thickness: the thickest wall, as a fraction of ``dx``, that ``thin_walls: membrane`` holds in
            plane stress; a wall from this fraction up to ``dx`` sampled in two or three Gauss layers on its
            mid-surface carries full 3D stress, the grid resolving enough of its thickness (one layer, which has no
            bending as a solid either, stays in plane stress).  Past about half a cell the
            plane-stress wall softens as the grid refines, a 3D solid in Gauss layers locks on a coarse grid and
            converges from above: the rubber ball between surface flats at 3 mm (two layers) reads 0.85x (plane
            stress) / 0.99x (solid) the FE at 0.94 of a cell (dx 3.2 mm), 0.92x / 1.02x at 0.75, 0.95x / 1.07x at
            0.6 and 1.03x / 1.34x at 0.375 (the default grid); docs/limits/thin-walls.md.
        wall_fibres: a membrane wall sampled in two Gauss layers (``sampling.thin_wall_layers: 2``) keeps the
            distance between its layers at each point, Kirchhoff-Love's inextensible normal fibre
            (:func:`tasks.physics.mpm.kernels.walls.k_wall_fibres`, after every substep's advection).  The grid cannot
            resolve the wall's thickness and its plane-stress particles carry no normal stress, so nothing else keeps
            it: the rubber ball between two flats had its layers closed to 11 % of their distance under the flats at
            4 mm, its bending lever arm with them, and read 0.35-0.56x the FE of the hollow sphere at dx 4 mm (with
            the fibres 0.70-1.02x, 0.70-0.95x with the contact at the wall's face; ``python -m flows.studies.ball
            plates=[surface]``).  False: the layers move with
            the grid alone (the former behaviour).
        wall_normal_stiffness: kappa, dimensionless: an elastic (fixed-corotated, neo-Hookean) membrane particle's
            F_E keeps the normal stretch its grid gives it, and its stress, its plane-stress projection's, gains a
            stiffness kappa x 2 mu against that stretch's departure from the plane-stress one
            (:func:`tasks.physics.mpm.kernels.walls.wall_normal_energy`; no Poisson coupling, so no volumetric locking).
            0: F_E is stored projected and the normal velocity gradient across the wall costs nothing, and two
            particle layers across a wall then leave the grid velocity modes that move the particles at no strain
            energy: a clamped two-layer strip crept under its weight at every grid alignment (1.10x -> 1.39x its
            Euler-Bernoulli sag over 0.1 -> 0.5 s), the rubber ball held between two flats lost 11-23 % of its
            force in 5 s.  At 0.25 (with ``wall_stencil: shared``) the strip settles at 1.02-1.08x the closed form
            and the ball loses 2.2 % over 20 s; at 1 it loses 1.0 % over 5 s, but the stiffness's stress holds the
            projection fixed (not the energy's full gradient), so where a grid holds a wall's thickness it does
            work of its own: at 1 the rubber duck's rollout tripped the energy guard.  Von Mises walls keep their
            plane-stress return.
        wall_stencil: ``shared``: the two Gauss layers of a membrane wall use the stencil of their mid-surface
            (:func:`tasks.physics.mpm.kernels.walls.particle_stencil`); ``own``: each its own.  With their own, layers on
            either side of a plane of cell centres spread over four node layers across the wall, which leaves
            the grid modes above even to a solid: a 3 mm solid strip there crept, a quarter cell away it settled.
        finger_friction: Coulomb coefficient of the collider fingertips (0 = frictionless, < 0 = no slip while
            touching), dimensionless.
    Acceleration knobs (each changes the physics; reported in the frame statistics)
        mass_scaling: time (mass) scaling, the one acceleration mechanism of the project.  ``off``; ``manual`` (every
            density x ``mass_scale``); ``global`` (every density x s, s the smallest factor >= 1 for which the
            elastic CFL of the non-fluid materials needs at most ``target_substeps_per_frame`` substeps per output
            frame, fixed at the first frame: s = max(1, (c_p frame_dt / (N C dx))^2), see
            :func:`tasks.physics.mpm.mass_scaling.mass_scale_for`; ``auto`` is its former name); ``selective`` (the same
            s, but only for the materials that deform quasi-statically, ``Material.is_mass_scaled``: every
            model but fluids unless a material says otherwise; released material and fluids keep their physical
            inertia, as Abaqus/Explicit variable mass scaling by element set or LS-DYNA selective mass scaling).
            A scaled material's waves are sqrt(s) slower; gravity acts with the PHYSICAL weight (the grid node's
            gravity impulse is dt g sum_p w_ip m_phys,p), so weights and quasi-static states under gravity are
            unchanged and a scaled solid feels g / s while unscaled material falls at g.  The stable time step
            takes every material's own (un)scaled wave speed.  With scaling on, the quasi-static check warns
            (once, naming object, frames and these knobs) when the kinetic/internal energy ratio of the scaled
            materials declared quasi-static (not released material or fluids), sum KE / sum IE over the frames of a
            contact, judged when the contact ends (the fingers load the object; its first two frames, the start-up
            sag under the weight before any contact and the frames after a rupture are not checked), exceeds
            ``quasi_static_ke_ie_max`` (0.1: explicit FE practice asks KE below 5-10 % of IE over most of the
            process; see
            :class:`tasks.physics.mpm.solver.MPMSolver`).  The project's default (``conf/mpm/default.yaml``) is ``selective`` (with
            ``multi_field``); this schema's default ``off`` serves unit tests and closed-form checks.
        multi_field: under ``mass_scaling=selective``, released material and fluids (``Material.is_mass_scaled``
            False: physical inertia) get their own velocity field on the grid (multi-field MPM, Bardenhagen et al.
            2000) whenever they share the scene with the body: their nodal velocity is no longer the (heavier,
            mass-scaled) body's, and the two fields meet only through a
            frictionless, non-sticking contact at the nodes both carry mass on (normal from the body's mass
            gradient; approaching normal velocities become the centre-of-mass one, momentum-conserving; a released
            material with a ``cohesion``, the torn-out stuffing, also holds a separation up to it in tension; see
            :func:`tasks.physics.mpm.kernels.grid.k_field_contact`).  Fingers (Dirichlet, force patches) act on the body
            field.  False: one shared field (the former behaviour).
        mass_scale: the factor s of ``manual`` (>= 1, dimensionless).
        target_substeps_per_frame: N of ``global`` and ``selective``: substeps per output frame the elastic CFL
            of the scaled materials may need.
        quasi_static_margin: k >= 0 (dimensionless, 0 = off): quasi-static bound of ``global`` / ``selective``
            scaling: the scaled body's slowest mode (period T1(s) = sqrt(s) 4 H / c_s, H its height in m, c_s the
            slowest physical shear-wave speed of its scaled solids in m/s) must be k times shorter than the rise time
            t_load (s) of the fingers' load, so s <= (t_load / (k T1(1)))^2 (the rollout takes t_load from the
            force coefficients of a force-driven squeeze, ``variant.boundary=force``: Dirichlet fingers hold the
            body, whose free slowest mode then does not exist); under ``selective`` each scaled material is bounded
            by its own T1, which bounds the composite body's (see
            :func:`tasks.physics.mpm.mass_scaling.material_mass_scales`); it costs sqrt(s_cfl / s) times the substeps
            where it binds (see :func:`tasks.physics.mpm.mass_scaling.mass_scale_for`).  Hollow bodies rock slower than T1
            (the force-driven ball needs k = 2.5 to stay quasi-static, the duck 1.5); 2.5 in the project's defaults
            (sweep and cost per scene: ``conf/mpm/default.yaml``, docs/limits/quasi-static.md).
        quasi_static_damping: local damping coefficient a in [0, 1) (0 = off): dynamic relaxation of the materials the
            quasi-static check measures (mass-scaled solids, not released material or fluids), in the frames before
            a rupture: the net force on a particle becomes F - a |F| sign(v) (Cundall's local damping, as FLAC and
            PFC use for static solutions, 0.8 there; see :class:`tasks.physics.mpm.solver.MPMSolver`).  It vanishes
            at equilibrium and damps the ringing of a mass-scaled body (a block pushed by a constant force settles on
            its closed-form compression).  Off in the project's defaults: in the squeezes, whose loads rise within a
            few frames, the particles' substep-scale force noise makes it act as friction and delays the response.
        stiffness_scaling: factor on E (and K) of every material; yield stresses are unchanged.
    Guards
        j_min, j_max: admissible range of det(F_E); outside raises SimulationError.
        energy_guard_tolerance: energy guard (0 = off): a frame whose total energy (kinetic + internal +
            gravitational, so falling released material gains nothing) exceeds the reference frame's plus the
            boundary work put in since (the positive part of each frame's work) by more than this fraction of the
            run's energy scale raises SimulationError naming object, frame, time and the materials whose energy
            grew (see :class:`tasks.physics.mpm.diagnostics.EnergyBudget`).  The energy scale is the largest of the
            kinetic + internal energy at the reference frames, the work put in, the change of gravitational energy
            and the weight of the whole body lifted by one grid cell (sum m g dx: smaller exchanges, e.g. a body
            settling on the floor, are below what the grid resolves); it never contains the energy being checked.
            0.25: an unstable Courant number (0.95, nu = 0.45) gains 120x energy, while the default squeezes peak
            at 0.09 (force-driven orange) and 0.015 at most (the other 15 of the 8 objects x 2 variants).
        check_every: read the kernels' error flags every this many substeps (and at every frame end).
        debug: compile the kernels in Warp debug mode (bounds checks) and check flags every substep.
        threads: CPU threads of the fused particle kernel (~95 % of a substep) for one scene: the particles are
            cut into 2 chunks per thread, each scattering into its own P2G grid, summed in chunk order after every
            substep (the same physics, reproducible; sums in another order than on one thread, so positions differ
            at float32 round-off).  1 where the run already keeps every core busy with one scene per core
            (``flows.evaluate``'s Dask workers); ``flows.squeeze`` and ``flows.bench.mpm`` use 2.  Ignored on CUDA;
            scenes under 4096 particles per thread use fewer.
    Solver details
        polar_method: per-substep rotation update of fixed-corotated particles, warm-started from the previous
            substep: ``newton`` (default; Newton step on SO(3), matches the SVD rotation to float precision) or
            ``track`` (one scaled gradient step; lags by O(strain x rotation increment), 2e-4 rad at 10 % strain
            and 2e-3 rad per substep; no measurable speed gain on the CPU, kept as a lighter option).
        polar_iterations: iterations of that update per substep.
        polar_restart_iterations: iterations at the start and end of every frame (re-converges the tracked
            rotation, e.g. after F was set from outside).
        polar_tol: convergence tolerance of the polar iteration (rad).
    """

    device: str = "auto"
    dx: Optional[float] = None
    cells_across: int = 32
    particles_per_cell: int = 8
    margin_cells: int = 8
    domain_lo: Optional[list[float]] = None
    domain_hi: Optional[list[float]] = None
    padding: int = 3
    courant: float = 0.3
    max_speed_cfl: float = 0.5
    dt: Optional[float] = None
    courant_limit: float = 0.8
    max_substeps_per_frame: int = 200000
    gravity: list[float] = field(default_factory=lambda: [0.0, 0.0, -9.81])
    floor: bool = True
    floor_height: Optional[float] = None
    floor_friction: float = 0.0
    floor_sticky: bool = False
    wall_sticky: bool = False
    contact: str = "grid"
    table_hold: str = "none"
    fingers: str = "particles"
    finger_friction: float = 0.0
    thin_walls: str = "membrane"
    membrane_max_thickness: float = 0.75
    wall_fibres: bool = True
    wall_normal_stiffness: float = 0.25
    wall_stencil: str = "shared"
    mass_scaling: str = "off"
    multi_field: bool = True
    mass_scale: float = 1.0
    target_substeps_per_frame: int = 100
    quasi_static_ke_ie_max: float = 0.1
    quasi_static_margin: float = 0.0
    quasi_static_damping: float = 0.0
    stiffness_scaling: float = 1.0
    j_min: float = 0.05
    j_max: float = 20.0
    energy_guard_tolerance: float = 0.25
    check_every: int = 50
    debug: bool = False
    threads: int = 1
    polar_method: str = "newton"
    polar_iterations: int = 1
    polar_restart_iterations: int = 16
    polar_tol: float = 1.0e-6


MASS_SCALING_MODES = ("selective", "global", "manual", "off")
CONTACT_MODES = ("grid", "surface")
TABLE_HOLD_MODES = ("none", "footprint")
FINGER_MODES = ("dirichlet", "particles", "collider")
WALL_MODES = ("membrane", "solid")
WALL_STENCILS = ("shared", "own")


class MPMConfigError(ValueError):
    """An ``mpm`` config value is out of range."""


def validate_mpm_config(cfg: MPMConfig) -> MPMConfig:
    """Range checks the type system cannot express; returns ``cfg``."""

    def bad(key: str, msg: str) -> None:
        raise MPMConfigError(f"mpm.{key}: {msg}")

    if not (cfg.device == "auto" or cfg.device == "cpu" or str(cfg.device).startswith("cuda")):
        bad("device", f"'{cfg.device}' is not auto, cpu, cuda or cuda:N")
    if cfg.dx is not None and not cfg.dx > 0:
        bad("dx", f"must be > 0 m (got {cfg.dx})")
    if cfg.cells_across < 4:
        bad("cells_across", f"must be >= 4 (got {cfg.cells_across})")
    if cfg.padding < 2:
        bad("padding", f"must be >= 2 nodes (got {cfg.padding}); the stencil needs room")
    if cfg.margin_cells < 0:
        bad("margin_cells", "must be >= 0")
    if not 0 < cfg.courant <= cfg.courant_limit:
        bad("courant", f"must be in (0, courant_limit={cfg.courant_limit}] (got {cfg.courant}); 0.3-0.5 is stable, "
                       "above 0.85 explicit MPM was measured unstable for nearly incompressible materials")
    if not 0 < cfg.max_speed_cfl <= 1.0:
        bad("max_speed_cfl", f"must be in (0, 1] (got {cfg.max_speed_cfl})")
    if cfg.dt is not None and not cfg.dt > 0:
        bad("dt", f"must be > 0 s (got {cfg.dt})")
    if not cfg.courant_limit > 0:
        bad("courant_limit", "must be > 0")
    if len(cfg.gravity) != 3:
        bad("gravity", "must have 3 components")
    if cfg.floor_friction < 0:
        bad("floor_friction", "must be >= 0")
    if cfg.contact not in CONTACT_MODES:
        bad("contact", f"'{cfg.contact}' is not one of {', '.join(CONTACT_MODES)}")
    if cfg.table_hold not in TABLE_HOLD_MODES:
        bad("table_hold", f"'{cfg.table_hold}' is not one of {', '.join(TABLE_HOLD_MODES)}")
    if cfg.table_hold != "none" and cfg.floor and cfg.contact != "surface":
        bad("table_hold", f"'{cfg.table_hold}' holds the body on the surface table: needs mpm.contact=surface "
                          f"(got contact={cfg.contact}; the grid-node table already glues ~1.5 cells of the body to "
                          "it): set mpm.table_hold=none with it")
    if cfg.fingers not in FINGER_MODES:
        bad("fingers", f"'{cfg.fingers}' is not one of {', '.join(FINGER_MODES)}")
    if cfg.thin_walls not in WALL_MODES:
        bad("thin_walls", f"'{cfg.thin_walls}' is not one of {', '.join(WALL_MODES)}")
    if not 0 < cfg.membrane_max_thickness <= 1:
        bad("membrane_max_thickness", f"must be in (0, 1], a fraction of dx (got {cfg.membrane_max_thickness}); "
                                      "a wall as thick as dx is sampled as a volume, 1 holds every thinner one in "
                                      "plane stress")
    if cfg.wall_stencil not in WALL_STENCILS:
        bad("wall_stencil", f"'{cfg.wall_stencil}' is not one of {', '.join(WALL_STENCILS)}")
    if not (math.isfinite(cfg.wall_normal_stiffness) and cfg.wall_normal_stiffness >= 0):
        bad("wall_normal_stiffness", f"must be a finite number >= 0; got {cfg.wall_normal_stiffness}")
    if cfg.mass_scaling not in MASS_SCALING_MODES:
        bad("mass_scaling", f"'{cfg.mass_scaling}' is not one of {', '.join(MASS_SCALING_MODES)}")
    if not cfg.mass_scale >= 1.0 and cfg.mass_scaling == "manual":
        bad("mass_scale", f"must be >= 1 (got {cfg.mass_scale})")
    if not 0 <= cfg.quasi_static_damping < 1:
        bad("quasi_static_damping", f"must be in [0, 1) (0 = off; got {cfg.quasi_static_damping})")
    if not 0 <= cfg.quasi_static_margin < math.inf:
        bad("quasi_static_margin", f"must be a finite number >= 0 (0 = off; got {cfg.quasi_static_margin})")
    if cfg.target_substeps_per_frame < 1:
        bad("target_substeps_per_frame", "must be >= 1")
    if not cfg.stiffness_scaling > 0:
        bad("stiffness_scaling", f"must be > 0 (got {cfg.stiffness_scaling})")
    if not 0 < cfg.j_min < 1 < cfg.j_max:
        bad("j_min/j_max", f"need 0 < j_min < 1 < j_max (got {cfg.j_min}, {cfg.j_max})")
    if cfg.polar_method not in ("track", "newton"):
        bad("polar_method", f"'{cfg.polar_method}' is not track or newton")
    if cfg.polar_iterations < 1 or cfg.polar_restart_iterations < 1:
        bad("polar_iterations", "must be >= 1")
    if not cfg.energy_guard_tolerance >= 0:
        bad("energy_guard_tolerance", f"must be >= 0 (0 = off; got {cfg.energy_guard_tolerance})")
    if cfg.check_every < 1:
        bad("check_every", "must be >= 1")
    if cfg.threads < 1:
        bad("threads", "must be >= 1 (CPU threads of one scene's particle kernel)")
    for key in ("domain_lo", "domain_hi"):
        val = getattr(cfg, key)
        if val is not None and len(val) != 3:
            bad(key, "must have 3 components")
    if (cfg.domain_lo is None) != (cfg.domain_hi is None):
        bad("domain_lo/domain_hi", "give both or neither")
    return cfg


def mpm_config_from(obj: Any = None, **overrides: Any) -> MPMConfig:
    """Build a validated :class:`MPMConfig` from None, an MPMConfig, a mapping or an OmegaConf node."""
    if obj is None:
        data: dict[str, Any] = {}
    elif isinstance(obj, MPMConfig):
        data = {f.name: getattr(obj, f.name) for f in fields(MPMConfig)}
    else:
        try:
            from omegaconf import DictConfig, OmegaConf

            if isinstance(obj, DictConfig):
                obj = OmegaConf.to_container(obj, resolve=True)
        except ImportError:  # pragma: no cover
            pass
        if not isinstance(obj, Mapping):
            raise MPMConfigError(f"cannot build an MPMConfig from {type(obj).__name__}")
        data = dict(obj)
    data.update(overrides)
    known = {f.name for f in fields(MPMConfig)}
    unknown = set(data) - known
    if unknown:
        raise MPMConfigError(f"unknown mpm config keys {sorted(unknown)}; known: {sorted(known)}")
    if data.get("mass_scaling") == "auto":  # the former name of global scaling
        data["mass_scaling"] = "global"
    for key in ("gravity", "domain_lo", "domain_hi"):
        if data.get(key) is not None:
            data[key] = [float(x) for x in data[key]]
    return validate_mpm_config(MPMConfig(**data))
