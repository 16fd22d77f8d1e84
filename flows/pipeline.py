"""The VirSqueezer flow: wires the declared method steps per object and variant.  No computation lives here.

Each step declares its inputs (by producing step), the config paths it reads and its outputs next to its
function (:func:`tasks.core.step.artifact_step`); this module only lists the steps in pipeline order and
submits each with the futures its declaration names.  Per object, computed once and shared by every variant
(paper sec. 3.1-3.2):

    object_model -> squeeze_signals -> signal_smoothing -> force_coefficients -> contact_patches
    -> dirichlet_field; mpm_particles (the physics stage's: the only per-object step that reads the grid);
    material_oracle; gravity_preload (the body settled under its weight once, for every rollout of it)

Per object and variant (Table 2: ``full`` = Dirichlet boundary conditions, ``no_dirichlet`` = force-driven),
sec. 3.2-3.3 and Table 2:

    mpm_rollout -> deformation_metrics; gbuffer -> conditions (eq. 6)

(a force-matched variant, the default ``no_dirichlet``: its mpm_rollout calibrates its push's constant first,
:func:`variant_chain`)

Per object, variant and effect backend (``grid.backends``, default ``[generation.backend]``), sec. 3.3 and
Tables 1 and 3:

    effect -> appearance_refinement (eq. 7) -> video_metrics; llm_evaluation; paper_metrics (only when a
    ``paper_metrics`` weight file is named: the paper's VBench metrics); display_video (the watched videos: every
    view and a close-up at the video resolution with the hand drawn; nothing scores them)

Per object and variant, the report's media (videos, contact sheet, figures) are made on the task runner as soon as
the artifacts they show exist (:func:`tasks.reporting.report.cache_scene_media`), so that the report build after
the last task only links them.  A run whose every step is already on disk and intact (:func:`cached_grid`) writes
the report without starting the Prefect server or the task runner.  So does a run on a read-only artifacts folder
(a lab's cache shared read-only, :func:`flows.preflight_env.read_only_cache`), which writes nothing there (its new
report media go to ``<paths.reports>/.media``, :func:`media_folders`) and is refused in one line, before anything
is computed, when a step is not cached there (:func:`shared_cache_grid`).
"""
from __future__ import annotations

import contextlib
import time
from datetime import datetime
from functools import partial
from pathlib import Path
from typing import Any, Callable, NamedTuple

import dask
from omegaconf import DictConfig, OmegaConf
from prefect import flow, task
from prefect.cache_policies import NO_CACHE
from prefect.logging import get_logger

from flows.heartbeat import heartbeat
from flows.lifecycle import temporary_server
from flows.preflight import particle_bound, preflight, work_estimate
from flows.preflight_env import read_only_cache
from flows.report_marker import incomplete_report, writing_report
from flows.runtime import RunTable, make_task_runner, profile_table, result_storage_settings, runner_workers
from flows.selection import selected_backends, selected_objects, selected_seeds, selected_variants
from flows.sweep_summary import sweep_job_dir
from tasks.control.contact_patches import contact_patches_step
from tasks.control.dirichlet_field import dirichlet_field_step
from tasks.control.force_coefficients import force_coefficients_step
from tasks.control.object_model import object_model_step
from tasks.control.signal_smoothing import signal_smoothing_step
from tasks.control.squeeze_signals import squeeze_signals_step
from tasks.core.artifacts import ArtifactRef, digest_of, remove_stale_temporaries
from tasks.core.params import resolve_reads
from tasks.core.scope import seed_scope
from tasks.core.step import StepTask, WiringError, artifact_path, artifact_rel, step_key, valid_artifact
from tasks.evaluation.deformation_metrics import deformation_metrics_step
from tasks.evaluation.llm_evaluation import llm_evaluation_step
from tasks.evaluation.paper_metrics import paper_metrics_step
from tasks.evaluation.video_metrics import video_metrics_step
from tasks.generation.appearance_refinement import appearance_refinement_step
from tasks.generation.display_video import display_video_step
from tasks.generation.effect import effect_step
from tasks.physics.force_matched_rollout import force_matched_rollout_step
from tasks.physics.gravity_preload import gravity_preload_step
from tasks.physics.material_oracle import material_oracle_step
from tasks.physics.mpm_particles import mpm_particles_step
from tasks.physics.mpm_rollout import mpm_rollout_step
from tasks.render.conditions import conditions_step
from tasks.render.gbuffer import gbuffer_step
from tasks.reporting.media_cache import MEDIA_DIR
from tasks.reporting.report import SCENE_MEDIA_INPUTS, cache_scene_media, write_run_report

