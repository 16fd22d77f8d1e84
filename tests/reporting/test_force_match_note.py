"""Table 2's note on the ablation's input strength (issue 45): the force-matched variant's calibrated K per object
and its peak indentation against the prescribed one, read from the rollout artifacts; nothing without one."""
from __future__ import annotations

import numpy as np

from tasks.core.artifacts import Array, write_artifact
from tasks.reporting.report_tables import force_match_note


def _rollout(tmp_path, name: str, attrs: dict):
    return write_artifact(tmp_path / name / "mpm_rollout" / "k.zarr", {"time": Array(np.zeros(2), ("frame",), "s")},
                          step="mpm_rollout", scope=name, config_digest="x", attrs=attrs, root=tmp_path)


def test_the_note_names_each_objects_constant_and_its_indentation_against_the_prescribed_one(tmp_path):
    cal = {"force_per_coefficient": 83.836, "reached_indentation": 0.19262, "target_indentation": 0.19231,
           "converged": True, "rtol": 0.1}
    refs = {"clay": {"variants": {"full": {"mpm_rollout": _rollout(tmp_path, "full_clay", {})},
                                  "no_dirichlet": {"mpm_rollout": _rollout(tmp_path, "clay",
                                                                           {"force_calibration": cal})}}},
            "can": {"variants": {"no_dirichlet": {"mpm_rollout": _rollout(
                tmp_path, "can", {"force_calibration": {**cal, "force_per_coefficient": 4192.0,
                                                        "reached_indentation": 0.5, "target_indentation": 0.355,
                                                        "converged": False}})}}}}
    note = force_match_note(refs, {"no_dirichlet": "w/o Dirichlet"})
    assert note.startswith("Input strength: w/o Dirichlet is force-matched")
    assert "within 10 %" in note and "the same input strength" in note
    assert "clay K 83.84 N (peak 0.193 / 0.192)" in note
    assert "can K 4192 N (peak 0.500 / 0.355, not converged)" in note
    assert note.count(" N (peak ") == 2  # the full variant carries no calibration


def test_no_force_matched_variant_no_note(tmp_path):
    refs = {"clay": {"variants": {"full": {"mpm_rollout": _rollout(tmp_path, "clay", {})}}}}
    assert force_match_note(refs, {}) is None
