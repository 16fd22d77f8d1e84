"""Speed of the splatting renderer (``splat.rasterization``) against a physical floor (issue 14).

Scene (as in the generation notes, Q1): N flattened Gaussians on a unit sphere 4 m in front of the camera, 40 deg
field of view (the sphere spans ~70 % of the frame width; the rig's ``render.fill`` is 60 %), tangential sigma
0.6 sqrt(4 pi / N) m, normal sigma a tenth of it, opacity 0.8, colours RGB + one mask channel, render mode RGB+ED:
5 composited channels, like the G-buffer.  Defaults: the default resolution (``render.width`` x ``render.height``,
conf/render_schema.py) and the object sizes of the evaluation grid: ``sampling.surface_points`` surface Gaussians
alone, and with RELEASED_MAX more (the most released particles any grid object draws: the plush toy's ~370).
Times are per frame and view (one camera) on one thread: the CPU time of the calling thread (torch and Warp's CPU
kernels run on it with torch.set_num_threads(1)), the best of a few runs, less sensitive than wall time to other
jobs sharing the machine; the wall time is printed beside it.

Floor model, per frame: every kept (Gaussian, pixel) pair (alpha >= 1/255) costs KEPT_PAIR_FLOP flop + 1 exp
to be tested; every contributing pair (in front of its pixel's stop) CONTRIBUTING_FLOP_FORWARD (+ 2 per channel)
to composite and, in the backward pass, the 3DGS backward's BACKWARD_FLOP (+ 4 per channel) + 1 exp; the
projection PROJECTION_FLOP per Gaussian (twice that backward).  The floor is the larger of (flop at this core's
measured fp32 matmul rate - all FMA, all SIMD lanes - + exps at the best vectorised exp rate measured here, torch
or numpy, cache-resident) and (compulsory bytes: Gaussian parameters in, image out, their gradients back, at the
measured copy bandwidth); it assumes perfect SIMD use and no pair lists in memory, so real designs sit above it.
It is the floor of the 3DGS formulation (one exp per pair).  An exp per pair is not intrinsic: exp(-sigma) is
exp of a quadratic along an image row, so the compositor evaluates it by a recurrence (2 multiplies per pair,
2 exps per row span, ``splat_warp``); the exp-free floor charges that instead (RECURRENCE_FLOP per kept pair,
2 exps per box row) and is printed beside the first: the stricter bound.  The exp rate is that of this machine's
vectorised libraries (torch / numpy, ~0.8 G exp/s on one AVX2 core here); a hand-tuned SIMD exp could be ~3x faster,
which would lower the 3DGS floor by up to ~2x (not the exp-free one).

Example (this 2-core AMD EPYC, AVX2, shared with ~14 other jobs, 1 thread): 192 x 192 px, N = 3,000 (3,400):
0.41 M kept pairs of 0.89 M box pairs; floor 0.60-0.68 / 1.43-1.57 ms forward / forward+backward (exp-free
0.22-0.24 / 0.69-0.76; the rates measured vary with the load); warp 4.5-4.9 / 11.0-12.2 ms at best under load
(7.5-8.7x the floor in the runs of the README's "Renderer speed", medians 8.6-10.0x; the measured rates move with
the load; ~16-22x the exp-free floor), torch
0.17-0.22 / 0.22-0.26 s.
"""

import ctypes
import math
import os
import time

import numpy as np
import torch

from conf.render_schema import RenderConfig
from conf.schema import SamplingConfig

from .splat import rasterization
from .splat_projection import pixel_boxes, project_gaussians, quat_scale_to_covar
from .splat_torch import pair_weights

KEPT_PAIR_FLOP = 13            # sigma (10), alpha and the two tests, plus one exp
CONTRIBUTING_FLOP_FORWARD = 3  # transmittance and weight, plus 2 per channel
BACKWARD_FLOP = 44             # recompute alpha, T_i, dL/dalpha, behind-sums, dL/dsigma, mean/conic/opacity grads
PROJECTION_FLOP = 250          # R S S^T R^T, W cov W^T, J cov J^T, conic, radius
RECURRENCE_FLOP = 5            # exp-free floor, per kept pair: two multiplies (the recurrence), alpha, two tests
N_COLORS = 4                   # RGB + mask
FOV_DEG, DISTANCE_M = 40.0, 4.0
RELEASED_MAX = 400             # released-particle Gaussians on top of the surface's (grid maximum: plush toy 368)