log = get_logger("virsqueezer")

# The pipeline, in order.  A step runs once per object unless it reads the variant (its spec's per_variant) or
# consumes a per-variant step: then once per object and variant; the effect steps, which read ``generation``, run
# once per object, variant and backend.  A step may consume only steps of its own or an outer stage.
PER_OBJECT: tuple[StepTask, ...] = (
    object_model_step, squeeze_signals_step, signal_smoothing_step, force_coefficients_step, contact_patches_step,
    dirichlet_field_step, mpm_particles_step, material_oracle_step, gravity_preload_step,
)
PER_VARIANT: tuple[StepTask, ...] = (mpm_rollout_step, deformation_metrics_step, gbuffer_step, conditions_step)
PER_BACKEND: tuple[StepTask, ...] = (effect_step, appearance_refinement_step, video_metrics_step,
                                     llm_evaluation_step, paper_metrics_step, display_video_step)
STEPS: tuple[StepTask, ...] = PER_OBJECT + PER_VARIANT + PER_BACKEND
STAGE_OF: dict[str, str] = {s.name: s.compute.__module__.split(".")[1] for s in STEPS}  # e.g. gbuffer -> render


def variant_chain(variant: DictConfig | None, per_variant: tuple[StepTask, ...] = PER_VARIANT) -> tuple[StepTask, ...]:
    """The per-variant steps of ``variant``: ``per_variant`` (a leading part of :data:`PER_VARIANT`), with the
    rollout replaced by the force-matched one (:mod:`tasks.physics.force_matched_rollout`: the force-driven push's
    constant calibrated, then the rollout) for a variant with ``force_match != none``."""
    if variant is None or variant.get("force_match", "none") == "none":
        return per_variant
    return tuple(force_matched_rollout_step if s is mpm_rollout_step else s for s in per_variant)


def _reads_generation(step: StepTask) -> bool:
    return any(p.split(".")[0] == "generation" for p in step.spec.reads)


def check_wiring(per_object: tuple[StepTask, ...] = PER_OBJECT, per_variant: tuple[StepTask, ...] = PER_VARIANT,
                 per_backend: tuple[StepTask, ...] = PER_BACKEND) -> None:
    """Refuse a wiring that disagrees with the declarations: every input produced by an earlier step, no step
    listed twice, per-object steps that read no variant and consume no per-variant output, and steps that read
    the effect backend (``generation``) only in the per-backend stage."""
    produced: set[str] = set()
    inner: set[str] = {s.name for s in per_variant + per_backend}
    for stage, steps in (("per-object", per_object), ("per-variant", per_variant), ("per-backend", per_backend)):
        for step in steps:
            if step.name in produced:
                raise WiringError(f"step {step.name!r} is wired twice")
            missing = [name for name in step.spec.inputs if name not in produced]
            if missing:
                raise WiringError(f"step {step.name!r} needs {missing}, which no earlier step of the wiring produces")
            if stage == "per-object" and step.spec.per_variant:
                raise WiringError(f"step {step.name!r} reads the variant but is wired per object")
            if stage == "per-object" and any(i in inner for i in step.spec.inputs):
                raise WiringError(f"step {step.name!r} is wired per object but consumes a per-variant step")
            if _reads_generation(step) and stage != "per-backend":
                raise WiringError(f"step {step.name!r} reads the effect backend but is wired {stage}")
            produced.add(step.name)
        if stage == "per-variant":
            inner = {s.name for s in per_backend}


check_wiring()
check_wiring(per_variant=variant_chain(OmegaConf.create({"force_match": "indentation"})))


