"""The MPM throughput benchmark's scene and our solver's timed run (``python -m flows.bench.mpm``).

Scene (identical for our solver and the Taichi peer, :mod:`tasks.verification.taichi_peer`): a fixed-corotated
elastic cube, ``ppc_axis``^3 particles per cell, falling with an initial downward velocity ``v0`` (m/s) onto the
floor of an n^3 grid in the unit box (dx = 1/n m, slip walls on a ``BOUND``-node boundary layer, the bottom wall is
the floor), dt forced to ``courant`` x dx / c_p (the P-wave speed), float32.  Each solver runs in a fresh process
(``python -m tasks.verification.mpm_throughput --scene ...`` here, ``python -m tasks.verification.taichi_peer``
there) and prints one JSON line: throughput = particles x substeps / wall time, compile/JIT excluded.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

BOUND = 3  # nodes of the slip-wall boundary layer on each side of the grid


def make_scene(n_grid: int, cube: float, ppc_axis: int, E: float, nu: float, rho: float, v0: float,
               courant: float) -> dict:
    """Particles on a lattice (ppc_axis^3 per cell) filling a cube of side ``cube`` (m) in the unit box."""
    dx = 1.0 / n_grid
    h = dx / ppc_axis
    lo = np.array([0.5 - cube / 2, 0.5 - cube / 2, BOUND * dx + 2 * dx])
    m = int(round(cube / h))
    g = (np.arange(m) + 0.5) * h
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3) + lo
    V = np.zeros_like(X)
    V[:, 2] = -v0
    cp = np.sqrt(E * (1 - nu) / (rho * (1 + nu) * (1 - 2 * nu)))
    dt = courant * dx / cp
    return dict(positions=X.astype(np.float32), velocities=V.astype(np.float32), n_grid=n_grid, dx=dx, dt=dt, E=E,
                nu=nu, rho=rho, p_vol=h ** 3, gravity=-9.81, bound=BOUND, cp=cp)


MAX_PARTICLES = 20_000_000  # a scene beyond this would not fit a laptop's memory in the three solvers


def check_scene_config(c: Any) -> None:
    """One line (``SystemExit``) naming a key of the benchmark's config (``conf/study/bench_mpm.yaml``) whose value
    no scene can be built from, before Warp is loaded."""
    def need(ok: bool, key: str, msg: str) -> None:
        if not ok:
            raise SystemExit(f"input error: {key} {msg}")

    for key in ("E", "rho", "courant", "cube"):
        need(math.isfinite(c[key]) and c[key] > 0, key, f"must be a finite number > 0, got {c[key]}")
    need(math.isfinite(c["v0"]), "v0", f"must be a finite speed (m/s), got {c['v0']}")
    need(0 <= c["nu"] < 0.5, "nu", f"must be in [0, 0.5), got {c['nu']}")
    need(c["n_grid"] >= 2 * BOUND + 4, "n_grid", f"must be >= {2 * BOUND + 4} (walls of {BOUND} nodes), got "
         f"{c['n_grid']}")
    need(c["cube"] <= 0.8, "cube", f"must be <= 0.8 (the side in the unit box, walls and fall included), got "
         f"{c['cube']}")
    for key in ("ppc_axis", "substeps", "repeats", "rounds", "polar_iters", "threads"):
        need((key == "threads" and c[key] is None) or c[key] >= 1, key, f"must be >= 1, got {c[key]}")  # None: all
    n = round(c["cube"] * c["n_grid"] * c["ppc_axis"]) ** 3
    need(n <= MAX_PARTICLES, "n_grid", f"{c['n_grid']} with cube {c['cube']} and ppc_axis {c['ppc_axis']} gives "
         f"{n:.3g} particles, above {MAX_PARTICLES:.0e}: lower one of them")


def run_warp(scene_path: str, device: str, substeps: int, repeats: int, save: str | None = None,
             polar_iters: int = 1, threads: int = 1) -> dict:
    """Run our solver on the saved scene (called in a subprocess)."""
    import warp as wp

    from tasks.physics.mpm import Material, MPMSolver

    sc = np.load(scene_path)
    n, dx, dt = int(sc["n_grid"]), float(sc["dx"]), float(sc["dt"])
    mat = Material(name="cube", model="fixed_corotated", youngs_modulus=float(sc["E"]), poisson_ratio=float(sc["nu"]),
                   density=float(sc["rho"]))
    pad = int(sc["bound"])
    cfg = dict(device=device, dx=dx, dt=dt, padding=pad, floor=False, gravity=[0.0, 0.0, float(sc["gravity"])],
               domain_lo=[pad * dx] * 3, domain_hi=[(n - 1 - pad) * dx] * 3, check_every=max(substeps, 1),
               courant_limit=1.0, polar_iterations=polar_iters, threads=threads)
    solver = MPMSolver(sc["positions"], float(sc["p_vol"]), mat, velocities=sc["velocities"], config=cfg)
    assert solver.dims == (n, n, n), solver.dims
    frame_dt = substeps * dt
    t0 = time.perf_counter()
    solver.step_frame(3 * dt)  # JIT compile (or cache load) + warm-up, excluded
    compile_s = time.perf_counter() - t0
    times = []
    subs = []
    cpu = []  # this thread's CPU seconds per run (a one-thread run on a shared machine: what the others do not slow)
    for _ in range(repeats):
        cpu0 = time.thread_time()
        with wp.ScopedTimer(f"warp-{device}", synchronize=True, print=False) as timer:
            st = solver.step_frame(frame_dt)
        cpu.append(time.thread_time() - cpu0)
        times.append(timer.elapsed / 1000.0)
        subs.append(st.substeps)
    x = solver.positions()
    if save:
        np.save(save, x)
    N = solver.n_particles
    best = min(times)
    return dict(solver="warp", device=device, threads=solver.threads if device == "cpu" else "gpu", polar="quat",
                n_particles=N, substeps=subs[0], seconds=times, best_seconds=best,
                throughput=N * subs[0] / best, thread_cpu_seconds=cpu, throughput_cpu=N * subs[0] / min(cpu),
                compile_seconds=compile_s, total_substeps=3 + sum(subs),
                bytes_per_particle=solver.bytes_per_particle(), state_bytes=solver.state_nbytes(),
                grid_dims=list(solver.dims), com=x.mean(0).tolist(), x_min=x.min(0).tolist(),
                x_max=x.max(0).tolist(), finite=bool(np.isfinite(x).all()), warp_version=wp.__version__)


def main(argv: list[str] | None = None) -> None:
    """Subprocess entry used by ``flows.bench.mpm``: one Warp run on a saved scene, print one JSON line."""
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", required=True, help=".npz written from make_scene")
    ap.add_argument("--device", default="cpu", help="Warp device (cpu, cuda:0)")
    ap.add_argument("--substeps", type=int, default=100)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1, help="mpm.threads of the CPU run")
    ap.add_argument("--polar-iters", type=int, default=1, help="quaternion polar iterations per substep")
    ap.add_argument("--save", default=None, help="write the final positions to this .npy")
    a = ap.parse_args(argv)
    print(json.dumps(run_warp(a.scene, a.device, a.substeps, a.repeats, a.save, a.polar_iters, a.threads)))


if __name__ == "__main__":
    main()
