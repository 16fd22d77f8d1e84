"""Numerical stability suite:  ``python -m flows.studies.stability`` (all cases, ~10 min on 2 cores),
``python -m flows.studies.stability quick=true`` (< 1 min),
``python -m flows.studies.stability cases=[courant,deep_poke]``.

Wires :mod:`tasks.verification.stability` (cases, runners, report) to the Hydra config
(``conf/study/stability.yaml``, schema ``conf/study/stability_schema.py``) and writes
``<paths.reports>/stability/<run>/stability.md`` and ``stability.csv``.  No Prefect: the cases are short
diagnostics run in this process, one after the other (a case that fails is a row of the table, never the end of
the run).
"""
from __future__ import annotations

from datetime import datetime
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from conf.study.stability_schema import register_stability_config

register_stability_config()


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/stability")
def main(cfg: DictConfig) -> None:
    from flows.preflight import preflight_stability

    cases = preflight_stability(cfg)  # bad config: one line, before any case runs
    from tasks.verification.stability import SuiteContext, run_suite, table_text, write_report

    run = cfg.run_name or f"stability-{datetime.now():%Y%m%d-%H%M%S}"
    out = Path(cfg.paths.reports) / "stability" / run
    print(f"stability suite: {len(cases)} cases -> {out}")
    rows = run_suite(SuiteContext.from_config(cfg), cases, log=print)
    report = write_report(rows, out, config=OmegaConf.to_container(cfg, resolve=True))
    print("\n" + table_text(rows))
    print(f"\nreport: {report.resolve()}\ntable: {(out / 'stability.csv').resolve()}")


if __name__ == "__main__":
    main()
