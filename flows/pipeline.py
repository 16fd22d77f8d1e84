"""The VirSqueezer flow: wires the method steps per object.  No computation lives here.

Per object (paper sec. "Squeezing Control Mapping"), computed once and shared by every variant:
  object_model -> squeeze_signals -> signal_smoothing -> force_coefficients -> contact_patches -> dirichlet_field
  material_oracle
Per object and variant (paper Table 2: ``full`` = Dirichlet boundary conditions, ``no_dirichlet`` = force-driven):
  mpm_rollout -> deformation_metrics
Each call below submits a cached Prefect task (tasks.step) with exactly the config values the step reads.
"""
from __future__ import annotations

import hashlib

from prefect.logging import get_logger
import time
from datetime import datetime
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from prefect import flow

from flows.runtime import RunTable, make_task_runner, result_storage_settings
from tasks.contact_patches import contact_patches_step
from tasks.deformation_metrics import deformation_metrics_step
from tasks.dirichlet_field import dirichlet_field_step
from tasks.force_coefficients import force_coefficients_step
from tasks.material_oracle import material_oracle_step
from tasks.mpm_rollout import mpm_rollout_step
from tasks.object_model import object_model_step
from tasks.report import write_run_report
from tasks.signal_smoothing import signal_smoothing_step
from tasks.squeeze_signals import squeeze_signals_step

log = get_logger("virsqueezer")


