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

REPO = Path(__file__).resolve().parents[1]


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
    assert msg.count("huggingface-cli download") == 3 and "nothing is downloaded" in msg
    assert not (tmp_path / "artifacts").exists()
