"""Zarr artifacts between method steps.

A step's result is one zarr group.  It is written under a temporary name, every array is stamped with
``dimension_names``, ``units`` and the digest of the config that produced it, the group is stamped last with
its content digest and ``complete: true``, and only then renamed into place.  A half-written group is
therefore never at the final path, and a group without ``complete`` is never read as valid.

Steps pass :class:`ArtifactRef` (path + content digest) between each other, never open handles, so a cache
key built from the digests changes whenever the data does.
"""
from __future__ import annotations

import errno
import hashlib
import json
import os
import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import zarr
from pydantic import BaseModel

FORMAT_VERSION = 1


class ArtifactError(RuntimeError):
    """An artifact is missing, incomplete or does not match the digest a reference expects."""


class ArtifactRef(BaseModel):
    """A reference to a complete zarr artifact: where it is and what it contains (content digest)."""

    path: str
    digest: str
    step: str
    scope: str
    nbytes: int = 0
    compute_seconds: float = 0.0
    reused: bool = False  # found complete on disk (e.g. its cache record was lost to a kill): not recomputed

    def exists(self) -> bool:
        """True when the group at ``path`` is complete and carries this reference's digest."""
        try:
            return read_group_attrs(self.path).get("digest") == self.digest
        except ArtifactError:
            return False


@dataclass(frozen=True)
class Array:
    """An array plus what it means: one name per axis and its SI unit (``"1"`` for dimensionless)."""

    data: np.ndarray
    dims: Sequence[str]
    units: str
    description: str = ""

    def __post_init__(self) -> None:
        data = np.asarray(self.data)
        object.__setattr__(self, "data", data)
        if data.ndim != len(self.dims):
            raise ValueError(f"array with shape {data.shape} needs {data.ndim} dimension names, got {list(self.dims)}")


def as_numpy(value: Any, dtype=np.float64) -> np.ndarray:
    """An input as a numpy array (accepts :class:`Array` or array-likes)."""
    if isinstance(value, Array):
        value = value.data
    return np.asarray(value, dtype=dtype)


def config_value(cfg: Any, name: str) -> Any:
    """Read ``name`` from a dataclass, an OmegaConf node or a plain mapping (step params are plain dicts)."""
    if isinstance(cfg, Mapping):
        return cfg[name]
    return getattr(cfg, name)


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no whitespace: the input of every digest."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), default=_json_default)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, BaseModel):
        return value.model_dump()
    raise TypeError(f"cannot hash a {type(value).__name__} in a config digest; pass plain values")


def digest_of(value: Any) -> str:
    """sha256 of the canonical JSON of ``value`` (config dicts, lists of digests ...)."""
    return hashlib.sha256(canonical_json(value).encode()).hexdigest()


def content_digest(arrays: Mapping[str, Array], attrs: Mapping[str, Any]) -> str:
    """sha256 over every array's name, dtype, shape, labels and bytes, and the group's descriptive attrs."""
    h = hashlib.sha256()
    h.update(canonical_json(attrs).encode())
    for name in sorted(arrays):
        a = arrays[name]
        data = np.ascontiguousarray(a.data)
        h.update(canonical_json([name, str(data.dtype), list(data.shape), list(a.dims), a.units]).encode())
        h.update(data.tobytes())
    return h.hexdigest()


