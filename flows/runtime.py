"""What every flow shares: task runner from config, result storage, the per-task status table."""
from __future__ import annotations


from prefect.logging import get_logger
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import pandas as pd
from omegaconf import DictConfig
from prefect.task_runners import ThreadPoolTaskRunner

from tasks.artifacts import ArtifactRef, directory_size

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
        return DaskTaskRunner(
            cluster_kwargs={
                "n_workers": int(runner.n_workers),
                "threads_per_worker": int(runner.threads_per_worker),
                "processes": True,
                "dashboard_address": None,
            }
        )
    raise SystemExit(f"runner.kind={kind!r} is unknown: use sequential, threads or dask")


def result_storage_settings(artifacts_root: str | Path):
    """A settings context in which Prefect keeps its cache records (JSON) next to the artifacts."""
    from prefect.settings import PREFECT_RESULTS_LOCAL_STORAGE_PATH, temporary_settings

    path = Path(artifacts_root).resolve() / ".prefect" / "results"
    path.mkdir(parents=True, exist_ok=True)
    return temporary_settings(updates={PREFECT_RESULTS_LOCAL_STORAGE_PATH: str(path)})


@dataclass
class TaskRow:
    object: str
    step: str
    status: str  # ran | cached | skipped | failed
    wall_seconds: float
    artifact_bytes: int
    artifact: str
    note: str = ""


@dataclass
class RunTable:
    """Collects one row per (object, step) as the flow resolves its futures."""

    rows: list[TaskRow] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)

    def add_future(self, obj: str, step: str, future) -> Optional[ArtifactRef]:
        """Wait for a submitted step and record ran / cached / failed; returns its reference or None."""
        future.wait()
        state = future.state
        if state.is_failed() or state.is_crashed() or state.is_cancelled():
            try:
                future.result(raise_on_failure=True)
                msg = state.message or "failed"
            except Exception as exc:  # the step's own error message
                msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            self.rows.append(TaskRow(obj, step, "failed", 0.0, 0, "", msg))
            return None
        ref: ArtifactRef = future.result()
        cached = state.name == "Cached" or ref.reused
        self.rows.append(
            TaskRow(obj, step, "cached" if cached else "ran", 0.0 if cached else ref.compute_seconds,
                    directory_size(ref.path), ref.path, "reused from disk" if ref.reused else "")
        )
        return ref

    def skip(self, obj: str, step: str, why: str) -> None:
        self.rows.append(TaskRow(obj, step, "skipped", 0.0, 0, "", why))

    def frame(self) -> pd.DataFrame:
        return pd.DataFrame([r.__dict__ for r in self.rows],
                            columns=["object", "step", "status", "wall_seconds", "artifact_bytes", "artifact", "note"])

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


def _human_bytes(n: int) -> str:
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)
