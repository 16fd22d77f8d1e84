"""The physical floor of an MLS-MPM substep on one core (issue 51), printed by ``python -m flows.bench.mpm`` beside
the measured throughput, as ``tasks.render.benchmark`` prints the renderer's.

Per particle-substep the fused G2P/P2G kernel (``tasks.physics.mpm.kernels.transfer``) must at least
  * do PARTICLE_FLOP_FIXED_COROTATED floating-point operations (hand count below, all FMA, all SIMD lanes), and
  * read every per-particle state array once and write the ones a substep changes (``compulsory_particle_bytes``:
    the arrays of ``MPMSolver.state_nbytes``; the particles of a scene do not fit a core's caches);
per active grid node (a node some particle's 3 x 3 x 3 stencil reaches) the grid update does GRID_NODE_FLOP and its
two vec4 buffers move GRID_NODE_BYTES.  The floor is the larger of the flop time at this core's measured fp32
matmul rate and the byte time at its measured copy bandwidth (``tasks.core.machine_rates``), particle and grid work
added: it assumes perfect SIMD use, perfect prefetching and no atomics, so real codes sit above it.
:func:`scene_floor` sets a real rollout's squeeze against it (``python -m flows.bench.scenes``).

Hand count of PARTICLE_FLOP_FIXED_COROTATED (quadratic B-splines, APIC/MLS, one quaternion Newton step for the
polar rotation, compensated position and F_E updates; a multiply-add counts 2):
  weights 3 x 10; G2P 27 nodes x (weight 2, offset 3, v 6, C's outer product 18) = 783, C's scale 9; x += dt v 6;
  F_E <- (I + dt C) F_E 66; polar rotation (R from q 30, R^T F 54, gradient and H 9, 3 x 3 solve 40, update 47) 180;
  Kirchhoff stress of fixed-corotated (J, F - R, cofactor, P F^T) 120; the affine matrix 27; P2G 27 nodes x
  (weight 2, offset 3, A dpos 18, m v + A dpos 3, weighted 4, adds 4, node index 1) = 945; compensated sums of x and F_E 48;
  total 2,214.  GRID_NODE_FLOP: momentum / mass 3, gravity 3, the walls' slip projection ~9.
"""
from __future__ import annotations

import numpy as np

PARTICLE_FLOP_FIXED_COROTATED = 2214   # hand count (module docstring), per particle-substep
GRID_NODE_FLOP = 15                    # per active node and substep
GRID_NODE_BYTES = 64                   # two vec4 buffers (16 B each), each read and written once per substep
READ_ONLY_STATE = ("vol", "mat_id", "wall_offset")   # state arrays a substep reads but never writes


def compulsory_particle_bytes(state_nbytes: dict[str, int], n_particles: int) -> float:
    """Bytes a substep must move per particle: every state array read once, every one but READ_ONLY_STATE written
    once (``state_nbytes``: array name -> bytes over all particles, ``MPMSolver.state_nbytes``)."""
    read = sum(state_nbytes.values())
    written = sum(v for k, v in state_nbytes.items() if k not in READ_ONLY_STATE)
    return (read + written) / n_particles


def active_nodes(positions: np.ndarray, dx: float) -> int:
    """Grid nodes reached by the quadratic B-spline stencils of particles at ``positions`` (N, 3) m: base node
    floor(x / dx - 0.5) plus 0-2 along each axis."""
    base = np.floor(np.asarray(positions, np.float64) / dx - 0.5).astype(np.int64)
    offsets = np.stack(np.meshgrid(*([np.arange(3)] * 3), indexing="ij"), -1).reshape(-1, 3)
    nodes = (base[:, None, :] + offsets[None]).reshape(-1, 3)
    return len(np.unique(nodes, axis=0))


def substep_floor(n_particles: int, particle_bytes: float, n_active_nodes: int, rates: dict,
                  particle_flop: float = PARTICLE_FLOP_FIXED_COROTATED) -> dict:
    """The floor of one substep on one core (s) and its parts: flop time at ``rates["flops"]`` (flop/s), byte time at
    ``rates["bandwidth"]`` (bytes/s), each the particles' plus the active grid nodes' work; the floor is the larger.
    Also the floor as particle-substeps per second and per-particle-substep figures."""
    flop = n_particles * particle_flop + n_active_nodes * GRID_NODE_FLOP
    moved = n_particles * particle_bytes + n_active_nodes * GRID_NODE_BYTES
    flop_s, byte_s = flop / rates["flops"], moved / rates["bandwidth"]
    seconds = max(flop_s, byte_s)
    return {"seconds": seconds, "flop_seconds": flop_s, "byte_seconds": byte_s,
            "bound": "memory" if byte_s >= flop_s else "compute",
            "flop_per_particle_substep": flop / n_particles, "bytes_per_particle_substep": moved / n_particles,
            "throughput": n_particles / seconds, "active_nodes": n_active_nodes}


def scene_floor(s: dict, rates: dict) -> dict:
    """A profiled rollout's squeeze (``s``: ``tasks.verification.rollout_profile.summary``, what
    ``flows.bench.scenes`` prints per scene) against its floor on one core: the scene's state bytes and nodes with
    mass, every particle charged the fixed-corotated count (the transfers and the simplest stress; plastic returns and
    membranes do more, so this is a lower bound), and the squeeze's ratio to it (CPU seconds: the plain run's median,
    else the profiled run's)."""
    n = s["particles"]
    floor = substep_floor(n, compulsory_particle_bytes(s["state_bytes"], n), int(round(s["mass_nodes"])), rates)
    seconds = s.get("plain_squeeze_cpu_seconds", s["squeeze_seconds"])   # the plain run's when there is one
    measured = seconds / (n * s["substeps"]) if s["substeps"] else float("nan")
    floor["ratio"] = measured / (floor["seconds"] / n)
    floor["text"] = (f"Floor on one core (fixed-corotated flop count, a lower bound; {rates['flops'] / 1e9:.0f} "
                     f"GFLOP/s, {rates['bandwidth'] / 1e9:.1f} GB/s): {floor['bytes_per_particle_substep']:.0f} bytes "
                     f"and {floor['flop_per_particle_substep']:.0f} flop per particle-substep -> "
                     f"{1e9 * floor['seconds'] / n:.1f} ns ({floor['bound']}-bound); the squeeze "
                     f"{1e9 * measured:.0f} ns = {floor['ratio']:.1f}x")
    return floor