def with_seed(cfg: DictConfig, seed: int) -> DictConfig:
    """``cfg`` with ``sampling.seed`` = ``seed`` (one run of the seed grid)."""
    return OmegaConf.merge(cfg, {"sampling": {"seed": int(seed)}})


def step_params(step: StepTask, cfg: DictConfig, obj: DictConfig, variant: DictConfig | None = None) -> dict:
    """Exactly the config values ``step`` declares (its parameters and cache key) for one object and variant."""
    return resolve_reads(step.name, step.spec.reads, step.spec.files, cfg, obj, variant)


def backend_config(cfg: DictConfig, backend: str) -> DictConfig:
    """``cfg`` with ``generation.backend`` set to ``backend``."""
    return cfg if cfg.generation.backend == backend else OmegaConf.merge(cfg, {"generation": {"backend": backend}})


def missing_backends(cfg: DictConfig) -> dict[str, str]:
    """The diffusion backends this run did not use, and why (Table 1's n/a rows)."""
    ran = set(selected_backends(cfg))
    why = ("weights not present: generation.weights is not set (docs/tutorials/diffusion-weights.md, 'Download')"
           if not cfg.generation.weights else "not selected: add it to grid.backends")
    return {b: why for b in ("diffusers", "text_only") if b not in ran}


def wanted(step: StepTask, cfg: DictConfig) -> bool:
    """False for the paper-metrics step when no weight file is named (``paper_metrics``): it is not run at all."""
    pm = cfg.paper_metrics
    return step is not paper_metrics_step or bool(pm.musiq_weights or pm.amt_weights or pm.videophy_weights
                                          or pm.videocon_weights)


def variant_key(variant: str, backend: str | None = None) -> str:
    """How the run table names a per-variant (``full``) or per-backend (``full/physics``) step's chain."""
    return variant if backend is None else f"{variant}/{backend}"


def submit_object(cfg: DictConfig, obj: DictConfig, variants: list[DictConfig], backends: list[str] | None = None,
                  per_variant: tuple[StepTask, ...] = PER_VARIANT, scope: str | None = None,
                  call: Callable[..., Any] = StepTask.submit,
                  priorities: StepPriorities | None = None) -> dict[tuple[str, str], Any]:
    """Submit one object's steps: the per-object chain once, the per-variant chain for each variant, and the
    per-backend chain for each variant and backend.

    Returns the futures keyed by (step, chain): ``""`` for per-object steps, the variant name for per-variant
    steps and ``variant/backend`` for per-backend ones.  ``per_variant`` may be a leading part of
    :data:`PER_VARIANT` (e.g. the deformation chain alone, with ``backends=[]``); ``scope`` names the run's
    artifacts and labels (default: the object's name).  ``call(step, root=, scope=, params=, inputs=, label=)``
    makes each step's result from its inputs' (default :meth:`StepTask.submit`: a future).  ``priorities``:
    the Dask priorities of the per-object steps (``set_up``) and of every other step (``steps``), higher first."""
    scope = scope or obj.name
    kw = dict(root=cfg.paths.artifacts, scope=scope)
    shared: dict[str, Any] = {}
    with _priority(priorities, "set_up"):
        for step in PER_OBJECT:
            shared[step.name] = call(step, params=step_params(step, cfg, obj),
                                     inputs={n: shared[n] for n in step.spec.inputs}, label=scope, **kw)
    out: dict[tuple[str, str], Any] = {(name, ""): fut for name, fut in shared.items()}
    with _priority(priorities, "steps"):
        for variant in variants:
            available = dict(shared)
            for step in variant_chain(variant, per_variant):
                available[step.name] = call(
                    step, params=step_params(step, cfg, obj, variant),
                    inputs={n: available[n] for n in step.spec.inputs}, label=f"{scope}[{variant.name}]", **kw)
                out[(step.name, variant.name)] = available[step.name]
            for backend in (backends if backends is not None else selected_backends(cfg)):
                cfg_b, chain = backend_config(cfg, backend), dict(available)
                for step in filter(lambda s: wanted(s, cfg), PER_BACKEND):
                    chain[step.name] = call(
                        step, params=step_params(step, cfg_b, obj, variant),
                        inputs={n: chain[n] for n in step.spec.inputs},
                        label=f"{scope}[{variant_key(variant.name, backend)}]", **kw)
                    out[(step.name, variant_key(variant.name, backend))] = chain[step.name]
    return out


