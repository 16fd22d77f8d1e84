"""No silent "nothing was squeezed" (issue 15): a control chain whose displacement field is empty carries a warning
with the likely cause into the task's progress line and the report; a non-finite field fails the step."""
from __future__ import annotations

import numpy as np
import pytest

from flows.pipeline import run_object_local
from flows.runtime import RunTable, TaskRow, artifact_warning
from tasks.control.dirichlet_field import FieldError
from tasks.reporting.report import write_run_report


def test_an_empty_field_is_flagged_in_the_task_row_and_the_report(tmp_path, compose_cfg):
    cfg = compose_cfg("squeeze", ["object=rubber_ball", "control.force.beta=0.99"])  # flexion never passes beta
    refs = run_object_local(cfg, cfg.object, None, tmp_path / "artifacts", until="dirichlet_field")
    line = ("nothing was squeezed: no finger flexes past control.force.beta (every force coefficient is 0); check "
            "the recording's flexion scale (0..1 or 0..10000) or lower control.force.beta")
    assert artifact_warning(refs["dirichlet_field"].path) == line
    assert artifact_warning(refs["contact_patches"].path) == ""
    row = TaskRow("rubber_ball", "dirichlet_field", "ran", 0.1, 0, refs["dirichlet_field"].path,
                  f"WARNING {line}", warning=line)
    report = write_run_report(tmp_path / "report", cfg={}, table=RunTable(rows=[row]),
                              refs={"rubber_ball": {"dirichlet_field": refs["dirichlet_field"]}}, wall_seconds=1.0)
    md = report.read_text()
    assert f"## Warnings\n\n- rubber_ball dirichlet_field: {line}\n" in md
    assert "<h2>Warnings</h2><ul><li>rubber_ball dirichlet_field: nothing was squeezed: no finger flexes past " \
        "control.force.beta" in (report.parent / "index.html").read_text().replace("\n", "")


def test_a_non_finite_field_fails_the_step_naming_the_likely_cause(tmp_path, compose_cfg):
    cfg = compose_cfg("squeeze", ["object=rubber_ball", "control.displacement.eta=1e308"])  # finite, overflows float32
    with pytest.raises(FieldError) as exc, np.errstate(over="ignore"):
        run_object_local(cfg, cfg.object, None, tmp_path / "artifacts", until="dirichlet_field")
    msg = str(exc.value)
    assert msg.startswith("the displacement field is not finite at ") and msg.endswith(
        "point-frames: a config value is out of range (control.displacement.eta or object.eta, "
        "control.contact.sigma_min/sigma_max)")
