"""The layering rules, read from the imports of every module (AST), so that they cannot rot:

* ``conf`` declares and imports nothing of ours but ``conf`` itself (no tasks, no flows);
* ``tasks`` never imports ``flows``;
* the stages import in the paper's order: a module of stage S imports only stages at or below S (core <
  control < physics < render < generation < evaluation < reporting; verification beside reporting, and of the two
  only reporting reads the other: verification never imports reporting, so they never import each other);
* no test imports a study or benchmark module (``flows.studies``, ``flows.bench``): their library parts live in
  ``tasks/verification`` (the studies run as ``python -m``);
* no step module imports another step module (shared helpers live in non-step modules of a stage);
* the MPM engine (``tasks/physics/mpm/``) imports nothing of ours outside itself but the ``mpm`` config schema
  (``conf.mpm_schema``);
* package ``__init__`` files under ``tasks`` hold only a docstring (a step's code version is the import closure
  of its module: code in a parent package would run without being part of it), except the engine's re-exports.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tasks.core.code_version import imported_modules

REPO = Path(__file__).resolve().parents[2]
REEXPORTING_PACKAGES = {"tasks.physics.mpm"}  # `from tasks.physics.mpm import MPMSolver` is the engine's API
# the paper's stage order (tasks/<stage>/): a stage imports only stages of its rank or lower
STAGE_RANK = {"core": 0, "control": 1, "physics": 2, "render": 3, "generation": 4, "evaluation": 5, "verification": 6,
              "reporting": 7}  # verification beside reporting: the report reads the studies, never the other way
# known crossings, each with the change that removes it (a strict xfail: the test fails once it is gone, so the
# entry is deleted with the fix)
KNOWN_CROSSINGS: dict[str, str] = {}


def _modules(package: str) -> dict[str, Path]:
    out = {}
    for path in sorted((REPO / package).rglob("*.py")):
        rel = path.relative_to(REPO).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        out[".".join(parts)] = path
    return out


def _all_imports(path: Path) -> set[str]:
    """Every module name imported anywhere in the file (absolute names; relative imports resolved)."""
    names = set()
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
    return names


def _is_step_module(path: Path) -> bool:
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.FunctionDef):
            for dec in node.decorator_list:
                target = dec.func if isinstance(dec, ast.Call) else dec
                if isinstance(target, ast.Name) and target.id == "artifact_step":
                    return True
    return False


STEP_MODULES = sorted(name for name, path in _modules("tasks").items() if _is_step_module(path))


def test_the_step_modules_are_found():
    assert {"tasks.control.object_model", "tasks.physics.mpm_rollout",
            "tasks.evaluation.deformation_metrics"} <= set(STEP_MODULES)


@pytest.mark.parametrize("name,path", sorted(_modules("conf").items()))
def test_conf_imports_nothing_of_ours(name, path):
    ours = {m for m in _all_imports(path) if m.split(".")[0] in ("tasks", "flows")}
    assert not ours, f"{name} imports {sorted(ours)}: conf only declares (move the code to tasks/ or flows/)"


@pytest.mark.parametrize("name,path", sorted(_modules("tasks").items()))
def test_tasks_never_import_flows(name, path):
    flows = {m for m in _all_imports(path) if m.split(".")[0] == "flows"}
    assert not flows, f"{name} imports {sorted(flows)}: flows wire tasks, never the other way round"


def _stage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "tasks" and len(parts) > 1 and parts[1] in STAGE_RANK else None


def test_every_stage_has_a_rank():
    stages = {p.name for p in (REPO / "tasks").iterdir() if (p / "__init__.py").exists()}
    assert stages == set(STAGE_RANK), f"stages without a rank (or ranks without a stage): {stages ^ set(STAGE_RANK)}"


@pytest.mark.parametrize("name", [
    pytest.param(n, marks=pytest.mark.xfail(reason=KNOWN_CROSSINGS[n], strict=True)) if n in KNOWN_CROSSINGS else n
    for n in sorted(_modules("tasks")) if _stage(n)])
def test_stages_import_in_the_papers_order(name):
    path = _modules("tasks")[name]
    rank = STAGE_RANK[_stage(name)]
    above = sorted(m for m in imported_modules(name, path.read_text()) if _stage(m) and STAGE_RANK[_stage(m)] > rank)
    assert not above, (f"{name} (stage {_stage(name)}) imports {above} of a later stage: the stages import downward "
                       "(core < control < physics < render < generation < evaluation < reporting; verification "
                       "beside reporting, never importing it): move the shared code down (e.g. tasks/core)")


@pytest.mark.parametrize("path", sorted((REPO / "tests").rglob("*.py")),
                         ids=lambda p: p.relative_to(REPO / "tests").as_posix())
def test_no_test_imports_a_study_or_a_benchmark(path):
    studies = {m for m in _all_imports(path) if m.split(".")[:2] in (["flows", "studies"], ["flows", "bench"])}
    assert not studies, (f"{path.name} imports {sorted(studies)}: test the library function in tasks/verification "
                         "(or run the study with python -m)")


@pytest.mark.parametrize("name", STEP_MODULES)
def test_no_step_module_imports_another(name):
    path = _modules("tasks")[name]
    others = imported_modules(name, path.read_text()) & (set(STEP_MODULES) - {name})
    assert not others, (f"step module {name} imports step module(s) {sorted(others)}: move the shared helper into a "
                        "non-step module of the stage")


@pytest.mark.parametrize("name,path", [(n, p) for n, p in sorted(_modules("tasks").items())
                                       if p.name == "__init__.py" and n not in REEXPORTING_PACKAGES])
def test_package_inits_hold_only_a_docstring(name, path):
    body = ast.parse(path.read_text()).body
    assert len(body) == 1 and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant), (
        f"{path} must hold only a docstring")


ENGINE = "tasks.physics.mpm"
# the engine reads its settings as the ``mpm`` config group's schema (MPMConfig): the one import outside itself
ENGINE_MAY_IMPORT = {"conf.mpm_schema"}


@pytest.mark.parametrize("name,path", [(n, p) for n, p in sorted(_modules("tasks").items())
                                       if n == ENGINE or n.startswith(ENGINE + ".")])
def test_the_engine_imports_nothing_of_ours_outside_itself(name, path):
    """The MPM engine (``tasks/physics/mpm/``) is a library of its own: it imports numpy, warp, scipy and itself,
    and of ours only the ``mpm`` config schema, never a stage (its relative imports stay inside it by construction;
    a relative import that climbs out of it counts too)."""
    outside = set()
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = package.split(".")
            base = base[: len(base) - (node.level - 1)]
            target = ".".join(base + ([node.module] if node.module else []))
            if not (target == ENGINE or target.startswith(ENGINE + ".")):
                outside.add(target)
        else:
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module] if isinstance(node, ast.ImportFrom) and node.module else [])
            outside |= {m for m in names if m.split(".")[0] in ("tasks", "flows", "conf", "tests")
                        and not (m == ENGINE or m.startswith(ENGINE + ".")) and m not in ENGINE_MAY_IMPORT}
    assert not outside, f"{name} imports {sorted(outside)}: the engine imports nothing of ours outside itself"


def test_the_engine_check_catches_an_import_from_a_stage(tmp_path):
    """The check above is not vacuous: the engine's own modules are found, and the solver as it was before the
    engine held its thin-wall definitions (``from tasks.physics.wall_resolution import gauss_layer_face``) fails."""
    engine = [n for n in _modules("tasks") if n == ENGINE or n.startswith(ENGINE + ".")]
    assert {"tasks.physics.mpm.solver", "tasks.physics.mpm.kernels.transfer", "tasks.physics.mpm.thin_walls"} <= set(
        engine)
    bad = tmp_path / "solver.py"
    bad.write_text("from tasks.physics.wall_resolution import gauss_layer_face\nfrom ..wall_resolution import x\n")
    with pytest.raises(AssertionError, match=r"wall_resolution"):
        test_the_engine_imports_nothing_of_ours_outside_itself("tasks.physics.mpm.solver", bad)
