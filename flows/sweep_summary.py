"""After a Hydra ``-m`` sweep: one table across its jobs, with the swept parameters as columns.

Each job writes its report (``metrics.csv`` among it) into its own Hydra output folder
``<sweep dir>/<job number>/`` next to ``.hydra/overrides.yaml`` (see :func:`flows.pipeline.sweep_job_dir`).
:class:`SweepSummary` is registered as a Hydra callback in ``conf/evaluate.yaml``; at the end of the sweep it
writes ``<sweep dir>/sweep_metrics.csv``, ``sweep_metrics.parquet`` and ``sweep_summary.md``.  Run
``python -m flows.sweep_summary <sweep dir>`` to rebuild them by hand (e.g. after a sweep was interrupted).
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

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


def summarize_sweep(sweep_dir: str | Path) -> pd.DataFrame:
    """Concatenate the jobs' metric rows; columns: ``job``, the overrides that differ between jobs, then the
    metric rows' own columns.  Writes the summary files into ``sweep_dir`` and returns the table."""
    # imported here, not at the top: Hydra imports this callback at every start of flows.evaluate, before the
    # pre-flight checks, and pandas with the report tables is most of that start-up (~2 s of CPU per start)
    import pandas as pd

    from tasks.core.tables import markdown_table
    from tasks.reporting.report_tables import TABLE2

    sweep_dir = Path(sweep_dir)
    frames, overrides = [], {}
    for job_dir in sorted((p for p in sweep_dir.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name)):
        csv = job_dir / "metrics.csv"
        overrides[job_dir.name] = _override_columns(job_dir)
        if csv.is_file():
            frames.append(pd.read_csv(csv).assign(job=int(job_dir.name)))
    if not frames:
        raise SystemExit(f"no job in {sweep_dir} wrote metrics.csv: nothing to summarise (did every job fail?)")
    keys = sorted({k for o in overrides.values() for k in o})
    swept = [k for k in keys if len({o.get(k) for o in overrides.values()}) > 1]
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
        f"rows per job and object: `sweep_metrics.csv` / `.parquet`\n\n{table}\n")
    return df


class SweepSummary(Callback):
    """Hydra callback: summarise the sweep when all its jobs have finished."""

    def on_multirun_end(self, config: Any, **kwargs: Any) -> None:
        try:
            df = summarize_sweep(config.hydra.sweep.dir)
        except SystemExit as exc:
            print(f"sweep summary: {exc}")
            return
        print(f"sweep summary: {len(df)} rows -> {Path(config.hydra.sweep.dir).resolve() / 'sweep_summary.md'}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit("usage: python -m flows.sweep_summary <sweep dir>")
    print(summarize_sweep(sys.argv[1]).to_string(index=False))
