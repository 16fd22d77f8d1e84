"""What every flow shares: task runner from config, result storage, the per-task status table."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import pandas as pd
from omegaconf import DictConfig
from prefect.logging import get_logger
from prefect.task_runners import ThreadPoolTaskRunner

from flows.lifecycle import remove_at_exit, watch_progress
from tasks.core.artifacts import ArtifactError, ArtifactRef, directory_size, read_group_attrs

log = get_logger("virsqueezer")


def make_task_runner(runner: DictConfig):
    """Task runner chosen by ``runner.kind``: sequential | threads | dask (local cluster or ``address``)."""
    kind = runner.kind
    if kind == "sequential":
        return ThreadPoolTaskRunner(max_workers=1)
    if kind == "threads":
        return ThreadPoolTaskRunner(max_workers=int(runner.max_workers))
    if kind == "dask":
        try:
            from prefect_dask import DaskTaskRunner
        except ImportError as exc:  # optional extra
            raise SystemExit("runner=dask needs the dask extra: pip install -e '.[dask]'") from exc
        if runner.address:
            return DaskTaskRunner(address=runner.address)
        keep_glibc_malloc_thresholds()
        import dask

        dask.config.set(LOCAL_SCHEDULER_CONFIG)
        return DaskTaskRunner(
            cluster_kwargs={
                "n_workers": dask_workers(runner),
                "threads_per_worker": int(runner.threads_per_worker),
                "processes": True,
                "dashboard_address": None,
            }
        )
    raise SystemExit(f"runner.kind={kind!r} is unknown: use sequential, threads or dask")


# How our local Dask scheduler orders the grid's steps (flows.pipeline.object_priorities gives the priorities).
# * No root-task queueing (worker-saturation inf): with Dask's default (1.1) a step without inputs (each object's
#   object_model, the head of its set-up) waits in the scheduler's queue until a worker holds fewer than two
#   tasks, while every step with inputs is handed to a worker as soon as it is ready; on the grid the workers are
#   never that empty, so the last objects' set-up ran one small step per finished rollout (measured: tomato's nine
#   set-up steps spread over 28 s, each worker idle for up to 60 % of a 10-s window).
# * Expected seconds of the long steps on the default grid (before the first of a kind finishes Dask assumes
#   0.5 s): the workers' queues are balanced by duration rather than count (without them, the measured rollouts
#   started out of priority order; with them, largest object first).
# Neither changes the CPU work: the main job keeps both cores busy either way (docs/results/benchmarks.md,
# "Scheduling the grid").
LOCAL_SCHEDULER_CONFIG = {
    "distributed.scheduler.worker-saturation": float("inf"),
    "distributed.scheduler.default-task-durations": {
        "mpm_rollout": "30s", "force_matched_rollout": "30s", "display_video": "5s", "gbuffer": "1.5s",
        "video_metrics": "1.5s", "appearance_refinement": "1.5s", "effect": "1s",
    },
}


MALLOC_TRIM_KEY = "distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_"


def keep_glibc_malloc_thresholds() -> None:
    """Spawn our local Dask workers without Dask's default ``MALLOC_TRIM_THRESHOLD_=65536`` (bytes).

    Setting that variable turns off glibc's dynamic mmap threshold, so every NumPy temporary of 128 KiB or more
    is mmap'ed and unmapped again: page faults and system CPU in every step. Dask's documented way to unset a
    pre-spawn variable is a ``None`` config value. A value the user chose (in the shell's environment or in a
    Dask config other than the built-in default) is left as it is.
    """
    import dask
    import distributed  # noqa: F401  (loads distributed.yaml, the built-in default)

    if "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return
    default = dask.config.get(MALLOC_TRIM_KEY, default=None, config=dask.config.merge(*dask.config.defaults))
    if dask.config.get(MALLOC_TRIM_KEY, default=None) == default:
        dask.config.set({MALLOC_TRIM_KEY: None})


def dask_workers(runner: DictConfig) -> int:
    """Worker processes of the local Dask cluster: ``runner.n_workers``, or one per core."""
    return int(runner.n_workers) if runner.n_workers else max(1, os.cpu_count() or 1)


def runner_workers(runner: DictConfig) -> int:
    """How many tasks the runner executes at once (for the parallel efficiency)."""
    if runner.kind == "threads":
        return int(runner.max_workers)
    if runner.kind == "dask":
        return dask_workers(runner) * int(runner.threads_per_worker)
    return 1


def result_storage_settings(artifacts_root: str | Path):
    """A settings context in which Prefect keeps its cache records (JSON) next to the artifacts, and in
    which the temporary Prefect server of this process gets a database no other running flow uses
    (:func:`prefect_database_settings`)."""
    from prefect.settings import PREFECT_RESULTS_LOCAL_STORAGE_PATH, temporary_settings

    path = Path(artifacts_root).resolve() / ".prefect" / "results"
    path.mkdir(parents=True, exist_ok=True)
    return temporary_settings(updates={PREFECT_RESULTS_LOCAL_STORAGE_PATH: str(path), **prefect_database_settings()})


# ----------------------------------------------------------------------------------------------- Prefect database
# Without PREFECT_API_URL every flow process starts its own temporary Prefect server, and every such server
# opens the SQLite database under PREFECT_HOME.  Two runs started at once on one artifacts folder then race:
# both servers migrate the same fresh database (one dies with alembic's "expected to match one row ... 0 found"
# and is restarted after a lost start-up), and both write run states into one SQLite file ("database is
# locked").  The database holds only run history - cache records are JSON files in result storage and the
# data are the zarr artifacts - so the first process claims the shared database with an OS file lock held
# until it exits (released by the OS on any exit, kill -9 included), and a process that finds it claimed
# keeps its run history in a private database in a temporary folder, deleted at exit.
_DATABASE_CHOICE: dict | None = None
_HELD_LOCKS: list = []  # the claim lives as long as the process


def prefect_database_settings() -> dict:
    """Prefect settings updates that give this process's temporary server a database of its own.

    Empty when ``PREFECT_API_URL`` names a running server (it serialises its own database), when the database
    is not a SQLite file, or when this process holds the claim on the shared database.  Decided once per process
    (a Hydra multirun reuses the temporary server of its first job)."""
    global _DATABASE_CHOICE
    from prefect.settings import PREFECT_API_DATABASE_CONNECTION_URL, PREFECT_API_URL

    if PREFECT_API_URL.value():
        return {}
    if _DATABASE_CHOICE is None:
        _DATABASE_CHOICE = claim_prefect_database(PREFECT_API_DATABASE_CONNECTION_URL.value())
    return dict(_DATABASE_CHOICE)


def claim_prefect_database(connection_url: str | None) -> dict:
    """Claim the SQLite database at ``connection_url`` for this process (non-blocking file lock next to it).

    Returns ``{}`` when claimed (or not a SQLite file), else the settings of a private database and memo store
    in a new temporary folder that is removed when the process exits."""
    import tempfile

    from filelock import FileLock, Timeout
    from prefect.settings import (
        PREFECT_API_DATABASE_CONNECTION_URL,
        PREFECT_MEMO_STORE_PATH,
    )

    prefix = "sqlite+aiosqlite:///"
    url = str(connection_url or "")
    if not url.startswith(prefix) or ":memory:" in url:
        return {}
    db = Path(url[len(prefix):])
    db.parent.mkdir(parents=True, exist_ok=True)
    lock = FileLock(f"{db}.lock")
    try:
        lock.acquire(timeout=0)
    except Timeout:
        private = Path(tempfile.mkdtemp(prefix="virsqueezer-prefect-"))
        remove_at_exit(private)  # registered before the server's own stop: runs after it
        log.info("another flow run is using the Prefect database %s: this run keeps its run history in a "
                 "private database in %s (removed at exit); artifacts and cache records are shared as usual",
                 db, private)
        return {PREFECT_API_DATABASE_CONNECTION_URL: f"{prefix}{private / 'prefect.db'}",
                PREFECT_MEMO_STORE_PATH: str(private / "memo_store.toml")}
    _HELD_LOCKS.append(lock)
    return {}


def artifact_warning(path: str | Path) -> str:
    """The ``warning`` attribute a step stored on its artifact (e.g. "nothing was squeezed: ..."), or ""."""
    try:
        return str(read_group_attrs(path).get("attrs", {}).get("warning") or "")
    except ArtifactError:
        return ""


@dataclass
class TaskRow:
    object: str
    step: str
    status: str  # ran | cached | skipped | failed
    wall_seconds: float
    artifact_bytes: int
    artifact: str
    note: str = ""
    variant: str = ""  # "" for the steps every variant shares
    warning: str = ""  # the artifact's own ``warning`` attribute (e.g. nothing was squeezed, and the likely cause)


@dataclass
class RunTable:
    """Collects one row per (object, step) as the flow resolves its futures."""

    rows: list[TaskRow] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)
    total: int = 0  # tasks expected (for the progress line); 0 = unknown

    def __post_init__(self) -> None:
        watch_progress(self)  # a stopped run's line counts the steps finished (flows.lifecycle)

    def add_future(self, obj: str, step: str, future, *, root: str | Path, variant: str = "") -> Optional[ArtifactRef]:
        """Wait for a submitted step and record ran / cached / failed; returns its reference, rooted at the
        artifacts folder ``root`` of this run (cache records hold paths relative to it), or None.

        Prints one progress line per finished task (long steps log their own frame progress)."""
        future.wait()
        ref, row = self._row(obj, step, future, variant, root)
        self._record(row)
        return ref

    def add_cached(self, obj: str, step: str, ref: ArtifactRef, *, variant: str = "") -> ArtifactRef:
        """Record a step whose intact artifact ``ref`` was found on disk without running it (cached), with the
        same progress line as :meth:`add_future`."""
        self._record(_done_row(obj, step, ref, variant, cached=True))
        return ref

    def _record(self, row: TaskRow) -> None:
        self.rows.append(row)
        done = f"{len(self.rows)}/{self.total}" if self.total else str(len(self.rows))
        what = f"{row.object} {row.step}" + (f" [{row.variant}]" if row.variant else "")
        took = f" {row.wall_seconds:.1f} s" if row.status == "ran" else ""
        print(f"[{done}] {what}: {row.status}{took}{(' - ' + row.note) if row.note else ''}"
              f" (elapsed {time.perf_counter() - self.started:.0f} s)", flush=True)

    def _row(self, obj: str, step: str, future, variant: str, root: str | Path) -> tuple[Optional[ArtifactRef], TaskRow]:
        state = future.state
        if not state.is_final():  # never ran (Prefect leaves it pending): a step it depends on failed
            return None, TaskRow(obj, step, "skipped", 0.0, 0, "", "not run: a step it needs failed", variant)
        if state.is_failed() or state.is_crashed() or state.is_cancelled():
            try:
                future.result(raise_on_failure=True)
                msg = state.message or "failed"
            except Exception as exc:  # the step's own error message
                msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            return None, TaskRow(obj, step, "failed", 0.0, 0, "", msg, variant)
        ref: ArtifactRef = future.result().at(root)
        return ref, _done_row(obj, step, ref, variant, cached=state.name == "Cached" or ref.reused)

    def frame(self) -> pd.DataFrame:
        return pd.DataFrame([r.__dict__ for r in self.rows],
                            columns=["object", "variant", "step", "status", "wall_seconds", "artifact_bytes",
                                     "artifact", "note"])

    def summary(self) -> str:
        df = self.frame()
        counts = df["status"].value_counts().to_dict() if len(df) else {}
        return ", ".join(f"{k}: {v}" for k, v in sorted(counts.items())) or "no tasks"

    def to_text(self) -> str:
        df = self.frame().copy()
        if df.empty:
            return "(no tasks)"
        df["wall_seconds"] = df["wall_seconds"].map(lambda s: f"{s:.2f}")
        df["artifact_bytes"] = df["artifact_bytes"].map(_human_bytes)
        return df.drop(columns=["artifact"]).to_string(index=False)


def _done_row(obj: str, step: str, ref: ArtifactRef, variant: str, cached: bool) -> TaskRow:
    """The row of a step that produced (``cached``: found) the artifact ``ref``, with its stored warning."""
    warning = artifact_warning(ref.path)
    note = "; ".join(n for n in ("reused from disk" if ref.reused else "", warning and f"WARNING {warning}") if n)
    return TaskRow(obj, step, "cached" if cached else "ran", 0.0 if cached else ref.compute_seconds,
                   directory_size(ref.path), ref.path, note, variant, warning)


def _human_bytes(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


def profile_table(table: RunTable, stage_of: dict[str, str], wall_seconds: float, workers: int) -> str:
    """Markdown: compute seconds of the tasks that ran, per object (rows) and stage (columns), with the totals,
    the flow's wall time and the parallel efficiency = total compute / (wall x workers)."""
    df = table.frame()
    ran = df[df["status"] == "ran"].copy()
    if ran.empty:
        return "(every task was cached: no compute in this run)"
    ran["stage"] = ran["step"].map(lambda s: stage_of.get(s, "other"))
    pivot = ran.pivot_table(index="object", columns="stage", values="wall_seconds", aggfunc="sum", fill_value=0.0)
    stages = [s for s in dict.fromkeys(stage_of.values()) if s in pivot.columns]
    header = ["object", *stages, "total"]
    rows = [[obj, *(f"{pivot.loc[obj, s]:.1f}" for s in stages), f"{pivot.loc[obj].sum():.1f}"] for obj in pivot.index]
    total = float(ran["wall_seconds"].sum())
    rows.append(["all", *(f"{pivot[s].sum():.1f}" for s in stages), f"{total:.1f}"])
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]
    efficiency = total / max(wall_seconds * workers, 1e-9)
    lines += ["", f"wall time of the flow {wall_seconds:.1f} s with {workers} worker(s): parallel efficiency "
              f"{100 * efficiency:.0f} % (compute seconds / (wall x workers))"]
    return "\n".join(lines)
