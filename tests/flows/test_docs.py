"""The documentation: the site builds offline with ``mkdocs build --strict`` (a broken link, a missing page or a bad
anchor fails), the generated reference pages say what the code declares, every pointer from a runtime message into
the docs names a page and a heading that exist, and the README keeps its test command in step with ``.ci/run``."""
from __future__ import annotations

import ast
import dataclasses
import importlib.util
import re
import subprocess
import sys
import typing
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
POINTER = re.compile(r"(docs/[A-Za-z0-9_/.-]+\.md)(?:, '([^']+)')?")


def _reference_module():
    spec = importlib.util.spec_from_file_location("docs_reference_hook", REPO / "docs" / "hooks" / "reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def reference():
    return _reference_module()


def test_site_builds_offline_and_strict(tmp_path):
    site = tmp_path / "site"
    done = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)], cwd=REPO,
                          capture_output=True, text=True, timeout=600, env={"NO_MKDOCS_2_WARNING": "1",
                                                                              "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    pages = {p.relative_to(site).as_posix() for p in site.rglob("*.html")}
    for page in ("index.html", "quickstart.html", "tutorials/diffusion-weights.html", "reference/config.html",
                 "reference/artifacts.html", "limits/index.html", "results/main-job.html"):
        assert page in pages
    config = (site / "reference" / "config.html").read_text()
    assert "mpm.target_substeps_per_frame" in config and "<!-- reference:config -->" not in config
    artifacts = (site / "reference" / "artifacts.html").read_text()
    assert "mpm_rollout" in artifacts and "<!-- reference:artifacts -->" not in artifacts
    for html in site.rglob("*.html"):  # nothing fetched from the network when the pages are read
        text = html.read_text()
        assert "fonts.googleapis" not in text and "fonts.gstatic" not in text, html


def _schema_keys(cls: type, prefix: str) -> set[str]:
    keys = set()
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        sub = next((a for a in (tp, *typing.get_args(tp)) if dataclasses.is_dataclass(a) and isinstance(a, type)), None)
        key = f"{prefix}.{f.name}" if prefix else f.name
        if sub is not None and typing.get_origin(tp) is not dict:
            keys |= _schema_keys(sub, key)
        else:
            keys.add(key)
    return keys


def test_config_reference_lists_every_key_with_the_main_jobs_value(reference):
    from conf.schema import Config

    groups = reference.config_rows()
    main = {g: r for g, r in groups.items() if g[0].islower() or g == "(top level)"}  # the main config's groups
    rows = {key: (tp, value, unit, text) for group in main.values() for key, tp, value, unit, text in group}
    assert _schema_keys(Config, "") <= set(rows)
    # values of the composed main-job config (YAML groups and the standard preset over the schema defaults)
    assert rows["mpm.target_substeps_per_frame"][1] == "`100`"
    assert rows["sampling.particle_spacing"][1] == "`0.004`"
    assert rows["mpm.mass_scaling"][1] == "`'selective'`"  # conf/mpm/default.yaml over the schema's "off"
    assert rows["object.geometry.kind"][1] == "`'ellipsoid'`"  # the tomato's catalog entry
    assert rows["sampling.particle_spacing"][2] == "m" and rows["signal.sensor_rate"][2] == "Hz"
    assert rows["object.material.youngs_modulus"][2] == "Pa"
    ranges = reference._ranges()
    assert ranges["render.fov_deg"] == ["must be in (0, 180)"]
    assert "must be one of sequential, threads, dask" in ranges["runner.kind"][0]  # module-level names resolved
    assert ranges["render.height"] == ranges["render.width"]  # "render.width/height" names both keys
    assert any(k.startswith("mpm.") for k in ranges) and any(k.startswith("generation.") for k in ranges)
    # the other schemas (studies, suites) are listed too
    assert any("StabilityConfig" in g for g in groups) and any("ConvergenceConfig" in g for g in groups)


def test_artifact_reference_matches_the_live_step_declarations(reference):
    from flows.pipeline import STEPS

    generated = {s["name"]: s for s in reference.artifact_steps()}
    assert [s["name"] for s in reference.artifact_steps()][:3] == ["object_model", "squeeze_signals",
                                                                    "signal_smoothing"]
    for step in STEPS:
        doc = generated[step.spec.name]
        assert tuple(doc.get("inputs", ())) == step.spec.inputs
        assert tuple(doc.get("reads", ())) == step.spec.reads
        assert tuple(doc.get("outputs", ())) == step.spec.outputs
        assert tuple(doc.get("files", ())) == step.spec.files


def _runtime_strings(path: Path) -> list[str]:
    """String literals of a module that are not docstrings (f-strings by their literal parts, joined)."""
    tree = ast.parse(path.read_text())
    docstrings = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                docstrings.add(id(first.value))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            out.append("".join(str(v.value) for v in node.values if isinstance(v, ast.Constant)))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings:
            out.append(node.value)
    return out


def _headings(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return {m.group(1).strip() for m in re.finditer(r"^#{1,6}\s+(.+?)\s*#*$", text, flags=re.M)}


def test_every_docs_pointer_in_a_message_names_a_page_and_heading_that_exist():
    pointers = []
    for folder in ("flows", "conf", "tasks"):
        for path in sorted((REPO / folder).rglob("*.py")):
            for text in _runtime_strings(path):
                assert "README:" not in text and "README," not in text and 'README "' not in text, (
                    f"{path.relative_to(REPO)}: a message points into the README: {text[:120]!r}; point it to its "
                    f"docs page instead (docs/<page>.md, '<heading>')")
                pointers += [(path, m.group(1), m.group(2)) for m in POINTER.finditer(text)]
    assert len(pointers) >= 3  # the missing-weights messages of flows/pipeline.py and tasks/generation/components.py
    for path, page, heading in pointers:
        target = REPO / page
        assert target.is_file(), f"{path.relative_to(REPO)} points to {page}, which does not exist"
        if heading is not None:
            assert heading in _headings(target), f"{path.relative_to(REPO)}: {page} has no heading {heading!r}"


def test_readme_is_short_and_ci_runs_its_test_command():
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 200
    commands = re.findall(r"^python3 -m venv \.venv && \. \.venv/bin/activate && (.+)$", readme, flags=re.M)
    assert len(commands) == 2 and commands[0].endswith("&& python -m flows.evaluate")
    install, _, run = commands[1].rpartition(" && ")
    assert run == "pytest -q"
    ci = (REPO / ".ci" / "run").read_text().splitlines()
    line = ci[ci.index("# README test command:") + 1]
    assert line.replace(" -q", "") == install  # the same install, quiet
    assert "pytest -q" in ci and "ruff check ." in ci
    image = REPO / "docs" / "images" / "contact-sheet.png"
    assert image.is_file() and image.stat().st_size < 300_000