def file_sha256(path: str) -> str:
    """Content digest of a user input file, so that editing the file invalidates the steps reading it."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise SystemExit(f"input file {p} does not exist: check the path in your config")
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _selected(single: Any, catalog: Any, names: Any, what: str) -> list[DictConfig]:
    """``single`` when the user picked one (``object=NAME`` / ``variant=NAME``), else ``catalog[n]`` for every name
    in ``names`` (``grid.objects`` / ``grid.variants``)."""
    if single is not None:
        return [single]
    missing = [n for n in names if n not in catalog]
    if missing:
        raise SystemExit(f"grid.{what}s names unknown {what}s {missing}: known {sorted(catalog)}")
    return [catalog[n] for n in names]


def selected_objects(cfg: DictConfig) -> list[DictConfig]:
    """``object=NAME`` selects one object; otherwise every name in ``grid.objects`` from the catalog."""
    return _selected(cfg.object, cfg.catalog, cfg.grid.objects, "object")


def selected_variants(cfg: DictConfig) -> list[DictConfig]:
    """``variant=NAME`` selects one variant; otherwise every name in ``grid.variants`` from ``variants``."""
    return _selected(cfg.variant, cfg.variants, cfg.grid.variants, "variant")


def _plain(node: Any) -> Any:
    return OmegaConf.to_container(node, resolve=True)


def step_params(cfg: DictConfig, obj: DictConfig) -> dict[str, dict]:
    """Exactly the config values each step reads (its cache key), per object."""
    plain_obj = _plain(obj)
    shape = {k: plain_obj[k] for k in ("name", "geometry", "appearance", "filled", "interior")}
    object_params = {"object": shape, "sampling": _plain(cfg.sampling)}
    if obj.geometry.kind in ("ply", "mesh"):
        object_params["file_sha256"] = file_sha256(obj.geometry.path)
    signal = _plain(cfg.signal)
    signal["session"] = cfg.signal.session or obj.session
    signal_params = {"signal": signal, "frame_rate": cfg.control.smoothing.frame_rate}
    if cfg.signal.source == "csv":
        signal_params["file_sha256"] = file_sha256(cfg.signal.path)
        # a recording does not depend on the generator's knobs
        signal_params["signal"] = {"source": "csv", "path": cfg.signal.path}
    return {
        "object_model": object_params,
        "squeeze_signals": signal_params,
        "signal_smoothing": {"smoothing": _plain(cfg.control.smoothing)},
        "force_coefficients": {"force": _plain(cfg.control.force), "frame_rate": cfg.control.smoothing.frame_rate},
        "contact_patches": {"contact": _plain(cfg.control.contact)},
        "dirichlet_field": {"displacement": {**_plain(cfg.control.displacement),
                                             "eta": obj.eta if obj.eta is not None else cfg.control.displacement.eta}},
        "material_oracle": {"description": obj.description, "name": obj.name, "overrides": plain_obj["material"],
                            "interior": obj.interior, "oracle": _plain(cfg.oracle)},
    }


def variant_params(cfg: DictConfig, variant: DictConfig) -> dict[str, dict]:
    """Exactly the config values each per-variant step reads (its cache key): not the variant's name, so two
    variants that simulate the same thing share one artifact."""
    return {
        "mpm_rollout": {"mpm": _plain(cfg.mpm), "simulation": _plain(cfg.simulation), "boundary": variant.boundary},
        "deformation_metrics": {"metrics": _plain(cfg.metrics)},
    }


def submit_object(cfg: DictConfig, obj: DictConfig, variants: list[DictConfig]) -> dict[tuple[str, str], Any]:
    """Submit one object's steps: the shared chain once, then the rollout and metrics per variant.

    Returns the futures keyed by (step, variant name); shared steps have variant ``""``."""
    root, scope = cfg.paths.artifacts, obj.name
    p = step_params(cfg, obj)
    kw = dict(root=root, scope=scope)
    f: dict[str, Any] = {}
    f["object_model"] = object_model_step.submit(params=p["object_model"], **kw)
    f["squeeze_signals"] = squeeze_signals_step.submit(
        params=p["squeeze_signals"], inputs={"object": f["object_model"]}, **kw)
    f["signal_smoothing"] = signal_smoothing_step.submit(
        params=p["signal_smoothing"], inputs={"signals": f["squeeze_signals"]}, **kw)
    f["force_coefficients"] = force_coefficients_step.submit(
        params=p["force_coefficients"], inputs={"frames": f["signal_smoothing"]}, **kw)
    f["contact_patches"] = contact_patches_step.submit(
        params=p["contact_patches"],
        inputs={"object": f["object_model"], "frames": f["signal_smoothing"], "forces": f["force_coefficients"]}, **kw)
    f["dirichlet_field"] = dirichlet_field_step.submit(
        params=p["dirichlet_field"],
        inputs={"object": f["object_model"], "contacts": f["contact_patches"], "forces": f["force_coefficients"]}, **kw)
    f["material_oracle"] = material_oracle_step.submit(params=p["material_oracle"], **kw)
    out: dict[tuple[str, str], Any] = {(step, ""): fut for step, fut in f.items()}
    for variant in variants:
        vp = variant_params(cfg, variant)
        rollout = mpm_rollout_step.submit(
            params=vp["mpm_rollout"],
            inputs={"object": f["object_model"], "frames": f["signal_smoothing"], "forces": f["force_coefficients"],
                    "contacts": f["contact_patches"], "field": f["dirichlet_field"], "materials": f["material_oracle"]},
            **kw)
        metrics = deformation_metrics_step.submit(
            params=vp["deformation_metrics"],
            inputs={"rollout": rollout, "field": f["dirichlet_field"], "forces": f["force_coefficients"],
                    "contacts": f["contact_patches"], "frames": f["signal_smoothing"], "object": f["object_model"]},
            **kw)
        out[("mpm_rollout", variant.name)] = rollout
        out[("deformation_metrics", variant.name)] = metrics
    return out


@flow(name="virsqueezer", log_prints=True, validate_parameters=False, persist_result=False)
def virsqueezer_flow(config: dict, flow_label: str = "evaluate", report_dir: str | None = None) -> dict:
    """Run the selected objects x variants through the method steps, then write the run report to
    ``report_dir`` (default ``paths.reports/<run_name>``).

    Returns the report folder and the per-task table (as records).
    """
    cfg = OmegaConf.create(config)
    t0 = time.perf_counter()
    objects, variants = selected_objects(cfg), selected_variants(cfg)
    futures = {obj.name: submit_object(cfg, obj, variants) for obj in objects}
    table = RunTable(total=sum(len(f) for f in futures.values()))
    refs: dict[str, dict[str, Any]] = {}
    for name, steps in futures.items():
        refs[name] = {}
        for (step, variant), fut in steps.items():
            ref = table.add_future(name, step, fut, variant=variant)
            if variant:
                refs[name].setdefault("variants", {}).setdefault(variant, {})[step] = ref
            else:
                refs[name][step] = ref
    report_dir = Path(report_dir) if report_dir else Path(cfg.paths.reports) / (cfg.run_name or _fresh_run_name(
        Path(cfg.paths.reports), flow_label))
    labels = {v.name: v.label or v.name for v in variants}
    write_run_report(report_dir, cfg=config, table=table, refs=refs, variants=labels,
                     wall_seconds=time.perf_counter() - t0)
    print(f"\nper-task table ({table.summary()}), wall {time.perf_counter() - t0:.1f} s\n{table.to_text()}")
    print(f"report: {report_dir.resolve() / 'report.md'}")
    failed = [r for r in table.rows if r.status == "failed"]
    if failed:
        first = failed[0]
        raise RuntimeError(f"{len(failed)} step(s) failed; first: {first.object}/{first.step}: {first.note}")
    return {"report": str(report_dir.resolve()), "tasks": table.frame().to_dict("records")}


def _fresh_run_name(reports: Path, flow_label: str) -> str:
    """``<flow>-<timestamp>``, claimed atomically; two runs started in the same second get distinct folders."""
    reports.mkdir(parents=True, exist_ok=True)
    stem = f"{flow_label}-{datetime.now():%Y%m%d-%H%M%S}"
    for n in range(1, 1000):
        name = stem if n == 1 else f"{stem}-{n}"
        try:
            (reports / name).mkdir()
            return name
        except FileExistsError:
            continue
    raise RuntimeError(f"cannot find a free report folder name under {reports} for {stem}")


def sweep_job_dir() -> str | None:
    """Inside a Hydra ``-m`` sweep, the job's own output folder (``<sweep dir>/<job number>``), where its report
    goes next to Hydra's ``.hydra/overrides.yaml`` so that :mod:`flows.sweep_summary` can aggregate the jobs."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized() or HydraConfig.get().mode != RunMode.MULTIRUN:
        return None
    return str(HydraConfig.get().runtime.output_dir)


def run(cfg: DictConfig, flow_label: str) -> dict:
    """Entry used by the Hydra mains: validate the config, pick the runner, run the flow."""
    from conf.schema import ConfigError, validate

    try:
        validate(cfg)
    except ConfigError as exc:
        raise SystemExit(f"config error: {exc}") from None
    runner = make_task_runner(cfg.runner)
    config = OmegaConf.to_container(cfg, resolve=True)
    job_dir = sweep_job_dir()
    if config.get("run_name") is None and job_dir is not None:
        config["run_name"] = f"{flow_label}-{Path(job_dir).parent.name}-job{Path(job_dir).name}"
    with result_storage_settings(cfg.paths.artifacts):
        return virsqueezer_flow.with_options(task_runner=runner, name=f"virsqueezer-{flow_label}")(
            config, flow_label, job_dir)
