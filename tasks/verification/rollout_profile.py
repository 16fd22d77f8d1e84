"""Where a real rollout's time goes (``python -m flows.bench.scenes``): per Warp kernel and per phase of
:func:`tasks.physics.mpm_rollout.mpm_rollout`, with the grid's size and the share of it the substeps work on.

The profile times the rollout as the pipeline runs it (same step function, same config), by wrapping, for the
run's duration only, every Warp launch (``wp.launch`` and the replayed recorded launches, ``Launch.launch``; on the
CPU a launch returns when its kernel has run, so its wall time is the kernel's plus ~2 us of Python) and the
Python functions of the rollout and of the solver's frame (:data:`PHASES`).  Each timed region's own seconds
(exclusive of the regions timed inside it) are summed per name, and split in two sections: the gravity preload
(:meth:`MPMSolver.preload_gravity`, before the first frame) and the squeeze (everything else).  The wrappers cost
~1 us per call (a few per substep, against ~1 ms substeps): the profiled run is not the figure to quote for speed,
the benchmark's separate untimed run is (:func:`run_rollout`).
"""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import import_module
from typing import Any, Callable, Iterator

import numpy as np

# (module, attribute) -> category of the phase list; functions are timed where their callers look them up
PHASES: dict[tuple[str, str], str] = {
    ("tasks.physics.mpm_rollout", "build_scene"): "scene set-up",
    ("tasks.physics.mpm_rollout", "dirichlet_points"): "fingers (host)",
    ("tasks.physics.mpm_rollout", "particle_pins"): "pins",
    ("tasks.physics.mpm_rollout", "finger_colliders"): "fingers (host)",
    ("tasks.physics.mpm_rollout", "force_patch"): "fingers (host)",
    ("tasks.physics.mpm_rollout", "record_frame"): "records (per-frame host copies)",
    ("tasks.physics.mpm_rollout", "rupture_and_release"): "rupture and release",
    ("tasks.physics.mpm_rollout", "collect_outputs"): "records (per-frame host copies)",
    ("tasks.physics.mpm.solver", "upload_dirichlet"): "boundary conditions",
    ("tasks.physics.mpm.solver", "upload_forces"): "boundary conditions",
    ("tasks.physics.mpm.solver", "upload_colliders"): "boundary conditions",
    ("tasks.physics.mpm.solver", "record_bc"): "boundary conditions",
    ("tasks.physics.mpm.solver", "set_pins"): "pins",
    ("tasks.physics.mpm.solver", "check_flags"): "guards and stats",
    ("tasks.physics.mpm.solver", "check_state"): "guards and stats",
    ("tasks.physics.mpm.solver", "check_energy"): "guards and stats",
    ("tasks.physics.mpm.solver", "frame_stats"): "guards and stats",
    ("tasks.physics.mpm.solver", "energy_baseline"): "guards and stats",
    ("tasks.physics.mpm.solver", "resolve_auto_mass_scale"): "guards and stats",
    ("tasks.physics.mpm.solver", "set_damping"): "guards and stats",
    ("tasks.physics.mpm.solver", "place_tracers"): "tracers",
    ("tasks.physics.mpm.solver", "read_box"): "Python and launch overhead",
    ("tasks.physics.mpm.solver", "reset_bbox"): "Python and launch overhead",
    ("tasks.physics.mpm.solver", "launch_grid"): "Python and launch overhead",
    ("tasks.physics.mpm.solver", "launch_fused"): "Python and launch overhead",
    ("tasks.physics.mpm.solver", "substep_params"): "Python and launch overhead",
    ("tasks.physics.mpm.solver.MPMSolver", "_advance_frame"): "Python and launch overhead",
    ("tasks.physics.mpm.solver.MPMSolver", "preload_gravity"): "gravity preload (host)",
}

# Warp kernel key -> category (kernels not listed: "other kernels")
KERNELS: dict[str, str] = {
    "k_g2p_p2g": "particle work", "k_p2g": "particle work", "k_g2p": "particle work",
    "k_grid_update": "grid work", "k_grid_accumulate": "grid work",
    "k_field_contact": "multi-field",
    "k_bc_scatter": "boundary conditions", "k_bc_reaction": "boundary conditions",
    "k_bc_clear_advance": "boundary conditions", "k_force_weights": "boundary conditions",
    "k_force_apply": "boundary conditions", "k_force_work": "boundary conditions",
    "k_collider_advance": "boundary conditions", "k_pin_advance": "pins",
    "k_wall_fibres": "thin walls", "k_plane_stress_F": "thin walls",
    "k_tracer_embed": "tracers",
}

# the profile's clock: this thread's CPU seconds (one-thread rollouts run their kernels on the calling thread), so a
# machine shared with other processes slows the run but not its profile
CLOCK = time.thread_time
PRELOAD = "preload"
SQUEEZE = "squeeze"


