"""A real Dask cluster: ``dask scheduler`` and ``dask worker`` processes (the ``distributed`` CLIs) on the loopback
address, as a user starts them on nodes, running the pipeline through ``runner=dask runner.address=...``.

One object, one variant, the tiny sizes of the cache tests: each run is seconds of compute, most of a test's time
is the workers' first imports."""
from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tasks.core.artifacts import read_group_attrs, verify_artifact
from tests.flows.loopback_cluster import REPO, loopback_cluster, start_worker, wait_for_workers, worker_env
from tests.small_runs import SMALL as SMALL_RUN

SMALL = [o for o in SMALL_RUN if not o.startswith("runner=")]  # the runner is each test's
OBJECT = "clay"
N_STEPS = 18  # 9 per object + 4 per variant + 5 per backend (no paper-metric weights; display_video included)


def digests(root: Path) -> dict[tuple[str, str], str]:
    return {(g.parent.parent.name, g.parent.name): read_group_attrs(g)["digest"] for g in root.glob("*/*/*.zarr")}


def executed(client) -> dict[str, int]:
    """Tasks each worker has executed since it started."""
    return client.run(lambda dask_worker: dask_worker.state.executed_count)


def grid_cfg(compose_cfg, root: Path, runner: list[str]):
    return compose_cfg("evaluate", [f"paths.artifacts={root / 'artifacts'}", f"paths.reports={root / 'reports'}",
                                    f"grid.objects=[{OBJECT}]", *runner, *SMALL])


@pytest.fixture(scope="module")
def local_digests(prefect_server, tmp_path_factory):
    """The artifacts of the grid run in one process (runner=sequential)."""
    from flows.pipeline import run
    from tests.conftest import compose

    root = tmp_path_factory.mktemp("local")
    out = run(grid_cfg(compose, root, ["runner=sequential"]), "test")
    assert {r["status"] for r in out["tasks"]} == {"ran"} and len(out["tasks"]) == N_STEPS
    return digests(root / "artifacts")


@pytest.fixture(scope="module")
def cluster(prefect_server, tmp_path_factory):
    """A scheduler and two one-thread workers on 127.0.0.1, started in this checkout with the tests' Prefect API."""
    with loopback_cluster(tmp_path_factory.mktemp("cluster"), worker_env(prefect_server)) as c:
        yield c


def test_grid_runs_on_the_workers_with_the_local_digests_and_reruns_from_cache(cluster, local_digests, tmp_path,
                                                                               compose_cfg, capsys):
    from distributed import Client

    from flows.pipeline import run

    cfg = grid_cfg(compose_cfg, tmp_path, ["runner=dask", f"runner.address={cluster.address}"])
    with Client(cluster.address) as client:
        before = executed(client)
        out = run(cfg, "test")
        after = executed(client)
        assert "checked 2 Dask worker(s)" in capsys.readouterr().out
        assert {r["status"] for r in out["tasks"]} == {"ran"} and len(out["tasks"]) == N_STEPS
        # every step and the report media of the one scene ran on the two workers, none in this process
        assert sum(after[w] - before[w] for w in after) == N_STEPS + 1
        assert digests(tmp_path / "artifacts") == local_digests

        # a lost leaf: the runner starts, the workers find the other 15 through the shared cache records
        (leaf,) = (tmp_path / "artifacts" / OBJECT / "llm_evaluation").glob("*.zarr")
        shutil.rmtree(leaf)
        again = run(cfg, "test")
        status = {r["step"]: r["status"] for r in again["tasks"]}
        assert status.pop("llm_evaluation") == "ran" and set(status.values()) == {"cached"}
        assert sum(executed(client)[w] - after[w] for w in after) == N_STEPS + 1
    assert digests(tmp_path / "artifacts") == local_digests
    # nothing left to do: every artifact is checked on disk, no runner started
    assert {r["status"] for r in run(cfg, "test")["tasks"]} == {"cached"}
    assert "every step is cached" in capsys.readouterr().out


