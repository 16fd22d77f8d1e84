"""SHA-256 digests of large files (model weights), computed once per file version and remembered across runs.

The diffusion models and the VideoPhy-2 rater are ~7 GB and ~14 GB: hashing them on every run's pre-flight check
costs a minute or more.  A digest is stored under the file's (resolved path, size in bytes, mtime in ns); while
those three are unchanged the stored digest is returned, and when any changes (a new download, an edit, ``touch``)
the file is read and hashed again.  The digest itself, not the (path, size, mtime) triple, is what callers put in
cache keys, so a cached result still follows the file's content.  Limit: a rewrite that keeps the size and restores
the mtime is not noticed (as make and rsync's quick check).

Store: one JSON file, ``$VIRSQUEEZER_DIGEST_CACHE`` or ``~/.cache/virsqueezer/file-digests.json``, updated under a
file lock and replaced atomically (several runs may hash at once).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

CHUNK_BYTES = 8 << 20
_memory: dict[str, str] = {}


def cache_file() -> Path:
    """Where the digests are stored."""
    default = Path.home() / ".cache" / "virsqueezer" / "file-digests.json"
    return Path(os.environ.get("VIRSQUEEZER_DIGEST_CACHE", default)).expanduser()


def _key(path: Path) -> tuple[str, str]:
    status = path.stat()
    resolved = str(path.resolve())
    return resolved, f"{resolved}|{status.st_size}|{status.st_mtime_ns}"


def _read(store: Path) -> dict[str, str]:
    try:
        return json.loads(store.read_text())
    except (OSError, ValueError):
        return {}


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        while chunk := stream.read(CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


def file_digest(path: str | Path) -> str:
    """SHA-256 (hex) of the file's bytes, from the store while its (path, size, mtime) is unchanged."""
    path = Path(path).expanduser()
    resolved, key = _key(path)
    if key in _memory:
        return _memory[key]
    store = cache_file()
    digest = _read(store).get(key)
    if digest is None:
        digest = _sha256(path)
        _remember(store, resolved, key, digest)
    _memory[key] = digest
    return digest


def _remember(store: Path, resolved: str, key: str, digest: str) -> None:
    """Add ``key`` to the store, dropping the entries of older versions of the same path."""
    from filelock import FileLock

    try:
        store.parent.mkdir(parents=True, exist_ok=True)
        with FileLock(str(store) + ".lock", timeout=60):
            entries = {k: v for k, v in _read(store).items() if k.rsplit("|", 2)[0] != resolved}
            entries[key] = digest
            partial = store.with_suffix(f".{os.getpid()}.tmp")
            partial.write_text(json.dumps(entries, indent=0, sort_keys=True))
            os.replace(partial, store)
    except OSError:  # a read-only home: the digest is still right, only not remembered across runs
        pass
