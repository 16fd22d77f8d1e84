"""Sweeps whose jobs run at the same time over one shared ``paths.artifacts``: Hydra's joblib launcher (two job
processes) and Hydra's submitit launcher with submitit's local executor (the SLURM launcher's code path, each job a
process submitit starts; no SLURM here)."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from tasks.core.artifacts import read_group_attrs, verify_artifact
from tests.small_runs import SMALL

REPO = Path(__file__).resolve().parents[2]
# gamma (eq. 1) is read from force_coefficients on: the steps before it and the material oracle have one key for
# every job, which the jobs race on
SHARED = ("object_model", "squeeze_signals", "signal_smoothing", "mpm_particles", "material_oracle")


def sweep(tmp_path: Path, prefect_server: str, values: str, launcher: list[str]) -> tuple[subprocess.CompletedProcess,
                                                                                          Path]:
    env = dict(os.environ, PREFECT_API_URL=prefect_server)
    cmd = [sys.executable, "-m", "flows.evaluate", "-m", f"control.force.gamma={values}", "object=clay",
           f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}",
           f"hydra.sweep.dir={tmp_path / 'sweep'}", *launcher, *SMALL]
    return subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=600), tmp_path / "sweep"


def started_and_ended(job: Path) -> tuple[float, float]:
    return (job / ".hydra" / "config.yaml").stat().st_mtime, (job / "metrics.csv").stat().st_mtime


def assert_one_intact_artifact_per_shared_step(root: Path) -> None:
    for step in SHARED:
        groups = list((root / "clay" / step).glob("*.zarr"))
        assert len(groups) == 1, (step, groups)  # one key: one group, whoever wrote it
    for group in root.glob("*/*/*.zarr"):
        verify_artifact(group)
    assert not [p for p in root.rglob("*") if ".tmp-" in p.name or ".trash-" in p.name]


def test_parallel_sweep_shares_one_cache(prefect_server, tmp_path):
    """Two jobs on two joblib processes run at the same time, race on the shared steps' keys and both finish; the
    summary lists both.  (A job whose config is refused now stops the sweep before job 0 runs:
    tests/flows/test_preflight_settings.py.)"""
    out, sweep_dir = sweep(tmp_path, prefect_server, "1.5,2.0", ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"])
    assert out.returncode == 0, out.stderr[-3000:]
    (s0, e0), (s1, e1) = started_and_ended(sweep_dir / "0"), started_and_ended(sweep_dir / "1")
    assert s1 < e0 and s0 < e1, "the two jobs did not run at the same time"
    for job in ("0", "1"):
        status = {r["step"]: r["status"] for r in csv.DictReader((sweep_dir / job / "tasks.csv").open())}
        assert set(status.values()) <= {"ran", "cached"} and len(status) == 18  # one object, one variant
    assert_one_intact_artifact_per_shared_step(tmp_path / "artifacts")
    summary = pd.read_csv(sweep_dir / "sweep_metrics.csv")
    assert summary[["job", "control.force.gamma"]].values.tolist() == [[0, 1.5], [1, 2.0]]
    text = (sweep_dir / "sweep_summary.md").read_text()
    assert "| 1 | 2.0 | ok |" in text and "| 0 | 1.5 | ok |" in text


def test_submitit_local_launcher_runs_two_jobs_on_one_cache(prefect_server, tmp_path):
    """Hydra's submitit launcher (the SLURM path) with submitit's local executor: both jobs run as processes that
    submitit starts and waits for, share the cache, and the sweep is summarised."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    out, sweep_dir = sweep(tmp_path, prefect_server, "1.5,2.0",
                           ["hydra/launcher=submitit_local", "hydra.launcher.timeout_min=10",
                            "hydra.launcher.cpus_per_task=1"])
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-3000:]
    assert list((sweep_dir / ".submitit").glob("*/*_submitted.pkl"))  # submitit's own job records
    summary = pd.read_csv(sweep_dir / "sweep_metrics.csv")
    assert summary[["job", "control.force.gamma"]].values.tolist() == [[0, 1.5], [1, 2.0]]
    assert_one_intact_artifact_per_shared_step(tmp_path / "artifacts")
    digests = {g.parent.name: read_group_attrs(g)["digest"] for g in (tmp_path / "artifacts").glob("clay/*/*.zarr")
               if g.parent.name in SHARED}
    assert len(digests) == len(SHARED)
