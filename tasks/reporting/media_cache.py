"""Report media cached by content, so that a warm report build encodes and draws nothing.

Every video and figure of the report is a pure function of some artifacts (named by their content digests),
a few parameters (labels, frame rate, the metric values it plots) and the reporting code.  :class:`MediaCache`
keys each medium by ``sha256(kind, parameters, input digests, code version of the reporting modules)`` and keeps
it as ``<artifacts>/.media/<key><suffix>``; a later build with the same key links (or copies) that file into
the report folder instead of loading the artifacts and encoding again.  Entries are written under a temporary
name and renamed into place, so a killed build never leaves a half-written medium under a key.  Without a
cache folder (``root=None``) every medium is made afresh, as before.  ``shared`` folders (the ``.media`` of a
read-only artifacts cache) are looked up too and never written: their entries are copied into the report (a hard
link would change the shared file's link count), and what they lack is made under ``root``.
"""
from __future__ import annotations

import functools
import os
import shutil
import uuid
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, Optional

from tasks.core.artifacts import digest_of
from tasks.core.code_version import code_version

MEDIA_DIR = ".media"  # under the artifacts root


@functools.cache
def reporting_code_version() -> str:
    """Code version of :mod:`tasks.reporting.report` and everything it imports (watch, video, tables)."""
    return code_version("tasks.reporting.report")


def _place(source: Path, target: Path, link: bool = True) -> None:
    """Put ``source``'s bytes at ``target`` atomically: a hard link when ``link`` and the file system allows, else a
    copy."""
    tmp = target.with_name(f".{target.name}.tmp-{uuid.uuid4().hex[:12]}")
    try:
        if link:
            try:
                os.link(source, tmp)
            except OSError:  # another file system, or links not supported
                link = False
        if not link:
            shutil.copyfile(source, tmp)
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)


class MediaCache:
    """Content-addressed store of report media under ``root`` (``None``: no caching), also reading (never writing)
    the ``shared`` folders."""

    def __init__(self, root: Optional[Path], shared: Sequence[Path] = ()) -> None:
        self.root = Path(root) if root is not None else None
        self.shared = tuple(Path(p) for p in shared)
        self.made = 0  # media encoded or drawn by this cache (the rest were reused)

    def key(self, kind: str, params: Mapping[str, Any], refs: Mapping[str, Any]) -> str:
        """sha256 of what a medium shows: its kind, parameters, input artifacts' digests and the reporting code."""
        return digest_of({"kind": kind, "params": dict(params), "code": reporting_code_version(),
                          "inputs": {k: getattr(r, "digest", None) for k, r in sorted(refs.items())}})

    def lookup(self, key: str) -> Optional[Path]:
        """The cached file of ``key`` (any suffix) in ``root`` or a ``shared`` folder, or None."""
        if self.root is None:
            return None
        return next((p for folder in (self.root, *self.shared) for p in folder.glob(f"{key}.*") if p.is_file()), None)

    def get(self, target: Path, key: str, make: Callable[[Path], Optional[Path]]) -> Optional[Path]:
        """The medium of ``key`` at ``target`` in the report folder (its suffix may change, e.g. a WebP
        fallback for an MP4): linked from the cache when there, else made by ``make(path) -> path written or
        None`` and stored.  Returns the report-folder path, or None when ``make`` had nothing to show."""
        target = Path(target)
        cached = self.lookup(key)
        if cached is None:
            self.made += 1
            if self.root is None:
                return make(target)
            self.root.mkdir(parents=True, exist_ok=True)
            scratch = self.root / f".tmp-{uuid.uuid4().hex[:12]}-{key}{target.suffix}"
            try:
                written = make(scratch)
                if written is None:
                    return None
                cached = self.root / f"{key}{Path(written).suffix}"
                os.replace(written, cached)
            finally:
                scratch.unlink(missing_ok=True)
        placed = target.with_suffix(cached.suffix)
        _place(cached, placed, link=cached.parent == self.root)
        return placed
