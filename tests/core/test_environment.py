"""The identity a worker checks before it runs a step: code version from its own files, installed packages."""
from __future__ import annotations

from importlib import metadata

import numpy as np
import pytest

from tasks.core.environment import (
    PACKAGES,
    WorkerMismatch,
    check_step_identity,
    local_code_version,
    package_mismatches,
    package_versions,
)


def test_package_versions_are_the_installed_ones_and_a_difference_is_named():
    found = dict(package_versions())
    assert found["numpy"] == np.__version__ == metadata.version("numpy")
    assert set(found) == {"python", *PACKAGES}
    assert package_mismatches(package_versions(), package_versions()) == []
    older = tuple((n, "1.0.0" if n == "zarr" else v) for n, v in package_versions())
    assert package_mismatches(older, package_versions()) == [f"zarr 1.0.0 (flow) vs {found['zarr']} (here)"]


def test_a_step_with_the_flows_identity_passes_and_any_difference_is_refused_in_one_line():
    from tasks.control.force_coefficients import force_coefficients_step as step

    module = step.compute.__module__
    assert local_code_version(module) == step.version
    check_step_identity(step.name, module, None, step.version, package_versions())  # same: no error
    with pytest.raises(WorkerMismatch, match=rf"refuses step 'force_coefficients': its code of {module} \("):
        check_step_identity(step.name, module, None, "0" * 64, package_versions())
    other = tuple((n, "0.0" if n == "numpy" else v) for n, v in package_versions())
    with pytest.raises(WorkerMismatch) as exc:
        check_step_identity(step.name, module, None, step.version, other)
    assert "\n" not in str(exc.value) and f"numpy 0.0 (flow) vs {np.__version__} (here)" in str(exc.value)
