"""Where the cache records of the steps are kept: Prefect's local file storage, with each record written atomically.

Prefect's own ``LocalFileSystem.write_path`` opens the record file for writing (truncating it) and writes it in
place; a process that reads the record meanwhile (another sweep job, another worker, the same step of another
flow) reads an empty or cut record.  Two jobs of a sweep that miss the same key both compute it and both write
its record, so a third can read one half-written.  Here a record is written under a temporary name in the same
folder and renamed over the old one (``os.replace``, atomic on POSIX file systems, NFS included): a reader sees
the old record or the new one, never a part of either.
"""
from __future__ import annotations

import os
import uuid
from pathlib import Path

from prefect._internal.compatibility.async_dispatch import async_dispatch
from prefect.filesystems import LocalFileSystem


class AtomicLocalFileSystem(LocalFileSystem):
    """Prefect's local file storage whose :meth:`write_path` replaces the file at once (see module docstring)."""

    _block_type_name = "Atomic Local File System"

    def _replace(self, path: str, content: bytes) -> str:
        target = Path(self._resolve_path(path))
        target.parent.mkdir(parents=True, exist_ok=True)
        if target.exists() and not target.is_file():
            raise ValueError(f"Path {target} already exists and is not a file.")
        tmp = target.with_name(f".{target.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")
        try:
            with open(tmp, "wb") as f:
                f.write(content)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return str(target)

    async def awrite_path(self, path: str, content: bytes) -> str:
        return self._replace(path, content)

    @async_dispatch(awrite_path)
    def write_path(self, path: str, content: bytes) -> str:
        return self._replace(path, content)


def record_storage(artifacts_root: str | Path) -> AtomicLocalFileSystem:
    """The cache records of the run whose artifacts folder is ``artifacts_root`` (as
    :func:`flows.runtime.result_storage_settings` names it for Prefect)."""
    return AtomicLocalFileSystem(basepath=str(Path(artifacts_root).resolve() / ".prefect" / "results"))
