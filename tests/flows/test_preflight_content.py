"""Content the preflight looks at (issue 49): a user's 3DGS PLY, mesh and recording that are well-formed but cannot
make a run, each refused with exactly one line naming the file and the fix, before any step, server or artifact.

The files are real, written with the project's own writers (:func:`write_gaussian_ply`, :func:`write_recording`,
trimesh's exporters).  Each case asserts the line :func:`flows.preflight.preflight` stops with (Python prints a
``SystemExit``'s message as the one line on stderr); two cases run the real entry point in a subprocess.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tasks.control.gaussian_ply import write_gaussian_ply

REPO = Path(__file__).resolve().parents[2]
BOX = "object.geometry.size=[0.05,0.05,0.05]"


def _splat(path: Path, n: int = 2000, scale: float = 0.002, opacity: float = 0.9) -> Path:
    """``n`` Gaussians on a sphere 5 cm across (file units = m): std ``scale``, opacity ``opacity``, grey."""
    rng = np.random.default_rng(0)
    means = rng.normal(size=(n, 3))
    means = 0.025 * means / np.linalg.norm(means, axis=1, keepdims=True)
    return write_gaussian_ply(path, means, np.full((n, 3), scale), np.tile([1.0, 0, 0, 0], (n, 1)), np.full(n, opacity),
                              np.full((n, 3), 0.5))


def _refusal(compose_cfg, tmp_path: Path, overrides: list[str]) -> str:
    from flows.preflight import preflight

    with pytest.raises(SystemExit) as exc:
        preflight(compose_cfg("squeeze", [f"paths.artifacts={tmp_path / 'artifacts'}", *overrides]))
    assert not (tmp_path / "artifacts").exists()  # nothing written, no step ran
    return str(exc.value)


def _ply(path: Path) -> list[str]:
    return ["object=clay", "object.geometry.kind=ply", BOX, f"object.geometry.path={path}"]


def _mesh(path: Path) -> list[str]:
    return ["object=clay", "object.geometry.kind=mesh", BOX, f"object.geometry.path={path}"]


# ----------------------------------------------------------------------------------------------- 3DGS PLY
def test_a_transparent_splat_is_refused_naming_the_opacity_encoding(tmp_path, compose_cfg):
    path = _splat(tmp_path / "ghost.ply", opacity=1 / (1 + np.exp(20.0)))  # stored logit -20
    assert _refusal(compose_cfg, tmp_path, _ply(path)) == (
        f"input error: object.geometry.path: PLY {path}: 0 of 2000 Gaussians have an opacity of at least 1/255 "
        f"(median 2.06e-09, the sigmoid of the stored 'opacity'): every frame would be empty background; store "
        f"opacity as logit(opacity) as the Inria layout does (4.6 for 0.99), or export the trained splat again")


def test_gaussians_larger_than_the_object_are_refused(tmp_path, compose_cfg):
    path = _splat(tmp_path / "fog.ply", scale=5.0)  # 5 m Gaussians on a 5 cm sphere
    assert _refusal(compose_cfg, tmp_path, _ply(path)) == (
        f"input error: object.geometry.path: PLY {path}: the median Gaussian's largest standard deviation (exp of "
        f"scale_0..2) is 5, more than the 0.05 its centres span (file units): every frame would be one solid colour; "
        f"store scale_0..2 as log(standard deviation) in the units of x y z as the Inria layout does, or export the "
        f"trained splat again")


@pytest.mark.parametrize("n", [2, 7])
def test_too_few_gaussians_are_refused_before_the_flow(tmp_path, compose_cfg, n):
    path = _splat(tmp_path / f"few{n}.ply", n=n)
    assert _refusal(compose_cfg, tmp_path, _ply(path)) == (
        f"input error: object.geometry.path: PLY {path} holds only {n} Gaussians: at least 8 are needed to make a "
        f"surface; export the whole trained splat")


def test_nan_positions_are_named(tmp_path, compose_cfg):
    path = _splat(tmp_path / "nan.ply")
    raw = bytearray(path.read_bytes())
    body = raw.index(b"end_header\n") + len(b"end_header\n")
    raw[body + 4:body + 8] = np.float32(np.nan).tobytes()  # y of Gaussian 0
    path.write_bytes(bytes(raw))
    assert _refusal(compose_cfg, tmp_path, _ply(path)) == (
        f"input error: object.geometry.path: PLY {path}: 1 Gaussian has NaN/inf values (in y, e.g. Gaussian 0): "
        f"remove them from the splat (or export it again) before loading")


def test_a_mesh_saved_as_ply_is_told_to_use_kind_mesh(tmp_path, compose_cfg):
    path = tmp_path / "ball.ply"
    trimesh.creation.icosphere(subdivisions=1, radius=0.025).export(path)
    assert _refusal(compose_cfg, tmp_path, _ply(path)) == (
        f"input error: object.geometry.path: PLY {path} is a triangle mesh (80 faces, no Gaussian properties such "
        f"as f_dc_0), not a 3DGS splat: give it as a mesh with geometry.kind=mesh (e.g. object.geometry.kind=mesh)")


def test_a_good_splat_passes(tmp_path, compose_cfg, capsys):
    from flows.preflight import preflight

    preflight(compose_cfg("squeeze", _ply(_splat(tmp_path / "ball.ply"))))
    assert capsys.readouterr().out == ""  # fits geometry.size as it is: nothing to state


# ----------------------------------------------------------------------------------------------- meshes
def test_a_nan_vertex_is_named_as_nan_not_as_holes(tmp_path, compose_cfg):
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.025)
    vertices = ball.vertices.copy()
    vertices[5] = np.nan
    path = tmp_path / "nan.obj"
    trimesh.Trimesh(vertices, ball.faces, process=False).export(path)
    assert _refusal(compose_cfg, tmp_path, _mesh(path)) == (
        f"input error: object.geometry.path: mesh {path} has 1 vertex with NaN/inf coordinates (e.g. vertex 5): fix "
        f"or delete them in the modelling tool and export again")


def test_inconsistent_winding_is_named_with_the_file_and_the_repair(tmp_path, compose_cfg):
    ball = trimesh.creation.icosphere(subdivisions=1, radius=0.025)
    faces = ball.faces.copy()
    faces[::2] = faces[::2, ::-1]  # every other face flipped
    path = tmp_path / "flipped.obj"
    trimesh.Trimesh(ball.vertices, faces, process=False).export(path)
    line = _refusal(compose_cfg, tmp_path, _mesh(path))
    assert line.startswith(f"input error: object.geometry.path: mesh {path} has inconsistent winding (")
    assert line.endswith("): inside and outside are ambiguous; make the winding consistent, e.g. "
                         "trimesh.repair.fix_winding (or Blender's Mesh > Normals > Recalculate Outside), and export "
                         "again")
    # the suggested repair is enough: the fixed file passes
    mesh = trimesh.load(path, force="mesh")
    trimesh.repair.fix_winding(mesh)
    mesh.export(tmp_path / "fixed.obj")
    from flows.preflight import preflight

    preflight(compose_cfg("squeeze", _mesh(tmp_path / "fixed.obj")))


# ----------------------------------------------------------------------------------------------- recordings
def _csv(path: Path, sep: str = ",", decimal: str = ".") -> Path:
    """The 1 s squeeze recording of tests/flows/test_preflight.py, written with the project's writer and then
    re-separated as a spreadsheet in a decimal-comma locale would export it."""
    from tests.flows.test_preflight import _recording

    text = _recording(path).read_text()
    path.write_text(text.replace(",", "\0").replace(".", decimal).replace("\0", sep))
    return path


def test_recording_separators_and_decimal_commas_are_named(tmp_path, compose_cfg):
    semi, tab = _csv(tmp_path / "semi.csv", sep=";"), _csv(tmp_path / "tab.csv", sep="\t", decimal=",")
    comma = _csv(tmp_path / "comma.csv", decimal=",")
    head = "'0,0\\t0,0\\t0,0\\t0,0\\t0,0\\t0,0\\t-0,045\\t0,0\\t0,0\\t0,045\\t0,0\\t0,01\\t0,045\\t0,0\\t0,02\\t0,045\\t0,0\\t0'"
    cases = [
        (semi, f"recording {semi} separates its columns with semicolons (';'): save it as comma-separated text (e.g. "
               f"pandas df.to_csv(path), or a spreadsheet's CSV export with field separator ',')"),
        (tab, f"recording {tab} separates its columns with tabs and writes decimal commas (line 2 reads {head}... "
              f"(128 characters)): save it as comma-separated text with decimal points (e.g. pandas df.to_csv(path), "
              f"or a spreadsheet's CSV export with field separator ',' and decimal separator '.')"),
        (comma, f"recording {comma}: line 2 has 56 comma-separated fields where the header has 28, and no decimal "
                f"point: the numbers look written with decimal commas ('0,0,0,0,0,0,0,0,0,0,0,0,-0,045,0,0,0,0,0,045,"
                f"0,0,0,01,0,045,0,0,0,02,0,045,0,0,0'... (128 characters)); write decimal points (0.5, not 0,5)"),
    ]
    for path, expected in cases:
        line = _refusal(compose_cfg, tmp_path, ["object=can", "signal=csv", f"signal.path={path}"])
        assert line == f"input error: signal.path: {expected}"


# ----------------------------------------------------------------------------------------------- the real main
def _main(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "VIRSQUEEZER_ARTIFACTS": str(tmp_path / "artifacts")}
    return subprocess.run([sys.executable, "-m", "flows.squeeze", f"paths.artifacts={tmp_path / 'artifacts'}",
                           f"paths.reports={tmp_path / 'reports'}", *overrides],
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=env)


@pytest.mark.parametrize("case", ["transparent splat", "unquoted unicode path"])
def test_the_real_main_prints_the_one_line_and_starts_nothing(tmp_path, case):
    if case == "transparent splat":
        path = _splat(tmp_path / "ghost.ply", opacity=1 / (1 + np.exp(20.0)))
        out = _main(tmp_path, *_ply(path))
        expected = f"input error: object.geometry.path: PLY {path}: 0 of 2000 Gaussians have an opacity of at least"
    else:
        out = _main(tmp_path, "signal=csv", "signal.path=/data/données.csv")
        expected = ("config error: the override signal.path=/data/données.csv holds characters Hydra reads only inside "
                    "quotes: quote its value, e.g. 'signal.path=\"/data/données.csv\"' (single quotes around it all for "
                    "the shell)")
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 1, out.stderr
    assert len(lines) == 1 and lines[0].startswith(expected), out.stderr
    assert "Traceback" not in out.stderr + out.stdout and "temporary server" not in out.stdout.lower()
    assert not list((tmp_path / "artifacts").glob("*/*/*.zarr"))


def test_the_visibility_threshold_is_the_rasterisers():
    """A Gaussian the preflight counts as visible is one the renderers draw (they skip alpha below ALPHA_MIN)."""
    from tasks.control.splat_content import VISIBLE_OPACITY
    from tasks.render.splat_torch import ALPHA_MIN

    assert VISIBLE_OPACITY == ALPHA_MIN


def test_the_quoting_hint_is_what_hydra_reads():
    """The hinted override parses to the path given (each job's path in a -m sweep); a flag's value and ASCII
    overrides are left alone."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from flows.override_quoting import check_override_quoting

    parser = OverridesParser.create()
    for argv, values in ((["signal.path=/d/é.csv"], ["/d/é.csv"]),
                         (["-m", "signal.path=/d/é.csv,/d/ü.csv"], ['"/d/é.csv"', '"/d/ü.csv"'])):
        with pytest.raises(SystemExit) as exc:
            check_override_quoting(argv)
        hinted = str(exc.value).split("e.g. '")[1].split("' (single quotes")[0]
        parsed = parser.parse_overrides([hinted])[0]
        assert (list(parsed.sweep_string_iterator()) if parsed.is_sweep_override() else [parsed.value()]) == values
    check_override_quoting(["-cd", "/tmp/é", "object=can", "signal.path=/d/e.csv"])


# ----------------------------------------------------------------------------------------------- sweeps
@pytest.mark.parametrize("kind", ["ply", "recording"])
def test_a_bad_input_file_of_job_1_stops_the_sweep_before_job_0_runs(tmp_path, kind):
    """The sweep's pre-check reads every job's input files (flows.hydra_checks.PreflightCallback): job 0's file is
    good, job 1's is refused with the single-run preflight's line, prefixed with the job, before job 0 runs."""
    if kind == "ply":
        good, bad = _splat(tmp_path / "good.ply"), _splat(tmp_path / "few7.ply", n=7)
        overrides = [*_ply(Path(f"{good},{bad}"))]
        key, why = "object.geometry.path", (f"PLY {bad} holds only 7 Gaussians: at least 8 are needed to make a "
                                            f"surface; export the whole trained splat")
    else:
        from tests.flows.test_preflight import _recording

        good, bad = _recording(tmp_path / "good.csv"), _csv(tmp_path / "semi.csv", sep=";")
        overrides = ["object=can", "signal=csv", f"signal.path={good},{bad}"]
        key, why = "signal.path", (f"recording {bad} separates its columns with semicolons (';'): save it as "
                                   f"comma-separated text (e.g. pandas df.to_csv(path), or a spreadsheet's CSV export "
                                   f"with field separator ',')")
    out = subprocess.run([sys.executable, "-m", "flows.squeeze", "-m", *overrides,
                          f"paths.artifacts={tmp_path / 'artifacts'}", f"paths.reports={tmp_path / 'reports'}",
                          f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=REPO, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 1 and out.stderr.strip().splitlines() == [
        f"sweep job 1 ({key}={bad}): input error: {key}: {why}"], out.stderr
    assert not (tmp_path / "sweep").exists() and not (tmp_path / "artifacts").exists()


def test_a_sweep_reads_each_input_file_once(tmp_path, compose_cfg, capsys):
    """Three jobs on one splat: the file is read by the first job's check and its bounds serve the others; each job
    still gets its own fit into its geometry.size."""
    from flows.preflight import check_config, check_geometry_files

    path = _splat(tmp_path / "one.ply")
    seen: dict = {}
    for gamma in (1.5, 2.0, 2.5):
        check_config(compose_cfg("squeeze", [*_ply(path), f"control.force.gamma={gamma}"]), seen)
    assert list(seen) == [("geometry", "ply", str(path))] and seen[("geometry", "ply", str(path))][2] == f"PLY {path}"
    assert capsys.readouterr().out == ""  # the sweep's check prints no fit: each job prints its own when it runs
    check_geometry_files(compose_cfg("squeeze", [*_ply(path), "object.geometry.size=[0.1,0.1,0.1]"]), seen)
    assert capsys.readouterr().out.startswith(f"object.geometry.path: PLY {path} spans ")
