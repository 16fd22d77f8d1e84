"""Method steps as cached Prefect tasks over zarr artifacts.

A step is a pure function ``compute(inputs, params) -> (arrays, attrs)`` of loaded input artifacts and the
exact config values it reads.  It is declared once, next to the function, with :func:`artifact_step`::

    @artifact_step("dirichlet_field",
                   inputs=("object_model", "contact_patches", "force_coefficients"),   # producing steps
                   reads=("control.displacement", "object.eta"),                          # config paths = cache key
                   outputs=("displacement", "weight", "constrained", "finger", "surface_points"))
    def dirichlet_field_step(inputs, params): ...

* ``inputs`` are named by the step that produces them (one name per dataset, at both ends); the flow wires a
  step's inputs from these names (:mod:`flows.pipeline`) and refuses a wiring that disagrees.
* ``reads`` are config paths (:mod:`tasks.core.params`); the step sees only those values (:class:`Params`), so
  everything it reads is in its key.  ``files`` are config paths of input files whose content digest joins it.
* ``outputs`` are the array names the step writes (a trailing ``?`` marks an array written only for some
  scenes); a step returning anything else fails with the difference named.
* The code version in the key is the import closure of the step's module (:mod:`tasks.core.code_version`).

The Prefect task made from the declaration

* computes a content-addressed key = sha256(step name, code version, scope, params, digests of the input
  artifacts) - nothing else (no run id, job number or output dir);
* stores its result as a zarr group at ``<root>/<scope>/<step>/<key[:20]>.zarr`` (atomic, see
  :mod:`tasks.core.artifacts`) and returns an :class:`ArtifactRef` holding that path relative to ``root``;
  the inputs it is given are re-rooted at its own ``root`` (a moved or copied artifacts folder works from its
  new place and never reads the original's files);
* is cached by Prefect under that key (JSON result records, no pickle, no absolute path).  The cache policy
  checks the artifact on disk against the manifest written with it (every file's size and sha256): if it
  was deleted, is incomplete or damaged, it is removed with one warning line, the stale cache record is
  dropped and the step runs again instead of returning a dangling or wrong reference.
"""
from __future__ import annotations

import inspect
import json
import time
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

from prefect import task
from prefect.cache_policies import CachePolicy
from prefect.context import TaskRunContext
from prefect.logging import get_logger

from tasks.core.artifacts import (
    Array,
    Artifact,
    ArtifactDamaged,
    ArtifactMissing,
    ArtifactOutdated,
    ArtifactRef,
    digest_of,
    discard_artifact,
    read_artifact,
    verify_artifact,
    write_artifact,
)
from tasks.core.code_version import code_version, module_file
from tasks.core.environment import check_step_identity, package_versions, process_label
from tasks.core.params import Params
from tasks.core.records import atomic_record_writes

atomic_record_writes()  # Prefect's cache records replaced at once, never seen half-written (tasks.core.records)

log = get_logger("virsqueezer")

ComputeFn = Callable[[Mapping[str, Artifact], Mapping[str, Any]], tuple[Mapping[str, Array], Mapping[str, Any]]]


class StepOutputError(RuntimeError):
    """A step returned arrays that its declaration does not list (or missed a required one)."""


@dataclass(frozen=True)
class StepSpec:
    """What a step is: its inputs (named by the producing step), the config paths it reads, the files whose
    content it reads, and the arrays it writes (``name?`` = written only for some scenes)."""

    name: str
    inputs: tuple[str, ...] = ()
    reads: tuple[str, ...] = ()
    files: tuple[str, ...] = ()
    outputs: tuple[str, ...] = ()
    unkeyed: tuple[str, ...] = ()

    @property
    def per_variant(self) -> bool:
        """True when the step reads the method variant (it runs once per object and variant)."""
        return any(p.split(".")[0] == "variant" for p in self.reads + self.files)

    def check_outputs(self, arrays: Mapping[str, Any]) -> None:
        required = {o for o in self.outputs if not o.endswith("?")}
        allowed = required | {o[:-1] for o in self.outputs if o.endswith("?")}
        missing, extra = sorted(required - set(arrays)), sorted(set(arrays) - allowed)
        if missing or extra:
            raise StepOutputError(f"step {self.name!r} wrote arrays that disagree with its declared outputs: "
                                  f"missing {missing}, undeclared {extra}")


