"""After a Hydra ``-m`` sweep: one table across its jobs, with the swept parameters as columns.

Each job writes its report (``metrics.csv`` among it) into its own Hydra output folder
``<sweep dir>/<job number>/`` next to ``.hydra/overrides.yaml`` (see :func:`sweep_job_dir`).
A job that fails (a refused config, a failed step) writes its one-line reason to ``<job>/job_failed.txt``
(:func:`sweep_job`) and ends normally, so that the jobs after it, or beside it under a parallel launcher, go on.
:class:`SweepSummary` is registered as a Hydra callback in ``conf/evaluate.yaml``; at the end of the sweep it
writes ``<sweep dir>/sweep_metrics.csv``, ``sweep_metrics.parquet`` and ``sweep_summary.md`` (every job with its
status), and ends the sweep with exit status 1 and one line when a job failed.  Run
``python -m flows.sweep_summary <sweep dir>`` to rebuild them by hand (e.g. after a sweep was interrupted).
"""
from __future__ import annotations

import sys
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import yaml
from hydra.experimental.callback import Callback

if TYPE_CHECKING:
    import pandas as pd


def _override_columns(job_dir: Path) -> dict[str, str]:
    """The job's command-line overrides as {key: value} (``+``/``++`` prefixes dropped)."""
    path = job_dir / ".hydra" / "overrides.yaml"
    if not path.is_file():
        return {}
    out = {}
    for item in yaml.safe_load(path.read_text()) or []:
        key, _, value = str(item).partition("=")
        out[key.lstrip("+~")] = value
    return out


FAILED = "job_failed.txt"


def sweep_job_dir() -> str | None:
    """Inside a Hydra ``-m`` sweep, the job's own output folder (``<sweep dir>/<job number>``), where its report
    goes next to Hydra's ``.hydra/overrides.yaml`` so that :func:`summarize_sweep` can aggregate the jobs."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return None
    return str(HydraConfig.get().runtime.output_dir)


@contextmanager
def sweep_job() -> Iterator[None]:
    """Within a job of a ``-m`` sweep: an error (or a refusal, ``SystemExit`` with a message) is written to the job's
    ``job_failed.txt`` and printed as one line, and the job ends normally.  Outside a sweep: nothing changes."""
    job_dir = sweep_job_dir()
    if job_dir is None:
        yield
        return
    Path(job_dir, FAILED).unlink(missing_ok=True)  # a job run again in its old folder
    try:
        yield
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - whatever stops the job is its reason
        if isinstance(exc, SystemExit) and not isinstance(exc.code, str):
            raise  # an exit status, not a refusal with its reason (e.g. a stop): the sweep stops too
        text = str(exc.code if isinstance(exc, SystemExit) else exc) or type(exc).__name__
        line = text.splitlines()[0]
        Path(job_dir, FAILED).write_text(line + "\n")
        print(f"sweep job {Path(job_dir).name} failed: {line}", file=sys.stderr, flush=True)


def job_status(job_dir: Path) -> str:
    """``ok`` (its metrics were written), ``failed: <reason>`` or ``not finished``."""
    if (job_dir / FAILED).is_file():
        return "failed: " + (job_dir / FAILED).read_text().strip()
    return "ok" if (job_dir / "metrics.csv").is_file() else "not finished"


def summarize_sweep(sweep_dir: str | Path) -> pd.DataFrame:
    """Concatenate the jobs' metric rows; columns: ``job``, the overrides that differ between jobs, then the
    metric rows' own columns.  Writes the summary files into ``sweep_dir`` and returns the table."""
    # imported here, not at the top: Hydra imports this callback at every start of flows.evaluate, before the
    # pre-flight checks, and pandas with the report tables is most of that start-up (~2 s of CPU per start)
    import pandas as pd

    from tasks.core.tables import markdown_table
    from tasks.reporting.report_tables import TABLE2

    sweep_dir = Path(sweep_dir)
    frames, overrides, status = [], {}, {}
    for job_dir in sorted((p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name)):
        csv = job_dir / "metrics.csv"
        overrides[job_dir.name] = _override_columns(job_dir)
        status[job_dir.name] = job_status(job_dir)
        if csv.is_file():
            frames.append(pd.read_csv(csv).assign(job=int(job_dir.name)))
    keys = sorted({k for o in overrides.values() for k in o})
    swept = [k for k in keys if len({o.get(k) for o in overrides.values()}) > 1]
    jobs = markdown_table(["job", *swept, "status"], [[j, *(o.get(k, "") for k in swept), status[j]]
                                                      for j, o in overrides.items()])
    if not frames:
        (sweep_dir / "sweep_summary.md").write_text(f"# Sweep `{sweep_dir.name}`\n\nno job wrote metrics\n\n{jobs}\n")
        raise SystemExit(f"no job in {sweep_dir} wrote metrics.csv: nothing to summarise (did every job fail?)")
    df = pd.concat(frames, ignore_index=True)
    for k in reversed(swept):
        df.insert(0, k, df["job"].map(lambda j, k=k: overrides[str(j)].get(k)))
    df.insert(0, "job", df.pop("job"))
    df.to_csv(sweep_dir / "sweep_metrics.csv", index=False)
    df.to_parquet(sweep_dir / "sweep_metrics.parquet", index=False)
    main = [k for k, _, _ in TABLE2 if k in df.columns]
    by = ["job", *swept, "variant"]
    mean = df.groupby(by, dropna=False)[main].mean().reset_index()
    table = markdown_table([*by, *(f"{name} (mean over objects)" for k, name, _ in TABLE2 if k in main)],
                           [[*(str(r[c]) for c in by), *(f"{r[k]:.3f}" for k in main)] for _, r in mean.iterrows()])
    (sweep_dir / "sweep_summary.md").write_text(
        f"# Sweep `{sweep_dir.name}`\n\nswept: {', '.join(swept) or '(nothing differs between jobs)'}; "
        f"rows per job and object: `sweep_metrics.csv` / `.parquet`\n\n{table}\n\n## Jobs\n\n{jobs}\n")
    return df


