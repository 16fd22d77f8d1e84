"""The step framework: declarations, the wiring that uses them, and code versions derived from imports."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from tasks.core.artifacts import Array
from tasks.core.code_version import code_version, import_closure
from tasks.core.params import ConfigPathError, Params, UndeclaredConfigRead, resolve_reads
from tasks.core.step import StepOutputError, StepSpec, WiringError, artifact_step

REPO = Path(__file__).resolve().parents[2]
STEP_MODULES = {
    "object_model": "tasks.control.object_model",
    "mpm_particles": "tasks.physics.mpm_particles",
    "squeeze_signals": "tasks.control.squeeze_signals",
    "signal_smoothing": "tasks.control.signal_smoothing",
    "force_coefficients": "tasks.control.force_coefficients",
    "contact_patches": "tasks.control.contact_patches",
    "dirichlet_field": "tasks.control.dirichlet_field",
    "material_oracle": "tasks.physics.material_oracle",
    "gravity_preload": "tasks.physics.gravity_preload",
    "mpm_rollout": "tasks.physics.mpm_rollout",
    "deformation_metrics": "tasks.evaluation.deformation_metrics",
    "gbuffer": "tasks.render.gbuffer",
    "conditions": "tasks.render.conditions",
    "effect": "tasks.generation.effect",
    "appearance_refinement": "tasks.generation.appearance_refinement",
    "video_metrics": "tasks.evaluation.video_metrics",
}


# ------------------------------------------------------------------------------------------ code versions
@pytest.fixture
def tree_copy(tmp_path):
    for package in ("tasks", "conf"):
        shutil.copytree(REPO / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__"))
    return tmp_path


def _versions(root: Path) -> dict[str, str]:
    return {step: code_version(module, root) for step, module in STEP_MODULES.items()}


def _edit(root: Path, rel: str) -> None:
    path = root / rel
    path.write_text(path.read_text() + "\n# an edit\n")


@pytest.mark.parametrize("edited,expected", [
    # reached only through the engine (tasks.physics.mpm -> solver -> kernels -> constitutive): the rollout, and the
    # particle fill, which places a thin wall's particles at the engine's own Gauss layers (mpm.thin_walls)
    ("tasks/physics/mpm/constitutive.py", {"mpm_particles", "gravity_preload", "mpm_rollout"}),
    # the recording format, imported by the signal step and by the smoothing step (its validate_signals)
    ("tasks/control/recording.py", {"squeeze_signals", "signal_smoothing"}),
    # shared by the rollout (threshold) and the metrics (Table 2)
    ("tasks/physics/regions.py", {"gravity_preload", "mpm_rollout", "deformation_metrics"}),
    # the glove: every step that counts fingers or sizes their pads
    ("conf/hand.py", {"squeeze_signals", "signal_smoothing", "force_coefficients", "contact_patches", "gravity_preload",
                      "mpm_rollout",
                      "deformation_metrics", "video_metrics"}),
    # the framework: every step
    ("tasks/core/artifacts.py", set(STEP_MODULES)),
    # a data file named in DATA_FILES of the oracle's table module: the oracle and the rollout that uses it
    ("tasks/physics/oracle/materials.yaml", {"material_oracle"}),
])
def test_editing_a_module_changes_exactly_the_steps_whose_imports_reach_it(tree_copy, edited, expected):
    before = _versions(tree_copy)
    assert before == _versions(REPO)  # the copy is the tree
    _edit(tree_copy, edited)
    after = _versions(tree_copy)
    assert {step for step in STEP_MODULES if after[step] != before[step]} == expected


def test_import_closure_follows_late_and_relative_imports(tree_copy):
    closure = import_closure("tasks.physics.mpm_rollout", tree_copy)
    # the kernels are imported relatively inside the engine package (`from .kernels.transfer import k_g2p`,
    # `from .kernels import walls as wall_kernels`)
    assert {"tasks.physics.mpm.solver", "tasks.physics.mpm.kernels", "tasks.physics.mpm.kernels.transfer",
            "tasks.physics.mpm.kernels.walls", "tasks.physics.mpm.constitutive"} <= set(closure)
    # a function-local import counts too
    (tree_copy / "tasks" / "core" / "late_helper.py").write_text("X = 1\n")
    dirichlet = tree_copy / "tasks" / "control" / "dirichlet_field.py"
    dirichlet.write_text(dirichlet.read_text() + "\n\ndef _late():\n    from tasks.core.late_helper import X\n"
                         "    return X\n")
    assert "tasks.core.late_helper" in import_closure("tasks.control.dirichlet_field", tree_copy)


# ------------------------------------------------------------------------------------------ declarations
def test_params_hold_only_the_declared_reads():
    params = Params("demo", {"control.displacement": {"eta": 0.01, "support": 2.5}, "object.eta": None})
    assert params["control.displacement"]["eta"] == 0.01
    assert params["control.displacement.support"] == 2.5  # below a declared path
    with pytest.raises(UndeclaredConfigRead) as info:
        params["control.force"]
    assert "demo" in str(info.value) and "control.force" in str(info.value) and "reads=" in str(info.value)


def test_resolve_reads_names_an_unknown_path(compose_cfg):
    cfg = compose_cfg("squeeze", ["object=tomato"])
    values = resolve_reads("demo", ("control.force.gamma", "object.eta", "variant.boundary"), (), cfg, cfg.object,
                           cfg.variant)
    assert values == {"control.force.gamma": 1.5, "object.eta": 0.012, "variant.boundary": "dirichlet"}
    with pytest.raises(ConfigPathError, match="control.force.gama"):
        resolve_reads("demo", ("control.force.gama",), (), cfg, cfg.object)


def test_a_file_input_joins_the_key_by_content(compose_cfg, tmp_path):
    cfg = compose_cfg("squeeze", ["object=tomato", "signal=csv", f"signal.path={tmp_path / 'rec.csv'}"])
    (tmp_path / "rec.csv").write_text("time\n0\n")
    a = resolve_reads("demo", ("signal.source",), ("signal.path",), cfg)
    (tmp_path / "rec.csv").write_text("time\n1\n")
    b = resolve_reads("demo", ("signal.source",), ("signal.path",), cfg)
    assert a["signal.source"] == b["signal.source"] == "csv" and a != b


def test_outputs_are_checked_against_the_declaration():
    spec = StepSpec("demo", outputs=("a", "b?"))
    spec.check_outputs({"a": 1})
    spec.check_outputs({"a": 1, "b": 2})
    with pytest.raises(StepOutputError, match=r"missing \['a'\]"):
        spec.check_outputs({"b": 2})
    with pytest.raises(StepOutputError, match=r"undeclared \['c'\]"):
        spec.check_outputs({"a": 1, "c": 3})


def test_a_step_reading_an_undeclared_value_fails_and_writes_nothing(tmp_path):
    @artifact_step("sloppy", reads=("control.force",), outputs=("c",))
    def sloppy(inputs, params):
        return {"c": Array(np.zeros(2), ("frame",), "1")}, {"gamma": params["control.contact"]}

    with pytest.raises(UndeclaredConfigRead, match="control.contact"):
        sloppy.run_local(root=str(tmp_path), scope="x", params={"control.force": {"gamma": 1.5}})
    assert not any(tmp_path.rglob("*.zarr"))


def test_a_step_is_given_exactly_its_declared_inputs(tmp_path):
    @artifact_step("needs_two", inputs=("object_model", "force_coefficients"), outputs=())
    def needs_two(inputs, params):
        return {}, {}

    with pytest.raises(WiringError, match="force_coefficients"):
        needs_two.run_local(root=str(tmp_path), scope="x", params={}, inputs={"object_model": None})


def test_the_pipeline_wiring_agrees_with_every_declaration(compose_cfg):
    from flows.pipeline import PER_OBJECT, PER_VARIANT, STEPS, check_wiring, step_params

    check_wiring()
    assert {s.name for s in STEPS} >= set(STEP_MODULES)
    assert all(not s.spec.per_variant for s in PER_OBJECT) and all(s.spec.per_variant or any(
        i in {v.name for v in PER_VARIANT} for i in s.spec.inputs) for s in PER_VARIANT)
    # every declared read names a key of the real default config (a typo in reads= fails here)
    cfg = compose_cfg("evaluate", [])
    for step in STEPS:
        step_params(step, cfg, cfg.catalog.tomato, cfg.variants.full)
    # a wiring that feeds a step before its producer ran is refused
    by_name = {s.name: s for s in STEPS}
    with pytest.raises(WiringError, match="dirichlet_field"):
        check_wiring((by_name["object_model"], by_name["dirichlet_field"]), ())
    with pytest.raises(WiringError, match="reads the variant"):
        check_wiring(PER_OBJECT + (by_name["mpm_rollout"],), ())


def test_a_long_step_reports_its_progress_once_per_tenth(tmp_path):
    """A step of many frames logs where it is (issue 15: no silent hours): one line per tenth of its work, named
    by object and step, whatever the number of frames."""
    import logging
    import re

    from tasks.core.step import log, report_progress

    @artifact_step("long", outputs=("x",))
    def long(inputs, params):
        for f in range(1, 201):
            report_progress(f, 200)
        return {"x": Array(np.zeros(1), ("i",), "1")}, {}

    lines: list[str] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = lambda record: lines.append(record.getMessage())
    log.addHandler(handler)
    try:
        long.run_local(root=str(tmp_path), scope="ball", params={}, label="ball")
    finally:
        log.removeHandler(handler)
    progress = [line for line in lines if line.startswith("ball/long: ")]
    assert [re.sub(r", \d+ s$", "", line) for line in progress] == [
        f"ball/long: frame {20 * k}/200 ({10 * k} %)" for k in range(1, 11)]
