"""Zarr artifacts between method steps.

A step's result is one zarr group.  It is written under a temporary name, every array is stamped with
``dimension_names``, ``units`` and the digest of the config that produced it, the group is stamped last with
its content digest and ``complete: true``, and only then renamed into place.  A half-written group is
therefore never at the final path, and a group without ``complete`` is never read as valid.

Steps pass :class:`ArtifactRef` (content digest + path *relative to the artifacts root*) between each other,
never open handles, so a cache key built from the digests changes whenever the data does, and an artifacts
folder that is moved or copied works from its new place: every consumer re-roots a reference at the root of
its own run (:meth:`ArtifactRef.at`), and nothing absolute is stored in a reference or a cache record.

Format (``format_version`` in the group attributes; a group of another version is not valid and is
recomputed):

* 2 - the group attributes hold a ``manifest`` {file path inside the group: [size in bytes, sha256]} of
  every file of the group except the root ``zarr.json`` (which holds the manifest), recorded before the
  ``complete`` stamp, and a ``seal`` = sha256 of the canonical JSON of all other group attributes.  A missing,
  extra, resized or altered file, or edited group attributes, make the artifact invalid
  (:func:`verify_artifact`): a cache hit on it is refused and the step recomputes, and reading it as an input
  fails with a line naming it.  Arrays above 16 MiB are chunked along the leading axis in blocks of about
  16 MiB (many frames per file, :func:`chunk_shape`).  Temporary and trash folders are named
  ``.<name>.tmp-<host>-<pid>-<start>-<id>`` / ``.<name>.trash-<host>-<pid>-<start>-<id>`` (``start`` = the
  process's start time in ms) so that a later run can remove those of dead processes, also when their pid has
  been reused by another process (:func:`remove_stale_temporaries`).
* 1 - no manifest, one chunk per frame above 8 MiB, absolute paths in references (no longer read).
"""
from __future__ import annotations

import errno
import hashlib
import json
import math
import os
import re
import shutil
import socket
import time
import uuid
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any, Mapping, Sequence

import numpy as np
import zarr
from pydantic import BaseModel, ConfigDict, PrivateAttr, field_validator

from tasks.core.processes import START_TOLERANCE, process_started

FORMAT_VERSION = 2


class ArtifactError(RuntimeError):
    """An artifact is missing, incomplete, damaged or does not match the digest a reference expects."""


class ArtifactMissing(ArtifactError):
    """No artifact at the path (never written, or removed): not an error of the artifact itself."""


class ArtifactDamaged(ArtifactError):
    """An artifact is at the path but is not what was written (see :func:`verify_artifact`).

    ``problem`` says what is wrong in a few words (``missing file displacement/c/3/0``, ...)."""

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path, self.problem = Path(path), problem
        super().__init__(f"artifact {path} is damaged: {problem}")


class ArtifactOutdated(ArtifactDamaged):
    """An artifact written in another format version (``problem`` names both): not trusted, recomputed."""


