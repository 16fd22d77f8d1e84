"""Issue 49: a lab's artifacts cache shared read-only serves a fully cached run, and receives nothing.

The run's report, its media, Prefect's home and the caches go under ``paths.reports``; a run that the cache does
not fully hold is refused in one line, naming the first step it lacks, before anything is computed.  Tests run as
root, whom file modes do not stop, so "read-only" is made real twice over: a Python audit hook that refuses (and
records) every write under the artifacts folder (``tests/flows/audit_writes.py``), and a read-only bind mount in a
mount namespace of its own (``unshare``), skipped where the machine does not allow one.  Besides, every file and
folder of the cache is compared before and after (size, mtime, mode).
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from tests.small_runs import SMALL

REPO = Path(__file__).resolve().parents[2]
PROBE = ".virsqueezer-write-probe-"  # flows.preflight_env.unwritable's one empty file (refused: that is the finding)


@pytest.fixture(scope="module")
def shared_cache(tmp_path_factory, prefect_server) -> Path:
    """tomato's smallest evaluation (tests/small_runs.py) computed once: the artifacts folder a lab would share."""
    from flows.pipeline import run
    from tests.conftest import compose

    root = tmp_path_factory.mktemp("lab")
    cfg = compose("evaluate", [f"paths.artifacts={root / 'artifacts'}", f"paths.reports={root / 'reports'}",
                               "grid.objects=[tomato]", *SMALL])
    assert {r["status"] for r in run(cfg, "test")["tasks"]} == {"ran"}
    assert any((root / "artifacts" / ".media").iterdir())  # the report media are cached with the artifacts
    return root / "artifacts"


def snapshot(root: Path) -> dict[str, tuple[int, int, int]]:
    """(size, mtime in ns, mode) of every file and folder under ``root``, the folder itself included."""
    return {str(p.relative_to(root)): (st.st_size if p.is_file() else 0, st.st_mtime_ns, st.st_mode)
            for p in [root, *root.rglob("*")] for st in [p.lstat()]}


def user_env(**changes: str | None) -> dict[str, str]:
    """The environment of a user's shell (none of the Prefect settings the test session set for itself), with
    ``changes`` (None: unset)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("PREFECT_") and k != "VIRSQUEEZER_ARTIFACTS"}
    for key, value in changes.items():  # None: unset
        env.pop(key, None) if value is None else env.__setitem__(key, value)
    return env


def evaluate_args(artifacts: Path, reports: Path, objects: str = "tomato") -> list[str]:
    return [f"paths.artifacts={artifacts}", f"paths.reports={reports}", f"grid.objects=[{objects}]", *SMALL]


def audited(artifacts: Path, log: Path, args: list[str], env: dict[str, str],
            flow: str = "flows.evaluate") -> subprocess.CompletedProcess:
    """``python -m <flow> args`` with every write under ``artifacts`` refused and logged to ``log``."""
    return subprocess.run([sys.executable, "-m", "tests.flows.audit_writes", str(artifacts), str(log), flow, *args],
                          cwd=REPO, capture_output=True, text=True, timeout=600, env=env)


def refused_writes(log: Path) -> list[str]:
    """The logged write attempts other than the write probes that found the folder read-only."""
    lines = log.read_text().splitlines() if log.exists() else []
    return [line for line in lines if not Path(line.split("\t")[1]).name.startswith(PROBE)]


def read_only_line(artifacts: Path, reports: Path, reason: str = "Read-only file system") -> str:
    return (f"paths.artifacts={artifacts} is a read-only cache ({artifacts} is not writable ({reason})): the run is "
            f"served from it if every step is cached there and writes nothing into it; Prefect's home, caches and "
            f"new report media go under paths.reports={reports}")


def assert_report(reports: Path) -> Path:
    [report] = [p for p in reports.iterdir() if p.name.startswith("evaluate-")]
    names = {p.name for p in report.iterdir()}
    assert {"report.md", "index.html", "metrics.csv", "contact_sheet.png", "tomato_control.png"} <= names, names
    assert {"tomato_full_final.mp4", "tomato_full_stages.mp4"} <= names or \
        {"tomato_full_final.webp", "tomato_full_stages.webp"} <= names, names
    return report


def test_a_fully_cached_run_on_a_read_only_cache_writes_nothing_into_it(shared_cache, tmp_path):
    """Every write under the cache refused by the audit hook (as a read-only mount refuses it): the run passes,
    writes its report, makes the media the cache lacks under ``<paths.reports>/.media``, keeps Prefect's home and -
    with a home that cannot be written - Warp's and matplotlib's caches under ``paths.reports``; nothing but the
    folder's write probe tried to write into the cache, and nothing in it changed."""
    cache, reports, home = tmp_path / "cache", tmp_path / "reports", tmp_path / "home"
    shutil.copytree(shared_cache, cache, symlinks=True)
    shutil.rmtree(cache / ".media")  # media made by an older reporting code: made again, under paths.reports
    home.write_text("a home nothing can be written under")
    before = snapshot(cache)
    env = user_env(HOME=str(home), XDG_CACHE_HOME=None, XDG_CONFIG_HOME=None, WARP_CACHE_PATH=None, MPLCONFIGDIR=None)
    out = audited(cache, tmp_path / "writes.log", evaluate_args(cache, reports), env)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert read_only_line(cache, reports) in lines
    assert f"Warp's kernel cache goes to {reports / '.cache' / 'warp'} (WARP_CACHE_PATH): its default " \
           f"{home / '.cache' / 'warp'} cannot be written ({home} is a file, so {home / '.cache' / 'warp'} cannot be " \
           f"a folder)" in lines
    assert any(line.startswith("every step is cached (18 artifacts checked in ") for line in lines), out.stdout
    assert (tmp_path / "writes.log").read_text().count(PROBE) >= 1  # the folder was found read-only by its probe
    assert refused_writes(tmp_path / "writes.log") == []
    assert snapshot(cache) == before
    assert_report(reports)
    assert any((reports / ".media").iterdir()) and (reports / ".prefect").is_dir()


