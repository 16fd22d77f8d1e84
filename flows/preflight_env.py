"""Pre-flight checks of the folders and the environment a run writes into (issue 49), before Hydra makes its output
folder, before Prefect's home is created and before any server starts.  Each finding is one line (``SystemExit``)
naming the key or variable and the fix:

* ``paths.artifacts``, ``paths.reports`` (and Hydra's own ``hydra.run.dir`` / ``hydra.sweep.dir``, under
  ``paths.reports`` by default) are folders this process can write into: a regular file given as a folder, a path
  through a file, a read-only file system or a folder without write permission is refused (:func:`check_folders`,
  also run by the Hydra callback :class:`flows.hydra_checks.PreflightCallback` before Hydra creates its folder);
  except, for the mains that can be served from one (``flows.evaluate``, ``flows.squeeze``, ``flows.export``), an
  artifacts folder that exists and cannot be written (a lab's cache shared read-only, :func:`read_only_cache`): a
  run is then served from it when every step is cached there, refused otherwise
  (:func:`flows.pipeline.shared_cache_grid`), and writes nothing into it - Prefect's home, the caches below and new
  report media go under ``paths.reports`` (:func:`writable_root`);
* ``PREFECT_HOME`` and ``PREFECT_RESULTS_LOCAL_STORAGE_PATH`` when the user set them (a main then leaves them as
  they are, :data:`flows.USER_PREFECT_PATHS`): a folder this process can write into, and not inside a read-only
  cache (:func:`check_prefect_paths`; Prefect would fail creating its home or database after the run started);
* the reports' file system has room for the run's report (its videos and figures, also embedded in
  ``index.html``: :func:`flows.preflight.report_bytes_per_scene` x scenes), and the artifacts' for the run's
  estimated artifacts (with the report when both are on one file system), less what the artifacts folder already
  holds (:func:`check_free_space`; not for a read-only cache, which receives nothing);
* Warp's kernel cache and matplotlib's cache: when their default folders under ``HOME`` cannot be written (a
  read-only home), they are put under ``<writable root>/.cache`` (``WARP_CACHE_PATH``, ``MPLCONFIGDIR``, given to
  every process the run starts; the writable root is ``paths.artifacts``, or ``paths.reports`` for a read-only
  cache) with one line; a variable the user set to an unwritable folder is refused (:func:`redirect_caches`);
* ``PREFECT_API_URL``, when set, answers at ``/health`` (:func:`check_prefect_api`): a stale address is refused
  instead of a page of connection tracebacks after the flow started.
"""
from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig

if TYPE_CHECKING:
    from flows.preflight import WorkEstimate

_PROBE_TIMEOUT_S = 5.0  # s, for PREFECT_API_URL's /health


def unwritable(path: str | Path) -> str:
    """Why ``path`` cannot be (made and) written as a folder ("" when it can): a file at or above it, or the first
    existing folder above it refusing a new file (permissions, read-only file system).  Writes and removes one
    empty probe file; creates nothing else."""
    p = Path(path).expanduser().absolute()
    if p.exists() and not p.is_dir():
        return f"{p} is a file, not a folder"
    existing = p
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        return f"{existing} is a file, so {p} cannot be a folder"
    try:
        fd, name = tempfile.mkstemp(dir=existing, prefix=".virsqueezer-write-probe-")
    except OSError as exc:
        return f"{existing} is not writable ({exc.strerror or type(exc).__name__})"
    os.close(fd)
    os.unlink(name)
    return ""


def read_only_cache(artifacts: str | Path) -> str:
    """Why the artifacts folder ``artifacts`` is a read-only cache ("" when it is not): it exists as a folder and
    cannot be written (a read-only mount, no write permission).  A run uses it as a shared cache: every step must be
    cached there, and nothing is written into it."""
    p = Path(artifacts).expanduser().absolute()
    return unwritable(p) if p.is_dir() else ""