def sphere_scene(n_gaussians: int, seed: int = 0) -> list[torch.Tensor]:
    """means (N, 3) m on the unit sphere (Fibonacci lattice), quats (N, 4) turning local z to the normal,
    scales (N, 3) m, opacities (N,), colors (N, 4) RGB + mask in [0, 1]."""
    i = torch.arange(n_gaussians, dtype=torch.float64) + 0.5
    polar, azimuth = torch.acos(1 - 2 * i / n_gaussians), math.pi * (1 + math.sqrt(5)) * i
    normals = torch.stack([torch.cos(azimuth) * torch.sin(polar), torch.sin(azimuth) * torch.sin(polar),
                           torch.cos(polar)], dim=1)
    axis = torch.linalg.cross(torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(normals), normals)
    half = 0.5 * torch.atan2(torch.linalg.norm(axis, dim=1), normals[:, 2])
    axis = torch.nn.functional.normalize(axis, dim=1)
    quats = torch.cat([torch.cos(half)[:, None], axis * torch.sin(half)[:, None]], dim=1)
    sigma = 0.6 * math.sqrt(4 * math.pi / n_gaussians)
    scales = torch.tensor([sigma, sigma, 0.1 * sigma]).repeat(n_gaussians, 1)
    colors = torch.rand(n_gaussians, N_COLORS, generator=torch.Generator().manual_seed(seed))
    return [normals.float(), quats.float(), scales, torch.full((n_gaussians,), 0.8), colors]


def sphere_camera(resolution: int) -> tuple[torch.Tensor, torch.Tensor]:
    """One camera DISTANCE_M from the sphere's centre looking at it: viewmats (1, 4, 4), Ks (1, 3, 3)."""
    focal = 0.5 * resolution / math.tan(math.radians(FOV_DEG) / 2)
    Ks = torch.tensor([[[focal, 0.0, resolution / 2], [0.0, focal, resolution / 2], [0.0, 0.0, 1.0]]])
    viewmats = torch.eye(4)[None].clone()
    viewmats[0, 2, 3] = DISTANCE_M
    return viewmats, Ks