def failed_jobs(sweep_dir: str | Path) -> dict[str, str]:
    """{job number: its status} of the jobs of the sweep that did not end ``ok``."""
    dirs = [p for p in Path(sweep_dir).iterdir() if p.is_dir() and p.name.isdigit()]
    return {p.name: job_status(p) for p in sorted(dirs, key=lambda p: int(p.name)) if job_status(p) != "ok"}


class SweepSummary(Callback):
    """Hydra callback: summarise the sweep when all its jobs have finished, or when one failed in a way that stops
    the sweep (an error that escaped :func:`sweep_job`: Hydra's sweeper re-raises it after the job, and
    ``on_multirun_end`` never comes), so that a sweep always leaves its summary with every job's status."""

    def on_job_end(self, config: Any, job_return: Any, **kwargs: Any) -> None:
        from hydra.core.utils import JobStatus

        mode = config.hydra.get("mode")
        if job_return.status != JobStatus.FAILED or getattr(mode, "name", mode) != "MULTIRUN":
            return
        job_dir = Path(config.hydra.runtime.output_dir)
        if not (job_dir / FAILED).is_file():
            exc = job_return._return_value
            (job_dir / FAILED).write_text(((str(exc).splitlines() or [""])[0] or type(exc).__name__) + "\n")
        write_summary(job_dir.parent)

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        write_summary(config.hydra.sweep.dir)
        failed = failed_jobs(config.hydra.sweep.dir)
        if failed:
            first = next(iter(failed))
            raise SystemExit(f"sweep: {len(failed)} job(s) did not finish: job {first} {failed[first]} "
                             f"(every job's status: {Path(config.hydra.sweep.dir).resolve() / 'sweep_summary.md'})")


def write_summary(sweep_dir: str | Path) -> None:
    """:func:`summarize_sweep` with one line; when it fails, ``sweep_summary.md`` still lists every job's status."""
    summary = Path(sweep_dir).resolve() / "sweep_summary.md"
    try:
        df = summarize_sweep(sweep_dir)
        print(f"sweep summary: {len(df)} rows -> {summary}")
    except SystemExit as exc:
        print(f"sweep summary: {exc}")
    except Exception as exc:  # noqa: BLE001 - the jobs' statuses are written whatever failed in the table
        dirs = sorted((p for p in Path(sweep_dir).iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name))
        rows = "\n".join(f"| {p.name} | {job_status(p)} |" for p in dirs)
        summary.write_text(f"# Sweep `{Path(sweep_dir).name}`\n\nthe metrics table failed: {type(exc).__name__}: "
                           f"{(str(exc).splitlines() or [''])[0]}\n\n## Jobs\n\n| job | status |\n|---|---|\n{rows}\n")
        print(f"sweep summary: jobs' statuses only ({type(exc).__name__}) -> {summary}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m flows.sweep_summary <sweep dir>")
    print(summarize_sweep(sys.argv[1]).to_string(index=False))
