"""Task runners and sweeps: a real local Dask cluster and a real Hydra multirun share one cache."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

from tests.small_runs import CONTROL_SIZES, RENDER_SIZES, artifact_digests

REPO = Path(__file__).resolve().parents[2]
SMALL = [*CONTROL_SIZES, "mpm.target_substeps_per_frame=10", "mpm.quasi_static_margin=0", *RENDER_SIZES]



def test_dask_local_cluster_gives_the_same_artifacts_and_metrics_as_sequential(prefect_server, tmp_path, compose_cfg):
    """Both Table 2 variants on a real 2-process Dask cluster: the shared steps run once per object, the
    rollout and metrics once per variant, and every artifact and metric equals the sequential run's."""
    import pandas as pd

    from flows.pipeline import run

    outs = {}
    for kind in ("dask", "sequential"):
        root = tmp_path / kind
        cfg = compose_cfg("evaluate", [f"paths.artifacts={root / 'artifacts'}", f"paths.reports={root / 'reports'}",
                                       "grid.objects=[clay,rubber_ball]", f"runner={kind}", *SMALL])
        outs[kind] = run(cfg, "test")
        rows = outs[kind]["tasks"]
        assert {r["status"] for r in rows} == {"ran"}
        per_variant = [(r["object"], r["step"]) for r in rows if r["variant"]]
        chain = ("mpm_rollout", "deformation_metrics", "gbuffer", "conditions", "effect", "appearance_refinement",
                 "video_metrics", "llm_evaluation", "display_video")
        assert sorted(per_variant) == sorted((o, s) for o in ("clay", "rubber_ball") for s in chain
                                             for _ in ("full", "no_dirichlet"))
        shared = ("object_model", "squeeze_signals", "signal_smoothing", "force_coefficients", "contact_patches",
                  "dirichlet_field", "mpm_particles", "material_oracle", "gravity_preload")
        assert sorted((r["object"], r["step"]) for r in rows if not r["variant"]) == sorted(
            (o, s) for o in ("clay", "rubber_ball") for s in shared)  # shared steps: once per object
    assert artifact_digests(tmp_path / "dask") == artifact_digests(tmp_path / "sequential")
    assert len(artifact_digests(tmp_path / "dask")) == 2 * (len(shared) + 2 * len(chain))
    metrics = {k: pd.read_parquet(Path(outs[k]["report"]) / "metrics.parquet") for k in outs}
    assert list(metrics["dask"].columns[:3]) == ["object", "seed", "variant"] and len(metrics["dask"]) == 4
    pd.testing.assert_frame_equal(metrics["dask"], metrics["sequential"])
    table2 = (Path(outs["dask"]["report"]) / "report.md").read_text()
    assert "| Full VirSqueezer | BDC-T |" in table2 and "| VirSqueezer w/o Dirichlet Boundary Constraint | mIoU |" in table2


def test_multirun_sweep_reuses_cache_across_jobs_and_aggregates(prefect_server, tmp_path):
    env = dict(os.environ, PREFECT_API_URL=prefect_server)
    cmd = [sys.executable, "-m", "flows.evaluate", "-m", "control.force.gamma=1.5,2.0", "object=clay",
           f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}", "runner=sequential",
           "grid.variants=[full]", *SMALL]
    out = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    (sweep,) = (tmp_path / "reports" / "multirun").iterdir()
    tables = [sweep / job / "tasks.csv" for job in ("0", "1")]
    status = [{row["step"]: row["status"] for row in csv.DictReader(t.open())} for t in tables]
    assert set(status[0].values()) == {"ran"}
    assert [status[1][s] for s in ("object_model", "squeeze_signals", "signal_smoothing", "material_oracle")] == \
        ["cached"] * 4
    assert [status[1][s] for s in ("force_coefficients", "contact_patches", "dirichlet_field", "mpm_rollout",
                                   "deformation_metrics")] == ["ran"] * 5
    # one table across the jobs, the swept parameter as a column, each job's own metric row
    import pandas as pd

    summary = pd.read_csv(sweep / "sweep_metrics.csv")
    assert list(summary.columns[:2]) == ["job", "control.force.gamma"]
    assert summary[["job", "control.force.gamma", "object", "variant"]].values.tolist() == \
        [[0, 1.5, "clay", "full"], [1, 2.0, "clay", "full"]]
    for job in (0, 1):
        own = pd.read_csv(sweep / str(job) / "metrics.csv")
        assert summary.loc[summary.job == job, "bdc_t"].item() == own["bdc_t"].item()
    assert "control.force.gamma" in (sweep / "sweep_summary.md").read_text()


def test_local_dask_workers_keep_glibcs_dynamic_malloc_thresholds(monkeypatch):
    """A real worker process of the local cluster starts without Dask's MALLOC_TRIM_THRESHOLD_; a user's value stays."""
    import dask
    from distributed import Client, LocalCluster

    from flows.runtime import MALLOC_TRIM_KEY, keep_glibc_malloc_thresholds

    def worker_value(**env):
        with dask.config.set({MALLOC_TRIM_KEY: dask.config.get(MALLOC_TRIM_KEY)}):
            for key, value in env.items():
                monkeypatch.setenv(key, value)
            keep_glibc_malloc_thresholds()
            with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
                with Client(cluster) as client:
                    return client.submit(os.environ.get, "MALLOC_TRIM_THRESHOLD_", "unset", pure=False).result()

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    assert worker_value() == "unset"
    assert worker_value(MALLOC_TRIM_THRESHOLD_="1048576") == "1048576"
