"""Whether a process named by its pid is still the one that was recorded: pids are reused, so a pid alone does
not name a process; its start time with it does.  Used to tell stale temporary folders
(:mod:`tasks.core.artifacts`) and Prefect servers left by killed runs (:mod:`flows.lifecycle`)."""
from __future__ import annotations

# two readings of one process's start time differ by less than this (s; psutil derives it from clock ticks)
START_TOLERANCE = 1.0


def process_started(pid: int) -> float | None:
    """The start time of process ``pid`` (s since the epoch), None when there is no such process (or it cannot be
    read)."""
    import psutil

    try:
        return psutil.Process(pid).create_time()
    except psutil.Error:
        return None


def same_process(pid: int, started: float | None) -> bool:
    """True when ``pid`` is still the process that started at ``started``."""
    now = process_started(pid)
    return now is not None and started is not None and abs(now - started) < START_TOLERANCE
