"""Caching on the real Prefect engine, real zarr stores and the real method steps.

Each test asserts which steps actually ran (status ``ran``) and which were served from cache.
"""
from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tasks.core.artifacts import read_group_attrs
from tests.small_runs import CONTROL_SIZES, SMALL, artifact_digests

STEPS = ["object_model", "squeeze_signals", "signal_smoothing", "force_coefficients", "contact_patches",
         "dirichlet_field", "gravity_preload", "mpm_rollout", "deformation_metrics", "gbuffer", "conditions", "effect",
         "appearance_refinement", "video_metrics", "llm_evaluation", "display_video"]


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
    assert set(first.values()) == {"ran"} and len(first) == 2 * (len(STEPS) + 2)  # + material_oracle, mpm_particles
    assert run_grid(compose_cfg, tmp_path, ["tomato", "clay"]) == {k: "cached" for k in first}

    # gamma (eq. 1) is read by force_coefficients: it and everything downstream reruns, for both objects
    changed = run_grid(compose_cfg, tmp_path, ["tomato", "clay"], ["control.force.gamma=2.0"])
    for obj in ("tomato", "clay"):
        assert [changed[(obj, s)] for s in STEPS] == ["cached"] * 3 + ["ran"] * (len(STEPS) - 3)
        assert changed[(obj, "material_oracle")] == changed[(obj, "mpm_particles")] == "cached"

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
    [leaf] = artifact_of(tmp_path, "paper_cup", "llm_evaluation")
    shutil.rmtree(leaf)  # one step to run: the flow goes through Prefect, which has no record of the others
    before = artifact_digests(tmp_path)
    again = run_grid(compose_cfg, tmp_path, ["paper_cup"])
    assert {k: v for k, v in again.items() if v != "cached"} == {("paper_cup", "llm_evaluation"): "ran"}
    assert {k: v for k, v in artifact_digests(tmp_path).items() if k in before} == before



def test_sigkill_mid_run_resumes_only_unfinished_steps(prefect_server, tmp_path, compose_cfg, capsys):
    objects = ["tomato", "rubber_ball"]  # two objects: the kill lands mid-run as surely as in the 8-object grid
    killed = tmp_path / "killed"
    env = dict(os.environ, PREFECT_API_URL=prefect_server, VIRSQUEEZER_ARTIFACTS=str(killed / "artifacts"))
    cmd = [sys.executable, "-m", "flows.evaluate", f"paths.artifacts={killed / 'artifacts'}",
           f"paths.reports={killed / 'reports'}", f"grid.objects=[{','.join(objects)}]", *SMALL]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            cwd=Path(__file__).resolve().parents[2], start_new_session=True)
    deadline = time.time() + 240
    while time.time() < deadline and not list((killed / "artifacts").glob("*/signal_smoothing/*.zarr")):
        assert proc.poll() is None, "the flow ended before it could be killed"
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    before = {(obj, step) for obj, step, _ in artifact_digests(killed)}
    assert 0 < len(before) < len(objects) * (len(STEPS) + 1), "kill did not land mid-run"
    # a temporary the killed process was writing (named for it: this host, its pid) is removed at the next start
    from tasks.core.artifacts import scratch_name

    # (the grid runs its largest object first: take the object model of one that got as far as its signals)
    started = next((killed / "artifacts").glob("*/signal_smoothing/*.zarr")).parents[1]
    [model] = (started / "object_model").glob("*.zarr")
    stale = scratch_name(model, "tmp")
    stale = stale.with_name(stale.name.replace(f"-{os.getpid()}-", f"-{proc.pid}-"))
    (stale / "points" / "c").mkdir(parents=True)
    (stale / "points" / "c" / "0").write_bytes(b"x" * 1_000_000)
    capsys.readouterr()

    status = run_grid(compose_cfg, killed, objects)
    removed = re.search(r"removed (\d+) temporary folder\(s\) \(([\d.]+) MB\) left in \S+ by runs that were killed",
                        capsys.readouterr().out)
    assert removed and int(removed[1]) >= 1 and float(removed[2]) >= 1.0
    assert not list((killed / "artifacts").glob("*/*/.*"))
    for key, st in status.items():
        assert st == ("cached" if key in before else "ran"), key
    # the resumed run ends with exactly the artifacts of an uninterrupted run
    run_grid(compose_cfg, tmp_path / "clean", objects)
    assert artifact_digests(killed) == artifact_digests(tmp_path / "clean")