def test_a_step_the_read_only_cache_lacks_is_one_line_before_anything_runs(shared_cache, tmp_path):
    """A second object the cache does not hold: refused with one line naming its first step and the fix, before
    any step, server or report; nothing written into the cache, nor a report."""
    reports = tmp_path / "reports"
    before = snapshot(shared_cache)
    out = audited(shared_cache, tmp_path / "writes.log", evaluate_args(shared_cache, reports, "tomato,clay"), user_env())
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        f"config error: paths.artifacts={shared_cache} is a read-only cache ({shared_cache} is not writable (Read-only "
        f"file system)) and clay/object_model is not cached there (missing or damaged), so the run would have to write "
        f"into it: give a writable folder (paths.artifacts=/path/to/folder), e.g. a copy of the cache (cp -a "
        f"{shared_cache} /path/to/folder)"]
    assert out.stdout.splitlines() == [read_only_line(shared_cache, reports)]  # no work estimate, no step
    assert refused_writes(tmp_path / "writes.log") == []
    assert snapshot(shared_cache) == before
    assert not [p for p in reports.iterdir() if p.name.startswith("evaluate-")]


def test_the_viewer_records_a_scene_of_a_read_only_cache(shared_cache, tmp_path):
    """``python -m flows.view record=true`` on the read-only cache: the recording under paths.reports, Prefect's
    home there too, no write tried under the cache."""
    reports = tmp_path / "reports"
    before = snapshot(shared_cache)
    view_sizes = [a for a in SMALL if not a.startswith(("grid.", "runner="))]  # the viewer's config has neither
    out = audited(shared_cache, tmp_path / "writes.log", ["object=tomato", "compare=null", "record=true", "port=0",
                                                          f"paths.artifacts={shared_cache}", f"paths.reports={reports}",
                                                          *view_sizes], user_env(), flow="flows.view")
    assert out.returncode == 0, out.stderr[-3000:]
    recording = reports / "viewer" / "tomato_full.html"
    assert f"recording: {recording} (" in out.stdout and recording.stat().st_size > 0
    assert (reports / ".prefect").is_dir()
    assert refused_writes(tmp_path / "writes.log") == []
    assert snapshot(shared_cache) == before


