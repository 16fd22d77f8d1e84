"""How a flow process starts and stops: where Prefect keeps its home, the temporary Prefect server, Ctrl-C.

1. **Prefect's home follows ``paths.artifacts``.**  :func:`begin_run` (first line of every Hydra main, before
   Prefect is imported) points ``PREFECT_HOME`` and ``PREFECT_RESULTS_LOCAL_STORAGE_PATH`` at
   ``<paths.artifacts>/.prefect`` (``<paths.reports>/.prefect`` when the artifacts folder is a read-only shared
   cache) unless the user set them in the environment, so nothing is written to the working folder (it may be
   read-only).  Prefect reads its settings once, at import: in a Hydra multirun the
   first job's artifacts folder keeps the server's home (the cache records follow each job's folder anyway,
   :func:`flows.runtime.result_storage_settings`).
2. **Stopping.**  :func:`begin_run` also installs the SIGINT (Ctrl-C) and SIGTERM handlers (and the flow body
   takes SIGTERM back from Prefect's engine, :func:`watch_progress`).  The first signal silences this process,
   kills its children - the Dask workers and the temporary server (its database is SQLite: a kill loses no
   committed state, whereas a graceful shutdown with the flow's connections still open prints a page of
   cancelled-task tracebacks) -, then prints one line, how many steps finished and are kept (last: a Dask worker
   shares the run's output, and with the line printed before the workers were gone, a step one of them finished a
   moment later was logged after it), and exits with 130 (SIGINT) or 143 (SIGTERM) without talking to the Prefect
   API again.  Further signals are ignored; a watchdog exits
   after :data:`STOP_DEADLINE_S` whatever happens.  A step stopped half-way leaves only its temporary folder
   (artifacts are written under a temporary name and renamed when complete): nothing a later run trusts.  A stop
   while the report is written says "report incomplete" and names its folder (:mod:`flows.report_marker`).
3. **No server outlives its run.**  :func:`temporary_server` starts Prefect's temporary server itself, in its
   own session (a terminal's Ctrl-C reaches the flow, which stops the server in order) and, on Linux, with
   ``PR_SET_PDEATHSIG`` so that the kernel kills it when the flow process dies (SIGKILL included).
   Its API address is then given to everything the run starts (the Dask workers otherwise start one server
   each).  The server's pid and the flow's pid, with their start times, are recorded in
   ``<PREFECT_HOME>/servers/``; the next :func:`begin_run` ends any recorded server whose flow process is
   gone, and any temporary Prefect server of this ``PREFECT_HOME`` that was orphaned (adopted by pid 1),
   with one line each.
4. **Cheap tasks.**  On its temporary server a run's tasks skip what costs CPU on every task and serves no one:
   log lines shipped to the API, a CA bundle parsed for a plain-HTTP client, the server's event table and
   automations (:func:`loopback_client_settings`, :data:`LOOPBACK_SERVER_ENV`), and on any server the settings
   revalidated by each Dask task (:func:`settings_shipped_whole`).  ``python -m flows.bench.overhead`` measures it.
"""
from __future__ import annotations

import contextlib
import functools
import json
import logging
import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable, Iterator

from tasks.core.processes import process_started, same_process

STOP_DEADLINE_S = 10.0  # the stopping process exits after this many seconds whatever its cleanup is doing
SERVER_GRACE_S = 5.0  # an orphaned server gets this long to close its database after SIGTERM, then SIGKILL
EXIT_CODES = {signal.SIGINT: 130, signal.SIGTERM: 143}  # 128 + signal number, as a shell reports them
SIGNAL_NAMES = {signal.SIGINT: "Ctrl-C", signal.SIGTERM: "SIGTERM"}
_SERVER_APP = "prefect.server.api.server:create_app"  # the uvicorn factory every Prefect server runs


# ------------------------------------------------------------------------------------------------ Prefect's home
def follow_artifacts(artifacts: str | Path, user_set: frozenset[str], reports: str | Path | None = None) -> Path:
    """Point ``PREFECT_HOME`` and the cache records (``PREFECT_RESULTS_LOCAL_STORAGE_PATH``) at
    ``<artifacts>/.prefect`` (``<reports>/.prefect`` when ``reports`` is given and ``artifacts`` is a read-only
    cache, :func:`flows.preflight_env.writable_root`), except those in ``user_set`` (set by the user), and create
    the home.  Returns the home in effect.

    Only before Prefect is imported (it reads its settings once): afterwards the home in effect is kept."""
    from flows.preflight_env import check_prefect_paths, writable_root

    check_prefect_paths(artifacts, reports, user_set)  # one line, before the home is made (Prefect would fail later)
    home = (writable_root(artifacts, reports) if reports is not None else Path(artifacts)).resolve() / ".prefect"
    if "prefect" not in sys.modules:
        wanted = {"PREFECT_HOME": home, "PREFECT_RESULTS_LOCAL_STORAGE_PATH": home / "results"}
        for key, value in wanted.items():
            if key not in user_set:
                os.environ[key] = str(value)
    home = Path(os.environ["PREFECT_HOME"])
    home.mkdir(parents=True, exist_ok=True)  # Prefect creates its home without parents
    return home


