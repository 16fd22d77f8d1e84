"""Stopping a run and the temporary Prefect server's life (flows/lifecycle.py), with real flow processes.

Each test starts ``python -m flows.evaluate`` (or ``flows.squeeze``) on the smallest pipeline config
(``tests/small_runs.py``'s sizes, with a slower rollout so that a signal lands mid-step) and without
``PREFECT_API_URL``: the run starts its own temporary server, as a user's run does.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from flows.lifecycle import is_prefect_server
from tests.small_runs import CONTROL_SIZES, RENDER_SIZES

REPO = Path(__file__).resolve().parents[2]
SMALL = [*CONTROL_SIZES, *RENDER_SIZES,
         "mpm.target_substeps_per_frame=400"]  # ~10 s of rollout on 2 cores: the signal lands mid-step
STOP_LINE = re.compile(r"stopped by (Ctrl-C|SIGTERM): (\d+) of \d+ steps finished and kept, the rest will run on "
                       r"the next start \(same command\)")
START_TIMEOUT_S = 400  # imports and the server's start-up on a loaded 2-core machine


def _env(**extra: str) -> dict[str, str]:
    """The user's environment: no Prefect variables (the run starts its own server), our code first."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_") and k != "VIRSQUEEZER_ARTIFACTS"}
    return {**env, "PYTHONPATH": str(REPO), **extra}


def _start(root: Path, *overrides: str, cwd: Path = REPO, flow: str = "flows.evaluate") -> tuple[subprocess.Popen, Path]:
    log = root / "run.log"
    root.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", flow, "grid.objects=[rubber_ball]", "grid.variants=[full]",
           f"paths.artifacts={root / 'artifacts'}", f"paths.reports={root / 'reports'}", *SMALL, *overrides]
    proc = subprocess.Popen(cmd, cwd=cwd, env=_env(), stdout=log.open("w"), stderr=subprocess.STDOUT,
                            start_new_session=True)  # its own process group, as a terminal gives a command
    return proc, log


def _wait_for(proc: subprocess.Popen, log: Path, pattern: str) -> float:
    """Seconds until ``pattern`` appears in the run's output."""
    t0 = time.monotonic()
    while not re.search(pattern, log.read_text()):
        assert proc.poll() is None, f"the run ended (code {proc.returncode}) first:\n{log.read_text()[-3000:]}"
        assert time.monotonic() - t0 < START_TIMEOUT_S, log.read_text()[-3000:]
        time.sleep(0.1)
    return time.monotonic() - t0


def _servers_of(home: Path) -> list[psutil.Process]:
    """Running Prefect server processes whose PREFECT_HOME is ``home``."""
    found = []
    for p in psutil.process_iter(["cmdline"]):
        try:
            if is_prefect_server(p.info["cmdline"] or []) and p.environ().get("PREFECT_HOME") == str(home):
                found.append(p)
        except psutil.Error:
            continue
    return found


def _stop(proc: subprocess.Popen, sig: signal.Signals, group: bool) -> tuple[int, float]:
    """Send ``sig`` (to the process group, as a terminal's Ctrl-C does, when ``group``), then once more 0.5 s
    later; returns the exit code and the seconds from the first signal to the exit."""
    send = os.killpg if group else os.kill
    t0 = time.monotonic()
    send(proc.pid, sig)
    time.sleep(0.5)
    try:
        send(proc.pid, sig)  # impatient user: a second Ctrl-C must not make it worse
    except ProcessLookupError:
        pass
    code = proc.wait(timeout=30)
    return code, time.monotonic() - t0


def _the_stop_line(out: str, how: str) -> str:
    """The run's output ends with exactly one stop line naming ``how``; returns the count of kept steps."""
    stops = STOP_LINE.findall(out)
    assert len(stops) == 1 and stops[0][0] == how, out[-3000:]
    assert STOP_LINE.search(out.strip().splitlines()[-1]), f"printed after the stop line:\n{out[-3000:]}"
    assert "Traceback" not in out and "All connection attempts failed" not in out, out[-3000:]
    return stops[0][1]


