"""This core's measured rates, the denominators of the benchmarks' physical floors (``tasks.render.benchmark``,
``tasks.verification.mpm_floor``): fp32 matmul (flop/s: every FMA unit and SIMD lane busy), vectorised exp (1/s) and
copy bandwidth (bytes/s), each the best of three runs in thread CPU time on the calling thread."""
from __future__ import annotations

import math
import time

import numpy as np
import torch


def best_cpu_time(fn, repeats: int, walls: list | None = None) -> float:
    """The least thread CPU time (s) of ``repeats`` calls of fn; with walls, each call's wall time appended to it."""
    best = math.inf
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.thread_time()
        fn()
        best = min(best, time.thread_time() - cpu)
        if walls is not None:
            walls.append(time.perf_counter() - wall)
    return best


def machine_rates() -> dict:
    """This core's fp32 matmul rate (flop/s), vectorised exp rate (1/s: the faster of torch and numpy on 16k
    cache-resident floats, 64 calls a run) and copy bandwidth (bytes/s, 64 MB), best of 3; every output is
    preallocated (a fresh 64 MB copy's page faults halved the bandwidth read and made it swing with the load).
    One core's only if torch runs on one thread (``torch.set_num_threads(1)``)."""
    a, b, c = torch.rand(1024, 1024), torch.rand(1024, 1024), torch.empty(1024, 1024)
    x, y = torch.rand(1 << 14), torch.empty(1 << 14)
    xn, yn = x.numpy(), y.numpy()
    big = np.random.default_rng(0).random(1 << 24, dtype=np.float32)
    copy = np.empty_like(big)
    flops = 2 * 1024**3 / best_cpu_time(lambda: torch.mm(a, b, out=c), 3)
    exp_calls = (lambda: [torch.exp(x, out=y) for _ in range(64)], lambda: [np.exp(xn, out=yn) for _ in range(64)])
    exps = max(64 * len(x) / best_cpu_time(call, 3) for call in exp_calls)
    bandwidth = 2 * big.nbytes / best_cpu_time(lambda: np.copyto(copy, big), 3)
    return {"flops": flops, "exps": exps, "bandwidth": bandwidth}


def one_core_rates() -> dict:
    """:func:`machine_rates` with torch on one thread (its matmul rate then is one core's), torch's threads restored."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        return machine_rates()
    finally:
        torch.set_num_threads(threads)
