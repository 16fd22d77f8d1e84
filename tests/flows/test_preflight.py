"""Bad inputs from the command line: one line naming the input and the fix, before any flow starts.

Each case runs the real entry point (``python -m flows.squeeze``) in a subprocess and asserts what the user
sees: exit status 1, exactly one line on stderr with the key and the fix, no traceback, and no Prefect server
started for nothing (Prefect logs its temporary server's start-up, and no flow run appears).
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _run(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "VIRSQUEEZER_ARTIFACTS": str(tmp_path / "artifacts")}
    return subprocess.run([sys.executable, "-m", "flows.squeeze", f"paths.artifacts={tmp_path / 'artifacts'}",
                           f"paths.reports={tmp_path / 'reports'}", *overrides],
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=env)


def _cases(tmp_path: Path) -> list[tuple[list[str], str]]:
    (tmp_path / "not_a_mesh.obj").write_text("this is a shopping list, not a mesh\nmilk\n")
    (tmp_path / "notes.ply").write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n")
    huge = tmp_path / "huge.csv"
    with open(huge, "wb") as fh:  # sparse: above the size limit without using the disk
        fh.write(b"time,flex_thumb\n")
        fh.truncate(256 * 2**20 + 1)
    return [
        (["signal=csv", f"signal.path={tmp_path / 'missing.csv'}"],
         "input error: signal.path: "),
        (["signal=csv", f"signal.path={huge}"], "above the 256.0 MiB limit"),
        (["object=clay", "object.geometry.kind=mesh", f"object.geometry.path={tmp_path / 'not_a_mesh.obj'}"],
         "input error: object.geometry.path: mesh "),
        (["object=clay", "object.geometry.kind=ply", f"object.geometry.path={tmp_path / 'notes.ply'}"],
         "input error: object.geometry.path: PLY "),
        (["object=clay", "object.geometry.kind=mesh"], "object.geometry.path is required"),
        (["control.force.gamma=-1"], "config error: control.force.gamma must be > 0"),
    ]


@pytest.mark.parametrize("case", range(6))
def test_a_bad_input_is_one_line_before_any_flow_starts(tmp_path, case):
    overrides, expected = _cases(tmp_path)[case]
    out = _run(tmp_path, *overrides)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 1, out.stderr
    assert len(lines) == 1, out.stderr
    assert expected in lines[0]
    assert "Traceback" not in out.stderr + out.stdout
    assert "temporary server" not in (out.stderr + out.stdout).lower()
    assert not list((tmp_path / "artifacts").glob("*/*/*.zarr"))


def test_missing_diffusion_weights_name_each_model_and_where_it_goes(tmp_path, compose_cfg):
    """generation=diffusers with an empty weights folder stops before the flow with one message naming each
    missing model, the folder expected and the command that fetches it; nothing is loaded or written."""
    from flows.preflight import preflight

    cfg = compose_cfg("squeeze", ["generation=diffusers", f"generation.weights={tmp_path / 'models'}",
                                  f"paths.artifacts={tmp_path / 'artifacts'}"])
    with pytest.raises(SystemExit) as exc:
        preflight(cfg)
    msg = str(exc.value)
    assert msg.startswith("input error: generation.weights: ")
    for model, folder in (("an SD-1.5 base", "stable-diffusion"), ("an AnimateDiff motion adapter", "motion-adapter"),
                          ("a depth ControlNet", "controlnet-depth")):
        assert model in msg and str(tmp_path / "models" / folder) in msg
    assert msg.count("hf download ") == 3 and msg.count("--include") == 9 and "nothing is downloaded" in msg
    assert not (tmp_path / "artifacts").exists()


# ----------------------------------------------------------------------------------------------- issue 15
def _recording(path: Path, scale: float = 1.0, offset: float = 0.0, time_scale: float = 1.0) -> Path:
    """A 1 s squeeze of the default object at 100 Hz: fingertips 4-5 cm from its centre, palm 5 cm behind;
    positions x ``scale`` + ``offset`` (m), times x ``time_scale``."""
    import numpy as np

    from tasks.control.recording import write_recording

    n = 101
    t = np.linspace(0.0, 1.0, n)
    tips = np.zeros((n, 5, 3)) + [0.045, 0.0, 0.0] + np.arange(5)[None, :, None] * [0.0, 0.0, 0.01]
    tips[:, 0] = [-0.045, 0.0, 0.0]
    signals = {"time": t * time_scale, "flexion": np.outer(0.8 * np.sin(np.pi * t), np.ones(5)),
               "fingertip_positions": tips * scale + offset, "palm_position": np.tile([0.0, -0.05, 0.0], (n, 1)) * scale
               + offset, "palm_orientation": np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))}
    return write_recording(path, signals)


def _flat_mesh(path: Path) -> Path:
    """A closed (watertight) tetrahedron whose four corners lie in one plane: zero volume."""
    import numpy as np
    import trimesh

    v = np.array([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0.015, 0.015, 0]], float)
    trimesh.Trimesh(v, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [2, 0, 3]], process=False).export(path)
    return path


def _evaluate(tmp_path: Path, *overrides: str) -> tuple[subprocess.CompletedProcess, float]:
    import time

    env = {**os.environ, "VIRSQUEEZER_ARTIFACTS": str(tmp_path / "artifacts")}
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "flows.evaluate", f"paths.artifacts={tmp_path / 'artifacts'}",
                          f"paths.reports={tmp_path / 'reports'}", *overrides],
                         cwd=REPO, capture_output=True, text=True, timeout=300, env=env)
    return out, time.perf_counter() - t0


def _issue15_cases(tmp_path: Path) -> list[tuple[list[str], str]]:
    import numpy as np
    import trimesh

    mm = _recording(tmp_path / "mm.csv", scale=1000.0)
    ms = _recording(tmp_path / "ms.csv", time_scale=1000.0)
    trimesh.creation.icosphere(radius=500.0).export(tmp_path / "km.stl")
    flat = _flat_mesh(tmp_path / "flat.obj")
    reach = float(np.linalg.norm([0.045, 0.05, 0.04]) * 1000)  # the pinky (4 cm up) to the palm, in mm
    mesh = ["object=clay", "object.geometry.kind=mesh", "object.geometry.size=[0.05,0.05,0.05]"]
    return [
        (["+control.force.gama=2"], "config error: control.force.gama is not a key of ForceConfig (it would be "
                                    "ignored): did you mean control.force.gamma?"),
        (["control.displacement.eta=inf"], "config error: control.displacement.eta must be a finite number, got inf"),
        (["control.contact.sigma_max=inf"], "config error: control.contact.sigma_max must be a finite number, got inf"),
        (["grid.objects=[]"], "config error: grid.objects is empty: name at least one object, e.g. [rubber_ball] "
                              "(known ['can', 'clay', 'orange', 'paper_cup', 'plush_toy', 'rubber_ball', "
                              "'rubber_duck', 'tomato'])"),
        (["signal.duration=1e5"], "work limit: 3000001 frames per squeeze (signal.duration 100000 s x "
                                  "control.smoothing.frame_rate 30 Hz), above limits.max_frames=9000: shorten the "
                                  "squeeze or lower the frame rate (or raise limits.max_frames)"),
        (["control.smoothing.frame_rate=1e6"], "work limit: 3000001 frames per squeeze (signal.duration 3 s x "
                                               "control.smoothing.frame_rate 1e+06 Hz), above limits.max_frames=9000: "
                                               "shorten the squeeze or lower the frame rate (or raise "
                                               "limits.max_frames)"),
        (["object=can", "signal=csv", f"signal.path={mm}"],
         f"input error: signal.path: recording {mm}: fingertip positions reach {reach:.4g} m from the palm (a hand "
         f"spans ~0.2 m); the CSV looks like millimetres: divide the tip_ and palm_x/y/z columns by 1000"),
        (["object=can", "signal=csv", f"signal.path={ms}"],
         f"input error: signal.path: recording {ms}: time steps by 10 per sample (median; 1000 in all), a 0.1 Hz "
         f"sensor where SenseGlove streams at 100-1000 Hz; the time column looks like milliseconds: divide it by "
         f"1000 (seconds are expected)"),
        ([*mesh, f"object.geometry.path={tmp_path / 'km.stl'}"],
         f"input error: object.geometry.path: mesh {tmp_path / 'km.stl'} spans 1e+03 x 1e+03 x 1e+03 (file units) "
         f"and would be scaled by 5e-05 to fit geometry.size [0.05, 0.05, 0.05] m: export it in metres or "
         f"millimetres, or set geometry.size to the object's real size"),
        ([*mesh, f"object.geometry.path={flat}"],
         f"input error: object.geometry.path: mesh {flat} encloses no volume (0 within a 0.05 x 0.05 x 0 box, file "
         f"units): it is flat (a sheet); give it a thickness (e.g. Blender's Solidify modifier) and export a closed "
         f"solid"),
    ]


@pytest.mark.parametrize("case", range(10))
def test_issue15_mistakes_are_one_line_from_the_real_main(tmp_path, case):
    """Each mistake that used to run and squeeze nothing (or run for hours) stops python -m flows.evaluate with
    exactly this line, before any step, server or artifact."""
    overrides, expected = _issue15_cases(tmp_path)[case]
    out, _ = _evaluate(tmp_path, *overrides)
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 1, out.stderr
    assert lines == [expected]
    assert "Traceback" not in out.stdout and "temporary server" not in out.stdout.lower()
    assert not list((tmp_path / "artifacts").glob("*/*/*.zarr"))


def test_work_limits_refuse_fast_and_the_default_grid_passes_with_a_margin(compose_cfg):
    """The estimate needs the config alone: refusing a 1e5 s squeeze takes well under 5 s; the default grid
    stays far below every default limit."""
    import time

    from flows.preflight import estimate_work, preflight

    cfg = compose_cfg("evaluate", ["signal.duration=1e5"])
    t0 = time.perf_counter()
    with pytest.raises(SystemExit, match="^work limit: 3000001 frames per squeeze"):
        preflight(cfg)
    assert time.perf_counter() - t0 < 5.0
    cfg = compose_cfg("evaluate", [])
    est = estimate_work(cfg, cfg.signal.duration)
    assert est.frames == 91 and est.substeps == 100
    assert est.frames * 50 < cfg.limits.max_frames
    assert est.particle_steps * 50 < cfg.limits.max_particle_steps
    assert est.largest_bytes * 50 < cfg.limits.max_artifact_bytes
    with pytest.raises(SystemExit) as exc:
        preflight(compose_cfg("evaluate", ["limits.max_particle_steps=1e8"]))
    assert str(exc.value) == (
        f"work limit: about {est.particle_steps:.3g} particle-substeps (up to {est.particles} particles x 100 substeps "
        f"x 91 frames per object and variant), above limits.max_particle_steps=1e+08: raise "
        f"sampling.particle_spacing, lower mpm.target_substeps_per_frame or run fewer objects (or raise the limit)")


def test_a_rescaled_mesh_is_stated_and_a_recording_far_from_the_object_is_refused(tmp_path, compose_cfg, capsys):
    """A mesh in millimetres is fitted into geometry.size with a visible line giving the factor, one of a micron
    is refused; a recording in another frame (1 m away) is refused, naming the object."""
    import trimesh

    from flows.preflight import preflight

    trimesh.creation.icosphere(radius=25.0).export(tmp_path / "mm.stl")
    preflight(compose_cfg("squeeze", ["object=clay", "object.geometry.kind=mesh", "object.geometry.size=[0.05,0.05,0.05]",
                                      f"object.geometry.path={tmp_path / 'mm.stl'}"]))
    assert capsys.readouterr().out.splitlines() == [
        f"object.geometry.path: mesh {tmp_path / 'mm.stl'} spans 50 x 50 x 50 (file units): scaled by 0.001 to fit "
        f"geometry.size [0.05, 0.05, 0.05] m"]
    trimesh.creation.icosphere(radius=5e-7).export(tmp_path / "um.stl")  # 1 micron across: refused, not rescaled
    with pytest.raises(SystemExit) as exc:
        preflight(compose_cfg("squeeze", ["object=clay", "object.geometry.kind=mesh",
                                          "object.geometry.size=[0.05,0.05,0.05]", f"object.geometry.path={tmp_path / 'um.stl'}"]))
    assert str(exc.value) == (
        f"input error: object.geometry.path: mesh {tmp_path / 'um.stl'} spans 1e-06 x 1e-06 x 1e-06 (file units) and "
        f"would be scaled by 5e+04 to fit geometry.size [0.05, 0.05, 0.05] m: export it in metres or millimetres, or "
        f"set geometry.size to the object's real size")
    far = _recording(tmp_path / "far.csv", offset=1.0)
    with pytest.raises(SystemExit) as exc:
        preflight(compose_cfg("squeeze", ["object=can", "signal=csv", f"signal.path={far}"]))
    assert str(exc.value).startswith("input error: signal.path: no fingertip comes within 0.25 m of can (object; closest ")
    assert str(exc.value).endswith("nothing would be squeezed; write the positions in the object's frame (metres, "
                                   "object centred at the origin, z up)")
    preflight(compose_cfg("squeeze", ["object=can", "signal=csv", f"signal.path={_recording(tmp_path / 'ok.csv')}"]))


def test_llm_judge_settings_are_checked_before_the_flow(compose_cfg):
    from flows.preflight import preflight

    with pytest.raises(SystemExit) as exc:
        preflight(compose_cfg("squeeze", ["llm_judge.url=ftp://judge.example/v1"]))
    assert str(exc.value).startswith("config error: llm_judge.url ") and "must be the http:// or https://" in str(exc.value)
    with pytest.raises(SystemExit) as exc:
        preflight(compose_cfg("squeeze", ["llm_judge.url=http://127.0.0.1:9/v1", "llm_judge.frames=0"]))
    assert str(exc.value) == "config error: llm_judge.frames 0 must be an integer >= 1 (e.g. 8)"


# ----------------------------------------------------------------------------------------------- stability suite
@pytest.mark.parametrize("override, expected", [
    ("mpm.dt=inf", "config error: mpm.dt must be a finite number, got inf"),
    ("catalog.clay.material.density=nan", "config error: catalog.clay.material.density must be a finite number, got nan"),
    ("+control.force.gama=2", "config error: control.force.gama is not a key of ForceConfig (it would be ignored): "
                              "did you mean control.force.gamma?"),
    ("+mpm.massscaling=off", "config error: mpm.massscaling is not a key of MPMConfig (it would be ignored): did "
                             "you mean mpm.mass_scaling?"),
    ("signal.duration=-1", "config error: signal.duration must be > 0 s, got -1.0"),
])
def test_a_bad_stability_input_is_one_line_before_any_case_runs(compose_cfg, capsys, override, expected):
    """python -m flows.studies.stability goes through the same checks as the pipeline's mains: its first call
    (:func:`flows.preflight.preflight_stability`) stops with exactly this line (Python prints a SystemExit's message
    as the one line on stderr) and prints nothing before it (no case, no report folder)."""
    from flows.preflight import preflight_stability

    with pytest.raises(SystemExit) as exc:
        preflight_stability(compose_cfg("study/stability", [override]))
    assert str(exc.value) == expected
    assert capsys.readouterr().out == ""


def test_preflight_imports_no_prefect():
    """The checks run before Prefect is loaded (and so before a server can start): after a full preflight of the
    default grid, no Prefect module is imported."""
    code = ("import sys; from tests.conftest import compose; from flows.preflight import preflight; "
            "preflight(compose('evaluate', [])); print(sorted(m for m in sys.modules if m.split('.')[0] == 'prefect'))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[-1] == "[]"


# ----------------------------------------------------------------------------------------------- argparse entry points
def test_benchmark_and_human_study_refuse_bad_input_in_one_line(tmp_path, capsys, compose_cfg):
    """python -m flows.bench.mpm (its config's check, :func:`tasks.verification.mpm_throughput.check_scene_config`)
    and python -m flows.human_study stop on a bad key or a missing file with one line naming it, before Warp is
    loaded or anything is read or written."""
    import flows.human_study
    from tasks.verification.mpm_throughput import check_scene_config

    for override, expected in [
        ("E=inf", "input error: E must be a finite number > 0, got inf"),
        ("nu=0.5", "input error: nu must be in [0, 0.5), got 0.5"),
        ("n_grid=2000", "input error: n_grid 2000 with cube 0.4 and ppc_axis 2 gives 4.1e+09 particles, above "
                        "2e+07: lower one of them"),
    ]:
        with pytest.raises(SystemExit) as exc:
            check_scene_config(compose_cfg("study/bench_mpm", [override]))
        assert str(exc.value) == expected
    out = subprocess.run([sys.executable, "-m", "flows.bench.mpm", "nu=0.5", f"out={tmp_path / 'bench'}"], cwd=REPO,
                         capture_output=True, text=True, timeout=120)  # the entry point checks before its work
    assert out.returncode == 1 and out.stderr.strip().splitlines()[-1] == "input error: nu must be in [0, 0.5), got 0.5"
    assert not (tmp_path / "bench").exists()
    report = tmp_path / "evaluate-1"
    with pytest.raises(SystemExit) as exc:
        flows.human_study.main(["build", str(report)])
    assert str(exc.value) == (f"input error: report folder {report} does not exist: give a run's report folder "
                              "(reports/evaluate-<time>)")
    report.mkdir()
    with pytest.raises(SystemExit) as exc:
        flows.human_study.main(["analyse", str(report), str(tmp_path / "a.csv")])
    assert str(exc.value) == (f"input error: {report / 'human_study' / 'key.json'} does not exist: analyse the report "
                              f"folder whose questionnaire was built (python -m flows.human_study build {report})")
    (report / "human_study").mkdir()
    (report / "human_study" / "key.json").write_text('{"format": "something else"}')
    with pytest.raises(SystemExit) as exc:
        flows.human_study.main(["analyse", str(report), str(tmp_path / "a.csv")])
    assert str(exc.value) == f"input error: answer file(s) not found: {tmp_path / 'a.csv'}"
    (tmp_path / "a.csv").write_text("x\n")
    with pytest.raises(SystemExit) as exc:
        flows.human_study.main(["analyse", str(report), str(tmp_path / "a.csv")])
    assert str(exc.value).startswith(f"input error: {report / 'human_study' / 'key.json'} is not a questionnaire key")
    assert capsys.readouterr().out == ""
