"""Issue 49: the work estimate counts the grid, cheap config checks, folders and environment, sweeps and a cut
report.  Each case asserts the exact one line the user reads; none runs a step."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SEEDS_0_20 = "grid.seeds=[" + ",".join(map(str, range(21))) + "]"


def _refusal(cfg) -> str:
    from flows.preflight import preflight

    with pytest.raises(SystemExit) as exc:
        preflight(cfg)
    return str(exc.value)


# ------------------------------------------------------------------------------------------------ work estimate
def test_the_grid_is_sized_as_the_solver_sizes_it(compose_cfg):
    """The solver's grids of the default scenes, as the scene benchmark printed them (docs/results/benchmarks.md:
    plush toy 41x37x38 since it sits on its seat (41x37x40 before), can 32x32x30, rubber ball 32x32x24)."""
    from flows.preflight_settings import grid_dims

    cfg = compose_cfg("evaluate", [])
    assert [grid_dims(cfg, cfg.catalog[n]) for n in ("plush_toy", "can", "rubber_ball")] == [
        (41, 37, 38), (32, 32, 30), (32, 32, 24)]


def test_a_tiny_grid_spacing_is_refused_naming_mpm_dx(compose_cfg):
    assert _refusal(compose_cfg("evaluate", ["mpm.dx=1e-5"])) == (
        "work limit: mpm.dx=1e-05 m gives catalog.plush_toy a grid of 14423x11123x17715 = 2.84e+12 nodes, about 341 "
        "TiB (up to 132 bytes per node), above limits.max_grid_bytes=8.59e+09 (8 GiB): raise mpm.dx (unset: two "
        "particle spacings) (or raise the limit)")


def test_twenty_one_seeds_are_estimated_and_the_wall_limit_names_its_knob(compose_cfg):
    """The estimate itself (not the whole preflight, whose free-space check would make the answer depend on this
    disk: 21 seeds need ~54 GiB), then the wall limit, which the preflight checks before any folder."""
    from flows.preflight import check_recording, estimate_work

    cfg = compose_cfg("evaluate", [SEEDS_0_20])
    est = estimate_work(cfg, check_recording(cfg)[0])
    assert est.line() == (
        "work estimate: 336 scenes (8 objects x 2 variants x 21 seeds) x 1 effect backend, 91 frames each; largest "
        "grid 41x37x38 = 57,646 nodes (7.26 MiB, catalog.plush_toy); about 3.16e+10 particle-substeps, 51.8 GiB of "
        "artifacts; expected wall time ~2.2 h")
    assert _refusal(compose_cfg("evaluate", [SEEDS_0_20, "limits.max_wall_hours=1"])) == (
        "work limit: 336 scenes (8 objects x 2 variants x 21 seeds), about 3.16e+10 particle-substeps, would take "
        "about 2.21 h, above limits.max_wall_hours=1: run fewer seeds (grid.seeds), objects or variants (or raise "
        "limits.max_wall_hours)")


# ------------------------------------------------------------------------------------------------ settings
def _settings_cases() -> list[tuple[list[str], str]]:
    return [
        (["signal.session=squish"], "config error: signal.session 'squish' is not a squeeze session: use one of "
                                    "ramp_hold_release, pulses, poke, crush"),
        (["object=can", "object.session=squish"], "config error: object.session 'squish' is not a squeeze session: "
                                                  "use one of ramp_hold_release, pulses, poke, crush (or set "
                                                  "signal.session)"),
        (["object=can", "object.geometry.kind=cube"],
         "config error: object.geometry.kind 'cube' is unknown: use a shape (can, cup, sphere, ellipsoid, duck, plush, "
         "block), mesh (OBJ/PLY/STL/GLB mesh file) or ply (3DGS PLY) with geometry.path"),
        (["object=can", "object.appearance.pattern=plaid"],
         "config error: object.appearance.pattern 'plaid' is unknown: use one of solid, bands, label, speckle, "
         "dimples, stripes, fur"),
        (["object=tomato", "object.interior=gravy"],
         "config error: object.interior 'gravy' matches no known interior material (cola, tomato_juice, "
         "orange_juice, water, polyester_fibrefill): name one of them, or set interior: null for a hollow or solid "
         "object"),
        (["object=rubber_ball", "object.material.youngs_modulus=2e13"],
         "config error: object.material.youngs_modulus 2e+13 Pa is above diamond's (1.2e+12 Pa): give Young's "
         "modulus in pascals (rubber 2e6, aluminium 6.9e10)"),
        (["object=rubber_ball", "control.displacement.eta=0.05"],
         "config error: control.displacement.eta 0.05 m lets a finger travel 0.0556 m (eta x the largest eq. 1 "
         "coefficient 1.11) into rubber_ball, whose half-width is 0.0325 m: two fingers would pass its centre; use "
         "eta below 0.0292 m"),
        (["object=can", "object.eta=0.1"],
         "config error: object.eta 0.1 m lets a finger travel 0.111 m (eta x the largest eq. 1 coefficient 1.11) "
         "into can, whose half-width is 0.033 m: two fingers would pass its centre; use eta below 0.0297 m"),
        (["oracle.backend=llm", "oracle.llm_url=https://llm.example.com/v1", "oracle.api_key_env=PRE49B_NO_SUCH_KEY"],
         "config error: oracle.api_key_env names PRE49B_NO_SUCH_KEY, which is not set: export "
         "PRE49B_NO_SUCH_KEY=<your API key> for https://llm.example.com (the key is never written to the config), "
         "or use oracle.backend=table"),
        (["oracle.backend=llm", "oracle.llm_url=http://127.0.0.1:9/v1"],
         "config error: oracle.llm_url http://127.0.0.1:9 does not answer (Connection refused): start the server, "
         "fix oracle.llm_url or use oracle.backend=table"),
    ]


@pytest.mark.parametrize("case", range(len(_settings_cases())))
def test_a_value_a_step_would_refuse_is_one_line_before_the_flow(compose_cfg, case):
    overrides, expected = _settings_cases()[case]
    assert _refusal(compose_cfg("squeeze", overrides)) == expected


def test_cuda_without_a_cuda_device_is_refused(compose_cfg):
    from flows.preflight_settings import cuda_devices

    if cuda_devices():
        pytest.skip("this machine has a CUDA device")
    for key in ("mpm.device", "render.device", "generation.device"):
        assert _refusal(compose_cfg("squeeze", [f"{key}=cuda"])) == (
            f"config error: {key} is cuda but no CUDA device is present (no NVIDIA driver or GPU found): use "
            f"{key}=auto or cpu")


def test_the_default_configs_pass_the_settings(compose_cfg):
    from flows.preflight_settings import check_settings

    for name in ("evaluate", "squeeze"):
        check_settings(compose_cfg(name, []))
    for obj in ("can", "plush_toy", "rubber_duck", "clay", "tomato", "orange", "rubber_ball", "paper_cup"):
        check_settings(compose_cfg("squeeze", [f"object={obj}"]))


# ------------------------------------------------------------------------------------------------ folders, env
def test_folders_a_file_or_an_unwritable_place_are_one_line(tmp_path, compose_cfg):
    from flows.preflight_env import check_folders

    (tmp_path / "afile").write_text("x")
    cases = [
        (f"paths.artifacts={tmp_path / 'afile'}", f"config error: paths.artifacts={tmp_path / 'afile'}: "
         f"{tmp_path / 'afile'} is a file, not a folder: give a folder you can write to "
         f"(paths.artifacts=/path/to/folder)"),
        (f"paths.reports={tmp_path / 'afile' / 'reports'}", f"config error: paths.reports={tmp_path / 'afile' / 'reports'}"
         f": {tmp_path / 'afile'} is a file, so {tmp_path / 'afile' / 'reports'} cannot be a folder: give a folder you "
         f"can write to (paths.reports=/path/to/folder)"),
        ("paths.artifacts=/sys/virsqueezer", "config error: paths.artifacts=/sys/virsqueezer: /sys is not writable "
         "(Permission denied): give a folder you can write to (paths.artifacts=/path/to/folder)"),
    ]
    for override, expected in cases:
        with pytest.raises(SystemExit) as exc:
            check_folders(compose_cfg("squeeze", [override]))
        assert str(exc.value) == expected
    check_folders(compose_cfg("squeeze", [f"paths.artifacts={tmp_path / 'new' / 'a'}"]))
    assert not (tmp_path / "new").exists()  # checked, not created


def test_no_room_for_the_artifacts_or_the_report_is_one_line(tmp_path, compose_cfg):
    """The run's estimate with more artifacts, or a larger report, than any disk holds: one line naming the folder;
    the report counts into the artifacts' need when both folders are on one file system (here both under /tmp)."""
    from dataclasses import replace

    from flows.preflight import estimate_work
    from flows.preflight_env import check_free_space

    cfg = compose_cfg("squeeze", [f"paths.artifacts={tmp_path / 'a'}", f"paths.reports={tmp_path / 'r'}"])
    est = estimate_work(cfg, 3.0)
    with pytest.raises(SystemExit) as exc:
        check_free_space(cfg, replace(est, total_bytes=2.0**70))
    assert str(exc.value).startswith(f"config error: paths.artifacts={tmp_path / 'a'}: the run's artifacts need up to "
                                     "1.07e+09 TiB (rollouts and g-buffers of the work estimate, and the report's "
                                     "5.78 MiB on the same file system) and its file system has ")
    assert str(exc.value).endswith(" free: free some space or give a folder on a larger disk "
                                   "(paths.artifacts=/path/to/folder)")
    with pytest.raises(SystemExit) as exc:
        check_free_space(cfg, replace(est, report_bytes=2.0**70))
    assert str(exc.value).startswith(f"config error: paths.reports={tmp_path / 'r'}: the run's report needs up to "
                                     "1.07e+09 TiB (the videos and figures of 1 scene, also embedded in index.html) "
                                     "and its file system has ")
    assert str(exc.value).endswith(" free: free some space or give a folder on a larger disk "
                                   "(paths.reports=/path/to/folder)")
    check_free_space(cfg, est)
    assert not (tmp_path / "a").exists() and not (tmp_path / "r").exists()  # checked, not created


