"""Speed of the splatting renderer (``splat.rasterization``) against a physical floor (issue 14).

Scene (as in the generation notes, Q1): N flattened Gaussians on a unit sphere 4 m in front of the camera, 40 deg
field of view (the sphere spans ~70 % of the frame width; the rig's ``render.fill`` is 60 %), tangential sigma
0.6 sqrt(4 pi / N) m, normal sigma a tenth of it, opacity 0.8, colours RGB + one mask channel, render mode RGB+ED:
5 composited channels, like the G-buffer.  Defaults: the G-buffer's resolution (``render.width``, 192 px) and the
watched videos' (``render.video_width``, 384 px: four times the pixels; conf/render_schema.py) and the object sizes
of the evaluation grid: ``sampling.surface_points`` surface Gaussians alone, and with RELEASED_MAX more (the most
released particles any grid object draws: the plush toy's ~370).
Times are per frame and view (one camera) on one thread: the CPU time of the calling thread (torch and Warp's CPU
kernels run on it with torch.set_num_threads(1)); the wall time is printed beside it.  The machine's speed is not
constant: on the shared VMs this runs on, spells of seconds run every workload ~1.3-1.5x slower in thread CPU time -
the renderer, torch's exp and matmul and plain Python alike, timed side by side in one process; not steal time (the
kernel leaves it out of thread time), page faults or threads (README, "Renderer speed").  So the floor's rates are
measured again before each of REPEATS repeats, a repeat times the best of FRAMES_PER_REPEAT consecutive frames, and
each ratio to the floor is taken within its repeat; the best, median and worst ratio are printed, with how many
repeats are below 10x on both passes.

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
vectorised libraries (torch / numpy): ~0.8 G exp/s on one AVX2 core (AMD EPYC), 2.0-4.0 G exp/s on one AVX-512
core (Intel Xeon, torch): the 3DGS floor is ~3x lower on the second.

Example (2-core AMD EPYC Zen 5, AVX-512, 1 thread, idle; two runs, 331b9b8): 192 x 192 px, N = 3,000 and 3,400:
floor 0.25-0.26 / 0.65-0.67 ms; warp (the lanes compositor) 1.41-1.64 / 3.41-3.67 ms at best, medians 6.3-6.7x /
5.5-6.0x the floor, 20 of 20 repeats below 10x; warp-scalar (CUDA's kernels on the CPU) medians 8.9-9.9x / 8.4-8.8x.
Before the lanes compositor (2-core Intel Xeon, AVX-512, 1 thread, under load: load average 3-4; two runs,
de6686a):
192 x 192 px, N = 3,000 (3,400): 0.41 M kept pairs of 0.89 M box pairs; floor (medians) 0.18-0.23 / 0.46-0.58 ms
forward / forward+backward (exp-free 0.08-0.10 / 0.29-0.35); warp 3.7-3.9 / 8.7-8.9 ms at best, 17-22x / 16-17x
the floor at best, medians 21-25x / 18-23x, no repeat below 10x (exp-free: 49-57x / 31-37x); the code before
(9ec32b7) in the same session 4.5-4.6 / 10.4-10.8 ms, medians 27-28x / 24x.  On an AVX2 AMD EPYC (exp ~0.8 G/s,
floor 0.6-0.86 ms) the code before read 4.2-4.9 / 10.3-12.5 ms, 5.6-8.5x its floor (README, "Renderer speed").
"""

import ctypes
import math
import os

import numpy as np
import torch

from conf.render_schema import RenderConfig
from conf.schema import SamplingConfig
from tasks.core.machine_rates import best_cpu_time, machine_rates

from . import splat_warp
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
REPEATS = 20                  # repeats of the Warp backend (each: rates, then frames); torch: 3
FRAMES_PER_REPEAT = 3         # consecutive frames after each measurement of the rates (the copy leaves caches cold)
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