# ------------------------------------------------------------------ damaged artifacts, moved and copied folders


def warning_lines(caplog) -> list[str]:
    """The warning lines logged since the last call (the console shows them after the time and level)."""
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    caplog.clear()
    return lines


def control_chain_local(compose_cfg, root: Path) -> dict:
    from flows.pipeline import run_object_local

    cfg = compose_cfg("evaluate", [f"paths.artifacts={root}", "object=rubber_ball", *CONTROL_SIZES])
    return run_object_local(cfg, cfg.object, None, root, until="dirichlet_field")


@pytest.fixture(scope="module")
def control_artifacts(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """rubber_ball's control chain computed once: its artifacts folder and every step's digest."""
    from tests.conftest import compose

    root = tmp_path_factory.mktemp("control") / "artifacts"
    refs = control_chain_local(compose, root)
    assert list(refs)[-1] == "dirichlet_field"
    return root, {step: ref.digest for step, ref in refs.items()}


def _first_chunk(group: Path, array: str = "displacement") -> Path:
    return sorted(p for p in (group / array / "c").rglob("*") if p.is_file())[0]


def _delete_chunk(group: Path) -> str:
    chunk = _first_chunk(group, "displacement")
    chunk.unlink()
    return f"missing file {chunk.relative_to(group)}"


def _truncate_chunk(group: Path) -> str:
    chunk = _first_chunk(group, "displacement")
    data = chunk.read_bytes()
    chunk.write_bytes(data[:-10])
    return f"size mismatch of {chunk.relative_to(group)}: {len(data) - 10} bytes, written {len(data)}"


def _corrupt_metadata(group: Path) -> str:
    meta = group / "displacement" / "zarr.json"
    size = meta.stat().st_size
    meta.write_text(meta.read_text()[: size // 2])
    return f"size mismatch of displacement/zarr.json: {size // 2} bytes, written {size}"


def _flip_byte(group: Path, array: str = "displacement") -> str:
    chunk = _first_chunk(group, array)
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0x10
    chunk.write_bytes(bytes(data))
    return f"checksum mismatch of {chunk.relative_to(group)}"


@pytest.mark.parametrize("damage", [_delete_chunk, _truncate_chunk, _corrupt_metadata, _flip_byte],
                         ids=lambda f: f.__name__.strip("_"))
def test_a_damaged_artifact_is_recomputed_with_one_warning_naming_it(control_artifacts, tmp_path, compose_cfg,
                                                                    caplog, damage):
    """The issue's case: a chunk of dirichlet_field's displacement deleted (zarr would read zeros), truncated,
    its array metadata cut, or one byte flipped at the same size.  The rerun finds it, says so in one line,
    recomputes exactly that step, and the result is the original content again."""
    import shutil

    original, digests = control_artifacts
    root = tmp_path / "artifacts"
    shutil.copytree(original, root)
    [group] = (root / "rubber_ball" / "dirichlet_field").glob("*.zarr")
    problem = damage(group)
    warning_lines(caplog)
    refs = control_chain_local(compose_cfg, root)
    assert warning_lines(caplog) == [f"rubber_ball/dirichlet_field: artifact {group} is damaged ({problem}): removed, "
                             "the step is recomputed"]
    assert {s: r.reused for s, r in refs.items()} == {s: s != "dirichlet_field" for s in digests}
    assert {s: r.digest for s, r in refs.items()} == digests
    assert read_group_attrs(group)["digest"] == digests["dirichlet_field"]


def test_a_damaged_input_is_refused_with_one_line(control_artifacts, tmp_path, compose_cfg):
    """A step reading an input that was damaged after the cache check fails with one line naming the input;
    the next run's check finds it and recomputes it."""
    import shutil

    from tasks.core.artifacts import ArtifactError, ArtifactRef, read_artifact

    root = tmp_path / "artifacts"
    shutil.copytree(control_artifacts[0], root)
    [group] = (root / "rubber_ball" / "dirichlet_field").glob("*.zarr")
    problem = _delete_chunk(group)
    ref = ArtifactRef(rel=f"rubber_ball/dirichlet_field/{group.name}", digest=control_artifacts[1]["dirichlet_field"],
                      step="dirichlet_field", scope="rubber_ball").at(root)
    with pytest.raises(ArtifactError) as exc:
        read_artifact(ref)
    assert str(exc.value) == (f"input rubber_ball/dirichlet_field: artifact {group} is damaged ({problem}); rerun "
                              "the flow to recompute it")
    assert not control_chain_local(compose_cfg, root)["dirichlet_field"].reused  # the rerun recomputes it
    assert read_artifact(ref)["displacement"].any()


def test_an_artifact_of_the_previous_format_is_recomputed(control_artifacts, tmp_path, compose_cfg, caplog):
    """Format 1 (no manifest): recomputed once with an info line, no warning, same content."""
    import shutil

    root = tmp_path / "artifacts"
    shutil.copytree(control_artifacts[0], root)
    [group] = (root / "rubber_ball" / "force_coefficients").glob("*.zarr")
    meta = group / "zarr.json"
    doc = json.loads(meta.read_text())
    doc["attributes"]["format_version"] = 1
    del doc["attributes"]["manifest"], doc["attributes"]["seal"]
    meta.write_text(json.dumps(doc))
    with caplog.at_level(logging.INFO, logger="prefect.virsqueezer"):
        refs = control_chain_local(compose_cfg, root)
    assert (f"rubber_ball/force_coefficients: artifact {group} was written in artifact format 1, this code reads "
            "format 2: removed, the step is recomputed") in caplog.messages
    assert warning_lines(caplog) == []
    assert [s for s, r in refs.items() if not r.reused] == ["force_coefficients"]
    assert {s: r.digest for s, r in refs.items()} == control_artifacts[1]


def run_control_chain(compose_cfg, root: Path) -> dict[str, tuple[str, str]]:
    """The same chain as a Prefect flow (cache records, RunTable): {step: (status, artifact path)}."""
    from prefect import flow
    from prefect.task_runners import ThreadPoolTaskRunner

    from flows.pipeline import PER_OBJECT, step_params
    from flows.runtime import RunTable, result_storage_settings

    cfg = compose_cfg("evaluate", [f"paths.artifacts={root}", "object=rubber_ball", *CONTROL_SIZES])
    steps = PER_OBJECT[:[s.name for s in PER_OBJECT].index("dirichlet_field") + 1]

    @flow(name="control-chain", persist_result=False, validate_parameters=False,
          task_runner=ThreadPoolTaskRunner(max_workers=1))
    def control_chain() -> dict[str, tuple[str, str]]:
        futures: dict = {}
        for step in steps:
            futures[step.name] = step.submit(root=str(root), scope="rubber_ball", label="rubber_ball",
                                             params=step_params(step, cfg, cfg.object),
                                             inputs={n: futures[n] for n in step.spec.inputs})
        table = RunTable(total=len(futures))
        paths = {name: table.add_future("rubber_ball", name, fut, root=root).path for name, fut in futures.items()}
        return {row.step: (row.status, paths[row.step]) for row in table.rows}

    with result_storage_settings(root):
        return control_chain()


class StepWarnings(logging.Handler):
    """The warning lines of the step runner's own logger.  Attached to that logger, not the root: a Prefect flow
    run may set up logging again, which replaces the root's handlers (and with them pytest's caplog)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())

    def take(self) -> list[str]:
        lines, self.lines = self.lines, []
        return lines


@pytest.fixture
def step_warnings():
    from tasks.core.step import log

    handler = StepWarnings()
    log.addHandler(handler)
    yield handler
    log.removeHandler(handler)


def test_a_moved_or_copied_artifacts_folder_works_from_its_new_place(prefect_server, tmp_path, compose_cfg,
                                                                      step_warnings):
    """``mv A B``: the run on B is served from B's cache records and artifacts; a step recomputed there reads
    its inputs from B (A no longer exists).  ``cp -a B C`` then damage B: C's run is unaffected, B's recomputes
    the damaged step.  No cache record holds an absolute path."""
    a, b, c = tmp_path / "A", tmp_path / "B", tmp_path / "C"
    first = run_control_chain(compose_cfg, a)
    assert {s for s, _ in first.values()} == {"ran"}
    records = [json.loads(json.loads(r.read_text())["result"]) for r in (a / ".prefect" / "results").iterdir()]
    assert sorted(r["data"]["step"] for r in records) == sorted(first)
    assert not [r for r in records if str(tmp_path) in json.dumps(r)]  # relative: {"rel": "rubber_ball/...", ...}

    subprocess.run(["mv", str(a), str(b)], check=True)
    moved = run_control_chain(compose_cfg, b)
    assert moved == {s: ("cached", p.replace(str(a.resolve()), str(b.resolve()))) for s, (_, p) in first.items()}
    import shutil

    [field] = (b / "rubber_ball" / "dirichlet_field").glob("*.zarr")
    shutil.rmtree(field)  # recomputed from its inputs' cache records, rooted at B
    again = run_control_chain(compose_cfg, b)
    assert again["dirichlet_field"][0] == "ran" and field.is_dir()
    assert {p.startswith(str(b.resolve())) for _, p in again.values()} == {True}

    subprocess.run(["cp", "-a", str(b), str(c)], check=True)
    [patches] = (b / "rubber_ball" / "contact_patches").glob("*.zarr")
    problem = _flip_byte(patches, "patch_centers")
    step_warnings.take()
    copied = run_control_chain(compose_cfg, c)
    assert copied == {s: ("cached", p.replace(str(b.resolve()), str(c.resolve()))) for s, (_, p) in again.items()}
    assert step_warnings.take() == []
    original = run_control_chain(compose_cfg, b)
    assert step_warnings.take() == [f"rubber_ball/contact_patches: artifact {patches} is damaged ({problem}): removed, the "
                             "step is recomputed"]
    assert original["contact_patches"][0] == "ran" and original["dirichlet_field"][0] == "cached"



def test_a_fully_cached_run_starts_no_server_or_workers_and_still_finds_a_damaged_artifact(
        prefect_server, tmp_path, compose_cfg, capsys, step_warnings):
    """Warm: every artifact is checked in the flow process (same keys, same manifest check) and the report is
    written without a Prefect server or Dask cluster, saying so in one line, with every step's progress line.
    A byte flipped in one artifact is still found: one warning line, and the flow recomputes that step alone."""
    first = run_grid(compose_cfg, tmp_path, ["tomato"])
    assert set(first.values()) == {"ran"}
    capsys.readouterr()
    warm = run_grid(compose_cfg, tmp_path, ["tomato"], ["runner=dask"])
    out = capsys.readouterr().out
    assert warm == {k: "cached" for k in first}
    n = len(first)
    assert re.search(rf"^every step is cached \({n} artifacts checked in [\d.]+ s\): no Prefect server or task "
                     r"runner started, writing the report$", out, re.M), out
    assert f"[{n - 1}/{n}] tomato llm_evaluation [full/physics]: cached" in out  # display_video comes last
    assert step_warnings.take() == []

    [group] = artifact_of(tmp_path, "tomato", "deformation_metrics")
    problem = _flip_byte(group, "volume_ratio")
    again = run_grid(compose_cfg, tmp_path, ["tomato"])
    assert "every step is cached" not in capsys.readouterr().out
    assert step_warnings.take() == [f"tomato/deformation_metrics: artifact {group} is damaged ({problem}): removed, "
                                    "the step is recomputed"]
    assert again == {k: "ran" if k == ("tomato", "deformation_metrics") else "cached" for k in first}