def test_export_writes_its_plys_from_a_read_only_cache(shared_cache, tmp_path):
    """``python -m flows.export`` of the cached scene: its PLY files under paths.reports, every step found in the
    cache (none run), no write tried under it."""
    reports = tmp_path / "reports"
    before = snapshot(shared_cache)
    sizes = [a for a in SMALL if not a.startswith("grid.")]  # flows.export composes conf/squeeze.yaml: one variant
    out = audited(shared_cache, tmp_path / "writes.log", ["object=tomato", f"paths.artifacts={shared_cache}",
                                                          f"paths.reports={reports}", *sizes], user_env(),
                  flow="flows.export")
    assert out.returncode == 0, out.stderr[-3000:]
    folder = reports / "ply" / "tomato_full"
    assert out.stdout.splitlines()[-1].endswith(f"released particles) in {folder}")
    assert sorted(p.name for p in folder.iterdir()) == [f"frame_{i:04d}.ply" for i in (0, 5, 10, 15, 20)]
    assert refused_writes(tmp_path / "writes.log") == []
    assert snapshot(shared_cache) == before


def read_only_mount() -> list[str] | None:
    """The command prefix that runs a command with its first argument's folder bind-mounted read-only onto itself in
    a mount namespace of its own (``unshare``: as root, or as a user namespace's root), or None where neither
    is allowed."""
    if shutil.which("unshare") is None or shutil.which("mount") is None:
        return None
    script = 'mount --bind -o ro "$0" "$0" && exec "$@"'
    probe_dir = Path(tempfile.mkdtemp(prefix="ro-mount-probe-"))
    try:
        for unshare in (["unshare", "--mount"], ["unshare", "--user", "--map-root-user", "--mount"]):
            prefix = [*unshare, "sh", "-c", script]
            probe = subprocess.run([*prefix, str(probe_dir), "sh", "-c", 'touch "$0/x"', str(probe_dir)],
                                   capture_output=True, text=True, timeout=60)
            if probe.returncode != 0 and "Read-only file system" in probe.stderr and not any(probe_dir.iterdir()):
                return prefix
        return None
    finally:
        shutil.rmtree(probe_dir, ignore_errors=True)


def test_on_a_real_read_only_mount_the_cached_run_passes_and_the_cache_is_untouched(shared_cache, tmp_path):
    """The cache bind-mounted read-only (the kernel refuses every write, C code's included): the cached run
    passes, its media are copied from the cache's own, and nothing in the cache changed."""
    prefix = read_only_mount()
    if prefix is None:
        pytest.skip("no read-only bind mount here: unshare --mount (root) and unshare --user --map-root-user --mount "
                    "are both refused")
    reports = tmp_path / "reports"
    before = snapshot(shared_cache)
    out = subprocess.run([*prefix, str(shared_cache), sys.executable, "-m", "flows.evaluate",
                          *evaluate_args(shared_cache, reports)], cwd=REPO, capture_output=True, text=True,
                         timeout=600, env=user_env())
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert read_only_line(shared_cache, reports) in lines
    assert any(line.startswith("every step is cached (18 artifacts checked in ") for line in lines), out.stdout
    assert snapshot(shared_cache) == before
    report = assert_report(reports)
    assert not (reports / ".media").exists()  # every medium came from the cache's .media
    assert (report / "tomato_control.png").read_bytes() in {p.read_bytes() for p in (shared_cache / ".media").iterdir()}


