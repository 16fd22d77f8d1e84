"""Task runners and sweeps: a real local Dask cluster and a real Hydra multirun share one cache."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

from tasks.artifacts import read_group_attrs

REPO = Path(__file__).resolve().parents[1]
SMALL = ["sampling.surface_points=600", "sampling.particle_spacing=0.004", "signal.duration=1.5",
         "control.smoothing.frame_rate=15", "simulation.target_substeps_per_frame=10"]


def _digests(root: Path) -> dict:
    return {(g.parent.parent.name, g.parent.name): read_group_attrs(g)["digest"]
            for g in (root / "artifacts").glob("*/*/*.zarr")}


def test_dask_local_cluster_gives_the_same_artifacts_as_sequential(prefect_server, tmp_path, compose_cfg):
    from flows.pipeline import run

    outs = {}
    for kind in ("dask", "sequential"):
        root = tmp_path / kind
        cfg = compose_cfg("evaluate", [f"paths.artifacts={root / 'artifacts'}", f"paths.reports={root / 'reports'}",
                                       "grid.objects=[clay,rubber_ball]", f"runner={kind}", *SMALL])
        outs[kind] = run(cfg, "test")
        assert {r["status"] for r in outs[kind]["tasks"]} == {"ran"}
    assert _digests(tmp_path / "dask") == _digests(tmp_path / "sequential")
    assert len(_digests(tmp_path / "dask")) == 16


def test_multirun_sweep_reuses_cache_across_jobs(prefect_server, tmp_path):
    env = dict(os.environ, PREFECT_API_URL=prefect_server)
    cmd = [sys.executable, "-m", "flows.evaluate", "-m", "control.force.gamma=1.5,2.0", "object=clay",
           f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}", "runner=sequential",
           *SMALL]
    out = subprocess.run(cmd, env=env, cwd=REPO, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    tables = sorted((tmp_path / "reports").glob("evaluate-*-job*/tasks.csv"))
    assert [t.parent.name[-4:] for t in tables] == ["job0", "job1"]
    status = [{row["step"]: row["status"] for row in csv.DictReader(t.open())} for t in tables]
    assert set(status[0].values()) == {"ran"}
    assert [status[1][s] for s in ("object_model", "squeeze_signals", "signal_smoothing", "material_oracle")] == \
        ["cached"] * 4
    assert [status[1][s] for s in ("force_coefficients", "contact_patches", "dirichlet_field", "mpm_rollout")] == \
        ["ran"] * 4
