"""The config values a step reads: resolved from the run's config by the paths the step declares.

A step declares ``reads=("control.displacement", "object.eta", ...)`` next to its function
(:func:`tasks.core.step.artifact_step`).  A path starting with ``object.`` is read from the object being run, one
starting with ``variant.`` from the method variant; every other path from the root config.  The resolved values
are the step's parameters *and* its cache key, and the step sees only them (:class:`Params`), so a step cannot
read a value that is not in its key.  ``files=`` names config paths holding input file paths whose *content*
digest joins the key (editing the file invalidates the step even though the path is unchanged).
"""
from __future__ import annotations

import hashlib
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

FILE_DIGEST_PREFIX = "sha256:"
_ABSENT = object()


class UndeclaredConfigRead(KeyError):
    """A step read a config value it did not declare in ``reads=`` (it would not be in its cache key)."""

    def __str__(self) -> str:  # KeyError quotes its message otherwise
        return str(self.args[0])


class ConfigPathError(ValueError):
    """A declared config path names no key of the config (a typo in ``reads=`` or ``files=``)."""


class Params(Mapping[str, Any]):
    """Read-only view of the values a step declared, keyed by their config path.

    ``params["control.displacement"]`` is the plain dict of that group; a path below a declared one
    (``params["control.displacement.eta"]``) is looked up inside it.  Anything else raises
    :class:`UndeclaredConfigRead` naming the step and the path to declare."""

    def __init__(self, step: str, values: Mapping[str, Any]):
        self._step = step
        self._values = dict(values)

    def __getitem__(self, path: str) -> Any:
        if path in self._values:
            return self._values[path]
        for declared, value in self._values.items():
            if path.startswith(declared + "."):
                for part in path[len(declared) + 1:].split("."):
                    if not isinstance(value, Mapping) or part not in value:
                        break
                    value = value[part]
                else:
                    return value
        raise UndeclaredConfigRead(
            f"step {self._step!r} reads config {path!r}, which is not among its declared reads "
            f"{sorted(k for k in self._values if not k.startswith(FILE_DIGEST_PREFIX))}: add it to reads= of "
            f"@artifact_step({self._step!r}) so that it is part of the step's cache key")

    def __iter__(self) -> Iterator[str]:
        return iter(self._values)

    def __len__(self) -> int:
        return len(self._values)

    def __repr__(self) -> str:
        return f"Params({self._step!r}, {self._values!r})"


def file_sha256(path: str | Path) -> str:
    """Content digest of a user input file, read in 1 MiB chunks (a large mesh is never held in memory)."""
    h = hashlib.sha256()
    with open(Path(path).expanduser(), "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _node_for(path: str, cfg: DictConfig, obj: DictConfig | None, variant: DictConfig | None) -> tuple[Any, str]:
    head, _, rest = path.partition(".")
    if head == "object":
        return obj, rest
    if head == "variant":
        return variant, rest
    return cfg, path


def resolve_reads(step: str, reads: tuple[str, ...], files: tuple[str, ...], cfg: DictConfig,
                  obj: DictConfig | None = None, variant: DictConfig | None = None) -> dict[str, Any]:
    """The plain values of ``reads`` (and the content digests of ``files``) for one object and variant."""
    values: dict[str, Any] = {}
    for path in reads:
        node, rest = _node_for(path, cfg, obj, variant)
        if node is None:
            raise ConfigPathError(f"step {step!r} reads {path!r} but runs without an {path.split('.')[0]}")
        value = OmegaConf.select(node, rest, default=_ABSENT) if rest else node
        if value is _ABSENT:
            raise ConfigPathError(f"step {step!r} declares reads {path!r}, which is not a config key")
        values[path] = OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value
    for path in files:
        node, rest = _node_for(path, cfg, obj, variant)
        value = OmegaConf.select(node, rest, default=_ABSENT) if node is not None else _ABSENT
        if value is _ABSENT:
            raise ConfigPathError(f"step {step!r} declares files {path!r}, which is not a config key")
        if value:
            values[FILE_DIGEST_PREFIX + path] = file_sha256(value)
    return values