def test_ctrl_c_stops_the_run_once_within_seconds(tmp_path):
    """Ctrl-C mid-step: one line saying what is kept, exit 130 within seconds, the temporary server ended (it
    runs in its own session, so the terminal's Ctrl-C does not kill it under the flow), no record left."""
    proc, log = _start(tmp_path, "runner=sequential")
    _wait_for(proc, log, r"\[2/18\] rubber_ball squeeze_signals")
    home = tmp_path / "artifacts" / ".prefect"
    assert len(_servers_of(home)) == 1
    code, seconds = _stop(proc, signal.SIGINT, group=True)
    out = log.read_text()
    print(f"SIGINT to exit: {seconds:.1f} s")
    assert code == 130, out[-3000:]
    assert seconds < 15
    assert int(_the_stop_line(out, "Ctrl-C")) >= 2  # the steps of the progress lines printed before
    assert _servers_of(home) == []
    assert list((home / "servers").iterdir()) == []


def test_sigterm_ends_the_dask_cluster_and_prefect_home_follows_paths_artifacts(tmp_path):
    """From a read-only working folder, with paths.artifacts elsewhere: Prefect's home (database, cache records)
    is under paths.artifacts and nothing is written to the working folder (root ignores its mode: the folder
    must stay empty).  SIGTERM mid-step ends the Dask workers and the server and exits 143 with the one line."""
    cwd = tmp_path / "readonly"
    cwd.mkdir()
    cwd.chmod(0o555)
    try:
        proc, log = _start(tmp_path / "run", "runner=dask", "runner.n_workers=1", cwd=cwd)
        _wait_for(proc, log, r"\[1/18\] rubber_ball object_model")
        home = tmp_path / "run" / "artifacts" / ".prefect"
        assert len(_servers_of(home)) == 1  # the Dask worker ran its step against the run's server
        children = psutil.Process(proc.pid).children(recursive=True)
        code, seconds = _stop(proc, signal.SIGTERM, group=False)
    finally:
        cwd.chmod(0o755)
    out = log.read_text()
    print(f"SIGTERM to exit: {seconds:.1f} s")
    assert code == 143, out[-3000:]
    assert seconds < 15
    _the_stop_line(out, "SIGTERM")
    time.sleep(1)  # the resource tracker leaves when it sees its parent gone
    assert [c.pid for c in children if c.is_running() and c.status() != psutil.STATUS_ZOMBIE] == []
    assert (home / "prefect.db").is_file() and (home / "results").is_dir()
    assert list(cwd.iterdir()) == []