def test_the_report_is_estimated_from_the_measured_one(compose_cfg):
    """One scene of 91 frames at 384 x 384 is the measured report (can, 6,058,886 bytes); the default grid's 16
    scenes sixteen of it; videos of four times the pixels four times the videos (919,860 bytes, embedded again)."""
    from flows.preflight import estimate_work

    assert estimate_work(compose_cfg("squeeze", ["object=can"]), 3.0).report_bytes == pytest.approx(6_058_886)
    assert estimate_work(compose_cfg("evaluate", []), 3.0).report_bytes == pytest.approx(16 * 6_058_886)
    large = estimate_work(compose_cfg("squeeze", ["render.video_width=768", "render.video_height=768"]), 3.0)
    assert large.report_bytes == pytest.approx(6_058_886 + 3 * 919_860 * (919_860 + 1_629_844 + 3_445_823) /
                                               (919_860 + 1_629_844))


def test_a_read_only_home_puts_the_caches_under_the_artifacts(tmp_path, compose_cfg, monkeypatch):
    from flows.preflight_env import redirect_caches

    (tmp_path / "home").write_text("not a folder")  # HOME that nothing can be written under
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    for var in ("XDG_CACHE_HOME", "XDG_CONFIG_HOME", "WARP_CACHE_PATH", "MPLCONFIGDIR"):
        monkeypatch.delenv(var, raising=False)
    cfg = compose_cfg("squeeze", [f"paths.artifacts={tmp_path / 'a'}"])
    home = tmp_path / "home"
    assert redirect_caches(cfg) == [
        f"Warp's kernel cache goes to {tmp_path / 'a' / '.cache' / 'warp'} (WARP_CACHE_PATH): its default "
        f"{home / '.cache' / 'warp'} cannot be written ({home} is a file, so {home / '.cache' / 'warp'} cannot be a "
        f"folder)",
        f"matplotlib's cache goes to {tmp_path / 'a' / '.cache' / 'matplotlib'} (MPLCONFIGDIR): its default "
        f"{home / '.config' / 'matplotlib'} cannot be written ({home} is a file, so {home / '.config' / 'matplotlib'} "
        f"cannot be a folder)"]
    assert os.environ["WARP_CACHE_PATH"] == str(tmp_path / "a" / ".cache" / "warp")
    monkeypatch.setenv("MPLCONFIGDIR", "/sys/mpl")
    with pytest.raises(SystemExit) as exc:
        redirect_caches(cfg)
    assert str(exc.value) == ("environment error: MPLCONFIGDIR=/sys/mpl: /sys is not writable (Permission denied): "
                              "point MPLCONFIGDIR at a folder you can write to, or unset it")