def test_an_existing_folder_that_cannot_be_written_is_a_read_only_cache(tmp_path, compose_cfg):
    """/sys refuses a new file even to root: as paths.artifacts it is a read-only cache (passed by the folder check
    of a main that can be served from one, refused by the others; Prefect's home, caches and media go under
    paths.reports), while a folder that does not exist under it is refused in one line by every main."""
    from flows.preflight_env import check_folders, read_only_cache, writable_root

    cfg = compose_cfg("evaluate", ["paths.artifacts=/sys", f"paths.reports={tmp_path / 'r'}"])
    check_folders(cfg, read_only_ok=True)
    with pytest.raises(SystemExit) as exc:
        check_folders(cfg)  # e.g. python -m flows.studies.convergence, which computes
    assert str(exc.value) == ("config error: paths.artifacts=/sys: /sys is not writable (Permission denied): give a "
                              "folder you can write to (paths.artifacts=/path/to/folder)")
    assert read_only_cache("/sys") == "/sys is not writable (Permission denied)"
    assert writable_root("/sys", tmp_path / "r") == tmp_path / "r"
    assert read_only_cache(tmp_path) == "" and writable_root(tmp_path, tmp_path / "r") == tmp_path
    assert read_only_cache("/sys/virsqueezer") == ""  # not there: nothing to be served from
    with pytest.raises(SystemExit) as exc:
        check_folders(compose_cfg("evaluate", ["paths.artifacts=/sys/virsqueezer"]), read_only_ok=True)
    assert str(exc.value) == ("config error: paths.artifacts=/sys/virsqueezer: /sys is not writable (Permission denied): "
                              "give a folder you can write to (paths.artifacts=/path/to/folder)")


def test_a_study_refuses_an_unwritable_artifacts_folder_in_one_line_before_prefect(tmp_path):
    """A study computes, so it cannot be served from a read-only cache: its main refuses the folder in one line,
    before it would make Prefect's home in it (once a PermissionError traceback from ``begin_run``)."""
    out = subprocess.run([sys.executable, "-m", "flows.studies.convergence", "paths.artifacts=/sys/kernel",
                          f"paths.reports={tmp_path / 'r'}"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 1, out.stderr
    assert out.stderr.strip().splitlines()[-1] == (
        "config error: paths.artifacts=/sys/kernel: /sys/kernel is not writable (Permission denied): give a folder "
        "you can write to (paths.artifacts=/path/to/folder)")
    assert "Traceback" not in out.stderr + out.stdout


def test_a_user_set_prefect_home_inside_a_read_only_cache_is_one_line_before_anything(tmp_path, monkeypatch):
    """PREFECT_HOME (or PREFECT_RESULTS_LOCAL_STORAGE_PATH) set by the user is left as it is by the mains: inside a
    read-only cache Prefect would fail making its home or database.  The real main refuses it before Hydra makes
    its folder; the same line for the cache records' variable, and an unwritable one anywhere else."""
    reports = tmp_path / "r"
    out = subprocess.run([sys.executable, "-m", "flows.squeeze", "paths.artifacts=/sys/kernel", f"paths.reports={reports}",
                          "object=tomato"], cwd=REPO, capture_output=True, text=True, timeout=300,
                         env=user_env(PREFECT_HOME="/sys/kernel/.prefect"))
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        f"environment error: PREFECT_HOME=/sys/kernel/.prefect is inside paths.artifacts=/sys/kernel, a read-only "
        f"cache (/sys/kernel is not writable (Permission denied)) that receives nothing: unset PREFECT_HOME (the run "
        f"then puts it under paths.reports) or point it under paths.reports (PREFECT_HOME={reports / '.prefect'})"]
    assert not reports.exists() and "Traceback" not in out.stdout
    from flows.preflight_env import check_prefect_paths

    results = "PREFECT_RESULTS_LOCAL_STORAGE_PATH"
    monkeypatch.setenv(results, "/sys/kernel/results")
    with pytest.raises(SystemExit) as exc:
        check_prefect_paths("/sys/kernel", reports, frozenset({results}))
    assert str(exc.value) == (
        f"environment error: {results}=/sys/kernel/results is inside paths.artifacts=/sys/kernel, a read-only cache "
        f"(/sys/kernel is not writable (Permission denied)) that receives nothing: unset {results} (the run then puts "
        f"it under paths.reports) or point it under paths.reports ({results}={reports / '.prefect' / 'results'})")
    with pytest.raises(SystemExit) as exc:  # a writable artifacts folder, the variable somewhere unwritable
        check_prefect_paths(tmp_path / "a", reports, frozenset({results}))
    assert str(exc.value) == (f"environment error: {results}=/sys/kernel/results: /sys/kernel is not writable "
                              f"(Permission denied): point {results} at a folder you can write to, or unset it")
    monkeypatch.setenv(results, str(reports / ".prefect" / "results"))  # the fix the line gives passes
    check_prefect_paths("/sys/kernel", reports, frozenset({results}))
    assert not reports.exists()  # checked, not created