def write_artifact(
    path: str | Path,
    arrays: Mapping[str, Array],
    *,
    step: str,
    scope: str,
    config_digest: str,
    attrs: Mapping[str, Any] | None = None,
    compute_seconds: float = 0.0,
) -> ArtifactRef:
    """Write ``arrays`` as a zarr group at ``path`` atomically and return its reference.

    ``attrs`` are small descriptive values (JSON) stored on the group and included in the digest.
    If a complete group with the same digest is already there (a concurrent run of the same step),
    it is kept; an incomplete or different one is replaced.
    """
    final = Path(path)
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = final.with_name(f".{final.name}.tmp-{uuid.uuid4().hex[:12]}")
    attrs = dict(attrs or {})
    digest = content_digest(arrays, attrs)
    try:
        group = zarr.open_group(store=str(tmp), mode="w")
        nbytes = 0
        for name, a in arrays.items():
            data = a.data
            chunks = _chunks(data)
            arr = group.create_array(
                name,
                shape=data.shape,
                dtype=data.dtype,
                chunks=chunks,
                dimension_names=list(a.dims),
                fill_value=0,
            )
            if data.size:
                arr[...] = data
            arr.attrs.update(
                {"units": a.units, "description": a.description, "config_digest": config_digest}
            )
            nbytes += int(data.nbytes)
        group.attrs.update(
            {
                "step": step,
                "scope": scope,
                "config_digest": config_digest,
                "format_version": FORMAT_VERSION,
                "attrs": attrs,
                "compute_seconds": compute_seconds,
            }
        )
        # stamped last: a group without these two keys is not an artifact
        group.attrs.update({"digest": digest, "complete": True})
        _place(tmp, final, digest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return ArtifactRef(
        path=str(final.resolve()), digest=digest, step=step, scope=scope, nbytes=nbytes,
        compute_seconds=compute_seconds,
    )


def _chunks(data: np.ndarray) -> tuple[int, ...]:
    """One chunk per leading index (frame) for big arrays, whole array for small ones."""
    if data.ndim == 0 or data.nbytes <= 8 << 20:
        return tuple(max(1, s) for s in data.shape) if data.ndim else ()
    return (1,) + tuple(max(1, s) for s in data.shape[1:])


def _place(tmp: Path, final: Path, digest: str, attempts: int = 5) -> None:
    """Rename ``tmp`` to ``final``.  Two runs writing the same step at once race here: a directory rename
    onto an existing non-empty directory fails, and the other writer may place (or move away) ``final``
    between our check and our rename.  Whoever loses re-checks: an identical artifact in place is kept."""
    for _ in range(attempts):
        if final.exists():
            try:
                if read_group_attrs(final).get("digest") == digest:
                    return  # identical artifact already in place (concurrent writer)
            except ArtifactError:
                pass
            trash = final.with_name(f".{final.name}.trash-{uuid.uuid4().hex[:12]}")
            try:
                os.replace(final, trash)
            except FileNotFoundError:  # another writer moved it away first
                pass
            else:
                shutil.rmtree(trash, ignore_errors=True)
        try:
            os.replace(tmp, final)
            return
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
            # another writer placed its group between our check and our rename: check it again
    raise ArtifactError(f"artifact {final} keeps being replaced by another run; rerun when that run is done")


def read_group_attrs(path: str | Path) -> dict[str, Any]:
    """The group attributes of a complete artifact; :class:`ArtifactError` if missing or incomplete."""
    p = Path(path)
    if not (p / "zarr.json").is_file():
        raise ArtifactError(f"artifact {p} is missing; rerun the flow to recompute it")
    try:
        attrs = dict(zarr.open_group(store=str(p), mode="r").attrs)
    except Exception as exc:  # corrupt metadata
        raise ArtifactError(f"artifact {p} is unreadable ({exc}); delete it and rerun") from exc
    if attrs.get("complete") is not True or "digest" not in attrs:
        raise ArtifactError(f"artifact {p} is incomplete (interrupted write); delete it and rerun")
    return attrs


@dataclass
class Artifact:
    """A loaded artifact: its arrays as numpy, their labels, and the group's descriptive attributes."""

    ref: ArtifactRef
    arrays: dict[str, np.ndarray]
    dims: dict[str, list[str]]
    units: dict[str, str]
    attrs: dict[str, Any]

    def __getitem__(self, name: str) -> np.ndarray:
        try:
            return self.arrays[name]
        except KeyError:
            raise KeyError(f"artifact {self.ref.step}/{self.ref.scope} has no array {name!r}; "
                           f"it has {sorted(self.arrays)}") from None

    def __contains__(self, name: str) -> bool:
        return name in self.arrays


def read_artifact(ref: ArtifactRef, names: Sequence[str] | None = None) -> Artifact:
    """Load an artifact, checking that it is complete and is the content ``ref`` points to."""
    gattrs = read_group_attrs(ref.path)
    if gattrs["digest"] != ref.digest:
        raise ArtifactError(
            f"artifact {ref.path} holds digest {gattrs['digest'][:12]}, expected {ref.digest[:12]}; "
            "it was rewritten by another run: rerun the flow"
        )
    group = zarr.open_group(store=ref.path, mode="r")
    arrays, dims, units = {}, {}, {}
    for name, arr in group.arrays():
        if names is not None and name not in names:
            continue
        arrays[name] = np.asarray(arr[...]) if arr.size else np.zeros(arr.shape, dtype=arr.dtype)
        dims[name] = list(arr.metadata.dimension_names or [])
        units[name] = arr.attrs.get("units", "")
    return Artifact(ref=ref, arrays=arrays, dims=dims, units=units, attrs=dict(gattrs.get("attrs", {})))


def directory_size(path: str | Path) -> int:
    """Bytes on disk under ``path``."""
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            try:
                total += os.path.getsize(os.path.join(root, f))
            except OSError:
                pass
    return total
