"""A real Dask cluster for the tests: ``dask scheduler`` and ``dask worker`` processes (the ``distributed`` CLIs) on
the loopback address, ports chosen by the OS, each worker one process of one thread started in the repository's
root with the test's environment (as a user starts them on a node)."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

REPO = Path(__file__).resolve().parents[2]
DASK = str(Path(sys.executable).with_name("dask"))


@dataclass
class LoopbackCluster:
    address: str
    scheduler: subprocess.Popen
    workers: dict[str, subprocess.Popen] = field(default_factory=dict)  # worker name -> its process
    logs: Path = Path(".")

    def log_of(self, name: str) -> str:
        return (self.logs / f"{name}.log").read_text(errors="replace")

    def kill(self, name: str) -> None:
        """SIGKILL the worker process ``name`` (no nanny: it stays dead)."""
        proc = self.workers[name]
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=30)


def _start(cmd: list[str], log: Path, env: dict, cwd: Path) -> subprocess.Popen:
    with open(log, "wb") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=cwd, start_new_session=True)


def start_worker(cluster: LoopbackCluster, name: str, env: dict, cwd: Path = REPO,
                 prefix: tuple[str, ...] = ()) -> subprocess.Popen:
    """One ``dask worker`` process (no nanny, one thread) named ``name``, joined to ``cluster``; ``prefix`` is a
    command that execs the worker (same process id), e.g. in a mount namespace of its own."""
    proc = _start([*prefix, DASK, "worker", cluster.address, "--name", name, "--nthreads", "1", "--no-nanny",
                   "--host", "127.0.0.1", "--no-dashboard", "--death-timeout", "60", "--memory-limit", "0"],
                  cluster.logs / f"{name}.log", env, cwd)
    cluster.workers[name] = proc
    return proc


def wait_for_workers(address: str, names: list[str], timeout: float = 120.0) -> None:
    from distributed import Client

    with Client(address, timeout=timeout) as client:
        deadline = time.time() + timeout
        while {w["name"] for w in client.scheduler_info()["workers"].values()} < set(names):
            if time.time() > deadline:
                raise TimeoutError(f"workers {names} did not join {address} within {timeout:.0f} s")
            time.sleep(0.2)


@contextmanager
def loopback_cluster(tmp: Path, env: dict, n_workers: int = 2) -> Iterator[LoopbackCluster]:
    """A scheduler and ``n_workers`` workers (``w0``, ``w1``, ...) on 127.0.0.1; stopped (SIGTERM, then SIGKILL)
    on exit.  Their output goes to ``tmp/<name>.log``."""
    tmp.mkdir(parents=True, exist_ok=True)
    info = tmp / "scheduler.json"
    scheduler = _start([DASK, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                        "--scheduler-file", str(info)], tmp / "scheduler.log", env, REPO)
    cluster = LoopbackCluster(address="", scheduler=scheduler, logs=tmp)
    try:
        deadline = time.time() + 60
        while not info.is_file() or not info.read_text().strip():
            if scheduler.poll() is not None or time.time() > deadline:
                raise RuntimeError(f"dask scheduler did not start:\n{(tmp / 'scheduler.log').read_text()[-2000:]}")
            time.sleep(0.1)
        time.sleep(0.1)  # the file is written whole, but give its writer the moment to close it
        cluster.address = json.loads(info.read_text())["address"]
        names = [f"w{i}" for i in range(n_workers)]
        for name in names:
            start_worker(cluster, name, env)
        wait_for_workers(cluster.address, names)
        yield cluster
    finally:
        procs = [*cluster.workers.values(), scheduler]
        for proc in procs:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGTERM)
        for proc in procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()


def worker_env(prefect_api: str, **extra: str) -> dict:
    """The environment of a worker started by hand: this checkout importable, the flow's Prefect API."""
    return dict(os.environ, PYTHONPATH=str(REPO), PREFECT_API_URL=prefect_api, **extra)