class ArtifactRef(BaseModel):
    """A reference to a complete zarr artifact: where it is under the artifacts root and what it contains.

    ``rel`` is the group's path relative to the artifacts root.  The root itself is not part of the reference's
    data (neither validated from nor serialized to a cache record): whoever uses a reference roots it at the
    artifacts folder of its own run with :meth:`at`; ``path`` is then the absolute path of the group."""

    model_config = ConfigDict(extra="forbid")

    rel: str
    digest: str
    step: str
    scope: str
    nbytes: int = 0
    compute_seconds: float = 0.0
    reused: bool = False  # found complete on disk (e.g. its cache record was lost to a kill): not recomputed
    _root: str = PrivateAttr(default="")

    @field_validator("rel")
    @classmethod
    def _inside_root(cls, rel: str) -> str:
        p = PurePosixPath(rel)
        if not rel or p.is_absolute() or ".." in p.parts or "\\" in rel:
            raise ValueError(f"artifact path {rel!r} must be relative to the artifacts root, without '..'")
        return rel

    def at(self, root: str | Path) -> "ArtifactRef":
        """This reference rooted at the artifacts folder ``root``."""
        rooted = self.model_copy()
        rooted._root = str(Path(root).resolve())
        return rooted

    @property
    def path(self) -> str:
        """Absolute path of the group (the reference must be rooted, see :meth:`at`)."""
        if not self._root:
            raise ArtifactError(f"reference to {self.scope}/{self.step} ({self.rel}) is not rooted at an artifacts "
                                "folder: use ref.at(root)")
        return str(Path(self._root) / self.rel)

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
    root: str | Path | None = None,
) -> ArtifactRef:
    """Write ``arrays`` as a zarr group at ``path`` atomically and return its reference, rooted at ``root``
    (the artifacts folder; default the folder that holds ``path``).

    ``attrs`` are small descriptive values (JSON) stored on the group and included in the digest.
    If a valid group with the same digest is already there (a concurrent run of the same step),
    it is kept; an incomplete, damaged or different one is replaced.
    """
    final = Path(path).resolve()
    root = Path(root).resolve() if root is not None else final.parent
    rel = final.relative_to(root).as_posix()
    final.parent.mkdir(parents=True, exist_ok=True)
    tmp = scratch_name(final, "tmp")
    attrs = dict(attrs or {})
    digest = content_digest(arrays, attrs)
    try:
        group = zarr.open_group(store=str(tmp), mode="w")
        nbytes = 0
        for name, a in arrays.items():
            data = a.data
            arr = group.create_array(
                name,
                shape=data.shape,
                dtype=data.dtype,
                chunks=chunk_shape(data.shape, data.dtype.itemsize),
                dimension_names=list(a.dims),
                fill_value=0,
                attributes={"units": a.units, "description": a.description, "config_digest": config_digest},
            )
            if data.size:
                arr[...] = data
            nbytes += int(data.nbytes)
        group.attrs.update(
            {
                "step": step,
                "scope": scope,
                "config_digest": config_digest,
                "format_version": FORMAT_VERSION,
                "attrs": attrs,
                "compute_seconds": compute_seconds,
                "manifest": _manifest(tmp),  # every file is written: their sizes and checksums
            }
        )
        # stamped last: a group without these keys is not an artifact
        stamp = {"digest": digest, "complete": True}
        written = json.loads((tmp / "zarr.json").read_bytes())["attributes"]  # as a reader will parse them
        group.attrs.update({**stamp, "seal": _seal({**written, **stamp})})
        _place(tmp, final, digest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return ArtifactRef(rel=rel, digest=digest, step=step, scope=scope, nbytes=nbytes,
                       compute_seconds=compute_seconds).at(root)


CHUNK_BYTES = 16 << 20  # target size of one chunk (before compression)


def chunk_shape(shape: Sequence[int], itemsize: int, target: int = CHUNK_BYTES) -> tuple[int, ...]:
    """Chunks of at most ``target`` bytes: whole arrays up to ``target``, else blocks of as many leading indices
    (frames) as fit; a single frame above ``target`` is split the same way along its own leading axis."""
    chunks = [max(1, int(s)) for s in shape]
    for axis in range(len(chunks)):
        inner = itemsize * math.prod(chunks[axis + 1:])
        if inner * chunks[axis] <= target:
            break
        chunks[axis] = max(1, target // inner)
        if inner <= target:
            break
    return tuple(chunks)


def _manifest(group: Path) -> dict[str, list]:
    """{path inside the group: [size in bytes, sha256]} of every file except the root ``zarr.json``."""
    return {rel: [os.path.getsize(group / rel), _file_sha256(group / rel)] for rel in _group_files(group)}


def _group_files(group: Path, under: str = "") -> list[str]:
    """Paths (posix, relative to ``group``) of the files below ``group/under``, the root ``zarr.json`` excepted."""
    top = os.path.join(group, under) if under else str(group)
    out = []
    for dirpath, _, files in os.walk(top):
        rel_dir = os.path.relpath(dirpath, group).replace(os.sep, "/")
        out += files if rel_dir == "." else [f"{rel_dir}/{f}" for f in files]
    return sorted(f for f in out if f != "zarr.json")


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


# ----------------------------------------------------------------------------------------- checksum memo
# One process checks the same files many times: a Dask worker reads an input artifact for each of its consumer
# steps (object_model for eight), the report media and the report read them again, a warm run checks every
# artifact and then reads it.  The sha256 of a file is therefore remembered per process, keyed by what the file
# system says of that version of the file, and reused while the file is provably unchanged.
RACY_SECONDS = 2.0  # a file changed this recently may change again within one tick of the file-system clock
_CHECKED: dict[tuple[int, int], tuple[int, int, int, str]] = {}  # (st_dev, st_ino) -> (size, mtime_ns, ctime_ns, sha)


def _stamp(st: os.stat_result) -> tuple[int, int, int]:
    return st.st_size, st.st_mtime_ns, st.st_ctime_ns


def checked_sha256(path: Path, st: os.stat_result) -> str:
    """sha256 of the file at ``path`` whose ``os.stat`` (taken just before) is ``st``; computed once per process
    for each version of the file.

    The memo is keyed by the file's identity (device, inode) and holds its size, mtime and ctime (ns) when it was
    hashed; it is used only while all three are unchanged.  Any write through the file system changes them: a
    truncated or rewritten chunk, a flipped bit (also when the writer sets the mtime back: the ctime cannot be
    set back), a deleted and re-created or replaced file (another inode, or a new ctime).  So damage done after a
    check is still caught by the next one, in this process as in any other (a new process starts with an empty
    memo: every run hashes each file it checks at least once).  Not remembered: a file whose mtime or ctime is
    within :data:`RACY_SECONDS` of the hash (a change in the same tick of the file-system clock would leave the
    stamps as they were), or which changed while it was hashed."""
    key, stamp = (st.st_dev, st.st_ino), _stamp(st)
    known = _CHECKED.get(key)
    if known is not None and known[:3] == stamp:
        return known[3]
    sha = _file_sha256(path)
    after = os.stat(path)
    settled = time.time_ns() - int(RACY_SECONDS * 1e9)
    if _stamp(after) == stamp and (after.st_dev, after.st_ino) == key and max(stamp[1:]) < settled:
        _CHECKED[key] = (*stamp, sha)
    else:
        _CHECKED.pop(key, None)
    return sha


def _seal(attrs: Mapping[str, Any]) -> str:
    """sha256 of the group attributes other than the seal itself (an edited attribute breaks it)."""
    return digest_of({k: v for k, v in attrs.items() if k != "seal"})


_HOST = re.sub(r"[^A-Za-z0-9_.]", "_", socket.gethostname()) or "host"
# owner: host (no "-" in it), pid and (names written since it was added) the process's start time in ms
_SCRATCH = re.compile(r"^\..+\.(?P<kind>tmp|trash)-(?:(?P<host>[^-]+)-(?P<pid>\d+)-(?:(?P<started>\d+)-)?)?"
                      r"[0-9a-f]{12}$")


def scratch_name(final: Path, kind: str) -> Path:
    """``.<name>.<kind>-<host>-<pid>-<start>-<id>`` next to ``final``: whose it is (the process and when it
    started), so a later run can tell it stale."""
    pid = os.getpid()
    started = process_started(pid)
    owner = f"{_HOST}-{pid}" + (f"-{round(1000 * started)}" if started is not None else "")
    return final.with_name(f".{final.name}.{kind}-{owner}-{uuid.uuid4().hex[:12]}")


def _move_away(final: Path) -> None:
    """Remove the group at ``final``: renamed first (one atomic step that readers see), then deleted."""
    trash = scratch_name(final, "trash")
    try:
        os.replace(final, trash)
    except FileNotFoundError:  # another run moved it away first
        return
    shutil.rmtree(trash, ignore_errors=True)


def discard_artifact(path: str | Path) -> None:
    """Remove a damaged or incomplete artifact so that its step is recomputed."""
    _move_away(Path(path))


def _place(tmp: Path, final: Path, digest: str, attempts: int = 5) -> None:
    """Rename ``tmp`` to ``final``.  Two runs writing the same step at once race here: a directory rename
    onto an existing non-empty directory fails, and the other writer may place (or move away) ``final``
    between our check and our rename.  Whoever loses re-checks: an identical valid artifact in place is kept."""
    for _ in range(attempts):
        if final.exists():
            try:
                if verify_artifact(final).get("digest") == digest:
                    return  # identical artifact already in place (concurrent writer)
            except ArtifactError:
                pass
            _move_away(final)
        try:
            os.replace(tmp, final)
            return
        except OSError as exc:
            if exc.errno not in (errno.ENOTEMPTY, errno.EEXIST):
                raise
            # another writer placed its group between our check and our rename: check it again
    raise ArtifactError(f"artifact {final} keeps being replaced by another run; rerun when that run is done")


def read_group_attrs(path: str | Path) -> dict[str, Any]:
    """The group attributes of a complete artifact of this format whose attributes are as written (cheap: the
    files are not checked, see :func:`verify_artifact`).

    :class:`ArtifactMissing` when there is no group, :class:`ArtifactOutdated` when it is of another format
    version, :class:`ArtifactDamaged` when it is unreadable, incomplete or its attributes were edited."""
    p = Path(path)
    meta = p / "zarr.json"
    if not meta.is_file():
        if not p.exists():
            raise ArtifactMissing(f"artifact {p} is missing; rerun the flow to recompute it")
        if not meta.is_file():  # (a concurrent writer's group renamed into place between the two looks is whole)
            raise ArtifactDamaged(p, "no zarr.json (incomplete or damaged group)")
    try:
        attrs = dict(json.loads(meta.read_bytes())["attributes"])
    except Exception:  # noqa: BLE001 - any decoding failure is the same finding
        raise ArtifactDamaged(p, "unreadable metadata zarr.json") from None
    if attrs.get("complete") is not True or "digest" not in attrs:
        raise ArtifactDamaged(p, "incomplete (interrupted write)")
    if attrs.get("format_version") != FORMAT_VERSION or "manifest" not in attrs:
        raise ArtifactOutdated(p, f"written in artifact format {attrs.get('format_version')}, this code reads "
                                  f"format {FORMAT_VERSION}")
    if attrs.get("seal") != _seal(attrs):
        raise ArtifactDamaged(p, "group attributes in zarr.json were changed after the write")
    return attrs


def verify_artifact(path: str | Path, *, checksums: bool = True, arrays: Sequence[str] | None = None) -> dict[str, Any]:
    """:func:`read_group_attrs` after checking the group's files against its manifest: none missing, none extra,
    every size as written and (``checksums``) every sha256 as written (a file this process already hashed and
    that has not changed since is not read again, :func:`checked_sha256`).  ``arrays`` limits the check to the
    files of those arrays (a reader that loads only some).  Raises :class:`ArtifactDamaged` naming the first
    file that differs."""
    p = Path(path)
    attrs = read_group_attrs(p)
    manifest: dict[str, list] = attrs["manifest"]
    if arrays is not None:
        prefixes = tuple(f"{a}/" for a in arrays)
        manifest = {f: v for f, v in manifest.items() if f.startswith(prefixes)}
        present = [f for a in arrays for f in _group_files(p, a)]
    else:
        present = _group_files(p)
    extra = sorted(set(present) - set(manifest))
    if extra:
        raise ArtifactDamaged(p, f"unexpected file {extra[0]} (not written with the artifact)")
    for name, (size, sha) in sorted(manifest.items()):
        f = p / name
        try:
            st = os.stat(f)
        except OSError:
            raise ArtifactDamaged(p, f"missing file {name}") from None
        if st.st_size != size:
            raise ArtifactDamaged(p, f"size mismatch of {name}: {st.st_size} bytes, written {size}")
        if checksums and checked_sha256(f, st) != sha:
            raise ArtifactDamaged(p, f"checksum mismatch of {name}")
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
    """Load an artifact (all arrays, or only ``names``), checking that it is complete, that it is the content
    ``ref`` points to, and that the files read are those written (:func:`verify_artifact`).  A missing or
    damaged input is an :class:`ArtifactError` of one line naming it."""
    what = f"input {ref.scope}/{ref.step}: artifact {ref.path}"
    try:
        gattrs = verify_artifact(ref.path, arrays=names)
    except ArtifactDamaged as exc:
        raise ArtifactError(f"{what} is damaged ({exc.problem}); rerun the flow to recompute it") from None
    except ArtifactMissing:
        raise ArtifactError(f"{what} is missing; rerun the flow to recompute it") from None
    if gattrs["digest"] != ref.digest:
        raise ArtifactError(
            f"{what} holds digest {gattrs['digest'][:12]}, expected {ref.digest[:12]}; "
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


def remove_stale_temporaries(root: str | Path) -> tuple[int, int]:
    """Remove the temporary and trash folders that killed runs left under the artifacts folder ``root``, and the
    temporary files of the steps' cache records (``.prefect/results``, :mod:`tasks.core.records`): those named
    for a process of this host that is no longer alive, and folders of format 1 (no owner in the name).  A live
    process's (a concurrent run) and another host's are kept.  Returns (folders and files removed, bytes freed)."""
    count = freed = 0
    for dirpath, dirnames, filenames in os.walk(root):
        descend = []
        for d in dirnames:
            m = _SCRATCH.match(d)
            if m is None:
                if not d.endswith(".zarr"):  # no need to look inside groups
                    descend.append(d)
                continue
            if _stale(m):
                path = Path(dirpath) / d
                size = directory_size(path)
                shutil.rmtree(path, ignore_errors=True)
                if not path.exists():
                    count, freed = count + 1, freed + size
        for f in filenames:
            m = _SCRATCH.match(f)
            if m is not None and m["pid"] is not None and _stale(m):  # a record's temporary names its owner
                path = Path(dirpath) / f
                try:
                    size = path.stat().st_size
                    path.unlink()
                except FileNotFoundError:  # its writer renamed it (not stale after all) or another run removed it
                    continue
                count, freed = count + 1, freed + size
        dirnames[:] = descend
    return count, freed


def _stale(m: re.Match) -> bool:
    """Whether the scratch name matched by ``m`` is of format 1 (no owner) or of a dead process of this host."""
    return m["pid"] is None or (m["host"] == _HOST and not _owner_alive(int(m["pid"]), m["started"]))


def _owner_alive(pid: int, started_ms: str | None) -> bool:
    """Whether the process that named a scratch folder still runs: ``pid`` is alive and, when the name records
    its start time (``started_ms``), started then (else the pid was reused by another process)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        pass
    now = process_started(pid) if started_ms is not None else None
    return now is None or abs(now - int(started_ms) / 1000) < START_TOLERANCE  # unknown start: keep it


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


def newest_artifact(root: str | Path, scope: str, step: str) -> Artifact:
    """The newest complete artifact of ``step`` for ``scope`` under the store ``root`` (read-only; for studies and
    benchmarks that re-run part of a scene from a store that ran it once)."""
    root = Path(root)
    for path in sorted((root / scope / step).glob("*.zarr"), key=lambda p: p.stat().st_mtime, reverse=True):
        attrs = read_group_attrs(path)
        if attrs.get("complete"):
            ref = ArtifactRef(rel=f"{scope}/{step}/{path.name}", digest=attrs["digest"], step=step, scope=scope)
            return read_artifact(ref.at(root))
    raise ArtifactError(f"{root / scope / step}: no complete artifact: run `python -m flows.squeeze object={scope} "
                        f"paths.artifacts={root}` first")
