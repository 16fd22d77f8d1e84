"""What a process computes with: the code version of each step's module as its files say, and the versions of the
installed packages that shape a step's numbers.  A step made in the flow's process and run in another (a Dask
worker on another node) must find the same there, else the artifact it writes is not what its cache key says.

The code version is in the cache key already (:mod:`tasks.core.code_version`), but the key is computed by the
flow from the flow's files, while the step's helpers are imported by the worker from the worker's files: a worker
with an older checkout would compute with other code under the flow's key.  :func:`check_step_identity` refuses
that with one line naming the worker, the module and both versions; :func:`identity_mismatches` compares a whole
process (the flow's start-up check of every worker, :mod:`flows.cluster`).
"""
from __future__ import annotations

import functools
import os
import platform
import socket
from importlib import metadata
from pathlib import Path

from tasks.core.code_version import code_version

# installed distributions whose version changes what a step computes or how its artifacts are stored
PACKAGES = ("numpy", "scipy", "warp-lang", "zarr", "torch", "diffusers", "transformers", "opencv-python-headless",
            "scikit-image", "trimesh", "brisque", "av", "prefect", "pydantic")


class WorkerMismatch(RuntimeError):
    """A step was sent to a process whose code or packages differ from those of the flow that made its key."""


def process_label() -> str:
    """``host:pid`` of this process (how a mismatch names the worker)."""
    return f"{socket.gethostname()}:{os.getpid()}"


@functools.lru_cache(maxsize=None)
def package_versions() -> tuple[tuple[str, str], ...]:
    """(distribution, version) of :data:`PACKAGES` as installed for this process ("absent" when not installed),
    and Python's own version.  Read once per process: a running process does not change what it imported."""
    found = [("python", platform.python_version())]
    for name in PACKAGES:
        try:
            found.append((name, metadata.version(name)))
        except metadata.PackageNotFoundError:
            found.append((name, "absent"))
    return tuple(found)


@functools.lru_cache(maxsize=None)
def local_code_version(module: str, source: str | None = None) -> str:
    """The code version of ``module`` computed from this process's files (``source``: the file of a step defined
    outside the project packages); "unreadable: ..." when they cannot be read here.  Once per process."""
    try:
        return code_version(module, path=Path(source) if source else None)
    except (OSError, ModuleNotFoundError) as exc:
        return f"unreadable: {exc}"


def package_mismatches(flow: tuple[tuple[str, str], ...], here: tuple[tuple[str, str], ...]) -> list[str]:
    """``name flow-version vs here-version`` for each package whose version differs."""
    mine = dict(here)
    return [f"{name} {version} (flow) vs {mine.get(name, 'absent')} (here)" for name, version in flow
            if mine.get(name, "absent") != version]


def check_step_identity(step: str, module: str, source: str | None, version: str,
                        packages: tuple[tuple[str, str], ...]) -> None:
    """Raise :class:`WorkerMismatch` (one line) when this process's files give ``module`` another code version than
    ``version`` (the flow's, in the step's cache key), or when its packages differ from the flow's ``packages``."""
    here = local_code_version(module, source)
    if here != version:
        raise WorkerMismatch(
            f"worker {process_label()} refuses step {step!r}: its code of {module} ({here[:12]}, from "
            f"{Path(__file__).resolve().parents[2]}) differs from the flow's ({version[:12]}); run every worker from "
            "the flow's checkout (same commit, same path) and restart the workers")
    differ = package_mismatches(packages, package_versions())
    if differ:
        raise WorkerMismatch(f"worker {process_label()} refuses step {step!r}: installed packages differ from the "
                             f"flow's: {'; '.join(differ)}; install the flow's environment on every worker")
