"""A progress line every :data:`HEARTBEAT_S` seconds while a run computes (issue 49), whatever its runner
(threads, a local Dask cluster, a remote one): the steps' own lines come as the flow collects them, in order, and
before the first one a large grid spends minutes starting the Prefect server and the task runner and submitting its
steps, silently.  Each line says how many steps finished (the run's table, :func:`flows.lifecycle.progress_table`),
the time elapsed and the work estimate's expected wall time (:meth:`flows.preflight.WorkEstimate.line`)."""
from __future__ import annotations

import contextlib
import threading
import time
from typing import Iterator

HEARTBEAT_S = 30.0  # s between two lines: the first comes within the first minute of every run


def progress_line(table, elapsed: float, expected: float) -> str:
    """The heartbeat's line: ``table`` the run's table (None while the steps are being submitted)."""
    from flows.preflight_settings import expected_wall, human_seconds

    if table is None or not table.total:
        what = "starting the task runner and submitting the steps"
    else:
        done = sum(r.status in ("ran", "cached") for r in table.rows)
        what = f"{done} of {table.total} steps finished"
    return f"progress: {what}, {human_seconds(elapsed)} elapsed (work estimate {expected_wall(expected)})"


@contextlib.contextmanager
def heartbeat(expected_seconds: float, interval: float = HEARTBEAT_S) -> Iterator[None]:
    """Within: a daemon thread prints :func:`progress_line` every ``interval`` seconds."""
    from flows.lifecycle import progress_table

    stop, t0, before = threading.Event(), time.perf_counter(), progress_table()

    def beat() -> None:
        while not stop.wait(interval):
            table = progress_table()
            print(progress_line(None if table is before else table, time.perf_counter() - t0, expected_seconds),
                  flush=True)

    threading.Thread(target=beat, daemon=True, name="virsqueezer-heartbeat").start()
    try:
        yield
    finally:
        stop.set()
