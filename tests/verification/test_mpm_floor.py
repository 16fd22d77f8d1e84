"""The MPM substep's physical floor (tasks/verification/mpm_floor.py) against hand-computed answers, and the benchmark
that prints it: a real run of our solver never beats its floor."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tasks.verification.mpm_floor import (
    GRID_NODE_BYTES,
    GRID_NODE_FLOP,
    PARTICLE_FLOP_FIXED_COROTATED,
    active_nodes,
    compulsory_particle_bytes,
    scene_floor,
    substep_floor,
)

REPO = Path(__file__).resolve().parents[2]


def test_active_nodes_are_the_union_of_the_quadratic_stencils():
    dx = 0.1
    one = np.array([[0.55, 0.55, 0.55]])   # base node floor(5.5 - 0.5) = 5: nodes 5-7 on each axis
    assert active_nodes(one, dx) == 27
    assert active_nodes(np.array([[0.55, 0.55, 0.55], [0.58, 0.56, 0.64]]), dx) == 27   # same base node
    assert active_nodes(np.array([[0.55, 0.55, 0.55], [0.65, 0.55, 0.55]]), dx) == 4 * 9   # x nodes 5-8
    assert active_nodes(np.array([[0.55, 0.55, 0.55], [0.95, 0.15, 0.55]]), dx) == 54   # disjoint


def test_compulsory_bytes_read_every_array_and_write_all_but_the_read_only_ones():
    n = 10
    # the fixed-corotated cube's state (MPMSolver.state_nbytes): x, x_carry, v 12 B; C, F, F_carry 36 B; q 16 B;
    # vol, mat_id 4 B (read only)
    state = {"x": 12 * n, "x_carry": 12 * n, "v": 12 * n, "C": 36 * n, "F": 36 * n, "F_carry": 36 * n, "q": 16 * n,
             "vol": 4 * n, "mat_id": 4 * n}
    assert compulsory_particle_bytes(state, n) == 168 + 160


def test_the_floor_is_the_larger_of_the_flop_and_the_byte_time():
    rates = {"flops": 1e11, "bandwidth": 1e10}
    n, nodes = 1000, 500
    floor = substep_floor(n, 328.0, nodes, rates)
    flop = n * PARTICLE_FLOP_FIXED_COROTATED + nodes * GRID_NODE_FLOP   # 2,214,000 + 7,500
    moved = n * 328.0 + nodes * GRID_NODE_BYTES   # 328,000 + 32,000
    assert floor["flop_seconds"] == pytest.approx(flop / 1e11) == pytest.approx(2.2215e-5)
    assert floor["byte_seconds"] == pytest.approx(moved / 1e10) == pytest.approx(3.6e-5)
    assert floor["seconds"] == floor["byte_seconds"] and floor["bound"] == "memory"
    assert floor["throughput"] == pytest.approx(n / 3.6e-5)
    assert floor["bytes_per_particle_substep"] == pytest.approx(360.0)
    fast_memory = substep_floor(n, 328.0, nodes, {"flops": 1e11, "bandwidth": 1e12})
    assert fast_memory["bound"] == "compute" and fast_memory["seconds"] == pytest.approx(2.2215e-5)


def test_the_benchmark_prints_the_floor_and_our_solver_sits_above_it(tmp_path):
    """A small real run of ``python -m flows.bench.mpm`` (our solver alone, one thread): the floor line is printed,
    written to benchmark.json, and the measured throughput is below the floor's (the floor is a lower bound on time)."""
    out = subprocess.run([sys.executable, "-m", "flows.bench.mpm", "quick=true", "skip_taichi=true", "threads=1",
                          "repeats=1", f"out={tmp_path}"], cwd=REPO, capture_output=True,
                         text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    line = next(x for x in out.stdout.splitlines() if x.startswith("physical floor, one core"))
    report = json.loads((tmp_path / "benchmark.json").read_text())
    floor, measured = report["physical_floor"], report["results"]["warp-cpu"]
    assert f"{floor['ratio']:.1f}x the floor" in line
    assert floor["throughput"] > measured["throughput"] and floor["ratio"] > 1.0
    assert floor["bytes_per_particle_substep"] > compulsory_particle_bytes(measured["state_bytes"],
                                                                           measured["n_particles"])
    assert "physical floor, one core" in (tmp_path / "benchmark.md").read_text()


def test_a_scene_s_squeeze_is_set_against_its_floor_from_its_state_and_its_nodes_with_mass():
    """``scene_floor`` (what ``flows.bench.scenes`` prints per scene) on a profile summary: the plain run's CPU seconds
    when there is one."""
    n, substeps = 1000, 100
    summary = {"particles": n, "substeps": substeps, "mass_nodes": 499.6, "squeeze_seconds": 0.009,
               "state_bytes": {"x": 12 * n, "vol": 4 * n, "mat_id": 4 * n}}   # 20 read, 12 written per particle
    rates = {"flops": 1e11, "bandwidth": 1e9}
    floor = scene_floor(summary, rates)
    per_substep = max((n * PARTICLE_FLOP_FIXED_COROTATED + 500 * GRID_NODE_FLOP) / 1e11,
                      (n * 32 + 500 * GRID_NODE_BYTES) / 1e9)   # memory: 64,000 bytes -> 64 us
    assert floor["seconds"] == pytest.approx(per_substep) == pytest.approx(6.4e-5)
    assert floor["ratio"] == pytest.approx(90.0 / 64.0)   # 0.009 s / 1e5 particle-substeps = 90 ns against 64 ns
    summary["plain_squeeze_cpu_seconds"] = 0.0064   # the plain run's seconds win: 64 ns, the floor itself
    assert scene_floor(summary, rates)["ratio"] == pytest.approx(1.0)
    assert "64.0 ns (memory-bound); the squeeze 64 ns = 1.0x" in scene_floor(summary, rates)["text"]
