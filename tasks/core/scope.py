"""The scope of a step's artifacts: which object, run with which sampling seed.

A step stores its artifact at ``<root>/<scope>/<step>/<key>.zarr`` (:mod:`tasks.core.step`); the flow names the
scope of each object and seed with :func:`seed_scope`, and the report reads object and seed back from its keys
with :func:`split_seed_scope`.  Prefect-free, so that the report's modules need not import the step runner.
"""
from __future__ import annotations


def seed_scope(obj: str, seed: int) -> str:
    """The artifact scope and report key of ``obj`` run with ``sampling.seed`` = ``seed``: the object's name for
    seed 0 (the default grid's scopes), ``<object>@seed<k>`` otherwise."""
    return obj if int(seed) == 0 else f"{obj}@seed{int(seed)}"


def split_seed_scope(key: str) -> tuple[str, int]:
    """(object, seed) of a scope written by :func:`seed_scope`."""
    obj, sep, seed = key.rpartition("@seed")
    return (obj, int(seed)) if sep and seed.isdigit() else (key, 0)
