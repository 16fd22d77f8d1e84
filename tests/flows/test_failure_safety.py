"""Failure safety on the real flow (real Prefect, real zarr, real method steps).

* A step that fails on bad input leaves no artifact and no cache record a later run would trust; the
  upstream artifacts stay intact and are reused once the input is fixed.
* A cache record that is not plain JSON (e.g. a pickle planted in a shared result folder) is never decoded.
* Two runs started at once on one artifacts folder both finish, with the artifacts of a single run.
"""
from __future__ import annotations

import base64
import json
import os
import pickle
import re
import shutil
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from tasks.core.artifacts import read_group_attrs
from tests.small_runs import SMALL, artifact_digests

REPO = Path(__file__).resolve().parents[2]


def _overrides(root: Path, objects: list[str], extra: list[str] = ()) -> list[str]:
    return [f"paths.artifacts={root / 'artifacts'}", f"paths.reports={root / 'reports'}",
            f"grid.objects=[{','.join(objects)}]", *SMALL, *extra]



def _leftovers(root: Path) -> list[str]:
    """Temporary or trash folders of interrupted artifact writes."""
    return sorted(str(p) for p in (root / "artifacts").glob("*/*/.*"))


class _Touch:
    """Unpickling this calls ``Path.touch(path)``: proof that a planted pickle was decoded."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):
        return (Path.touch, (self.path,))


def test_bad_recording_is_refused_before_the_flow_starts(tmp_path, compose_cfg):
    """A truncated recording stops the run in the pre-flight check: one line naming the input and the row, no
    traceback, no Prefect server started (no flow runs), nothing written."""
    from flows.pipeline import run
    from tasks.control.object_model import build_object_model
    from tasks.control.recording import write_recording
    from tasks.control.squeeze_signals import synthesize_session

    # a recording made around the ball, then cut off mid-row the way an interrupted copy leaves it
    base = compose_cfg("evaluate", _overrides(tmp_path, ["rubber_ball"]))
    surface, _ = build_object_model(base.catalog.rubber_ball, base.sampling)
    raw = synthesize_session("pulses", surface["surface_points"].data, surface["surface_normals"].data,
                             {"duration": 1.5, "sensor_rate": 200.0})
    rec = write_recording(tmp_path / "session.csv", raw)
    text = rec.read_text()
    rec.write_text(text[: len(text) - 40])
    cfg = compose_cfg("evaluate", _overrides(tmp_path, ["rubber_ball"], ["signal=csv", f"signal.path={rec}"]))
    with pytest.raises(SystemExit) as exc:
        run(cfg, "test")
    msg = str(exc.value)
    assert msg.startswith("input error: signal.path: ") and "\n" not in msg
    assert f"recording {rec}: the last row 301 (line 302)" in msg and "looks truncated" in msg
    assert not list((tmp_path / "artifacts").glob("*/*/*.zarr"))


def test_a_failed_step_leaves_no_artifact_and_the_fixed_rerun_reuses_upstream(prefect_server, tmp_path,
                                                                             compose_cfg, monkeypatch):
    """A step that fails inside the flow (the LLM material oracle's endpoint accepts the connection, which the
    preflight checks, and hangs up on every request): the run fails with that step's own one-line message, the
    steps that need it are skipped, no artifact or cache record of them exists, and the rerun with the table
    oracle reuses every upstream artifact."""
    from flows.pipeline import run
    from tasks.core.step import plain_record

    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(0.2)
    done = threading.Event()

    def hang_up() -> None:  # accept, then close: the request gets no response
        while not done.is_set():
            try:
                listener.accept()[0].close()
            except OSError:
                pass

    threading.Thread(target=hang_up, daemon=True).start()
    monkeypatch.setenv("VIRSQUEEZER_LLM_API_KEY", "not-a-real-key")
    port = listener.getsockname()[1]
    llm = ["oracle.backend=llm", f"oracle.llm_url=http://127.0.0.1:{port}/v1", "oracle.llm_model=m",
           "oracle.timeout_s=2", f"oracle.cache_dir={tmp_path / 'llm-cache'}"]
    try:
        with pytest.raises(RuntimeError) as exc:
            run(compose_cfg("evaluate", _overrides(tmp_path, ["rubber_ball"], llm)), "test")
    finally:
        done.set()
        listener.close()
    msg = str(exc.value)
    assert "\n" not in msg and "rubber_ball/material_oracle" in msg

    art = tmp_path / "artifacts" / "rubber_ball"
    upstream_steps = ["contact_patches", "dirichlet_field", "force_coefficients", "mpm_particles", "object_model",
                      "signal_smoothing", "squeeze_signals"]
    # the failed step and everything after it: no artifact, complete or not, and no temporary
    assert sorted(p.parent.name for p in art.glob("*/*.zarr")) == upstream_steps
    assert _leftovers(tmp_path) == []
    [model] = art.glob("object_model/*.zarr")
    upstream = read_group_attrs(model)["digest"]
    # cache records: only for the complete artifacts; everything Prefect persisted is JSON (no pickle)
    results = tmp_path / "artifacts" / ".prefect" / "results"
    docs = [json.loads(p.read_bytes()) for p in results.iterdir()]  # (a pickle would not parse)
    refs = [json.loads(d["result"])["data"] for d in docs if "ArtifactRef" in str(d.get("result"))]
    assert sorted(r["step"] for r in refs) == upstream_steps
    assert all(read_group_attrs(tmp_path / "artifacts" / r["rel"])["digest"] == r["digest"] for r in refs)

    cfg = compose_cfg("evaluate", _overrides(tmp_path, ["rubber_ball"]))  # the user switches to the table
    status = {r["step"]: r["status"] for r in run(cfg, "test")["tasks"]}
    assert all(status.pop(s) == "cached" for s in upstream_steps)
    assert set(status.values()) == {"ran"} and "mpm_rollout" in status and "material_oracle" in status
    assert read_group_attrs(model)["digest"] == upstream

    # a pickle planted as the object model's cache record (anyone can compute the key) is removed unread
    [record] = [p for p in results.iterdir() if p.name.startswith(model.name[:-len(".zarr")])]
    marker = tmp_path / "planted-pickle-ran"
    record.write_text(json.dumps({
        "metadata": {"storage_key": str(record), "expiration": None, "prefect_version": "3.8.8",
                     "storage_block_id": None, "serializer": {"type": "pickle", "picklelib": "pickle"}},
        "result": base64.b64encode(pickle.dumps(_Touch(marker))).decode()}))
    [leaf] = art.glob("llm_evaluation/*.zarr")
    shutil.rmtree(leaf)  # one step to run: the flow goes through Prefect and its cache records
    rows = run(cfg, "test")["tasks"]
    assert not marker.exists()
    assert {r["step"]: r["status"] for r in rows if r["status"] != "cached"} == {"llm_evaluation": "ran"}
    assert [r["note"] for r in rows if r["step"] == "object_model"] == ["reused from disk"]
    assert plain_record(record)  # Prefect wrote a plain record again
    assert read_group_attrs(model)["digest"] == upstream


def test_a_second_flow_process_gets_a_private_prefect_database(tmp_path):
    """Fast twin of the test below (with tests/core/test_artifacts.py's concurrent writers): while another process
    holds the claim on an artifacts folder's Prefect database, a flow process gets a private database, and that
    is what the temporary server it starts is given; the claim dies with its holder, even under SIGKILL."""
    from prefect.settings import (
        PREFECT_API_DATABASE_CONNECTION_URL,
        get_current_settings,
        temporary_settings,
    )

    from flows.runtime import claim_prefect_database

    url = f"sqlite+aiosqlite:///{tmp_path / '.prefect' / 'prefect.db'}"
    script = ("import time; from flows.runtime import claim_prefect_database; "
              f"assert claim_prefect_database({url!r}) == {{}}; print('claimed', flush=True); time.sleep(600)")
    holder = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "claimed"
        private = claim_prefect_database(url)
        db_url = private[PREFECT_API_DATABASE_CONNECTION_URL]
        assert db_url.startswith("sqlite+aiosqlite:///") and db_url != url
        assert Path(db_url[len("sqlite+aiosqlite:///"):]).parent.is_dir()
        with temporary_settings(updates=private):  # the environment Prefect starts its temporary server with
            server_env = get_current_settings().to_environment_variables(exclude_unset=True)
        assert server_env["PREFECT_SERVER_DATABASE_CONNECTION_URL"] == db_url
    finally:
        holder.kill()
        holder.wait()
    assert claim_prefect_database(url) == {}  # the killed holder's claim is gone: the shared database is ours


@pytest.mark.slow
def test_two_runs_at_once_on_one_artifacts_folder(prefect_server, tmp_path, compose_cfg):
    """Both processes start their own temporary Prefect server (no PREFECT_API_URL) on the same artifacts
    folder: one claims the Prefect database there, the other keeps its run history in a private one; both
    finish and the artifacts are those of a single run.  (~2 min on 2 cores: two server start-ups at once.)"""
    from flows.pipeline import run

    objects = ["rubber_ball", "clay"]
    shared = tmp_path / "shared"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_")}
    env["VIRSQUEEZER_ARTIFACTS"] = str(shared / "artifacts")
    logs = [tmp_path / f"run{i}.log" for i in range(2)]
    procs = [subprocess.Popen([sys.executable, "-m", "flows.evaluate", *_overrides(shared, objects),
                               f"run_name=run{i}"], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                              stderr=log.open("w")) for i, log in enumerate(logs)]
    for p in procs:
        p.wait(timeout=600)
    errs = [log.read_text() for log in logs]
    for p, err in zip(procs, errs):
        assert p.returncode == 0, err[-3000:]
        assert "Application startup failed" not in err and "database is locked" not in err, err[-3000:]
    private = [m.group(1) for err in errs
               for m in re.finditer(r"keeps its run history in a private database in (\S+) ", err)]
    assert len(private) == 1 and not Path(private[0]).exists()  # the second run's database, removed at exit
    for i in range(2):
        statuses = (shared / "reports" / f"run{i}" / "tasks.csv").read_text()
        assert ",failed," not in statuses

    run(compose_cfg("evaluate", _overrides(tmp_path / "single", objects)), "test")
    assert artifact_digests(shared) == artifact_digests(tmp_path / "single")
    assert {(obj, step) for obj, step, _ in artifact_digests(shared)} >= {(o, "mpm_rollout") for o in objects}
    assert _leftovers(shared) == []
