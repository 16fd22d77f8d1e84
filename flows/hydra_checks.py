"""Checks around Hydra's own start of a pipeline main (issue 49), before Hydra creates its output folder:

* :func:`check_argv`: ``-m`` / ``--multirun`` after an override (``object=can -m seed=1,2``), which argparse
  reports as a bare "unrecognized arguments", is one usage line saying where ``-m`` goes;
* :class:`PreflightCallback` (registered in ``conf/squeeze.yaml`` and ``conf/evaluate.yaml``): before a run, the
  folders it writes (:func:`flows.preflight_env.check_folders`, Hydra's ``hydra.run.dir`` included; a read-only
  artifacts cache passes: these configs' mains can be served from one); before a
  ``-m`` sweep, those folders and then every job's config (composed as the job will be, then
  :func:`flows.preflight.check_config`: its ranges, settings, work and input files - the recording, the mesh or
  splat files, each distinct file read once), so that a config error or a bad input file in job 1 stops the sweep
  before job 0 runs, naming the job and its overrides; then the sweep's total expected wall time (its jobs one
  after another) against ``limits.max_wall_hours``, which bounds each job too.
"""
from __future__ import annotations

from typing import Any

from hydra.experimental.callback import Callback

_MULTIRUN = ("-m", "--multirun")


def check_argv(argv: list[str], prog: str) -> None:
    """Refuse ``-m`` placed after an override when more overrides follow it (argparse reads the overrides as one
    group and would reject the rest)."""
    flags = [i for i, a in enumerate(argv) if a in _MULTIRUN]
    if not flags:
        return
    i = flags[0]
    overrides = [a for a in argv if "=" in a and not a.startswith("-")]
    before = [a for a in argv[:i] if "=" in a and not a.startswith("-")]
    if before and len(before) < len(overrides):
        raise SystemExit(f"usage: -m goes before the overrides: python -m {prog} -m {' '.join(overrides)}")


def job_overrides(overrides: list[str]) -> list[list[str]]:
    """The override lists of a sweep's jobs, in Hydra's basic sweeper's order (its cartesian product)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(overrides)
    return [job for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


class PreflightCallback(Callback):
    """Hydra callback: the folders before a run; the folders and every job's config and input files before a
    sweep."""

    def on_run_start(self, config: Any, **kwargs: Any) -> None:
        from flows.preflight_env import check_folders

        check_folders(config, {"hydra.run.dir": str(config.hydra.run.dir)}, read_only_ok=True)

    def on_multirun_start(self, config: Any, **kwargs: Any) -> None:
        from hydra import compose

        from flows.preflight import check_config
        from flows.preflight_env import check_folders
        from flows.preflight_settings import expected_wall, human_seconds

        check_folders(config, {"hydra.sweep.dir": str(config.hydra.sweep.dir)}, read_only_ok=True)
        name = kwargs.get("config_name") or config.hydra.job.config_name
        jobs = job_overrides(list(config.hydra.overrides.task))
        swept = {o for job in jobs for o in job if sum(o in j for j in jobs) < len(jobs)}  # those that differ
        wall = 0.0
        seen: dict = {}  # the input files read so far: each distinct one is read once
        for n, overrides in enumerate(jobs):
            shown = " ".join(o for o in overrides if o in swept) or "no overrides"
            try:
                wall += check_config(compose(config_name=name, overrides=overrides), seen).wall_seconds
            except SystemExit as exc:
                if not isinstance(exc.code, str):
                    raise
                raise SystemExit(f"sweep job {n} ({shown}): {exc.code}") from None
            except Exception as exc:  # noqa: BLE001 - Hydra's own composition error (an unknown key or group)
                first = (str(exc).splitlines() or [type(exc).__name__])[0]
                raise SystemExit(f"sweep job {n} ({shown}): config error: {first}") from None
        limit = float(config.limits.max_wall_hours)
        if wall > limit * 3600:
            raise SystemExit(f"work limit: the sweep's {len(jobs)} jobs would take about {human_seconds(wall)} one "
                             f"after another, above limits.max_wall_hours={limit:g} ({human_seconds(limit * 3600)}): "
                             f"sweep fewer values or split the sweep (or raise limits.max_wall_hours)")
        print(f"sweep: the {len(jobs)} jobs' configs passed the checks; work estimate of the sweep: expected wall "
              f"time {expected_wall(wall)} (its jobs one after another)", flush=True)
