"""Method steps as cached Prefect tasks over zarr artifacts.

A step is a pure function ``compute(inputs, params) -> (arrays, attrs)`` of loaded input artifacts and the
exact config values it reads.  :func:`artifact_step` turns it into a Prefect task that

* computes a content-addressed key = sha256(step name, code version of its modules, scope,
  params, digests of the input artifacts) — nothing else (no run id, job number or output dir);
* stores its result as a zarr group at ``<root>/<scope>/<step>/<key[:20]>.zarr`` (atomic, see
  :mod:`tasks.artifacts`) and returns an :class:`ArtifactRef`;
* is cached by Prefect under that key (JSON result records, no pickle).  The cache policy checks the
  artifact on disk: if it was deleted or is incomplete, the stale cache record is removed and the step runs
  again instead of returning a dangling reference.
"""
from __future__ import annotations

import hashlib
import importlib
import inspect
import json

from prefect.logging import get_logger
import time
from contextvars import ContextVar
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional

from prefect import task
from prefect.cache_policies import CachePolicy
from prefect.context import TaskRunContext

from tasks.artifacts import Array, Artifact, ArtifactError, ArtifactRef, digest_of, read_artifact, read_group_attrs, write_artifact

log = get_logger("virsqueezer")

ComputeFn = Callable[[Mapping[str, Artifact], Mapping[str, Any]], tuple[Mapping[str, Array], Mapping[str, Any]]]


def code_version(modules: tuple[str, ...]) -> str:
    """sha256 of the source files of ``modules`` (the step's own module and the modules it computes with)."""
    h = hashlib.sha256()
    for name in sorted(set(modules)):
        mod = importlib.import_module(name)
        h.update(name.encode())
        h.update(Path(inspect.getfile(mod)).read_bytes())
    return h.hexdigest()


def step_key(step: str, version: str, scope: str, params: Mapping[str, Any], inputs: Mapping[str, ArtifactRef]) -> str:
    """The cache key of one step run: what it is, what code, which config values, which input contents."""
    return digest_of(
        {
            "step": step,
            "code": version,
            "scope": scope,
            "params": params,
            "inputs": {name: ref.digest for name, ref in sorted(inputs.items())},
        }
    )


def artifact_path(root: str | Path, scope: str, step: str, key: str) -> Path:
    return Path(root).resolve() / scope / step / f"{key[:20]}.zarr"


@dataclass
class ArtifactCachePolicy(CachePolicy):
    """Cache key = :func:`step_key`; a record whose artifact is gone from disk is dropped first."""

    step: str = ""
    version: str = ""

    def compute_key(self, task_ctx: TaskRunContext, inputs: dict[str, Any], flow_parameters: dict[str, Any], **kwargs: Any) -> Optional[str]:
        key = step_key(self.step, self.version, inputs["scope"], inputs["params"], inputs.get("inputs") or {})
        path = artifact_path(inputs["root"], inputs["scope"], self.step, key)
        try:
            read_group_attrs(path)
        except ArtifactError:
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
        log.info("cache record %s dropped: its artifact is missing on disk", key[:12])


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
        if set(result) != {"__class__", "data"} or result["__class__"] != "tasks.artifacts.ArtifactRef":
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
    """A method step: its pure ``compute`` function and the Prefect task that caches it."""

    name: str
    compute: ComputeFn
    version: str
    task: Any = field(repr=False)

    def submit(self, *, root: str, scope: str, params: Mapping[str, Any], inputs: Mapping[str, Any] | None = None):
        """Submit to the flow's task runner; ``inputs`` may hold futures of upstream steps."""
        return self.task.submit(root=str(root), scope=scope, params=dict(params), inputs=dict(inputs or {}))

    def run_local(self, *, root: str, scope: str, params: Mapping[str, Any], inputs: Mapping[str, ArtifactRef] | None = None) -> ArtifactRef:
        """Run the step without Prefect (tests, notebooks): same key, same artifact."""
        return _execute(self.name, self.version, self.compute, str(root), scope, dict(params), dict(inputs or {}))


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


def _execute(step: str, version: str, compute: ComputeFn, root: str, scope: str, params: dict, inputs: dict[str, ArtifactRef]) -> ArtifactRef:
    key = step_key(step, version, scope, params, inputs)
    path = artifact_path(root, scope, step, key)
    try:  # the artifact survived although its cache record did not (e.g. result storage wiped)
        attrs = read_group_attrs(path)
        return ArtifactRef(path=str(path), digest=attrs["digest"], step=step, scope=scope,
                           compute_seconds=float(attrs.get("compute_seconds", 0.0)), reused=True)
    except ArtifactError:
        pass
    loaded = {name: read_artifact(ref) for name, ref in inputs.items()}
    t0 = time.perf_counter()
    token = _PROGRESS.set(_Progress(f"{scope}/{step}" + (f"[{params['boundary']}]" if "boundary" in params else "")))
    try:
        arrays, attrs = compute(loaded, params)
    finally:
        _PROGRESS.reset(token)
    seconds = time.perf_counter() - t0
    ref = write_artifact(path, arrays, step=step, scope=scope, config_digest=digest_of(params), attrs=attrs,
                         compute_seconds=seconds)
    log.info("%-18s %-12s ran in %.2f s -> %s", step, scope, seconds, path)
    return ref


def artifact_step(name: str, *, modules: tuple[str, ...] = ()) -> Callable[[ComputeFn], StepTask]:
    """Decorator: expose a pure step function as a cached Prefect task (see module docstring).

    ``modules`` lists the modules whose source is the step's code version besides the decorated
    function's own module (e.g. the geometry module an object builder calls).
    """

    def decorate(compute: ComputeFn) -> StepTask:
        version = code_version((compute.__module__, "tasks.artifacts", "tasks.step", *modules))

        def run(root: str, scope: str, params: dict, inputs: dict) -> ArtifactRef:
            return _execute(name, version, compute, root, scope, params, inputs)

        run.__name__ = run.__qualname__ = name
        run.__doc__ = compute.__doc__

        prefect_task = task(
            run,
            name=name,
            task_run_name=f"{name}[{{scope}}]",
            cache_policy=ArtifactCachePolicy(step=name, version=version),
            persist_result=True,
            result_serializer="json",
            cache_result_in_memory=False,
        )
        return StepTask(name=name, compute=compute, version=version, task=prefect_task)

    return decorate