def test_a_stale_prefect_api_url_is_one_line(monkeypatch):
    from flows.preflight_env import check_prefect_api

    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:9/api")
    with pytest.raises(SystemExit) as exc:
        check_prefect_api()
    assert str(exc.value) == ("environment error: PREFECT_API_URL=http://127.0.0.1:9/api does not answer (Connection "
                              "refused): start that server (prefect server start) or unset PREFECT_API_URL (each run "
                              "then starts its own temporary server)")
    monkeypatch.delenv("PREFECT_API_URL")
    check_prefect_api()


def _main(tmp_path: Path, flow: str, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", f"flows.{flow}", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300, env={**os.environ, **(env or {})})


def test_from_the_real_main_unwritable_reports_and_a_stale_api_stop_before_any_folder(tmp_path):
    """An unwritable reports folder stops before Hydra makes its output folder; a stale PREFECT_API_URL before the
    flow starts.  One line on stderr each, no traceback."""
    out = _main(tmp_path, "squeeze", f"paths.artifacts={tmp_path / 'a'}", "paths.reports=/sys/reports")
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        "config error: paths.reports=/sys/reports: /sys is not writable (Permission denied): give a folder you can "
        "write to (paths.reports=/path/to/folder)"]
    assert not (tmp_path / "a").exists()
    out = _main(tmp_path, "squeeze", f"paths.artifacts={tmp_path / 'a'}", f"paths.reports={tmp_path / 'r'}",
                env={"PREFECT_API_URL": "http://127.0.0.1:9/api"})
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        "environment error: PREFECT_API_URL=http://127.0.0.1:9/api does not answer (Connection refused): start that "
        "server (prefect server start) or unset PREFECT_API_URL (each run then starts its own temporary server)"]
    assert "Traceback" not in out.stdout + out.stderr