def test_sigkill_of_the_busy_worker_mid_run_finishes_and_leaves_nothing_half_written(cluster, local_digests,
                                                                                       prefect_server, tmp_path,
                                                                                       compose_cfg):
    """The worker running the MPM rollout is killed with SIGKILL: Dask reschedules its task (and recomputes what it
    held) on the other worker, the flow finishes; every artifact verifies, and a rerun is fully cached."""
    from distributed import Client

    root = tmp_path / "artifacts"
    env = worker_env(prefect_server)
    cmd = [sys.executable, "-m", "flows.squeeze", f"object={OBJECT}", "runner=dask",
           f"runner.address={cluster.address}", f"paths.artifacts={root}", f"paths.reports={tmp_path / 'reports'}",
           *SMALL]
    from flows.pipeline import run

    with Client(cluster.address) as client:
        pid_of = client.run(os.getpid)
        flow = subprocess.Popen(cmd, env=env, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        victim, deadline = None, time.time() + 300
        while victim is None and time.time() < deadline and flow.poll() is None:
            busy = [w for w, keys in client.processing().items() if any(str(k).startswith("mpm_rollout") for k in keys)]
            if busy:
                victim = next(n for n, p in cluster.workers.items() if p.pid == pid_of[busy[0]])
                cluster.kill(victim)
            time.sleep(0.02)
        output, _ = flow.communicate(timeout=300)
    assert victim is not None, f"the rollout was never seen running:\n{output[-3000:]}"
    lines = output.splitlines()
    if flow.returncode == 0:
        assert f"{N_STEPS}/{N_STEPS}]" in output and "failed" not in output.split("per-task table")[-1]
    else:  # stopped: one line names the lost worker
        assert "worker" in lines[-1].lower(), lines[-5:]
    for group in root.glob("*/*/*.zarr"):
        verify_artifact(group)  # every file as its manifest says: nothing half-written at a final path
    assert digests(root) == {k: v for k, v in local_digests.items() if k in digests(root)}

    # a worker again, for the rerun and the next tests
    start_worker(cluster, victim, env)
    wait_for_workers(cluster.address, list(cluster.workers))
    rerun = run(compose_cfg("squeeze", cmd[3:]), "squeeze")  # the same command, in this process
    assert {r["status"] for r in rerun["tasks"]} == {"cached"} and len(rerun["tasks"]) == N_STEPS
    assert digests(root) == local_digests
    assert not [p for p in root.rglob("*") if ".tmp-" in p.name or ".trash-" in p.name]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _other_checkout(tmp: Path) -> Path:
    """A copy of this checkout whose ``tasks/core/artifacts.py`` differs by one comment line (another commit)."""
    copy = tmp / "checkout"
    for part in ("tasks", "conf", "flows"):
        shutil.copytree(REPO / part, copy / part, ignore=shutil.ignore_patterns("__pycache__"))
    with open(copy / "tasks" / "core" / "artifacts.py", "a") as f:
        f.write("# a later commit\n")
    return copy


def test_workers_that_differ_from_the_flow_are_named_before_any_step(prefect_server, tmp_path, compose_cfg):
    """Three workers: one as the flow, one from another checkout, one that sees its own empty folder at the path of
    ``paths.artifacts`` (a node-local disk; a mount namespace with a tmpfs there).  The run stops with one line per
    differing worker before any step; a step sent to the other checkout's worker anyway is refused by it."""
    from distributed import Client

    from flows.cluster import check_workers
    from flows.pipeline import STEPS, run, step_params
    from flows.selection import selected_objects
    from tasks.control.object_model import object_model_step

    root = tmp_path / "shared" / "artifacts"
    root.mkdir(parents=True)
    env = worker_env(prefect_server)
    blind = ("unshare", "--mount", "--propagation", "private", "sh", "-c",
             f'mount -t tmpfs none "{root}" && exec "$@"', "sh")
    if subprocess.run([*blind, "true"], capture_output=True).returncode != 0:
        pytest.skip("no mount namespace here (unshare needs root): the blind worker cannot be made")
    copy = _other_checkout(tmp_path)
    with loopback_cluster(tmp_path / "cluster", env, n_workers=1) as cl, Client(cl.address) as client:
        start_worker(cl, "old", dict(env, PYTHONPATH=str(copy)), cwd=copy)
        start_worker(cl, "blind", env, prefix=blind)
        wait_for_workers(cl.address, ["w0", "old", "blind"])
        address_of = {n: a for a, n in client.run(lambda dask_worker: dask_worker.name).items()}

        cfg = compose_cfg("evaluate", [f"paths.artifacts={root}", f"paths.reports={tmp_path / 'reports'}",
                                       f"object={OBJECT}", "runner=dask", f"runner.address={cl.address}", *SMALL])
        with pytest.raises(SystemExit) as stop:
            run(cfg, "test")
        lines = {line.split()[2]: line for line in str(stop.value).splitlines()}  # worker address -> its line
        assert set(lines) == {address_of["old"], address_of["blind"]}, lines
        assert "has other code than the flow: tasks.c" in lines[address_of["old"]]
        assert f"does not see paths.artifacts={root}: cannot read" in lines[address_of["blind"]]
        assert not list(root.rglob("*.zarr")) and not list(root.glob(".worker-probe-*"))

        # a Prefect API the workers cannot reach (the port is closed): every worker is named
        closed = f"http://127.0.0.1:{_free_port()}/api"
        with pytest.raises(SystemExit) as stop:
            check_workers(cl.address, root, STEPS, closed)
        api_lines = [x for x in str(stop.value).splitlines() if f"cannot reach the Prefect API {closed}" in x]
        assert len(api_lines) == 3

        # a step sent to the old checkout's worker all the same (e.g. one that joined after the check): refused
        (obj,) = selected_objects(cfg)
        params = step_params(object_model_step, cfg, obj)
        future = client.submit(object_model_step.run_local, root=str(root), scope=OBJECT, params=params,
                               workers=[address_of["old"]], pure=False)
        with pytest.raises(Exception, match=r"refuses step 'object_model': its code of tasks\.control\.object_model"):
            future.result(timeout=120)
        assert not list(root.rglob("*.zarr"))
        # the same step on the matching worker computes (the check passes where the code is the flow's)
        ok = client.submit(object_model_step.run_local, root=str(root), scope=OBJECT, params=params,
                           workers=[address_of["w0"]], pure=False).result(timeout=300)
        verify_artifact(ok.at(root).path)