def keyed_params(params: Mapping[str, Any], unkeyed: tuple[str, ...] = ()) -> dict[str, Any]:
    """``params`` without the ``unkeyed`` config paths (e.g. ``mpm.threads`` inside the declared ``mpm``): values that
    choose how a step runs (a thread count), not what it computes beyond float round-off, so that every flow running
    the same scene hits the same cache entry whatever its thread count."""
    out = dict(params)
    for path in unkeyed:
        head, _, rest = path.partition(".")
        for declared in list(out):
            if path == declared:
                out.pop(declared)
            elif path.startswith(declared + ".") and isinstance(out[declared], Mapping):
                parts = path[len(declared) + 1:].split(".")
                node = out[declared] = dict(out[declared])
                for part in parts[:-1]:
                    if not isinstance(node.get(part), Mapping):
                        break
                    node[part] = dict(node[part])
                    node = node[part]
                else:
                    node.pop(parts[-1], None)
    return out


def step_key(step: str, version: str, scope: str, params: Mapping[str, Any], inputs: Mapping[str, ArtifactRef],
             unkeyed: tuple[str, ...] = ()) -> str:
    """The cache key of one step run: what it is, what code, which config values (less the ``unkeyed`` ones), which
    input contents."""
    params = keyed_params(params, unkeyed)
    return digest_of(
        {
            "step": step,
            "code": version,
            "scope": scope,
            "params": params,
            "inputs": {name: ref.digest for name, ref in sorted(inputs.items())},
        }
    )


def artifact_rel(scope: str, step: str, key: str) -> str:
    """Where a step's artifact lives inside the artifacts folder."""
    return f"{scope}/{step}/{key[:20]}.zarr"


def artifact_path(root: str | Path, scope: str, step: str, key: str) -> Path:
    return Path(root).resolve() / artifact_rel(scope, step, key)


def valid_artifact(path: Path, scope: str, step: str, discard: bool = True) -> dict[str, Any] | None:
    """The group attributes of the artifact at ``path`` when it is there and is what was written (every file's
    size and sha256 as in its manifest, :func:`tasks.core.artifacts.verify_artifact`); ``None`` when it is not
    there.  A damaged or incomplete one is removed, with one warning line naming it and what was wrong, so that
    the step is computed again (one of an older artifact format too, with an info line); with ``discard=False``
    (a read-only cache) it is left as it is, and ``None`` returned."""
    try:
        return verify_artifact(path)
    except ArtifactMissing:
        return None
    except ArtifactDamaged as exc:
        if not discard:
            return None
        discard_artifact(path)
        if isinstance(exc, ArtifactOutdated):
            log.info("%s/%s: artifact %s was %s: removed, the step is recomputed", scope, step, path, exc.problem)
        else:
            log.warning("%s/%s: artifact %s is damaged (%s): removed, the step is recomputed", scope, step, path,
                        exc.problem)
        return None


@dataclass
class ArtifactCachePolicy(CachePolicy):
    """Cache key = :func:`step_key`; a record whose artifact is gone from disk or damaged (:func:`valid_artifact`)
    is dropped first."""

    step: str = ""
    version: str = ""
    unkeyed: tuple[str, ...] = ()

    def compute_key(self, task_ctx: TaskRunContext, inputs: dict[str, Any], flow_parameters: dict[str, Any], **kwargs: Any) -> Optional[str]:
        key = step_key(self.step, self.version, inputs["scope"], inputs["params"], inputs.get("inputs") or {},
                       self.unkeyed)
        path = artifact_path(inputs["root"], inputs["scope"], self.step, key)
        if valid_artifact(path, inputs["scope"], self.step) is None:
            _drop_record(task_ctx, key)
        else:
            _drop_unsafe_record(task_ctx, key)
        return key


def _record_path(task_ctx: TaskRunContext, key: str) -> Path | None:
    store = task_ctx.result_store
    storage = getattr(store, "result_storage", None)
    basepath = getattr(storage, "basepath", None)
    return None if basepath is None else Path(basepath).expanduser() / key