def _priority(priorities: StepPriorities | None, which: str) -> contextlib.AbstractContextManager:
    return contextlib.nullcontext() if priorities is None else dask.annotate(priority=getattr(priorities, which))


def nest(steps: dict[tuple[str, str], Any]) -> dict[str, Any]:
    """One object's results keyed by (step, chain) as the report reads them: the shared steps at the top,
    ``["variants"][variant][step]`` and ``["variants"][variant]["backends"][backend][step]``."""
    tree: dict[str, Any] = {}
    for (step, chain), value in steps.items():
        variant, _, backend = chain.partition("/")
        if backend:
            tree["variants"][variant].setdefault("backends", {}).setdefault(backend, {})[step] = value
        elif variant:
            tree.setdefault("variants", {}).setdefault(variant, {})[step] = value
        else:
            tree[step] = value
    return tree


class NotCached(LookupError):
    """A step has no intact artifact on disk; the message names it as ``<scope>[<variant>]/<step>``."""


def _cached(step: StepTask, *, root: str, scope: str, params: dict, inputs: dict[str, ArtifactRef],
            label: str, discard: bool = True) -> ArtifactRef:
    """The step's intact artifact on disk, found as its task's cache policy finds it (same key, same check,
    a damaged one removed with one warning line; left in place with ``discard=False``), without running anything."""
    key = step_key(step.name, step.version, scope, params, {n: ref.at(root) for n, ref in inputs.items()},
                   step.spec.unkeyed)
    attrs = valid_artifact(artifact_path(root, scope, step.name, key), scope, step.name, discard)
    if attrs is None:
        raise NotCached(f"{label}/{step.name}")
    return ArtifactRef(rel=artifact_rel(scope, step.name, key), digest=attrs["digest"], step=step.name, scope=scope,
                       compute_seconds=float(attrs.get("compute_seconds", 0.0))).at(root)


def cached_object(cfg: DictConfig, obj: DictConfig, variants: list[DictConfig], scope: str,
                  until: str, discard: bool = True) -> dict[tuple[str, str], ArtifactRef]:
    """One object's artifacts keyed as :func:`submit_object`'s futures, the per-variant chain up to step ``until``
    (no effect backend), each found on disk as the cached tasks find it, without running anything; raises
    :class:`NotCached` naming the first step that has no intact artifact (``discard=False``: a damaged one is left
    in place, for a read-only cache)."""
    names = [s.name for s in PER_VARIANT]
    return submit_object(cfg, obj, variants, backends=[], per_variant=PER_VARIANT[:names.index(until) + 1],
                         scope=scope, call=partial(_cached, discard=discard))


def find_cached_grid(cfg: DictConfig, discard: bool = True) -> dict[str, dict[tuple[str, str], ArtifactRef]]:
    """Every step's artifact of the grid, keyed as the flow's futures, each found on disk and intact (the same keys
    and manifest check as the cached tasks, in this process, without Prefect); raises :class:`NotCached` at the
    first step that must run (a damaged artifact is removed with one warning line on the way, unless
    ``discard=False``)."""
    return {seed_scope(obj.name, seed): submit_object(with_seed(cfg, seed), obj, selected_variants(cfg),
                                                      scope=seed_scope(obj.name, seed),
                                                      call=partial(_cached, discard=discard))
            for obj in selected_objects(cfg) for seed in selected_seeds(cfg)}


def cached_grid(cfg: DictConfig) -> dict[str, dict[tuple[str, str], ArtifactRef]] | None:
    """:func:`find_cached_grid`, or None at the first step that must run (a damaged artifact is removed with one
    warning line on the way: the flow recomputes it)."""
    try:
        return find_cached_grid(cfg)
    except NotCached:
        return None