def work_counts(scene: list[torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, resolution: int) -> dict:
    """Pixels, instances, box pairs, kept pairs (alpha >= 1/255) and contributing pairs of one frame."""
    means, quats, scales, opacities, _ = scene
    with torch.no_grad():
        proj = project_gaussians(means, quat_scale_to_covar(quats, scales), viewmats, Ks, resolution, resolution)
        cam, gid = torch.nonzero(proj.radii > 0, as_tuple=True)
        order = torch.sort(proj.depths[cam, gid], stable=True).indices
        cam, gid = cam[order], gid[order]
        boxes = pixel_boxes(proj.means2d[cam, gid], proj.radii[cam, gid], resolution, resolution)
        _, _, weight = pair_weights(proj.means2d[cam, gid], proj.conics[cam, gid], opacities[gid], boxes,
                                    cam * resolution**2, resolution)
    rows = (boxes[:, 3] - boxes[:, 2]).clamp_min(0) * (boxes[:, 1] > boxes[:, 0])
    area = (boxes[:, 1] - boxes[:, 0]).clamp_min(0) * rows
    return {"pixels": len(viewmats) * resolution**2, "gaussians": len(means), "instances": len(gid),
            "box_rows": int(rows.sum()), "box_pairs": int(area.sum()), "kept_pairs": len(weight),
            "contributing_pairs": int((weight > 0).sum())}


def machine_rates() -> dict:
    """This core's fp32 matmul rate (flop/s), vectorised exp rate (1/s: the faster of torch and numpy on 16k
    cache-resident floats, 64 calls a run) and copy bandwidth (bytes/s), best of 3."""
    a, b = torch.rand(1024, 1024), torch.rand(1024, 1024)
    x, y = torch.rand(1 << 14), torch.empty(1 << 14)
    xn, yn = x.numpy(), y.numpy()
    big = np.random.default_rng(0).random(1 << 24, dtype=np.float32)
    flops = 2 * 1024**3 / _best_cpu_time(lambda: torch.mm(a, b), 3)
    exp_calls = (lambda: [torch.exp(x, out=y) for _ in range(64)], lambda: [np.exp(xn, out=yn) for _ in range(64)])
    exps = max(64 * len(x) / _best_cpu_time(call, 3) for call in exp_calls)
    bandwidth = 2 * big.nbytes / _best_cpu_time(big.copy, 3)
    return {"flops": flops, "exps": exps, "bandwidth": bandwidth}


def floor_seconds(counts: dict, rates: dict, exp_free: bool = False) -> tuple[float, float]:
    """The physical floor (s) of one forward and one forward+backward frame (model in the module docstring);
    exp_free: the recurrence's floor (RECURRENCE_FLOP per kept pair, 2 exps per box row, each pass)."""
    channels, n, pixels = N_COLORS + 1, counts["gaussians"], counts["pixels"]
    kept, contributing = counts["kept_pairs"], counts["contributing_pairs"]
    pair_flop, exps_forward, exps_backward = ((RECURRENCE_FLOP, 2 * counts["box_rows"],
                                               2 * counts["box_rows"]) if exp_free else
                                              (KEPT_PAIR_FLOP, kept, contributing))
    flop_forward = (kept * pair_flop + contributing * (CONTRIBUTING_FLOP_FORWARD + 2 * channels)
                    + n * PROJECTION_FLOP)
    flop_backward = contributing * (BACKWARD_FLOP + 4 * channels) + 2 * n * PROJECTION_FLOP
    bytes_forward = 4 * (n * (11 + N_COLORS) + pixels * (channels + 1))
    forward = max(flop_forward / rates["flops"] + exps_forward / rates["exps"], bytes_forward / rates["bandwidth"])
    backward = max(flop_backward / rates["flops"] + exps_backward / rates["exps"],
                   2 * bytes_forward / rates["bandwidth"])
    return forward, forward + backward


def time_frame(scene: list[torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, resolution: int, backend: str,
               backward: bool, repeats: int) -> tuple[float, float]:
    """Best CPU time and median wall time (s) of one frame, forward or forward+backward w.r.t. every parameter."""
    leaves = [t.clone().requires_grad_(backward) for t in scene]

    def frame():
        image, alphas, _ = rasterization(*leaves, viewmats, Ks, resolution, resolution, backend=backend)
        if backward:
            (image.sum() + alphas.sum()).backward()

    frame()   # warm-up: Warp compiles or loads its kernels
    walls = []
    cpu = _best_cpu_time(frame, repeats, walls)
    return cpu, float(np.median(walls))


def peak_extra_memory(scene: list[torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, resolution: int,
                      backend: str) -> float | None:
    """Peak resident memory (bytes) a forward+backward frame adds, or None off Linux/glibc: the heap is trimmed,
    the peak (VmHWM) reset, a frame run and the new peak compared with the resident size before it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        before = _status_bytes("VmRSS")
        time_frame(scene, viewmats, Ks, resolution, backend, True, 1)
        return _status_bytes("VmHWM") - before
    except (OSError, AttributeError):
        return None


def main(resolutions: tuple[int, ...] = (RenderConfig.width,),
         sizes: tuple[int, ...] = (SamplingConfig.surface_points, SamplingConfig.surface_points + RELEASED_MAX),
         backends: tuple[str, ...] = ("torch", "warp")) -> list[dict]:
    """Print and return forward / forward+backward time per frame for every backend, resolution and N, with the
    work counts, the floors and the ratios to them (defaults: the default render resolution, the grid's sizes)."""
    torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))
    rates = machine_rates()
    print(f"machine (1 thread): {rates['flops'] / 1e9:.0f} GFLOP/s fp32 matmul, {rates['exps'] / 1e9:.2f} G exp/s "
          f"vectorised, {rates['bandwidth'] / 1e9:.1f} GB/s copy; times = best thread CPU time (median wall); "
          f"floors: 3DGS (an exp per pair) and exp-free (module docstring)")
    print(f"{'res':>4} {'N':>6} {'kept/box pairs':>16} {'contrib':>8} {'floor fwd / f+b':>16} {'exp-free':>12} "
          f"{'backend':>7} {'forward s':>18} {'fwd+bwd s':>18} {'x floor':>11} {'x exp-free':>11} {'extra MB':>8}")
    rows = []
    for resolution in resolutions:
        viewmats, Ks = sphere_camera(resolution)
        for n in sizes:
            scene = sphere_scene(n)
            counts = work_counts(scene, viewmats, Ks, resolution)
            floor_f, floor_fb = floor_seconds(counts, rates)
            free_f, free_fb = floor_seconds(counts, rates, exp_free=True)
            for backend in backends:
                repeats = 3 if backend == "torch" else 7
                forward = time_frame(scene, viewmats, Ks, resolution, backend, False, repeats)
                both = time_frame(scene, viewmats, Ks, resolution, backend, True, repeats)
                memory = peak_extra_memory(scene, viewmats, Ks, resolution, backend)
                row = {"resolution": resolution, "backend": backend, **counts, "floor_forward_s": floor_f,
                       "floor_forward_backward_s": floor_fb, "exp_free_floor_forward_s": free_f,
                       "exp_free_floor_forward_backward_s": free_fb, "forward_s": forward[0],
                       "forward_wall_s": forward[1], "forward_backward_s": both[0],
                       "forward_backward_wall_s": both[1], "peak_extra_bytes": memory}
                rows.append(row)
                print(f"{resolution:>4} {n:>6} {counts['kept_pairs'] / 1e6:>6.2f}M/{counts['box_pairs'] / 1e6:.2f}M "
                      f"{counts['contributing_pairs'] / 1e6:>7.2f}M {floor_f * 1e3:>6.2f}/{floor_fb * 1e3:.2f} ms "
                      f"{free_f * 1e3:>5.2f}/{free_fb * 1e3:.2f} {backend:>7} {forward[0]:>7.4f} ({forward[1]:.4f}) "
                      f"{both[0]:>7.4f} ({both[1]:.4f}) {forward[0] / floor_f:>5.1f}/{both[0] / floor_fb:<5.1f} "
                      f"{forward[0] / free_f:>5.1f}/{both[0] / free_fb:<5.1f} "
                      f"{'n/a' if memory is None else f'{memory / 2**20:.0f}':>8}")
    return rows


def _best_cpu_time(fn, repeats: int, walls: list | None = None) -> float:
    best = math.inf
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.thread_time()
        fn()
        best = min(best, time.thread_time() - cpu)
        if walls is not None:
            walls.append(time.perf_counter() - wall)
    return best


def _status_bytes(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return float(line.split()[1]) * 1024
    raise OSError(f"{field} not in /proc/self/status")


if __name__ == "__main__":
    main()
