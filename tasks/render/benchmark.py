"""Speed of the splatting renderer (``splat.rasterization``) against a physical floor (issue 14).

Scene (as in the generation notes, Q1): N flattened Gaussians on a unit sphere 4 m in front of the camera, 40 deg
field of view (the sphere spans ~70 % of the frame width), tangential sigma 0.6 sqrt(4 pi / N) m, normal sigma a
tenth of it, opacity 0.8, colours RGB + one mask channel, render mode RGB+ED: 5 composited channels, like the
G-buffer.  Times are per frame and view on one thread: the CPU time of the calling thread (torch and Warp's CPU
kernels run on it with torch.set_num_threads(1)), the best of a few runs, less sensitive than wall time to other
jobs sharing the machine; the wall time is printed beside it.

Floor model, per frame: every kept (Gaussian, pixel) pair (alpha >= 1/255) costs KEPT_PAIR_FLOP flop + 1 exp
to be tested; every contributing pair (in front of its pixel's stop) CONTRIBUTING_FLOP_FORWARD (+ 2 per channel)
to composite and, in the backward pass, the 3DGS backward's BACKWARD_FLOP (+ 4 per channel) + 1 exp; the
projection PROJECTION_FLOP per Gaussian (twice that backward).  The floor is the larger of (flop at this core's
measured fp32 matmul rate + exps at torch's vectorised exp rate) and (compulsory bytes: Gaussian parameters in,
image out, their gradients back, at the measured copy bandwidth); it assumes perfect SIMD use and no pair lists
in memory, so real designs sit above it.  Example (this 2-core Zen 4 machine, shared, 1 thread): 256 x 256 px,
N = 20,000: 1.9 M box pairs, 0.91 M kept, 0.86 M contributing; floor 1.4 ms forward / 3.3 ms forward+backward
(64-75 GFLOP/s, 0.8-0.9 G exp/s); measured warp 0.027-0.040 s / 0.067-0.098 s (19-27x the floor), torch
0.39-0.44 s / 0.55-0.64 s (170-310x).
"""

import ctypes
import math
import os
import time

import numpy as np
import torch

from .splat import rasterization
from .splat_projection import pixel_boxes, project_gaussians, quat_scale_to_covar
from .splat_torch import pair_weights

KEPT_PAIR_FLOP = 13            # sigma (10), alpha and the two tests, plus one exp
CONTRIBUTING_FLOP_FORWARD = 3  # transmittance and weight, plus 2 per channel
BACKWARD_FLOP = 44             # recompute alpha, T_i, dL/dalpha, behind-sums, dL/dsigma, mean/conic/opacity grads
PROJECTION_FLOP = 250          # R S S^T R^T, W cov W^T, J cov J^T, conic, radius
N_COLORS = 4                   # RGB + mask
FOV_DEG, DISTANCE_M = 40.0, 4.0


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
    area = (boxes[:, 1] - boxes[:, 0]).clamp_min(0) * (boxes[:, 3] - boxes[:, 2]).clamp_min(0)
    return {"pixels": len(viewmats) * resolution**2, "gaussians": len(means), "instances": len(gid),
            "box_pairs": int(area.sum()), "kept_pairs": len(weight), "contributing_pairs": int((weight > 0).sum())}


def machine_rates() -> dict:
    """This core's fp32 matmul rate (flop/s), vectorised exp rate (1/s) and copy bandwidth (bytes/s), best of 3."""
    a, b = torch.rand(1024, 1024), torch.rand(1024, 1024)
    x, y = torch.rand(1 << 22), torch.empty(1 << 22)
    big = np.random.default_rng(0).random(1 << 24, dtype=np.float32)
    flops = 2 * 1024**3 / _best_cpu_time(lambda: torch.mm(a, b), 3)
    exps = len(x) / _best_cpu_time(lambda: torch.exp(x, out=y), 3)
    bandwidth = 2 * big.nbytes / _best_cpu_time(big.copy, 3)
    return {"flops": flops, "exps": exps, "bandwidth": bandwidth}


def floor_seconds(counts: dict, rates: dict) -> tuple[float, float]:
    """The physical floor (s) of one forward and one forward+backward frame (model in the module docstring)."""
    channels, n, pixels = N_COLORS + 1, counts["gaussians"], counts["pixels"]
    kept, contributing = counts["kept_pairs"], counts["contributing_pairs"]
    flop_forward = (kept * KEPT_PAIR_FLOP + contributing * (CONTRIBUTING_FLOP_FORWARD + 2 * channels)
                    + n * PROJECTION_FLOP)
    flop_backward = contributing * (BACKWARD_FLOP + 4 * channels) + 2 * n * PROJECTION_FLOP
    bytes_forward = 4 * (n * (11 + N_COLORS) + pixels * (channels + 1))
    forward = max(flop_forward / rates["flops"] + kept / rates["exps"], bytes_forward / rates["bandwidth"])
    backward = max(flop_backward / rates["flops"] + contributing / rates["exps"],
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


def main(resolutions: tuple[int, ...] = (128, 256), sizes: tuple[int, ...] = (2000, 8000, 20000),
         backends: tuple[str, ...] = ("torch", "warp")) -> list[dict]:
    """Print and return forward / forward+backward time per frame for every backend, resolution and N, with the
    work counts, the floor and the ratio to it."""
    torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))
    rates = machine_rates()
    print(f"machine (1 thread): {rates['flops'] / 1e9:.0f} GFLOP/s fp32 matmul, {rates['exps'] / 1e9:.2f} G exp/s "
          f"vectorised, {rates['bandwidth'] / 1e9:.1f} GB/s copy; times = best thread CPU time (median wall)")
    print(f"{'res':>4} {'N':>6} {'kept/box pairs':>16} {'contrib':>8} {'floor fwd / f+b':>16} {'backend':>7} "
          f"{'forward s':>18} {'fwd+bwd s':>18} {'x floor':>11} {'extra MB':>8}")
    rows = []
    for resolution in resolutions:
        viewmats, Ks = sphere_camera(resolution)
        for n in sizes:
            scene = sphere_scene(n)
            counts = work_counts(scene, viewmats, Ks, resolution)
            floor_f, floor_fb = floor_seconds(counts, rates)
            for backend in backends:
                repeats = 3 if backend == "torch" else 7
                forward = time_frame(scene, viewmats, Ks, resolution, backend, False, repeats)
                both = time_frame(scene, viewmats, Ks, resolution, backend, True, repeats)
                memory = peak_extra_memory(scene, viewmats, Ks, resolution, backend)
                row = {"resolution": resolution, "backend": backend, **counts, "floor_forward_s": floor_f,
                       "floor_forward_backward_s": floor_fb, "forward_s": forward[0], "forward_wall_s": forward[1],
                       "forward_backward_s": both[0], "forward_backward_wall_s": both[1],
                       "peak_extra_bytes": memory}
                rows.append(row)
                print(f"{resolution:>4} {n:>6} {counts['kept_pairs'] / 1e6:>6.2f}M/{counts['box_pairs'] / 1e6:.2f}M "
                      f"{counts['contributing_pairs'] / 1e6:>7.2f}M {floor_f * 1e3:>6.2f}/{floor_fb * 1e3:.2f} ms "
                      f"{backend:>7} {forward[0]:>7.4f} ({forward[1]:.4f}) {both[0]:>7.4f} ({both[1]:.4f}) "
                      f"{forward[0] / floor_f:>5.0f}/{both[0] / floor_fb:<5.0f} "
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