def shared_cache_grid(cfg: DictConfig, why: str) -> dict[str, dict[tuple[str, str], ArtifactRef]]:
    """The grid's artifacts in the read-only cache ``paths.artifacts`` (``why``: what makes it read-only,
    :func:`flows.preflight_env.read_only_cache`), found without writing anything there, or one line
    (``SystemExit``) naming the first step (``<scope>[<variant>/<backend>]/<step>``) that is not cached there
    intact and the fix, before anything is computed."""
    try:
        return find_cached_grid(cfg, discard=False)
    except NotCached as first:
        raise _not_in_shared_cache(cfg, why, first) from None


def _not_in_shared_cache(cfg: DictConfig, why: str, first: NotCached) -> SystemExit:
    """The one line refusing a run that needs the step ``first`` names, which the read-only cache ``paths.artifacts``
    (``why``) does not hold intact."""
    root = cfg.paths.artifacts
    return SystemExit(f"config error: paths.artifacts={root} is a read-only cache ({why}) and {first} is not cached "
                      f"there (missing or damaged), so the run would have to write into it: give a writable folder "
                      f"(paths.artifacts=/path/to/folder), e.g. a copy of the cache (cp -a {root} /path/to/folder)")


# the report media of one scene, made on the task runner as soon as its artifacts are (not cached by Prefect:
# the media cache is by content, and a scene whose media are all there returns at once)
scene_media_task = task(cache_scene_media, name="report_media", task_run_name="report_media[{obj}/{variant}]",
                        cache_policy=NO_CACHE, persist_result=False)


def submit_scene_media(cfg: DictConfig, scope: str, futures: dict[tuple[str, str], Any]) -> list:
    """Submit the report media of each variant of one object (:func:`cache_scene_media`), each waiting for the
    futures of just the steps its media show."""
    shown = nest({(step, chain): fut for (step, chain), fut in futures.items() if step in SCENE_MEDIA_INPUTS})
    return [scene_media_task.submit(scope, {**{k: v for k, v in shown.items() if k != "variants"},
                                            "variants": {variant: refs}}, variant, cfg.paths.artifacts, first=k == 0)
            for k, (variant, refs) in enumerate(shown.get("variants", {}).items())]