def _drop_record(task_ctx: TaskRunContext, key: str) -> None:
    """Remove the cache record stored under ``key`` (its artifact no longer exists)."""
    candidate = _record_path(task_ctx, key)
    if candidate is not None and candidate.exists():
        candidate.unlink()
        log.info("cache record %s dropped: its artifact is missing or was damaged", key[:12])


_PLAIN_SERIALIZER = {"type": "json", "jsonlib": "json",
                     "object_encoder": "prefect.serializers.prefect_json_object_encoder",
                     "object_decoder": "prefect.serializers.prefect_json_object_decoder"}


def plain_record(path: Path) -> bool:
    """True when the cache record at ``path`` is what this module writes: JSON naming Prefect's JSON serializer,
    whose result is one :class:`ArtifactRef` of plain values.

    Prefect decodes a record with the serializer the record itself names - pickle included, whatever the task
    asks for - so a record planted in a shared result folder by anyone able to compute the key (code, config
    values and input digests are not secret) would run code when a later run reads it.  Records are therefore
    checked (as JSON, no object hooks) before Prefect sees them."""
    try:
        doc = json.loads(path.read_bytes())
        serializer = doc["metadata"]["serializer"]
        if any(serializer.get(k) != v for k, v in _PLAIN_SERIALIZER.items()) or serializer.get("loads_kwargs"):
            return False
        result = json.loads(doc["result"])
        data = result["data"]
        if set(result) != {"__class__", "data"} or result["__class__"] != "tasks.core.artifacts.ArtifactRef":
            return False
        if not all(isinstance(v, (str, int, float, bool)) or v is None for v in data.values()):
            return False
        ArtifactRef.model_validate(data)
        return True
    except Exception:  # noqa: BLE001 - unreadable, partial or foreign: not a record of ours
        return False


def _drop_unsafe_record(task_ctx: TaskRunContext, key: str) -> None:
    """Remove the record under ``key`` unread when it is not a :func:`plain_record` (the artifact on disk is
    reused instead, and Prefect writes a plain record again)."""
    candidate = _record_path(task_ctx, key)
    if candidate is not None and candidate.exists() and not plain_record(candidate):
        candidate.unlink(missing_ok=True)
        log.warning("cache record %s is not a plain JSON record of an artifact reference: removed unread "
                    "(the artifact on disk is reused)", candidate)


@dataclass
class StepTask:
    """A declared method step: its spec, its pure ``compute`` function and the Prefect task that caches it."""

    spec: StepSpec
    compute: ComputeFn
    version: str
    task: Any = field(repr=False)
    # where the step was declared (the flow's process), its source file when outside the project packages, and the
    # flow's package versions: a process that runs it elsewhere (a Dask worker) checks its own against them
    origin: str = field(default_factory=process_label, repr=False)
    source: str | None = field(default=None, repr=False)
    packages: tuple = field(default_factory=package_versions, repr=False)

    @property
    def name(self) -> str:
        return self.spec.name

    def submit(self, *, root: str, scope: str, params: Mapping[str, Any], inputs: Mapping[str, Any] | None = None,
               label: str = ""):
        """Submit to the flow's task runner; ``inputs`` (keyed by producing step) may hold futures."""
        return self.task.submit(root=str(root), scope=scope, params=dict(params), inputs=self._inputs(inputs),
                                label=label or scope)

    def run_local(self, *, root: str, scope: str, params: Mapping[str, Any],
                  inputs: Mapping[str, ArtifactRef] | None = None, label: str = "") -> ArtifactRef:
        """Run the step without Prefect (tests, notebooks): same key, same artifact."""
        return _execute(self, str(root), scope, dict(params), self._inputs(inputs), label or scope)

    def _inputs(self, inputs: Mapping[str, Any] | None) -> dict[str, Any]:
        given = dict(inputs or {})
        if set(given) != set(self.spec.inputs):
            raise WiringError(f"step {self.name!r} declares inputs {sorted(self.spec.inputs)} but was given "
                              f"{sorted(given)}")
        return given


class WiringError(RuntimeError):
    """The flow wired a step differently from its declaration."""


