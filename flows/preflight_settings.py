"""Pre-flight checks of config values that the steps would otherwise find late, and the grid part of the work
estimate (issue 49).  Everything here reads the config alone (no file, no Prefect, no Warp, no torch): each check
is the step's own rule, run before the flow starts, and a failure is one line naming the key and the fix
(``SystemExit``).

Settings (:func:`check_settings`), for every selected object:

* the squeeze session (``signal.session`` or the object's ``session``) is one that
  :func:`tasks.control.squeeze_signals.synthesize_session` makes (synthetic signals);
* ``geometry.kind`` is a procedural shape, ``mesh`` or ``ply``; ``appearance.pattern`` one the surface colours know;
* ``interior`` names a material of the oracle's table (or ``null``/``air``), with the step's own matching;
  ``material.youngs_modulus`` is at most diamond's (1.2e12 Pa: above it the value is not in pascals);
* ``eta`` (``object.eta`` or ``control.displacement.eta``): the largest patch travel of eq. 3, eta x the largest
  eq. 1 coefficient w_max (1 - beta)^gamma (flexion 1), stays below half the object's smallest extent (beyond it
  two opposite fingers would pass its centre);

and once: ``device: cuda`` (``mpm``, ``render``, ``generation``) only when a CUDA driver with a device is present;
with ``oracle.backend=llm``, the endpoint ``oracle.llm_url`` accepts a connection and the key variable
``oracle.api_key_env`` is set (not required for an endpoint on this machine).

The grid (:func:`grid_dims`, :func:`grid_bytes`): the background grid of a scene exactly as
:func:`tasks.physics.mpm.state.place_grid` sizes it, and its bytes as :func:`tasks.physics.mpm.state.grid_nbytes`
counts them.  The wall-time constant (:data:`PARTICLE_STEPS_PER_WALL_SECOND`) is derived from a measured main job.
"""
from __future__ import annotations

import math
import os
import socket
from urllib.parse import urlsplit

from omegaconf import DictConfig

from flows.selection import object_entries

# bytes per grid node at most: two vec4 float32 buffers per velocity field, two fields once material is released,
# and the Dirichlet target and reaction (vec4) and projector (mat33) once a constraint is used
# (tasks/physics/mpm/state.py: grid_nbytes); plus one vec4 buffer per field for each particle chunk after the first
GRID_BYTES_PER_NODE = 2 * 16 * 2 + 16 + 16 + 36
CHUNK_BYTES_PER_NODE = 16 * 2
# Wall time of the whole pipeline per particle-substep of the estimate (flows.preflight.estimate_work), on the
# project's 2-core machine with the default runner: the default grid (8 objects x 2 variants, one seed) is estimated
# at 1.561e9 particle-substeps, and its flow took 393 s (docs/results/main-job.md, 2026-12-05, commit 203bd98, Intel
# Xeon, 2 cores: the newest main-job row) - rollouts, render, effect and evaluation included.  Machines of this kind
# differ by ~2x (same page), so the figure is an order of magnitude, not a promise.
PARTICLE_STEPS_PER_WALL_SECOND = 1.561e9 / 393.0
# An LLM endpoint on one of these hosts may run without an API key
_LOOPBACK = ("localhost", "127.0.0.1", "::1", "0.0.0.0")


def grid_dims(cfg: DictConfig, obj: DictConfig) -> tuple[int, int, int]:
    """Nodes per axis of the object's background grid: its box (``geometry.size``) plus ``mpm.margin_cells`` (or
    ``simulation.release_margin_cells`` with an interior to release) on every side except below, where the floor
    is, or ``mpm.domain_lo``/``domain_hi``; the spacing of :func:`tasks.physics.wall_resolution.grid_spacing`; plus
    ``mpm.padding`` nodes on each side."""
    from tasks.physics.wall_resolution import grid_spacing

    m = cfg.mpm
    dx = grid_spacing(m, float(cfg.sampling.particle_spacing))
    if m.domain_lo is not None and m.domain_hi is not None:
        extent = [float(h) - float(lo) for lo, h in zip(m.domain_lo, m.domain_hi)]
    else:
        margin = int(m.margin_cells)
        if obj.interior is not None:
            margin = max(margin, int(cfg.simulation.release_margin_cells))
        below = 0 if m.floor else margin
        size = [float(s) for s in obj.geometry.size]
        extent = [size[0] + 2 * margin * dx, size[1] + 2 * margin * dx, size[2] + (margin + below) * dx]
    return tuple(int(math.ceil(e / dx - 1e-9)) + 2 * int(m.padding) + 1 for e in extent)  # type: ignore[return-value]


def grid_bytes(cfg: DictConfig, nodes: int) -> int:
    """Bytes of a scene's grid of ``nodes`` nodes at most (two fields, constraints, ``mpm.threads`` chunks)."""
    return nodes * (GRID_BYTES_PER_NODE + CHUNK_BYTES_PER_NODE * (max(1, int(cfg.mpm.threads)) - 1))


def human_bytes(n: float) -> str:
    for unit, scale in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n:.0f} B"


def human_seconds(s: float) -> str:
    return f"{s:.0f} s" if s < 120 else f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h"


def expected_wall(s: float) -> str:
    """An expected wall time of the estimate: the constant is a large grid's rate, so below a minute it says only
    that (a run's start-up, the Prefect server's ~20 s, is not in it)."""
    return "~" + human_seconds(s) if s >= 60 else "under a minute"


