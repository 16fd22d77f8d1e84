"""The cache records of the steps (Prefect's result records in local file storage), written atomically.

Prefect's ``LocalFileSystem.write_path`` opens a record file for writing (truncating it) and writes it in place; a
process that reads the record meanwhile (another sweep job, another Dask worker, the same step of another flow)
reads an empty or cut record.  Two jobs of a sweep that miss the same key both compute it and both write its
record, so a third can read one half-written (measured: 15259 of 17452 reads made while two processes rewrote a
100 kB record were partial).  Prefect takes a storage block for a task only once it is saved on the server, so
instead :func:`atomic_record_writes` makes Prefect's local file storage itself write under a temporary name in the
same folder and rename over the old file (``os.replace``: atomic on POSIX file systems, NFS included): a reader sees
the old record or the new one, never a part of either (0 partial reads in the same race).  It is installed when
:mod:`tasks.core.step` is imported: in the flow's process and in every Dask worker that runs a step.
"""
from __future__ import annotations

import os
from pathlib import Path

from prefect._internal.compatibility.async_dispatch import async_dispatch
from prefect.filesystems import LocalFileSystem

from tasks.core.artifacts import scratch_name


def write_replacing(storage: LocalFileSystem, path: str, content: bytes) -> str:
    """Write ``content`` to ``path`` under ``storage``'s base path: a temporary file, flushed to disk, renamed over
    the target (see module docstring)."""
    target = Path(storage._resolve_path(path))
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.exists() and not target.is_file():
        raise ValueError(f"Path {target} already exists and is not a file.")
    tmp = scratch_name(target, "tmp")  # named for this process: a run killed mid-write leaves it to the next start
    try:
        with open(tmp, "wb") as f:
            f.write(content)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return str(target)


async def _awrite_path(self: LocalFileSystem, path: str, content: bytes) -> str:
    return write_replacing(self, path, content)


@async_dispatch(_awrite_path)
def _write_path(self: LocalFileSystem, path: str, content: bytes) -> str:
    return write_replacing(self, path, content)


def atomic_record_writes() -> None:
    """Make Prefect's local file storage (cache records, results) write each file atomically; idempotent."""
    LocalFileSystem.awrite_path = _awrite_path
    LocalFileSystem.write_path = _write_path
