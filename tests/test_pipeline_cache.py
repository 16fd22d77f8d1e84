"""Caching on the real Prefect engine, real zarr stores and the real method steps.

Each test asserts which steps actually ran (status ``ran``) and which were served from cache.
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tasks.core.artifacts import read_group_attrs

STEPS = ["object_model", "squeeze_signals", "signal_smoothing", "force_coefficients", "contact_patches",
         "dirichlet_field", "mpm_rollout", "deformation_metrics", "gbuffer", "conditions", "effect",
         "appearance_refinement", "video_metrics", "llm_evaluation"]
SMALL = ["sampling.surface_points=600", "sampling.particle_spacing=0.004", "signal.duration=1.5",
         "control.smoothing.frame_rate=15", "grid.variants=[full]", "mpm.target_substeps_per_frame=10", "runner=sequential",
         "render.views=2", "render.width=32", "render.height=32", "render.frame_stride=5", "refinement.iterations=2",
         "video_metrics.interpolator=dis", "video_metrics.brisque_max_frames=2"]


def run_grid(compose_cfg, tmp_path: Path, objects: list[str], extra: list[str] = ()) -> dict:
    from flows.pipeline import run

    cfg = compose_cfg("evaluate", [f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}",
                                   f"grid.objects=[{','.join(objects)}]", *SMALL, *extra])
    out = run(cfg, "test")
    return {(r["object"], r["step"]): r["status"] for r in out["tasks"]}


def artifact_of(root: Path, obj: str, step: str) -> list[Path]:
    return sorted((root / "artifacts" / obj / step).glob("*.zarr"))


def test_rerun_is_all_cached_and_one_parameter_recomputes_only_downstream(prefect_server, tmp_path, compose_cfg):
    first = run_grid(compose_cfg, tmp_path, ["tomato", "clay"])
    assert set(first.values()) == {"ran"} and len(first) == 2 * (len(STEPS) + 1)  # + material_oracle
    assert run_grid(compose_cfg, tmp_path, ["tomato", "clay"]) == {k: "cached" for k in first}

    # gamma (eq. 1) is read by force_coefficients: it and everything downstream reruns, for both objects
    changed = run_grid(compose_cfg, tmp_path, ["tomato", "clay"], ["control.force.gamma=2.0"])
    for obj in ("tomato", "clay"):
        assert [changed[(obj, s)] for s in STEPS] == ["cached"] * 3 + ["ran"] * (len(STEPS) - 3)
        assert changed[(obj, "material_oracle")] == "cached"

    # a per-object change (the clay's session) reruns the clay's signal chain only
    per_object = run_grid(compose_cfg, tmp_path, ["tomato", "clay"], ["control.force.gamma=2.0", "catalog.clay.session=pulses"])
    assert all(per_object[("tomato", s)] == "cached" for s in STEPS)
    assert [per_object[("clay", s)] for s in STEPS] == ["cached"] + ["ran"] * (len(STEPS) - 1)


def test_deleted_or_half_written_artifact_is_recomputed(prefect_server, tmp_path, compose_cfg):
    run_grid(compose_cfg, tmp_path, ["orange"])
    import shutil

    shutil.rmtree(artifact_of(tmp_path, "orange", "force_coefficients")[0])
    status = run_grid(compose_cfg, tmp_path, ["orange"])
    assert status[("orange", "force_coefficients")] == "ran"
    # same content again -> identical digest -> downstream stays cached
    assert status[("orange", "contact_patches")] == "cached" and status[("orange", "dirichlet_field")] == "cached"

    # an artifact whose 'complete' stamp is missing (interrupted writer) is not trusted
    meta = artifact_of(tmp_path, "orange", "contact_patches")[0] / "zarr.json"
    doc = json.loads(meta.read_text())
    del doc["attributes"]["complete"]
    meta.write_text(json.dumps(doc))
    status = run_grid(compose_cfg, tmp_path, ["orange"])
    assert status[("orange", "contact_patches")] == "ran"
    assert status[("orange", "signal_smoothing")] == "cached"
    read_group_attrs(artifact_of(tmp_path, "orange", "contact_patches")[0])  # complete again


def test_lost_cache_records_reuse_the_artifacts_on_disk(prefect_server, tmp_path, compose_cfg):
    """A kill between an artifact's rename and Prefect's record write leaves an artifact without a record:
    the step finds it on disk and does not recompute it (reported as cached, 'reused from disk')."""
    import shutil

    first = run_grid(compose_cfg, tmp_path, ["paper_cup"])
    assert set(first.values()) == {"ran"}
    shutil.rmtree(tmp_path / "artifacts" / ".prefect" / "results")
    before = _digests(tmp_path)
    again = run_grid(compose_cfg, tmp_path, ["paper_cup"])
    assert set(again.values()) == {"cached"}
    assert _digests(tmp_path) == before


def _digests(root: Path) -> dict[tuple[str, str], str]:
    out = {}
    for group in (root / "artifacts").glob("*/*/*.zarr"):
        out[(group.parent.parent.name, group.parent.name)] = read_group_attrs(group)["digest"]
    return out


def test_sigkill_mid_run_resumes_only_unfinished_steps(prefect_server, tmp_path, compose_cfg):
    objects = ["can", "plush_toy", "rubber_duck", "clay", "tomato", "orange", "rubber_ball", "paper_cup"]
    killed = tmp_path / "killed"
    env = dict(os.environ, PREFECT_API_URL=prefect_server, VIRSQUEEZER_ARTIFACTS=str(killed / "artifacts"))
    cmd = [sys.executable, "-m", "flows.evaluate", f"paths.artifacts={killed / 'artifacts'}",
           f"paths.reports={killed / 'reports'}", *SMALL]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            cwd=Path(__file__).resolve().parents[1], start_new_session=True)
    deadline = time.time() + 240
    while time.time() < deadline and not list((killed / "artifacts").glob("*/signal_smoothing/*.zarr")):
        assert proc.poll() is None, "the flow ended before it could be killed"
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = _digests(killed)
    assert 0 < len(before) < len(objects) * (len(STEPS) + 1), "kill did not land mid-run"

    status = run_grid(compose_cfg, killed, objects)
    for key, st in status.items():
        assert st == ("cached" if key in before else "ran"), key
    # the resumed run ends with exactly the artifacts of an uninterrupted run
    run_grid(compose_cfg, tmp_path / "clean", objects)
    assert _digests(killed) == _digests(tmp_path / "clean")