def writable_root(artifacts: str | Path, reports: str | Path) -> Path:
    """The folder that receives what a run writes besides its artifacts (Prefect's home ``.prefect``, the caches
    ``.cache``, new report media ``.media``): ``artifacts``, or ``reports`` when ``artifacts`` is a read-only cache
    (:func:`read_only_cache`)."""
    root = reports if read_only_cache(artifacts) else artifacts
    return Path(root).expanduser().absolute()


def check_folders(cfg: DictConfig, hydra_dirs: dict[str, str] | None = None, read_only_ok: bool = False) -> None:
    """``paths.artifacts``, ``paths.reports`` and ``hydra_dirs`` ({key: folder}) writable, or one line; with
    ``read_only_ok`` (a main that can be served from a read-only cache) an existing artifacts folder that cannot be
    written passes (:func:`read_only_cache`); then the Prefect paths the user set (:func:`check_prefect_paths`)."""
    from flows import USER_PREFECT_PATHS

    for key, folder in (("paths.artifacts", cfg.paths.artifacts), ("paths.reports", cfg.paths.reports),
                        *(hydra_dirs or {}).items()):
        why = unwritable(folder)
        if why and not (read_only_ok and key == "paths.artifacts" and Path(folder).expanduser().is_dir()):
            raise SystemExit(f"config error: {key}={folder}: {why}: give a folder you can write to "
                             f"({key}=/path/to/folder)")
    check_prefect_paths(cfg.paths.artifacts, cfg.paths.reports, USER_PREFECT_PATHS)


def _unwritable_variable(var: str) -> str:
    """The one line for an environment variable ``var`` naming a folder that cannot be written ("" when it can)."""
    why = unwritable(os.environ[var])
    return (f"environment error: {var}={os.environ[var]}: {why}: point {var} at a folder you can write to, or unset "
            f"it") if why else ""


def check_prefect_paths(artifacts: str | Path, reports: str | Path | None, user_set: frozenset[str]) -> None:
    """The Prefect paths the user set (``user_set``, :data:`flows.USER_PREFECT_PATHS`: a main leaves them as they
    are) are writable folders, or one line: inside a read-only artifacts cache (:func:`read_only_cache`), the line
    says to unset the variable (the main then puts it under ``paths.reports``) or to point it there."""
    why_cache = read_only_cache(artifacts) if reports is not None else ""
    cache = Path(artifacts).expanduser().absolute()
    for var in sorted(user_set):
        value = Path(os.environ[var]).expanduser().absolute()
        if why_cache and (value == cache or cache in value.parents):
            under = Path(str(reports)).expanduser().absolute() / ".prefect"
            under = under / "results" if var == "PREFECT_RESULTS_LOCAL_STORAGE_PATH" else under
            raise SystemExit(f"environment error: {var}={os.environ[var]} is inside paths.artifacts={artifacts}, a "
                             f"read-only cache ({why_cache}) that receives nothing: unset {var} (the run then puts "
                             f"it under paths.reports) or point it under paths.reports ({var}={under})")
        line = _unwritable_variable(var)
        if line:
            raise SystemExit(line)


def _file_system(folder: str | Path) -> tuple[int, int]:
    """Free bytes and device of the file system ``folder`` is on (or would be made on: its first existing parent)."""
    existing = Path(folder).expanduser().absolute()
    while not existing.exists():
        existing = existing.parent
    return shutil.disk_usage(existing).free, existing.stat().st_dev