@dataclass
class Profile:
    """Seconds, calls and (kernels) launched threads per (section, kind, name); kind is ``kernel`` or ``phase``."""

    seconds: dict[tuple[str, str, str], float] = field(default_factory=lambda: defaultdict(float))
    calls: dict[tuple[str, str, str], int] = field(default_factory=lambda: defaultdict(int))
    threads: dict[tuple[str, str, str], int] = field(default_factory=lambda: defaultdict(int))
    total: float = 0.0
    # per substep of the squeeze: nodes the grid update ran over (its launch's box)
    grid_box_nodes: list[int] = field(default_factory=list)
    # per squeeze frame: nodes with mass after its last P2G (both velocity fields)
    mass_nodes: list[int] = field(default_factory=list)
    grid_nodes: int = 0  # nodes of the solver's grid
    grid_dims: tuple[int, ...] = ()
    particles: int = 0
    state_bytes: dict = field(default_factory=dict)  # the solver's per-particle state arrays, bytes each
    substeps: int = 0  # substeps of the squeeze (the preload's not counted)

    def category(self, kind: str, name: str) -> str:
        if kind == "kernel":
            return KERNELS.get(name, "other kernels")
        return next(c for (m, a), c in PHASES.items() if a == name)

    def by_category(self, section: str) -> dict[str, float]:
        out: dict[str, float] = defaultdict(float)
        for (s, kind, name), sec in self.seconds.items():
            if s == section:
                out[self.category(kind, name)] += sec
        return dict(out)

    def section_seconds(self, section: str) -> float:
        return sum(sec for (s, _, _), sec in self.seconds.items() if s == section)


class _Timer:
    """A stack of timed regions: each region's exclusive seconds go to its key."""

    def __init__(self, profile: Profile) -> None:
        self.p = profile
        self.stack: list[list] = []  # [key, start, seconds spent in children]
        self.section = SQUEEZE

    def enter(self, key: tuple[str, str]) -> None:
        self.stack.append([key, CLOCK(), 0.0])

    def leave(self, threads: int = 0) -> None:
        key, start, inner = self.stack.pop()
        spent = CLOCK() - start
        full = (self.section, *key)
        self.p.seconds[full] += spent - inner
        self.p.calls[full] += 1
        self.p.threads[full] += threads
        if self.stack:
            self.stack[-1][2] += spent


def kernel_name(kernel: Any) -> str:
    """The kernel's Python name (the fused kernel's variants share ``k_g2p_p2g``)."""
    name = kernel.key.split(".")[-1]
    return "k_g2p_p2g" if name.endswith("k_g2p_p2g") else name


@contextmanager
def profiled() -> Iterator[Profile]:
    """Inside, every Warp launch and every function of :data:`PHASES` is timed into the yielded :class:`Profile`;
    the originals are restored on exit."""
    import warp as wp
    import warp._src.context as wctx

    prof = Profile()
    timer = _Timer(prof)
    undo: list[tuple[Any, str, Any]] = []

    def patch(owner: Any, attr: str, new: Any) -> None:
        undo.append((owner, attr, getattr(owner, attr)))
        setattr(owner, attr, new)

    def timed(name: str, fn: Callable, preload: bool = False) -> Callable:
        def wrapper(*args, **kwargs):
            timer.enter(("phase", name))
            before = timer.section
            if preload:
                timer.section = PRELOAD
            try:
                return fn(*args, **kwargs)
            finally:
                timer.leave()
                timer.section = before
                if name == "_advance_frame":
                    grid_census(args[0], before)
        return wrapper

    def grid_census(solver: Any, section: str) -> None:
        """Outside the timers: the grid's size and, per squeeze frame, its nodes with mass."""
        paused = CLOCK()
        prof.grid_dims = tuple(int(d) for d in solver.dims)
        prof.grid_nodes = int(np.prod(prof.grid_dims))
        prof.particles = int(solver.n_particles)
        prof.state_bytes = solver.state_nbytes()
        if section == SQUEEZE:
            prof.substeps += int(solver.last_stats.substeps)
            grids = [solver.grid_a] + ([solver._field2[id(solver.grid_a)]] if solver.two_fields else [])
            mass = sum((g.numpy()[..., 3] > 0) for g in grids if g.shape == solver.grid_a.shape)
            prof.mass_nodes.append(int(np.count_nonzero(mass)))
        for frame in timer.stack:  # the census is no one's time
            frame[1] += CLOCK() - paused

    for (mod, attr) in PHASES:
        parts = mod.split(".")
        owner = import_module(mod) if parts[-1][0].islower() else getattr(import_module(".".join(parts[:-1])),
                                                                          parts[-1])
        patch(owner, attr, timed(attr, getattr(owner, attr), preload=attr == "preload_gravity"))

    launch_run = wctx.Launch.launch

    def launch_timed(self, *args, **kwargs):
        name = kernel_name(self.kernel)
        timer.enter(("kernel", name))
        try:
            return launch_run(self, *args, **kwargs)
        finally:
            size = int(self.bounds.size)
            timer.leave(size)
            if name == "k_grid_update" and timer.section == SQUEEZE:
                prof.grid_box_nodes.append(size)

    launch_fn = wp.launch

    def wp_launch_timed(kernel, *args, **kwargs):
        name = "record launch" if kwargs.get("record_cmd") else kernel_name(kernel)
        timer.enter(("kernel", name))
        try:
            return launch_fn(kernel, *args, **kwargs)
        finally:
            timer.leave(0 if kwargs.get("record_cmd") else int(np.prod(np.atleast_1d(kwargs.get("dim", 1)))))

    patch(wctx.Launch, "launch", launch_timed)
    patch(wp, "launch", wp_launch_timed)
    KERNELS.setdefault("record launch", "Python and launch overhead")
    start = CLOCK()
    try:
        yield prof
    finally:
        prof.total = CLOCK() - start
        for owner, attr, old in reversed(undo):
            setattr(owner, attr, old)


