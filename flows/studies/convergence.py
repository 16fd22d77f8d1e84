"""Error against run time:  ``python -m flows.studies.convergence``  (``object=clay`` for another object).

Runs one object and its session once per setting of ``convergence.settings`` (each a set of config overrides)
through the cached pipeline steps (:func:`flows.pipeline.submit_object`), so a rerun of the sweep is served from
the cache and a killed sweep resumes where it stopped; each step's recorded compute seconds are the wall time.
Then measures every setting against the reference setting and writes ``<paths.reports>/convergence/<run>/``
``convergence.md``, ``convergence.csv`` and ``pareto.png`` (:mod:`tasks.verification.convergence`).  No computation
here.  Config: ``conf/study/convergence.yaml``.
"""
from __future__ import annotations

import os
import platform
from datetime import datetime
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from conf.study.convergence_schema import register_convergence_config, validate_convergence

register_convergence_config()

PRESET_DIR = Path(__file__).resolve().parents[2] / "conf" / "preset"


def setting_configs(cfg: DictConfig) -> dict[str, DictConfig]:
    """The composed config of every setting (base + preset + overrides), validated like a pipeline run."""
    from conf.schema import ConfigError, validate
    from tasks.verification.convergence import ConvergenceError, load_preset, setting_config

    out = {}
    for s in cfg.convergence.settings:
        try:
            preset = load_preset(PRESET_DIR, s.preset) if s.preset else None
            c = setting_config(cfg, list(s.overrides), preset)
            validate(c)
        except (ConvergenceError, ConfigError) as exc:
            raise SystemExit(f"convergence setting {s.name!r}: {exc}") from None
        out[s.name] = c
    return out


def preset_configs(cfg: DictConfig) -> dict[str, DictConfig]:
    """Every ``conf/preset/*.yaml`` applied to the base config (to tell which setting each preset sits at)."""
    from tasks.verification.convergence import load_preset, setting_config

    return {p.stem: setting_config(cfg, [], load_preset(PRESET_DIR, p.stem)) for p in sorted(PRESET_DIR.glob("*.yaml"))}


def convergence_flow(configs: dict[str, dict], sweep: dict, report_dir: str) -> dict:
    """Submit every setting's pipeline, collect its artifacts, measure against the reference, write the report.
    (Made a Prefect flow in :func:`run_convergence`: Prefect is imported after the main has set its home.)"""
    from flows.pipeline import deformation_metrics_step, mpm_rollout_step, submit_object
    from flows.runtime import RunTable
    from tasks.verification import convergence as conv

    cfgs = {name: OmegaConf.create(c) for name, c in configs.items()}
    deformation = (mpm_rollout_step, deformation_metrics_step)  # no rendering: the study compares the physics
    futures = {name: submit_object(c, c.object, [c.variant], backends=[], per_variant=deformation)
               for name, c in cfgs.items()}
    table = RunTable(total=sum(len(f) for f in futures.values()))
    refs: dict[str, dict[str, Any]] = {}
    statuses: dict[str, str] = {}
    for name, steps in futures.items():
        refs[name] = {}
        for (step, variant), fut in steps.items():
            refs[name][step] = table.add_future(f"{cfgs[name].object.name}:{name}", step, fut,
                                                root=cfgs[name].paths.artifacts, variant=variant)
            statuses[f"{name}/{step}"] = table.rows[-1].status
    records = {name: conv.load_record(r) for name, r in refs.items() if None not in r.values()}
    reference = sweep["reference"]
    if reference not in records:
        raise RuntimeError(f"the reference setting {reference!r} did not finish: see the task table")
    presets = {n: OmegaConf.create(c) for n, c in sweep["presets"].items()}
    rows = []
    for s in sweep["settings"]:
        name = s["name"]
        if name in records:
            row = conv.setting_row(name, s["family"], cfgs[name], records[name], records[reference])
        else:
            failed = [r.note for r in table.rows if r.object.endswith(f":{name}") and r.status == "failed"]
            row = {"setting": name, "family": s["family"], "status": "failed", "note": "; ".join(failed)}
        row["preset"] = ", ".join(([s["preset"]] if s.get("preset") else [])
                                  + [p for p in conv.matching_presets(cfgs[name], presets) if p != s.get("preset")])
        rows.append(row)
    df = conv.convergence_table(rows, reference, pareto_on=sweep["pareto_error"])
    orders = conv.family_orders(df, sweep["families"], error=sweep["pareto_error"], records=records)
    base = cfgs[reference]
    meta = {"object": base.object.name, "session": base.signal.session or base.object.session,
            "reference": reference, "size_m": conv.bbox_diagonal(records[reference].bbox_min,
                                                                 records[reference].bbox_max),
            "machine": sweep["machine"], "presets": sorted(presets),
            "config": {"sweep": {k: v for k, v in sweep.items() if k != "presets"}, "reference": configs[reference]}}
    paths = conv.write_convergence_report(report_dir, df, orders=orders, meta=meta, error_name=sweep["pareto_error"])
    print(f"\nper-task table ({table.summary()})\n{table.to_text()}")
    print(f"report: {paths['markdown'].resolve()}")
    return {"report": str(Path(report_dir).resolve()), "statuses": statuses, "table": df.to_dict("records")}


def run_convergence(cfg: DictConfig) -> dict:
    """Entry used by the Hydra main and the tests: validate, build the settings, run the sweep flow."""
    from conf.schema import ConfigError
    from flows.preflight import preflight

    preflight(cfg)  # the base config and its input files, one line before anything starts
    from prefect import flow

    from flows.lifecycle import temporary_server
    from flows.runtime import make_task_runner, result_storage_settings

    try:
        validate_convergence(cfg)
    except ConfigError as exc:
        raise SystemExit(f"config error: {exc}") from None
    configs = {n: OmegaConf.to_container(c, resolve=True) for n, c in setting_configs(cfg).items()}
    presets = {n: OmegaConf.to_container(c, resolve=True) for n, c in preset_configs(cfg).items()}
    sweep = OmegaConf.to_container(cfg.convergence, resolve=True)
    sweep["presets"] = presets
    sweep["machine"] = f"{platform.machine()}, {os.cpu_count()} CPU cores, load average at start " \
                       f"{os.getloadavg()[0]:.1f}"
    run_name = cfg.run_name or f"{cfg.object.name}-{datetime.now():%Y%m%d-%H%M%S}"
    report_dir = Path(cfg.paths.reports) / "convergence" / run_name
    runner = make_task_runner(cfg.runner)
    sweep_flow = flow(convergence_flow, name="virsqueezer-convergence", log_prints=True, validate_parameters=False,
                      persist_result=False)
    with result_storage_settings(cfg.paths.artifacts), temporary_server():
        return sweep_flow.with_options(task_runner=runner)(configs, sweep, str(report_dir))


@hydra.main(version_base="1.3", config_path="../../conf", config_name="study/convergence")
def main(cfg: DictConfig) -> None:
    from flows.lifecycle import begin_run
    from flows.preflight_env import check_folders

    check_folders(cfg)  # a study computes: an unwritable artifacts folder is one line before Prefect's home is made
    begin_run(cfg.paths.artifacts)  # Prefect's home under paths.artifacts, Ctrl-C handling; before Prefect loads
    run_convergence(cfg)


if __name__ == "__main__":
    main()
