"""Orchestration overhead benchmark: what one cached Prefect task costs outside the step's own compute.

    python -m flows.bench.overhead                     # 8 chains x (1 source + 11 consumers) = 96 tasks, 3 MB sources
    python -m flows.bench.overhead chains=4 fan=5 mb=0

Runs small :func:`tasks.core.step.artifact_step` tasks through the main job's machinery (:func:`flows.pipeline.run`:
the same Prefect settings, result storage and cache policy, one temporary Prefect server, a local Dask cluster of
``workers`` worker processes via prefect-dask).  Each chain is one source step writing ``mb`` MB of float32
noise (the real artifacts average 3 MB, 0.2-20 MB) and ``fan`` consumer steps that read it, as
``object_model`` is read by eight steps of its object.  After a warm-up chain per worker (imports), the CPU
seconds of the flow process (Dask scheduler and nannies included), the Dask workers and the Prefect server are
read from ``/proc`` (utime + stime) before and after the timed tasks: first cold (every task runs), then again
with the same keys (every task is a cache hit).  Prints CPU seconds and wall seconds per task.  Config:
``conf/study/bench_overhead.yaml`` (keys: :class:`conf.study.schema.OverheadBenchConfig`).
"""
from __future__ import annotations

import tempfile
import time
import uuid

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from conf.study.schema import register_study_configs
from tasks.core.artifacts import Array
from tasks.core.step import artifact_step

register_study_configs()


@artifact_step("overhead_source", outputs=("noise",))
def overhead_source_step(inputs, params):
    """``bench.mb`` MB of float32 noise (incompressible: the worst case for the artifact checks)."""
    n = int(params["bench.mb"] * 2**20) // 4
    rng = np.random.default_rng(int(params["bench.chain"]))
    return {"noise": Array(rng.random(n, dtype=np.float32), ("sample",), "1")}, {}


@artifact_step("overhead_consumer", inputs=("overhead_source",), outputs=("mean",))
def overhead_consumer_step(inputs, params):
    """The mean of the source's noise (reads the whole input)."""
    noise = inputs["overhead_source"]["noise"]
    return {"mean": Array(np.array([noise.mean() if noise.size else 0.0]), ("one",), "1")}, {}


def _cpu_seconds() -> dict[str, float]:
    """utime + stime of this process and its descendants, summed per role (flow, workers, server)."""
    import psutil

    from flows.lifecycle import is_prefect_server

    out = {"flow": sum(psutil.Process().cpu_times()[:2]), "workers": 0.0, "server": 0.0}
    for child in psutil.Process().children(recursive=True):
        try:
            role = "server" if is_prefect_server(child.cmdline()) else "workers"
            out[role] += sum(child.cpu_times()[:2])
        except psutil.Error:
            pass
    return out


def _submit_chains(root: str, chains: range, fan: int, mb: float, nonce: str) -> list:
    futures = []
    for c in chains:
        params = {"bench.chain": c, "bench.mb": mb, "bench.nonce": nonce}
        src = overhead_source_step.submit(root=root, scope=f"chain{c}", params=params, inputs={})
        futures.append(src)
        futures += [overhead_consumer_step.submit(root=root, scope=f"chain{c}", params={**params, "bench.k": k},
                                                  inputs={"overhead_source": src}) for k in range(fan)]
    return futures


def _timed(root: str, chains: range, fan: int, mb: float, nonce: str) -> dict[str, float]:
    before, t0 = _cpu_seconds(), time.perf_counter()
    futures = _submit_chains(root, chains, fan, mb, nonce)
    for f in futures:
        f.wait()
    wall = time.perf_counter() - t0
    after = _cpu_seconds()
    states = {f.state.name for f in futures}
    n = len(futures)
    cpu = {k: (after[k] - before[k]) / n for k in after}
    return {"tasks": n, "states": ",".join(sorted(states)), "wall_per_task": wall / n, "wall": wall, **cpu,
            "cpu_per_task": sum(cpu.values())}


def benchmark_flow(root: str, chains: int, fan: int, mb: float, workers: int) -> dict:
    nonce = uuid.uuid4().hex[:8]
    _timed(root, range(chains, chains + workers), fan, 0.0, nonce)  # warm-up: each worker imports the steps
    cold = _timed(root, range(chains), fan, mb, nonce)
    warm = _timed(root, range(chains), fan, mb, nonce)
    return {"cold": cold, "cached": warm}


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/bench_overhead")
def main(cfg: DictConfig) -> None:
    for key in ("chains", "fan", "workers"):
        if cfg[key] < 1:
            raise SystemExit(f"input error: {key} must be >= 1, got {cfg[key]}")
    if not cfg.mb >= 0:
        raise SystemExit(f"input error: mb must be >= 0 MB, got {cfg.mb}")
    root = cfg.artifacts or tempfile.mkdtemp(prefix="virsqueezer-overhead-")

    from flows.lifecycle import begin_run

    begin_run(root)  # Prefect's home under the artifacts folder, before Prefect loads
    from prefect import flow

    from flows.lifecycle import temporary_server
    from flows.runtime import make_task_runner, result_storage_settings

    runner = make_task_runner(OmegaConf.create({"kind": "dask", "n_workers": cfg.workers, "threads_per_worker": 1,
                                                "address": None}))
    bench = flow(benchmark_flow, name="overhead", validate_parameters=False, persist_result=False,
                 task_runner=runner)
    with result_storage_settings(root), temporary_server():
        result = bench(root, cfg.chains, cfg.fan, cfg.mb, cfg.workers)
    print(f"artifacts {root}, {cfg.workers} workers, sources {cfg.mb} MB, fan {cfg.fan}")
    print(f"{'pass':7s} {'tasks':>5s} {'wall/task s':>11s} {'CPU/task s':>10s} {'flow':>6s} {'workers':>7s} "
          f"{'server':>6s}  states")
    for name, r in result.items():
        print(f"{name:7s} {r['tasks']:5d} {r['wall_per_task']:11.3f} {r['cpu_per_task']:10.3f} {r['flow']:6.3f} "
              f"{r['workers']:7.3f} {r['server']:6.3f}  {r['states']}")


if __name__ == "__main__":
    main()