def evaluate_config(overrides: list[str]) -> DictConfig:
    """The evaluation grid's config (``conf/evaluate.yaml``) with ``overrides``, composed outside Hydra's main (the
    study flows, notebooks; pair it with :func:`run_object_local`)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from conf.schema import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(Path(__file__).resolve().parents[1] / "conf"), version_base="1.3"):
        return compose(config_name="evaluate", overrides=list(overrides))


def run_object_local(cfg: DictConfig, obj: DictConfig, variant: DictConfig | None, root: str | Path,
                     until: str | None = None, call: Callable[..., ArtifactRef] = StepTask.run_local
                     ) -> dict[str, ArtifactRef]:
    """Run one object's chain (and one variant's, when given) without Prefect, up to step ``until`` (tests,
    notebooks).  Same keys and artifacts as the flow.  ``call`` makes each step's result (default: runs it or reuses
    its artifact; :func:`shared_cache_object` only finds it)."""
    refs: dict[str, ArtifactRef] = {}
    scope = seed_scope(obj.name, int(cfg.sampling.seed))
    for step in PER_OBJECT + (variant_chain(variant) + PER_BACKEND if variant is not None else ()):
        if not wanted(step, cfg):
            continue
        refs[step.name] = call(step, root=str(root), scope=scope, params=step_params(step, cfg, obj, variant),
                               inputs={n: refs[n] for n in step.spec.inputs}, label=scope)
        if step.name == until:
            break
    return refs


def shared_cache_object(cfg: DictConfig, obj: DictConfig, variant: DictConfig, why: str,
                        until: str | None = None) -> dict[str, ArtifactRef]:
    """:func:`run_object_local`'s artifacts found in the read-only cache ``paths.artifacts`` (``why``), nothing run or
    written, or the one line of :func:`shared_cache_grid` (``SystemExit``)."""
    try:
        return run_object_local(cfg, obj, variant, cfg.paths.artifacts, until, call=partial(_cached, discard=False))
    except NotCached as first:
        raise _not_in_shared_cache(cfg, why, first) from None


class StepPriorities(NamedTuple):
    """Dask priorities of one object's steps (higher runs first): its set-up steps, its other steps, its report
    media."""
    set_up: int
    steps: int
    media: int


def object_priorities(cfg: DictConfig, objects: list[DictConfig]) -> list[tuple[DictConfig, StepPriorities]]:
    """Each object with the Dask priorities of its steps, largest object first (a Dask cluster runs its ready steps
    by priority, higher first; other runners ignore it).

    Every object's set-up steps (cheap, up to its gravity preload) outrank every object's other steps: otherwise each
    small step of a late object waits for a whole rollout of an earlier one, and a freed worker finds no rollout
    ready.  Then the largest object (:func:`particle_bound`) first: the longest simulations start at once instead of
    last.  An object's report media come after its own steps and before the next object's: made while the grid
    runs, not all at its end."""
    by_work = sorted(objects, key=lambda o: particle_bound(cfg, o), reverse=True)
    n = len(by_work)
    return [(obj, StepPriorities(set_up=4 * n - rank, steps=2 * (n - rank), media=2 * (n - rank) - 1))
            for rank, obj in enumerate(by_work)]


@flow(name="virsqueezer", log_prints=True, validate_parameters=False, persist_result=False)
def virsqueezer_flow(config: dict, flow_label: str = "evaluate", report_dir: str | None = None) -> dict:
    """Run the selected objects x seeds x variants through the method steps, then write the run report to
    ``report_dir`` (default ``paths.reports/<run_name>``).

    Returns the report folder and the per-task table (as records).
    """
    cfg = OmegaConf.create(config)
    t0 = time.perf_counter()
    futures, media = {}, []
    objects = selected_objects(cfg)
    for obj, priorities in object_priorities(cfg, objects):
        for seed in selected_seeds(cfg):
            scope = seed_scope(obj.name, seed)
            futures[scope] = submit_object(with_seed(cfg, seed), obj, selected_variants(cfg), scope=scope,
                                           priorities=priorities)
            with dask.annotate(priority=priorities.media):
                media += submit_scene_media(cfg, scope, futures[scope])
    futures = {seed_scope(o.name, s): futures[seed_scope(o.name, s)] for o in objects for s in selected_seeds(cfg)}
    table = RunTable(total=sum(len(f) for f in futures.values()))
    refs = {name: nest({(step, chain): table.add_future(name, step, fut, root=cfg.paths.artifacts, variant=chain)
                        for (step, chain), fut in steps.items()}) for name, steps in futures.items()}
    for fut in media:
        fut.wait()  # a scene whose media failed (or whose steps did) is made, or reported, by the report build
    return write_report(cfg, config, flow_label, report_dir, table, refs, t0)


def write_report(cfg: DictConfig, config: dict, flow_label: str, report_dir: str | None, table: RunTable,
                 refs: dict[str, dict[str, Any]], t0: float) -> dict:
    """Write the run report of ``refs`` (:func:`nest` per object) and print the per-task table; raise when a step
    failed.  Returns the report folder and the per-task table (as records)."""
    digest = digest_of(config)
    reports = Path(cfg.paths.reports)
    report_dir = Path(report_dir) if report_dir else reports / (cfg.run_name or _report_name(reports, flow_label,
                                                                                              digest))
    labels = {v.name: v.label or v.name for v in selected_variants(cfg)}
    wall = time.perf_counter() - t0
    media_cache, *shared_media = media_folders(cfg)
    with writing_report(report_dir, digest):  # cut: REPORT_INCOMPLETE.txt stays, the stop line says so
        write_run_report(report_dir, cfg=config, table=table, refs=refs, variants=labels, wall_seconds=wall,
                         missing_backends=missing_backends(cfg),
                         profile=profile_table(table, STAGE_OF, wall, runner_workers(cfg.runner)),
                         media_cache=media_cache, shared_media=shared_media)
    print(f"\nper-task table ({table.summary()}), wall {time.perf_counter() - t0:.1f} s\n{table.to_text()}")
    print(f"report: {report_dir.resolve() / 'report.md'}")
    failed = [r for r in table.rows if r.status == "failed"]
    if failed:
        first = failed[0]
        raise RuntimeError(f"{len(failed)} step(s) failed; first: {first.object}/{first.step}: {first.note}")
    return {"report": str(report_dir.resolve()), "tasks": table.frame().to_dict("records")}


def media_folders(cfg: DictConfig) -> tuple[Path, ...]:
    """The report media cache's folders (:class:`tasks.reporting.media_cache.MediaCache`): the one written, then
    those only read.  ``<paths.artifacts>/.media``; for a read-only cache ``<paths.reports>/.media``, then the
    cache's own ``.media``."""
    shared = Path(cfg.paths.artifacts) / MEDIA_DIR
    if not read_only_cache(cfg.paths.artifacts):
        return (shared,)
    return (Path(cfg.paths.reports) / MEDIA_DIR, shared)