def check_free_space(cfg: DictConfig, est: WorkEstimate) -> None:
    """Refuse a run whose report (``est.report_bytes``, :func:`flows.preflight.report_bytes_per_scene`) does not fit
    into the free space of the reports' file system, or whose estimated artifacts (``est.total_bytes``, and the
    report when it is on the same file system) do not fit into that of the artifacts plus what the artifacts folder
    already holds (a cached run needs little)."""
    from flows.preflight_settings import human_bytes

    free, device = _file_system(cfg.paths.reports)
    if free < est.report_bytes:
        raise SystemExit(f"config error: paths.reports={cfg.paths.reports}: the run's report needs up to "
                         f"{human_bytes(est.report_bytes)} (the videos and figures of {est.scenes} "
                         f"scene{'s' if est.scenes != 1 else ''}, also embedded in index.html) and its file system has "
                         f"{human_bytes(free)} free: free some space or give a folder on a larger disk "
                         f"(paths.reports=/path/to/folder)")
    if read_only_cache(cfg.paths.artifacts):
        return
    free, artifacts_device = _file_system(cfg.paths.artifacts)
    shared = est.report_bytes if artifacts_device == device else 0.0  # one disk for both
    need = est.total_bytes + shared
    if free >= need:
        return
    root = Path(cfg.paths.artifacts).expanduser().absolute()
    held = sum(f.stat().st_size for f in root.rglob("*") if f.is_file()) if root.is_dir() else 0
    if free + held < need:
        report = f", and the report's {human_bytes(shared)} on the same file system" if shared else ""
        raise SystemExit(f"config error: paths.artifacts={cfg.paths.artifacts}: the run's artifacts need up to "
                         f"{human_bytes(need)} (rollouts and g-buffers of the work estimate{report}) and its file "
                         f"system has {human_bytes(free)} free: free some space or give a folder on a larger disk "
                         f"(paths.artifacts=/path/to/folder)")


def redirect_caches(cfg: DictConfig) -> list[str]:
    """Warp's and matplotlib's caches under a writable folder (module docstring); returns the lines to print."""
    home = Path.home()
    defaults = {"WARP_CACHE_PATH": (Path(os.environ.get("XDG_CACHE_HOME") or home / ".cache") / "warp",
                                    "Warp's kernel cache", "warp"),
                "MPLCONFIGDIR": (Path(os.environ.get("XDG_CONFIG_HOME") or home / ".config") / "matplotlib",
                                 "matplotlib's cache", "matplotlib")}
    lines = []
    for var, (default, what, sub) in defaults.items():
        if var in os.environ:
            line = _unwritable_variable(var)
            if line:
                raise SystemExit(line)
            continue
        why = unwritable(default)
        if why:
            target = writable_root(cfg.paths.artifacts, cfg.paths.reports) / ".cache" / sub
            os.environ[var] = str(target)
            lines.append(f"{what} goes to {target} ({var}): its default {default} cannot be written ({why})")
    return lines


def check_prefect_api() -> None:
    """``PREFECT_API_URL`` (when set) answers at ``/health``, or one line."""
    import urllib.error
    import urllib.request

    url = os.environ.get("PREFECT_API_URL")
    if not url:
        return
    try:
        with urllib.request.urlopen(url.rstrip("/") + "/health", timeout=_PROBE_TIMEOUT_S) as resp:
            resp.read()
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "reason", None) or exc
        why = getattr(reason, "strerror", None) or str(reason) or type(exc).__name__
        raise SystemExit(f"environment error: PREFECT_API_URL={url} does not answer ({why}): start that server "
                         "(prefect server start) or unset PREFECT_API_URL (each run then starts its own temporary "
                         "server)") from None


def check_environment(cfg: DictConfig, est: WorkEstimate, read_only_ok: bool = False) -> None:
    """Everything above, in order (``read_only_ok``: :func:`check_folders`; ``est``: the run's work estimate, for
    :func:`check_free_space`); prints the caches' lines (and the read-only cache's)."""
    check_folders(cfg, read_only_ok=read_only_ok)
    why = read_only_cache(cfg.paths.artifacts)
    if why:
        print(f"paths.artifacts={cfg.paths.artifacts} is a read-only cache ({why}): the run is served from it if "
              f"every step is cached there and writes nothing into it; Prefect's home, caches and new report media "
              f"go under paths.reports={cfg.paths.reports}", flush=True)
    check_free_space(cfg, est)
    for line in redirect_caches(cfg):
        print(line, flush=True)
    check_prefect_api()
