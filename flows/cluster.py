"""Before a run sends its steps to an existing Dask cluster (``runner=dask runner.address=...``): does every worker
see what the flow sees?

Each worker is asked (``Client.run``, on all of them at once) to

* read a probe file the flow has just written into ``paths.artifacts`` (same path, same content: the same folder,
  not a node-local one of the same name) and to write a file of its own there;
* compute the code version of every step's module from its own files, and list its package versions
  (:mod:`tasks.core.environment`);
* reach the Prefect API the run reports to (the run's temporary server listens on the flow's machine only).

Every worker that differs is named in one line with what differs and the fix, and the run stops before any step
is submitted (``SystemExit``).  A worker that joins later is still checked per step
(:func:`tasks.core.environment.check_step_identity`)."""
from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any, Iterable

from tasks.core.environment import local_code_version, package_mismatches, package_versions, process_label


def worker_view(probe: str, token: str, modules: list[tuple[str, str | None]], api_url: str | None) -> dict[str, Any]:
    """Run on a worker: what it sees of the probe file, the steps' code, its packages and the Prefect API."""
    view: dict[str, Any] = {"label": process_label(), "packages": package_versions(),
                            "versions": {m: local_code_version(m, s) for m, s in modules}}
    try:
        seen = Path(probe).read_text()
        view["artifacts"] = "" if seen == token else f"{probe} holds another run's probe"
    except OSError as exc:
        view["artifacts"] = f"cannot read {probe} ({exc.strerror or exc})"
    if not view["artifacts"]:
        mine = Path(f"{probe}.{os.getpid()}")
        try:
            mine.write_text(token)
            mine.unlink()
        except OSError as exc:
            view["artifacts"] = f"cannot write into {Path(probe).parent} ({exc.strerror or exc})"
    view["api"] = ""
    if api_url:
        import httpx

        try:
            httpx.get(f"{api_url.rstrip('/')}/health", timeout=10).raise_for_status()
        except Exception as exc:  # noqa: BLE001 - any failure to reach it is the same finding
            view["api"] = f"cannot reach the Prefect API {api_url} ({type(exc).__name__})"
    return view


def mismatch_lines(views: dict[str, dict[str, Any]], versions: dict[str, str], artifacts: str) -> list[str]:
    """One line per worker whose view differs from the flow's (``versions``: the flow's code version per module)."""
    lines = []
    for address, view in sorted(views.items()):
        who = f"dask worker {address} ({view['label']})"
        if view["artifacts"]:
            lines.append(f"{who} does not see paths.artifacts={artifacts}: {view['artifacts']}; mount the shared "
                         "folder at the same absolute path on every worker")
        differ = sorted(m for m, v in versions.items() if view["versions"].get(m) != v)
        if differ:
            lines.append(f"{who} has other code than the flow: {differ[0]} is {view['versions'].get(differ[0], '?')[:12]}"
                         f" there, {versions[differ[0]][:12]} here ({len(differ)} module(s) differ); run every worker "
                         "from the flow's checkout (same commit, same path) and restart it")
        packages = package_mismatches(package_versions(), tuple(view["packages"]))
        if packages:
            lines.append(f"{who} has other packages than the flow: {'; '.join(packages)}; install the flow's "
                         "environment on every worker")
        if view["api"]:
            lines.append(f"{who} {view['api']}; run one `prefect server start --host 0.0.0.0` and export "
                         "PREFECT_API_URL=http://<that host>:4200/api for the flow and every worker")
    return lines


def check_workers(address: str, artifacts: str | Path, steps: Iterable[Any], api_url: str | None,
                  timeout: float = 60.0) -> int:
    """Ask every worker of the scheduler at ``address`` (:func:`worker_view`); raise ``SystemExit`` with one line per
    worker that differs from this process.  Returns the number of workers checked."""
    from distributed import Client

    steps = list(steps)
    modules = sorted({(s.compute.__module__, s.source) for s in steps}, key=lambda m: m[0])
    versions = {s.compute.__module__: s.version for s in steps}
    root = Path(artifacts).resolve()
    root.mkdir(parents=True, exist_ok=True)
    token = uuid.uuid4().hex
    probe = root / f".worker-probe-{token[:12]}"
    probe.write_text(token)
    try:
        with Client(address, timeout=timeout) as client:
            workers = client.scheduler_info()["workers"]
            if not workers:
                raise SystemExit(f"the Dask scheduler at runner.address={address} has no worker: start "
                                 f"`dask worker {address}` on each node")
            try:
                views = client.run(worker_view, str(probe), token, modules, api_url)
            except Exception as exc:  # noqa: BLE001 - e.g. a worker that cannot import this project
                raise SystemExit(f"a Dask worker of {address} cannot run the flow's check ({type(exc).__name__}: "
                                 f"{str(exc).splitlines()[0] if str(exc) else ''}); start every worker in the flow's "
                                 "checkout and environment") from None
    finally:
        probe.unlink(missing_ok=True)
    lines = mismatch_lines(views, versions, str(root))
    if lines:
        raise SystemExit("\n".join(lines))
    return len(views)