def _report_name(reports: Path, flow_label: str, digest: str) -> str:
    """The folder of a report of this config cut by a stop (rewritten), else a fresh one."""
    cut = incomplete_report(reports, flow_label, digest)
    return cut.name if cut is not None else _fresh_run_name(reports, flow_label)


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


def run(cfg: DictConfig, flow_label: str) -> dict:
    """Entry used by the Hydra mains: check the config and inputs, pick the runner, run the flow."""
    preflight(cfg, read_only_ok=True)
    t0 = time.perf_counter()
    read_only = read_only_cache(cfg.paths.artifacts)
    shared = shared_cache_grid(cfg, read_only) if read_only else None  # before anything else: all there, or a line
    removed, freed = remove_stale_temporaries(cfg.paths.artifacts) if not read_only else (0, 0)
    if removed:
        print(f"removed {removed} temporary folder(s) ({freed / 1e6:.1f} MB) left in {cfg.paths.artifacts} by "
              "runs that were killed")
    if "physics" in selected_backends(cfg) and not cfg.generation.weights:
        print("effect backend: physics-rendered (weight-free). For the paper's diffusion backend put SD-1.5, an "
              "AnimateDiff motion adapter and a depth ControlNet under one folder and run generation=diffusers "
              "generation.weights=/path/to/models (docs/tutorials/diffusion-weights.md, 'Download').")
    config = OmegaConf.to_container(cfg, resolve=True)
    job_dir = sweep_job_dir()
    if config.get("run_name") is None and job_dir is not None:
        config["run_name"] = f"{flow_label}-{Path(job_dir).parent.name}-job{Path(job_dir).name}"
    cached = shared if read_only else cached_grid(cfg)
    if cached is not None:  # nothing to compute: the report alone, without a Prefect server or task runner
        print(f"every step is cached ({sum(len(s) for s in cached.values())} artifacts checked in "
              f"{time.perf_counter() - t0:.1f} s): no Prefect server or task runner started, writing the report")
        table = RunTable(total=sum(len(s) for s in cached.values()))
        refs = {name: nest({(step, chain): table.add_cached(name, step, ref, variant=chain)
                            for (step, chain), ref in steps.items()}) for name, steps in cached.items()}
        return write_report(OmegaConf.create(config), config, flow_label, job_dir, table, refs, t0)
    est = work_estimate(cfg)
    print(est.line(), flush=True)
    runner = make_task_runner(cfg.runner)
    with heartbeat(est.wall_seconds), result_storage_settings(cfg.paths.artifacts), temporary_server() as api_url:
        if cfg.runner.kind == "dask" and cfg.runner.address:  # an existing cluster: do its workers see ours?
            from flows.cluster import check_workers

            print(f"checked {check_workers(cfg.runner.address, cfg.paths.artifacts, STEPS, api_url)} Dask worker(s) "
                  f"of {cfg.runner.address}: same artifacts folder, code, packages and Prefect API as this flow")
        return virsqueezer_flow.with_options(task_runner=runner, name=f"virsqueezer-{flow_label}")(
            config, flow_label, job_dir)