def test_server_dies_with_a_killed_run_and_the_next_start_ends_orphans(tmp_path):
    """SIGKILL of a run takes its temporary server with it (PR_SET_PDEATHSIG).  A server that outlived its run
    anyway (recorded by a run that is gone, or an unrecorded temporary server adopted by pid 1) is ended by
    the next start of a flow on the same artifacts folder, with one line each, before anything else."""
    home = tmp_path / "artifacts" / ".prefect"
    proc, log = _start(tmp_path, "runner=sequential")
    _wait_for(proc, log, "Starting temporary server")
    while not list((home / "servers").glob("*.json")):
        time.sleep(0.1)
    (record,) = (home / "servers").glob("*.json")
    server_pid = json.loads(record.read_text())["server_pid"]
    proc.kill()
    proc.wait()
    t0 = time.monotonic()
    while psutil.pid_exists(server_pid) and psutil.Process(server_pid).status() != psutil.STATUS_ZOMBIE:
        assert time.monotonic() - t0 < 10, "the server outlived its SIGKILLed run"
        time.sleep(0.1)
    print(f"server gone {time.monotonic() - t0:.1f} s after the SIGKILL")

    # two servers left behind by runs that could not take them along: one recorded, one not
    server = [sys.executable, "-m", "uvicorn", "--factory", "prefect.server.api.server:create_app", "--port"]
    env = _env(PREFECT_HOME=str(home), PREFECT__SERVER_EPHEMERAL="1")
    orphans = []
    for port in ("8997", "8998"):  # started by a shell that exits at once: adopted by pid 1
        out = subprocess.run(["sh", "-c", f'{" ".join(server)} {port} >/dev/null 2>&1 & echo $!'], env=env,
                             capture_output=True, text=True, check=True)
        orphans.append(psutil.Process(int(out.stdout)))
    if any(p.ppid() != 1 for p in orphans):
        for p in orphans:
            p.kill()
        pytest.skip("orphans are adopted by a subreaper here, not pid 1")
    record.write_text(json.dumps({**json.loads(record.read_text()), "server_pid": orphans[0].pid,
                                  "server_started": orphans[0].create_time()}))
    next_run = subprocess.run([sys.executable, "-m", "flows.squeeze", f"paths.artifacts={tmp_path / 'artifacts'}",
                               f"paths.reports={tmp_path / 'reports'}", "signal.duration=-1"], cwd=REPO, env=_env(),
                              capture_output=True, text=True, timeout=300)
    lines = next_run.stderr.strip().splitlines()
    ended = [line for line in lines if line.startswith("ended a Prefect server left running by a killed run")]
    assert len(ended) == 2, next_run.stderr[-3000:]
    assert f"server pid {orphans[0].pid}" in ended[0] and f"flow pid {proc.pid}" in ended[0]
    assert f"server pid {orphans[1].pid}" in ended[1] and "its flow process is gone" in ended[1]
    assert lines[-1].startswith("config error: signal.duration"), next_run.stderr[-3000:]
    assert _servers_of(home) == [] and not record.exists()


def test_tasks_receive_the_flows_settings_whole_and_the_same():
    """What a Dask worker receives with each task: the settings object itself (not a dict it must validate into new
    settings, ~80 ms per task), equal to the flow's, its temporary updates included."""
    import cloudpickle
    from prefect.context import SettingsContext, serialize_context
    from prefect.settings import PREFECT_API_URL, Settings, temporary_settings

    from flows.lifecycle import settings_shipped_whole

    with temporary_settings(updates={PREFECT_API_URL: "http://127.0.0.1:1/api"}), settings_shipped_whole():
        shipped = serialize_context()["settings_context"]
        flow_settings = SettingsContext.get().settings
    assert isinstance(shipped["settings"], Settings)
    hydrated = SettingsContext(**cloudpickle.loads(cloudpickle.dumps(shipped)))  # as the worker's engine does
    assert hydrated.settings == flow_settings and hydrated.settings.api.url == "http://127.0.0.1:1/api"
    assert isinstance(SettingsContext.get().serialize(include_secrets=False)["settings"], dict)


def test_clients_of_the_temporary_server_load_one_ca_certificate_and_ship_no_logs(tmp_path, monkeypatch):
    import ssl

    from prefect.settings import PREFECT_API_SSL_CERT_FILE, PREFECT_LOGGING_TO_API_ENABLED

    from flows.lifecycle import loopback_client_settings

    monkeypatch.delenv("PREFECT_API_SSL_CERT_FILE", raising=False)
    updates = loopback_client_settings(tmp_path)
    assert updates[PREFECT_LOGGING_TO_API_ENABLED] is False
    one = Path(updates[PREFECT_API_SSL_CERT_FILE])
    assert one.parent == tmp_path and one.read_text().count("BEGIN CERTIFICATE") == 1
    ssl.create_default_context(cafile=str(one))  # a valid CA file for Prefect's client
    monkeypatch.setenv("PREFECT_API_SSL_CERT_FILE", str(tmp_path / "users.pem"))  # the user's own is kept
    assert PREFECT_API_SSL_CERT_FILE not in loopback_client_settings(tmp_path)