# ------------------------------------------------------------------------------------------------ sweeps
def test_m_after_the_overrides_gets_a_usage_line(tmp_path):
    out = _main(tmp_path, "evaluate", "object=can", "-m", "signal.duration=1,2")
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        "usage: -m goes before the overrides: python -m flows.evaluate -m object=can signal.duration=1,2"]


def test_a_config_error_in_job_1_stops_the_sweep_before_job_0_runs(tmp_path):
    out = _main(tmp_path, "evaluate", "-m", "object=can", "control.force.gamma=1.5,-1", f"paths.artifacts={tmp_path / 'a'}",
                f"paths.reports={tmp_path / 'r'}", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        "sweep job 1 (control.force.gamma=-1): config error: control.force.gamma must be > 0, got -1.0"]
    assert not (tmp_path / "sweep").exists() and not (tmp_path / "a").exists()


def test_a_sweep_beyond_the_wall_limit_stops_before_job_0_naming_the_knob(tmp_path):
    """object=can is estimated at 35.9 s a job: each of three seeds passes limits.max_wall_hours=0.02 (72 s), the
    three together (108 s) do not."""
    out = _main(tmp_path, "evaluate", "-m", "object=can", "sampling.seed=0,1,2", "limits.max_wall_hours=0.02",
                f"paths.artifacts={tmp_path / 'a'}", f"paths.reports={tmp_path / 'r'}", f"hydra.sweep.dir={tmp_path / 's'}")
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        "work limit: the sweep's 3 jobs would take about 108 s one after another, above limits.max_wall_hours=0.02 "
        "(72 s): sweep fewer values or split the sweep (or raise limits.max_wall_hours)"]
    assert not (tmp_path / "s").exists() and not (tmp_path / "a").exists()