def frame_function(scene: list[torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, resolution: int,
                   backend: str, backward: bool):
    """One frame, forward or forward+backward w.r.t. every parameter, as a call; run once (warm-up: Warp compiles
    or loads its kernels).  backend: "torch", "warp" or "warp-scalar" (the Warp backend with its pure-Warp
    compositing kernels, CUDA's, instead of the CPU's lanes compositor: ``splat_warp.COMPOSITOR``)."""
    leaves = [t.clone().requires_grad_(backward) for t in scene]
    name, compositor = ("warp", "scalar") if backend == "warp-scalar" else (backend, "auto")

    def frame():
        previous, splat_warp.COMPOSITOR = splat_warp.COMPOSITOR, compositor
        try:
            image, alphas, _ = rasterization(*leaves, viewmats, Ks, resolution, resolution, backend=name)
            if backward:
                (image.sum() + alphas.sum()).backward()
        finally:
            splat_warp.COMPOSITOR = previous

    frame()
    return frame


def time_against_floor(scene: list[torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, resolution: int,
                       backend: str, counts: dict, repeats: int) -> dict:
    """Per repeat: the floor's rates (``machine_rates``), then the best of FRAMES_PER_REPEAT forward and of as many
    forward+backward frames (thread CPU time, s; the median wall time beside it) and the floors from those rates.  The machine's speed drifts (on a shared VM whole
    seconds run ~1.3-1.5x slower, for every workload alike: the renderer, torch's exp and matmul, plain Python), so
    the floor is measured beside every frame, not once per run; a slow spell then moves both.  Returns lists (s;
    exp_rate: the measured exps/s, whose spread shows the machine's drift)."""
    frames = [frame_function(scene, viewmats, Ks, resolution, backend, backward) for backward in (False, True)]
    out = {key: [] for key in ("forward_s", "forward_backward_s", "forward_wall_s", "forward_backward_wall_s",
                               "floor_forward_s", "floor_forward_backward_s", "exp_free_floor_forward_s",
                               "exp_free_floor_forward_backward_s", "exp_rate")}
    for _ in range(repeats):
        rates = machine_rates()
        out["exp_rate"].append(rates["exps"])
        for key, value in zip(("floor_forward_s", "floor_forward_backward_s", "exp_free_floor_forward_s",
                               "exp_free_floor_forward_backward_s"),
                              floor_seconds(counts, rates) + floor_seconds(counts, rates, exp_free=True)):
            out[key].append(value)
        for name, frame in zip(("forward", "forward_backward"), frames):
            walls = []
            out[f"{name}_s"].append(best_cpu_time(frame, FRAMES_PER_REPEAT, walls))
            out[f"{name}_wall_s"].append(float(np.median(walls)))
    return out


def peak_extra_memory(scene: list[torch.Tensor], viewmats: torch.Tensor, Ks: torch.Tensor, resolution: int,
                      backend: str) -> float | None:
    """Peak resident memory (bytes) a forward+backward frame adds, or None off Linux/glibc: the heap is trimmed,
    the peak (VmHWM) reset, a frame run and the new peak compared with the resident size before it."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        before = _status_bytes("VmRSS")
        frame_function(scene, viewmats, Ks, resolution, backend, True)
        return _status_bytes("VmHWM") - before
    except (OSError, AttributeError):
        return None


def main(resolutions: tuple[int, ...] = tuple(dict.fromkeys((RenderConfig.width, RenderConfig.video_width))),
         sizes: tuple[int, ...] = (SamplingConfig.surface_points, SamplingConfig.surface_points + RELEASED_MAX),
         backends: tuple[str, ...] = ("torch", "warp-scalar", "warp")) -> list[dict]:
    """Print and return forward / forward+backward time per frame for every backend, resolution and N, with the
    work counts, the floors and the ratios to them (defaults: the G-buffer's and the videos' resolution, the grid's
    sizes), then per backend and N the median cost per frame and ratio to the floor at each resolution
    (``resolution_summary``)."""
    torch.set_num_threads(int(os.environ.get("VIRSQUEEZER_TORCH_THREADS", "1")))
    rates = machine_rates()
    print(f"machine (1 thread, at the start): {rates['flops'] / 1e9:.0f} GFLOP/s fp32 matmul, "
          f"{rates['exps'] / 1e9:.2f} G exp/s vectorised, {rates['bandwidth'] / 1e9:.1f} GB/s copy; rates and floors "
          f"re-measured before every repeat; times: thread CPU, best of the repeats (median); ratios to the floor "
          f"of the same repeat: best-median-worst; floors (medians): 3DGS (an exp per pair), exp-free (docstring); "
          f"x exp-free: medians; G exp/s: the range measured over the repeats")
    print(f"{'res':>4} {'N':>6} {'kept/box pairs':>16} {'contrib':>8} {'floor fwd / f+b':>16} {'exp-free':>12} "
          f"{'backend':>11} {'reps':>4} {'forward ms':>14} {'fwd+bwd ms':>14} {'x floor fwd':>15} "
          f"{'x floor f+b':>15} {'<10x':>7} {'x exp-free':>11} {'G exp/s':>9} {'extra MB':>8}")
    rows = []
    for resolution in resolutions:
        viewmats, Ks = sphere_camera(resolution)
        for n in sizes:
            scene = sphere_scene(n)
            counts = work_counts(scene, viewmats, Ks, resolution)
            for backend in backends:
                repeats = 3 if backend == "torch" else REPEATS
                t = {key: np.array(v) for key, v in
                     time_against_floor(scene, viewmats, Ks, resolution, backend, counts, repeats).items()}
                memory = peak_extra_memory(scene, viewmats, Ks, resolution, backend)
                ratios = {name: t[f"{name}_s"] / t[f"floor_{name}_s"] for name in ("forward", "forward_backward")}
                free = {name: t[f"{name}_s"] / t[f"exp_free_floor_{name}_s"] for name in ratios}
                row = {"resolution": resolution, "backend": backend, **counts, "repeats": repeats,
                       **{key: float(np.median(v)) for key, v in t.items() if "floor" in key},
                       **{key: float(t[key].min()) for key in ("forward_s", "forward_backward_s")},
                       **{f"median_{key}": float(np.median(t[key])) for key in ("forward_s", "forward_backward_s")},
                       "exp_rates": t["exp_rate"].tolist(),
                       **{key: float(np.median(v)) for key, v in t.items() if "wall" in key},
                       **{f"ratio_{name}": v.tolist() for name, v in ratios.items()},
                       **{f"exp_free_ratio_{name}": v.tolist() for name, v in free.items()},
                       "peak_extra_bytes": memory}
                rows.append(row)
                under = sum(int(v.max() < 10) for v in np.stack(list(ratios.values()), 1))
                times = "".join(f" {t[f'{name}_s'].min() * 1e3:>6.2f} ({np.median(t[f'{name}_s']) * 1e3:.2f})"
                                for name in ratios)
                spread = "".join(f" {v.min():>4.1f}-{np.median(v):.1f}-{v.max():<4.1f}" for v in ratios.values())
                print(f"{resolution:>4} {n:>6} {counts['kept_pairs'] / 1e6:>6.2f}M/{counts['box_pairs'] / 1e6:.2f}M "
                      f"{counts['contributing_pairs'] / 1e6:>7.2f}M {row['floor_forward_s'] * 1e3:>6.2f}/"
                      f"{row['floor_forward_backward_s'] * 1e3:.2f} ms {row['exp_free_floor_forward_s'] * 1e3:>5.2f}/"
                      f"{row['exp_free_floor_forward_backward_s'] * 1e3:.2f} {backend:>11} {repeats:>4}{times}{spread} "
                      f"{under:>3}/{repeats:<3} {np.median(free['forward']):>5.1f}/"
                      f"{np.median(free['forward_backward']):<5.1f} "
                      f"{t['exp_rate'].min() / 1e9:>4.2f}-{t['exp_rate'].max() / 1e9:<4.2f} "
                      f"{'n/a' if memory is None else f'{memory / 2**20:.0f}':>8}", flush=True)
    resolution_summary(rows)
    return rows


def resolution_summary(rows: list[dict]) -> None:
    """Print, per backend and number of Gaussians, the median forward and forward+backward time per frame and view
    (thread CPU ms) and median ratio to the floor at every resolution benchmarked, and each time relative to the
    first resolution's (the cost of a frame as the resolution grows)."""
    if len({row["resolution"] for row in rows}) < 2:
        return
    print("per resolution (medians over the repeats; cost relative to the first resolution):")
    for backend, n in dict.fromkeys((row["backend"], row["gaussians"]) for row in rows):
        same = [row for row in rows if row["backend"] == backend and row["gaussians"] == n]
        cells = []
        for row in same:
            parts = []
            for name, label in (("forward", "fwd"), ("forward_backward", "f+b")):
                seconds, ratio = row[f"median_{name}_s"], float(np.median(row[f"ratio_{name}"]))
                parts.append(f"{label} {seconds * 1e3:.2f} ms = {ratio:.1f}x floor "
                             f"({seconds / same[0][f'median_{name}_s']:.1f}x)")
            cells.append(f"{row['resolution']} px: " + ", ".join(parts))
        print(f"  {backend:>11} N={n:<6} " + "; ".join(cells), flush=True)


def _status_bytes(field: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return float(line.split()[1]) * 1024
    raise OSError(f"{field} not in /proc/self/status")


if __name__ == "__main__":
    main()