# ------------------------------------------------------------------------------------------------ settings
def check_settings(cfg: DictConfig) -> None:
    """The checks of the module docstring; ``SystemExit`` with one line at the first failure."""
    from tasks.control.geometry import SHAPE_KINDS
    from tasks.control.session_kinds import SESSION_KINDS
    from tasks.control.surface_colors import PATTERNS

    kinds = (*SHAPE_KINDS, "mesh", "ply")
    if cfg.signal.source == "synthetic" and cfg.signal.session is not None and cfg.signal.session not in SESSION_KINDS:
        _refuse("signal.session", f"{cfg.signal.session!r} is not a squeeze session: use one of "
                                  f"{', '.join(SESSION_KINDS)}")
    for key, obj in object_entries(cfg):
        if cfg.signal.source == "synthetic" and cfg.signal.session is None and obj.session not in SESSION_KINDS:
            _refuse(f"{key}.session", f"{obj.session!r} is not a squeeze session: use one of {', '.join(SESSION_KINDS)}"
                                      " (or set signal.session)")
        if obj.geometry.kind not in kinds:
            _refuse(f"{key}.geometry.kind", f"{obj.geometry.kind!r} is unknown: use a shape ({', '.join(SHAPE_KINDS)}),"
                                            " mesh (OBJ/PLY/STL/GLB mesh file) or ply (3DGS PLY) with geometry.path")
        if obj.appearance.pattern not in PATTERNS:
            _refuse(f"{key}.appearance.pattern", f"{obj.appearance.pattern!r} is unknown: use one of "
                                                 f"{', '.join(PATTERNS)}")
        _check_material(cfg, key, obj)
        _check_eta(cfg, key, obj)
    _check_cuda(cfg)
    if cfg.oracle.backend == "llm":
        _check_llm_oracle(cfg.oracle)


def _refuse(key: str, what: str) -> None:
    raise SystemExit(f"config error: {key} {what}")


def _check_material(cfg: DictConfig, key: str, obj: DictConfig) -> None:
    """Young's modulus against diamond's; the interior by the oracle table's own matching (table backend)."""
    from tasks.physics.oracle.matching import NO_INTERIOR, match_entry, resolve_interior
    from tasks.physics.oracle.schema import DIAMOND_YOUNGS_MODULUS, MaterialOracleError

    e = obj.material.youngs_modulus
    if e is not None and float(e) > DIAMOND_YOUNGS_MODULUS:
        _refuse(f"{key}.material.youngs_modulus", f"{float(e):g} Pa is above diamond's ({DIAMOND_YOUNGS_MODULUS:g} "
                                                  "Pa): give Young's modulus in pascals (rubber 2e6, aluminium 6.9e10)")
    interior = obj.interior
    if cfg.oracle.backend != "table" or interior is None or str(interior).strip().lower() in NO_INTERIOR:
        return
    try:
        entry = match_entry(str(obj.description), str(obj.name))
    except MaterialOracleError:
        entry = None  # explicit material values, or no match: the step's concern, not the interior's
    try:
        resolve_interior(str(interior), entry, str(obj.name))
    except MaterialOracleError as exc:
        _refuse(f"{key}.interior", f"{interior!r} {str(exc).split(f'interior {interior!r} ', 1)[-1]}")


def _check_eta(cfg: DictConfig, key: str, obj: DictConfig) -> None:
    f = cfg.control.force
    eta, eta_key = (obj.eta, f"{key}.eta") if obj.eta is not None else (cfg.control.displacement.eta,
                                                                        "control.displacement.eta")
    c_max = max(float(w) for w in f.weights) * (1.0 - float(f.beta)) ** float(f.gamma)
    travel, half = float(eta) * c_max, 0.5 * min(float(s) for s in obj.geometry.size)
    if travel >= half:
        _refuse(eta_key, f"{float(eta):g} m lets a finger travel {travel:.3g} m (eta x the largest eq. 1 coefficient "
                         f"{c_max:.3g}) into {obj.name}, whose half-width is {half:.3g} m: two fingers would pass its "
                         f"centre; use eta below {half / c_max:.3g} m")


def cuda_devices() -> int:
    """CUDA devices the driver reports (0 without an NVIDIA driver), asked of ``libcuda`` directly: no Warp or torch
    start-up (Warp would build its kernel cache)."""
    import ctypes

    try:
        lib = ctypes.CDLL("libcuda.so.1" if os.name == "posix" else "nvcuda.dll")
    except OSError:
        return 0
    count = ctypes.c_int(0)
    if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return 0
    return int(count.value)


def _check_cuda(cfg: DictConfig) -> None:
    wanted = [(k, str(v)) for k, v in (("mpm.device", cfg.mpm.device), ("render.device", cfg.render.device),
                                       ("generation.device", cfg.generation.device)) if str(v).startswith("cuda")]
    if wanted and cuda_devices() == 0:
        k, v = wanted[0]
        _refuse(k, f"is {v} but no CUDA device is present (no NVIDIA driver or GPU found): use {k}=auto or cpu")


def _check_llm_oracle(o: DictConfig) -> None:
    """The endpoint accepts a TCP connection (within min(oracle.timeout_s, 5 s)); the key variable is set, unless
    the endpoint is on this machine."""
    url = urlsplit(str(o.llm_url))
    host, port = url.hostname or "", url.port or (443 if url.scheme == "https" else 80)
    key_set = bool(os.environ.get(str(o.api_key_env)))
    if not key_set and host not in _LOOPBACK:
        _refuse("oracle.api_key_env", f"names {o.api_key_env}, which is not set: export {o.api_key_env}=<your API "
                                      f"key> for {url.scheme}://{host} (the key is never written to the config), or "
                                      "use oracle.backend=table")
    try:
        socket.create_connection((host, port), timeout=min(float(o.timeout_s), 5.0)).close()
    except OSError as exc:
        _refuse("oracle.llm_url", f"{url.scheme}://{host}:{port} does not answer ({exc.strerror or type(exc).__name__}"
                                  "): start the server, fix oracle.llm_url or use oracle.backend=table")