def test_a_job_whose_error_escaped_is_marked_and_the_summary_written(tmp_path):
    """Hydra's sweeper stops the sweep after a job whose error escaped it (no on_multirun_end): the callback's
    on_job_end records the job's one-line reason and writes the summary with every job's status."""
    from hydra.core.utils import JobReturn, JobStatus
    from omegaconf import OmegaConf

    from flows.sweep_summary import SweepSummary, job_status

    for job in ("0", "1"):
        (tmp_path / job / ".hydra").mkdir(parents=True)
        (tmp_path / job / ".hydra" / "overrides.yaml").write_text(f"- control.force.gamma={1.5 + int(job)}\n")
    ret = JobReturn()
    ret.status, ret.return_value = JobStatus.FAILED, MemoryError("cannot allocate the grid\nsecond line")
    config = OmegaConf.create({"hydra": {"mode": "MULTIRUN", "runtime": {"output_dir": str(tmp_path / "1")}}})
    SweepSummary().on_job_end(config, ret)
    assert job_status(tmp_path / "1") == "failed: cannot allocate the grid"
    text = (tmp_path / "sweep_summary.md").read_text()
    assert "| 1 | 2.5 | failed: cannot allocate the grid |" in text and "| 0 | 1.5 | not finished |" in text


# ------------------------------------------------------------------------------------------------ cut report
def test_a_sigterm_during_the_report_write_says_report_incomplete_and_the_next_run_rewrites_it(tmp_path):
    """A real SIGTERM while :func:`flows.report_marker.writing_report` is open: the stop line says "report
    incomplete" and names the folder, REPORT_INCOMPLETE.txt stays; the next run of the same config finds it."""
    code = ("import os, signal, sys, time; from pathlib import Path; from flows.lifecycle import install_stop_handlers;"
            "from flows.report_marker import writing_report; install_stop_handlers(); d = Path(sys.argv[1]);"
            "ctx = writing_report(d, 'abc123'); ctx.__enter__(); (d / 'report.md').write_text('# half');"
            "os.kill(os.getpid(), signal.SIGTERM); time.sleep(30)")
    folder = tmp_path / "reports" / "evaluate-20261206-010203"
    out = subprocess.run([sys.executable, "-c", code, str(folder)], cwd=REPO, capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 128 + signal.SIGTERM
    assert out.stderr.strip().splitlines() == [
        f"stopped by SIGTERM: the steps that finished are kept, the rest will run on the next start (same command); "
        f"report incomplete: {folder} (REPORT_INCOMPLETE.txt), the next start rewrites it"]
    assert (folder / "REPORT_INCOMPLETE.txt").read_text().startswith("abc123\n")
    from flows.pipeline import _report_name

    assert _report_name(tmp_path / "reports", "evaluate", "abc123") == folder.name
    assert _report_name(tmp_path / "reports", "evaluate", "another config") != folder.name


def test_a_report_written_whole_leaves_no_marker(tmp_path):
    from flows.report_marker import INCOMPLETE, writing_report

    with writing_report(tmp_path / "r", "d"):
        assert (tmp_path / "r" / INCOMPLETE).is_file()
    assert not (tmp_path / "r" / INCOMPLETE).exists()
    with pytest.raises(OSError), writing_report(tmp_path / "r", "d"):
        raise OSError("disk full")
    assert (tmp_path / "r" / INCOMPLETE).is_file()


# ------------------------------------------------------------------------------------------------ progress
def test_the_heartbeat_prints_a_progress_line(capsys):
    import time

    from flows.heartbeat import heartbeat, progress_line
    from flows.runtime import RunTable, TaskRow

    with heartbeat(400.0, interval=0.05):
        time.sleep(0.2)
    lines = capsys.readouterr().out.splitlines()
    assert lines and lines[0].startswith("progress: starting the task runner and submitting the steps, ")
    assert lines[0].endswith(" elapsed (work estimate ~6.7 min)")
    table = RunTable(total=17, rows=[TaskRow("can", "object_model", "ran", 1.0, 0, "", "")])
    assert progress_line(table, 75.0, 400.0) == "progress: 1 of 17 steps finished, 75 s elapsed (work estimate ~6.7 min)"