def run_rollout(inputs: dict, frames: int | None) -> tuple[dict, dict]:
    """The rollout step's function on ``inputs`` (``arts``: the step's input artifacts by step name, ``params``: its
    config values, as ``flows.bench.scenes`` reads them from the pipeline's cache), over its first ``frames`` output frames
    (None: all); returns its arrays and attributes."""
    from tasks.physics.mpm_rollout import mpm_rollout

    a, p = inputs["arts"], inputs["params"]
    obj, particles = a["object_model"], a["mpm_particles"]
    times = a["signal_smoothing"]["time"]
    T = len(times) if frames is None else min(len(times), int(frames) + 1)

    def cut(d: dict) -> dict:  # the per-frame arrays' first T frames
        return {k: v[:T] if getattr(v, "ndim", 0) and v.shape[0] == len(times) else v for k, v in d.items()}

    return mpm_rollout({**obj.arrays, **particles.arrays}, {**obj.attrs, **particles.attrs, "name": obj.ref.scope},
                       cut(dict(a["dirichlet_field"].arrays)), a["force_coefficients"]["force_coefficients"][:T],
                       cut(dict(a["contact_patches"].arrays)), times[:T], a["material_oracle"].attrs["materials"],
                       p["mpm"], p["simulation"], p["variant.boundary"])


@contextmanager
def preload_timed() -> Iterator[list[tuple[float, float]]]:
    """Inside, the (wall, process CPU) seconds of each :meth:`MPMSolver.preload_gravity` call are appended to the
    yielded list (the plain run's only wrapper: the squeeze's seconds are the rollout's less these)."""
    from tasks.physics.mpm.solver import MPMSolver

    spent: list[tuple[float, float]] = []
    original = MPMSolver.preload_gravity

    def wrapper(self, *args, **kwargs):
        start, cpu = time.perf_counter(), time.process_time()
        try:
            return original(self, *args, **kwargs)
        finally:
            spent.append((time.perf_counter() - start, time.process_time() - cpu))

    MPMSolver.preload_gravity = wrapper
    try:
        yield spent
    finally:
        MPMSolver.preload_gravity = original


def summary(prof: Profile) -> dict:
    """The profile's figures: grid nodes and the shares the substeps work on, the squeeze's throughput (particles x
    substeps / squeeze seconds, M/s; the profiled run's, wrappers included)."""
    squeeze = prof.section_seconds(SQUEEZE)
    box = float(np.mean(prof.grid_box_nodes)) if prof.grid_box_nodes else 0.0
    mass = float(np.mean(prof.mass_nodes)) if prof.mass_nodes else 0.0
    return dict(particles=prof.particles, grid_dims=list(prof.grid_dims), grid_nodes=prof.grid_nodes,
                box_nodes=box, box_share=box / prof.grid_nodes if prof.grid_nodes else 0.0,
                mass_nodes=mass, mass_share=mass / prof.grid_nodes if prof.grid_nodes else 0.0,
                state_bytes=prof.state_bytes,
                substeps=prof.substeps, squeeze_seconds=squeeze, preload_seconds=prof.section_seconds(PRELOAD),
                total_seconds=prof.total,
                throughput=prof.particles * prof.substeps / squeeze / 1e6 if squeeze else 0.0)


def phase_rows(prof: Profile) -> list[list[str]]:
    """Rows (category, squeeze s, % of the squeeze, preload s) of the issue's phases, largest first."""
    sq, pre = prof.by_category(SQUEEZE), prof.by_category(PRELOAD)
    total = prof.section_seconds(SQUEEZE) or 1.0
    cats = sorted(set(sq) | set(pre), key=lambda c: -sq.get(c, 0.0))
    return [[c, f"{sq.get(c, 0.0):.3f}", f"{100 * sq.get(c, 0.0) / total:.1f}", f"{pre.get(c, 0.0):.3f}"]
            for c in cats]


def kernel_rows(prof: Profile, top: int = 12) -> list[list[str]]:
    """Rows (name, kind, calls, squeeze s, us per call, ns per launched thread) of the squeeze's largest entries."""
    items = sorted(((k, v) for k, v in prof.seconds.items() if k[0] == SQUEEZE), key=lambda kv: -kv[1])[:top]
    rows = []
    for (sec, kind, name), s in items:
        calls, threads = prof.calls[(sec, kind, name)], prof.threads[(sec, kind, name)]
        per_thread = f"{1e9 * s / threads:.1f}" if threads else "-"
        rows.append([name, kind, str(calls), f"{s:.3f}", f"{1e6 * s / max(calls, 1):.1f}", per_thread])
    return rows