@dataclass
class _Progress:
    label: str
    started: float = field(default_factory=time.perf_counter)
    logged_tenth: int = 0


_PROGRESS: ContextVar[Optional[_Progress]] = ContextVar("virsqueezer_step_progress", default=None)


def report_progress(done: int, total: int, unit: str = "frame") -> None:
    """Log ``<object>/<step>: frame done/total`` from inside a running step, at most once per tenth of the work
    (so a grid of long steps shows where it is without flooding the log).  A no-op outside a step."""
    state = _PROGRESS.get()
    if state is None or total <= 0:
        return
    tenth = (10 * done) // total
    if tenth > state.logged_tenth:
        state.logged_tenth = tenth
        log.info("%s: %s %d/%d (%d %%), %.0f s", state.label, unit, done, total, 100 * done // total,
                 time.perf_counter() - state.started)


def _execute(step: StepTask, root: str, scope: str, params: dict, inputs: dict[str, ArtifactRef],
             label: str) -> ArtifactRef:
    name = step.name
    if step.origin != process_label():  # sent to another process (a Dask worker): same code, same packages?
        check_step_identity(name, step.compute.__module__, step.source, step.version, step.packages)
    inputs = {producer: ref.at(root) for producer, ref in inputs.items()}  # this run's folder, wherever written
    key = step_key(name, step.version, scope, params, inputs, step.spec.unkeyed)
    path = artifact_path(root, scope, name, key)
    attrs = valid_artifact(path, scope, name)
    if attrs is not None:  # the artifact survived although its cache record did not (e.g. result storage wiped)
        return ArtifactRef(rel=artifact_rel(scope, name, key), digest=attrs["digest"], step=name, scope=scope,
                           compute_seconds=float(attrs.get("compute_seconds", 0.0)), reused=True).at(root)
    loaded = {producer: read_artifact(ref) for producer, ref in inputs.items()}
    t0 = time.perf_counter()
    token = _PROGRESS.set(_Progress(f"{label}/{name}"))
    try:
        arrays, attrs = step.compute(loaded, Params(name, params))
    finally:
        _PROGRESS.reset(token)
    step.spec.check_outputs(arrays)
    seconds = time.perf_counter() - t0
    ref = write_artifact(path, arrays, step=name, scope=scope, config_digest=digest_of(params), attrs=attrs,
                         compute_seconds=seconds, root=root)
    log.info("%-18s %-12s ran in %.2f s -> %s", name, label, seconds, path)
    return ref


def artifact_step(name: str, *, inputs: tuple[str, ...] = (), reads: tuple[str, ...] = (),
                  files: tuple[str, ...] = (), outputs: tuple[str, ...] = (),
                  unkeyed: tuple[str, ...] = ()) -> Callable[[ComputeFn], StepTask]:
    """Decorator: declare a pure step function and expose it as a cached Prefect task (see module docstring).
    ``unkeyed``: paths inside ``reads`` the step sees but its cache key leaves out (:func:`keyed_params`)."""
    spec = StepSpec(name=name, inputs=tuple(inputs), reads=tuple(reads), files=tuple(files), outputs=tuple(outputs),
                    unkeyed=tuple(unkeyed))

    def decorate(compute: ComputeFn) -> StepTask:
        module = compute.__module__
        own_file = None if module_file(module) else Path(inspect.getsourcefile(compute))  # a step outside tasks/
        version = code_version(module, path=own_file)
        holder: dict[str, StepTask] = {}

        def run(root: str, scope: str, params: dict, inputs: dict, label: str) -> ArtifactRef:
            return _execute(holder["step"], root, scope, params, inputs, label)

        run.__name__ = run.__qualname__ = name
        run.__doc__ = compute.__doc__

        prefect_task = task(
            run,
            name=name,
            task_run_name=f"{name}[{{label}}]",
            cache_policy=ArtifactCachePolicy(step=name, version=version, unkeyed=spec.unkeyed),
            persist_result=True,
            result_serializer="json",
            cache_result_in_memory=False,
        )
        holder["step"] = StepTask(spec=spec, compute=compute, version=version, task=prefect_task,
                                  source=str(own_file) if own_file else None)
        return holder["step"]

    return decorate