def begin_run(artifacts: str | Path, reports: str | Path | None = None) -> None:
    """What every Hydra main does first: Prefect's home under ``artifacts`` (under ``reports``, when given, for a
    read-only cache), the stop handlers, and the end of any temporary Prefect server a killed run left behind (one
    line each)."""
    from flows import USER_PREFECT_PATHS

    home = follow_artifacts(artifacts, USER_PREFECT_PATHS, reports)
    install_stop_handlers()
    for line in end_orphaned_servers(home):
        print(line, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------------- stopping
_progress: list[Any] = []  # the run's table (flows.runtime.RunTable): its rows say which steps finished
_stopping = threading.Event()
_handlers_installed = threading.Event()  # by begin_run: this process is a flow main
_at_stop: list[tuple[Callable[..., Any], tuple]] = []  # cleanups an os._exit would skip (atexit does not run)


def watch_progress(table: Any) -> None:
    """Count the steps of ``table`` (rows with ``status``, and ``total``) in the stop line.

    Called from the flow body (the run's table is made there), where Prefect's flow engine has put its own
    SIGTERM handler in place (it reports the run as crashed through the API and shuts the task runner down
    gracefully: seconds to minutes, and a page of log lines): the stop handlers are put back."""
    _progress[:] = [table]
    if _handlers_installed.is_set():
        install_stop_handlers()


def progress_table() -> Any:
    """The run's table (:func:`watch_progress`), or None before the first."""
    return _progress[0] if _progress else None


_report: list[Path] = []  # the report folder being written (flows.report_marker)


def report_writing(folder: Path | None) -> None:
    """The report folder being written now (None: none); a stop line names it as incomplete."""
    _report[:] = [folder] if folder is not None else []


def remove_at_exit(path: Path) -> None:
    """Remove the folder ``path`` when the process exits, normally or stopped by a signal."""
    import atexit
    import shutil

    atexit.register(shutil.rmtree, path, True)
    _at_stop.append((shutil.rmtree, (path, True)))


def stop_line(signum: int) -> str:
    """The one line a stopped run prints."""
    how = f"stopped by {SIGNAL_NAMES.get(signum, signal.Signals(signum).name)}"
    rest = "the rest will run on the next start (same command)"
    if _report:
        rest += f"; report incomplete: {_report[0]} (REPORT_INCOMPLETE.txt), the next start rewrites it"
    if not _progress or not _progress[0].total:  # before the flow, or a run without a table (flows.export)
        return f"{how}: the steps that finished are kept, {rest}"
    table = _progress[0]
    kept = sum(r.status in ("ran", "cached") for r in table.rows)
    return f"{how}: {kept} of {table.total} steps finished and kept, {rest}"


def install_stop_handlers() -> None:
    """SIGINT and SIGTERM stop the run promptly, once (:func:`stop`).  Main thread only (Python's rule)."""
    if threading.current_thread() is threading.main_thread():
        for signum in EXIT_CODES:
            signal.signal(signum, _on_signal)
        _handlers_installed.set()


def _on_signal(signum: int, _frame: Any) -> None:
    stop(signum)


def stop(signum: int) -> None:
    """End the children (Dask workers, the temporary server), print the stop line and exit ``128 + signum``.

    Never returns.  Runs in the main thread, where Python delivers signals; the Prefect API is not called again
    (the steps' states are not reported: the artifacts on disk are the record)."""
    code = EXIT_CODES.get(signum, 128 + signum)
    if _stopping.is_set():  # a second signal while stopping: the first one's cleanup goes on
        return
    _stopping.set()
    for other in EXIT_CODES:
        signal.signal(other, signal.SIG_IGN)
    threading.Timer(STOP_DEADLINE_S, os._exit, (code,)).start()  # whatever hangs below, the process ends
    logging.disable(logging.CRITICAL)
    line = stop_line(signum)
    err = _silence_output()  # threads still running (Prefect's log shipping, Dask) print nothing from now on
    import psutil

    children = _children()
    for child in children:  # Dask workers mid-step (their half-written artifacts are temporary folders), server
        with contextlib.suppress(psutil.Error):
            child.kill()
    psutil.wait_procs(children, timeout=STOP_DEADLINE_S / 2)
    _write_line(line, err)  # the last line: the workers, which share the run's output, are gone
    _forget_server_record()
    # multiprocessing's exit-time cleanup, which os._exit skips: it unlinks the named semaphores of the Dask
    # cluster's queues.  Then its resource tracker goes too: it would print a warning for each semaphore it
    # still knows of (those the killed workers registered and had already unlinked)
    import multiprocessing.util

    with contextlib.suppress(Exception):
        multiprocessing.util._run_finalizers(0)
    for child in psutil.Process().children(recursive=True):
        with contextlib.suppress(psutil.Error):
            child.kill()
    for fn, args in _at_stop:
        with contextlib.suppress(Exception):
            fn(*args)
    os._exit(code)


def _write_line(line: str, fd: int) -> None:
    with contextlib.suppress(OSError):
        os.write(fd, (line + "\n").encode())


def _silence_output() -> int:
    """Point this process's stdout and stderr at the null device; returns a descriptor of the former stderr."""
    err = 2
    with contextlib.suppress(OSError):
        err = os.dup(2)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
    return err


def _children() -> list:
    """This process's descendants, except multiprocessing's resource tracker (it must outlive the processes it
    watches: :func:`stop` ends it last)."""
    import psutil

    return [p for p in psutil.Process().children(recursive=True)
            if not any("resource_tracker" in a for a in _cmdline(p))]


def _cmdline(proc) -> list[str]:
    try:
        return proc.cmdline()
    except Exception:  # noqa: BLE001 - gone, or not ours to read
        return []


def _end_process(pid: int, grace: float = SERVER_GRACE_S) -> None:
    """SIGTERM, then SIGKILL after ``grace`` seconds; returns when the process is gone."""
    import psutil

    try:
        proc = psutil.Process(pid)
        proc.terminate()
        proc.wait(grace)
    except psutil.TimeoutExpired:
        with contextlib.suppress(psutil.Error):
            proc.kill()
            proc.wait(grace)
    except psutil.Error:
        pass


# ------------------------------------------------------------------------------------------- temporary server
_SERVER: dict[str, Path] = {}  # the record file of the server this process started ("record")
# The temporary server's services that only feed what nobody uses in a run's private server: the event table
# (the UI's event feed; task runs are still recorded from the events) and automations (triggers and actions,
# which evaluate every event).  Less CPU on the two cores the run shares with the server; the user's own values win.
LOOPBACK_SERVER_ENV = {"PREFECT_SERVER_SERVICES_EVENT_PERSISTER_ENABLED": "false",
                       "PREFECT_SERVER_SERVICES_TRIGGERS_ENABLED": "false",
                       "PREFECT_SERVER_EVENTS_STREAM_OUT_ENABLED": "false"}


def _die_with_parent() -> Callable[[], None] | None:
    """A ``preexec_fn`` that asks the kernel to kill the child when its parent thread dies
    (Linux ``prctl(PR_SET_PDEATHSIG)``; the parent must stay alive - it is the main thread), or None elsewhere."""
    if not sys.platform.startswith("linux") or threading.current_thread() is not threading.main_thread():
        return None
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl  # looked up here: the child only calls it
    parent = os.getpid()
    pr_set_pdeathsig = 1

    def preexec() -> None:
        prctl(pr_set_pdeathsig, signal.SIGKILL)
        if os.getppid() != parent:  # the parent died before the call: nobody would send the signal
            os.kill(os.getpid(), signal.SIGKILL)

    return preexec


@functools.cache
def _server_class():
    """Prefect's temporary server, started in its own session and dying with the flow process.

    Prefect builds the server's command and environment inline in ``SubprocessASGIServer._run_uvicorn_command``
    and gives no way to pass options to its ``subprocess.Popen``; this subclass passes them (and
    :data:`LOOPBACK_SERVER_ENV`) by giving that module a ``subprocess`` whose ``Popen`` has them, for the duration
    of that one call.  Pinned by ``tests/flows/test_lifecycle.py`` (the server's session, and its end when the flow
    process is SIGKILLed)."""
    import subprocess
    import types

    import prefect.server.api.server as prefect_server
    from prefect.settings import PREFECT_HOME

    class TemporaryServer(prefect_server.SubprocessASGIServer):
        def _run_uvicorn_command(self):
            options: dict[str, Any] = {"start_new_session": True}
            preexec = _die_with_parent()
            if preexec is not None:
                options["preexec_fn"] = preexec
            shim = types.SimpleNamespace(**vars(subprocess))
            shim.Popen = lambda *args, env, **kw: subprocess.Popen(*args, env={**LOOPBACK_SERVER_ENV, **env}, **kw,
                                                                    **options)
            prefect_server.subprocess = shim
            try:
                process = super()._run_uvicorn_command()
            finally:
                prefect_server.subprocess = subprocess
            _record_server(Path(PREFECT_HOME.value()), process.pid, self.api_url)  # before its start-up
            return process

    return TemporaryServer


@contextlib.contextmanager
def temporary_server() -> Iterator[str | None]:
    """Within: the Prefect API of this run.  ``PREFECT_API_URL`` when set (a long-lived server: nothing is
    started), else this process's temporary server, started on first use (kept for the next run of a Hydra
    multirun, stopped at exit) and given to Prefect's settings and the environment of the processes the run
    starts (Dask workers).  Enter it inside :func:`flows.runtime.result_storage_settings` (the server's
    database)."""
    from prefect.settings import PREFECT_API_URL, PREFECT_HOME, PREFECT_UI_URL, temporary_settings

    if PREFECT_API_URL.value():
        with settings_shipped_whole():
            yield PREFECT_API_URL.value()
        return
    Path(PREFECT_HOME.value()).mkdir(parents=True, exist_ok=True)
    server = _server_class()()
    if not server.running:
        import atexit

        atexit.register(_forget_server_record)  # registered first: runs after Prefect's own stop of the server
        server.start()
    previous = os.environ.get("PREFECT_API_URL")
    os.environ["PREFECT_API_URL"] = server.api_url
    try:
        # no UI URL: the temporary server serves no UI (Prefect would print a dead "View at" link)
        with temporary_settings(updates={PREFECT_API_URL: server.api_url, PREFECT_UI_URL: "",
                                         **loopback_client_settings(Path(PREFECT_HOME.value()))}), \
                settings_shipped_whole():
            yield server.api_url
    finally:
        if previous is None:
            os.environ.pop("PREFECT_API_URL", None)
        else:
            os.environ["PREFECT_API_URL"] = previous


@functools.cache
def _shipped_settings_context():
    """A Prefect ``SettingsContext`` that a task runner ships to its workers as the settings object itself.

    Prefect sends each task to a Dask worker with the flow's settings as a plain dict (paths as strings), and
    the worker validates that dict into a new ``Settings`` with every task: ~50 nested pydantic-settings models,
    each re-reading the environment and the settings files, ~80 ms CPU per task on the 2-core machine.  Prefect
    never changes a ``Settings`` object (``temporary_settings`` makes a new one), it pickles as it is, and
    validated from an instance it is taken as it is (~0.2 ms).  Pinned by
    ``tests/flows/test_lifecycle.py`` (what a worker receives).  The workers run on this machine, or on a cluster
    (``runner.address``) with the same installation: the paths in the settings mean the same there."""
    from prefect.context import SettingsContext

    class ShippedSettingsContext(SettingsContext):
        def serialize(self, include_secrets: bool = True) -> dict[str, Any]:
            if not include_secrets:  # for display: Prefect's own (masked) dump
                return super().serialize(include_secrets=False)
            return {"profile": self.profile, "settings": self.settings}

    return ShippedSettingsContext


@contextlib.contextmanager
def settings_shipped_whole() -> Iterator[None]:
    """Within: the current Prefect settings, shipped whole to the task runner's workers
    (:func:`_shipped_settings_context`)."""
    from prefect.context import SettingsContext

    current = SettingsContext.get()
    with _shipped_settings_context()(profile=current.profile, settings=current.settings):
        yield


def loopback_client_settings(home: Path) -> dict:
    """Prefect client settings for a run on its temporary server (plain HTTP on 127.0.0.1, no UI); the tasks on
    the Dask workers receive them with each task's settings context.  Each spares CPU time on every task:

    * ``PREFECT_LOGGING_TO_API_ENABLED`` off: log lines go to the console only (the run's record is its console
      output, report and artifacts; nobody reads the temporary server's log table), not also one API call per
      batch and one database row per line;
    * ``PREFECT_API_SSL_CERT_FILE`` a file of one CA certificate: no certificate is ever checked on plain HTTP,
      yet Prefect builds an SSL context for each client it makes (two per task on a Dask worker), parsing the whole
      CA bundle each time (~30 ms CPU); one certificate takes ~1 ms.  The user's own ``PREFECT_API_SSL_CERT_FILE``
      is kept."""
    import re

    import certifi  # Prefect's own CA bundle (its default)
    from prefect.settings import PREFECT_API_SSL_CERT_FILE, PREFECT_LOGGING_TO_API_ENABLED

    updates: dict[Any, Any] = {PREFECT_LOGGING_TO_API_ENABLED: False}
    bundle = PREFECT_API_SSL_CERT_FILE.value() or certifi.where()
    if "PREFECT_API_SSL_CERT_FILE" not in os.environ:
        try:
            first = re.search(r"-----BEGIN CERTIFICATE-----.+?-----END CERTIFICATE-----\n?", Path(bundle).read_text(),
                              re.S)
        except OSError:
            first = None
        if first is not None:
            one = home / "loopback-ca.pem"
            if not one.is_file() or one.read_text() != first.group(0):
                tmp = one.with_name(f".{one.name}.{os.getpid()}")
                tmp.write_text(first.group(0))
                tmp.replace(one)
            updates[PREFECT_API_SSL_CERT_FILE] = str(one)
    return updates


# ------------------------------------------------------------------------------------------- server records
def _record_server(home: Path, server_pid: int, api_url: str) -> None:
    """``<home>/servers/<flow pid>.json``: who started which server, when (written whole, then renamed)."""
    folder = home / "servers"
    folder.mkdir(parents=True, exist_ok=True)
    me = os.getpid()
    record = {"server_pid": server_pid, "server_started": process_started(server_pid), "flow_pid": me,
              "flow_started": process_started(me), "flow_command": " ".join(sys.argv), "api_url": api_url}
    path = folder / f"{me}.json"
    tmp = folder / f".{me}.json.tmp"
    tmp.write_text(json.dumps(record))
    tmp.replace(path)
    _SERVER["record"] = path


def _forget_server_record() -> None:
    path = _SERVER.pop("record", None)
    if path is not None:
        with contextlib.suppress(OSError):
            path.unlink()


def is_prefect_server(cmdline: list[str]) -> bool:
    """A Prefect server process: uvicorn running Prefect's app factory."""
    return any("uvicorn" in a for a in cmdline) and _SERVER_APP in cmdline


def end_orphaned_servers(home: Path) -> list[str]:
    """End the temporary Prefect servers of ``home`` whose flow process is gone; one line for each.

    A server is orphaned when its record in ``<home>/servers/`` names a flow process that no longer runs (the
    record goes too), or, unrecorded (a Dask worker's server, a run of an older version), when it is a
    temporary server (``PREFECT__SERVER_EPHEMERAL``) of this ``PREFECT_HOME`` adopted by pid 1."""
    import psutil

    home = Path(home).resolve()
    lines: list[str] = []
    ended: set[int] = set()
    for path in sorted((home / "servers").glob("*.json")):
        try:
            rec = json.loads(path.read_text())
            flow_pid, server_pid = int(rec["flow_pid"]), int(rec["server_pid"])
        except (OSError, ValueError, KeyError, TypeError):
            path.unlink(missing_ok=True)  # unreadable: nothing to act on
            continue
        if same_process(flow_pid, rec.get("flow_started")):
            continue  # a run in progress
        if same_process(server_pid, rec.get("server_started")):
            with contextlib.suppress(psutil.Error):
                proc = psutil.Process(server_pid)
                if is_prefect_server(proc.cmdline()):
                    lines.append(_end_orphan(proc, f"flow pid {flow_pid}, {rec.get('flow_command', '?')}"))
                    ended.add(server_pid)
        path.unlink(missing_ok=True)
    for proc in psutil.process_iter(["pid", "ppid", "cmdline"]):
        if proc.info["ppid"] != 1 or proc.pid in ended or not is_prefect_server(proc.info["cmdline"] or []):
            continue
        try:
            env = proc.environ()
        except psutil.Error:
            continue
        if env.get("PREFECT__SERVER_EPHEMERAL") == "1" and env.get("PREFECT_HOME") and \
                Path(env["PREFECT_HOME"]).resolve() == home:
            lines.append(_end_orphan(proc, "its flow process is gone"))
    return lines


def _end_orphan(proc, whose: str) -> str:
    import psutil

    try:
        mb = proc.memory_info().rss / 2**20
        since = time.strftime("%Y-%m-%d %H:%M", time.localtime(proc.create_time()))
    except psutil.Error:
        mb, since = 0.0, "?"
    _end_process(proc.pid)
    return (f"ended a Prefect server left running by a killed run (server pid {proc.pid}, {mb:.0f} MB, running "
            f"since {since}; {whose})")
