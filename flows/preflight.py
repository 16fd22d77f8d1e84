"""Checks of the config and of every input file, run before the flow starts (no Prefect server, no step).

A bad input stops the run with one line naming the input (its config key) and the fix, and no traceback:
:func:`preflight` raises ``SystemExit(line)``.  What is checked:

1. the config's ranges (:func:`conf.schema.validate`) and the values the steps would refuse late
   (:func:`flows.preflight_settings.check_settings`: sessions, geometry kinds, patterns, interiors, a Young's modulus
   above diamond's, eta, ``device=cuda`` without CUDA, the LLM oracle's key and endpoint);
2. the SenseGlove recording (``signal=csv``): it exists, is at most ``MAX_RECORDING_BYTES``, and parses
   completely (columns, numbers, ranges, truncation, units), with the reader the step uses; some fingertip comes
   near every selected object (the recording is in the object's frame);
3. every selected object's geometry file (``kind: mesh`` or ``ply``): it exists and is a closed, non-flat,
   consistently wound, self-intersection-free mesh without NaN vertices, or a 3DGS PLY in the Inria layout with
   enough Gaussians, visible ones, smaller than the object (:mod:`tasks.control.splat_content`), with the loader the
   step uses, and its fit into ``geometry.size`` is a plausible scale (a line states the factor when it is not 1);
4. the run's work (:func:`estimate_work`: frames, the largest MPM grid, particle-substeps over objects x variants x
   seeds, bytes of the largest artifact, expected wall time) against ``limits``: a run beyond one is refused with
   the estimate and the knob to change; then the folders, their free space for the estimated artifacts and report,
   Warp's and matplotlib's caches and ``PREFECT_API_URL`` (:func:`flows.preflight_env.check_environment`);
5. the LLM judge's endpoint settings when ``llm_judge.url`` is set;
6. the diffusion weights when a diffusion backend runs: every model present in ``generation.weights`` (a message
   naming each missing model, the folder expected and how to fetch it); their identity (configs + file digests)
   is recorded in ``generation.weights_digest``, which is part of the effect step's cache key;
7. the paper metrics' weight files named in ``paper_metrics`` (absent ones are reported "not computed" by the
   step): the present files' digests are recorded in ``paper_metrics.weights_digest`` (cache key).

A ``-m`` sweep runs 1-4 but the folders and environment for every job before job 0 (:func:`check_config`), each
distinct input file read once.

The stability suite (``python -m flows.studies.stability``) has its own config: :func:`preflight_stability` checks it
the same way (its simulation groups and catalog, and the case names) before any case runs.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
from omegaconf import DictConfig, OmegaConf

from conf.schema import ConfigError, validate
from flows.preflight_env import check_environment
from flows.preflight_settings import check_settings
from flows.selection import object_entries, selected_backends, selected_seeds

# A hand's fingertips come closer than this to the object they squeeze (m; or twice the object's largest size)
_NEAR = 0.25
# bytes per frame and particle / surface point / pixel of the two largest artifacts (mpm_rollout: float32
# positions, J, von Mises, plastic strain; Gaussian positions, covariances, rotations; gbuffer: sRGB + 4 float32 maps)
_ROLLOUT_BYTES_PER_PARTICLE, _ROLLOUT_BYTES_PER_POINT, _GBUFFER_BYTES_PER_PIXEL = 24, 52, 19
# A report's bytes per scene (docs/reference/preflight-settings.md, "Free space"), measured on the report of
# python -m flows.squeeze object=can (one scene, 91 frames, 384 x 384 video; 2026-12-06), the largest of the four
# one-scene reports measured: 63,359 B of text and tables, 1,629,844 B of figures (PNG), 919,860 B of videos (MP4),
# and index.html embedding them all (base64) in 3,445,823 B, i.e. 1.35x the media again
_REPORT_TEXT_BYTES, _REPORT_IMAGE_BYTES = 63_359, 1_629_844
_REPORT_VIDEO_BYTES_PER_FRAME_PIXEL = 919_860 / (91 * 384 * 384)  # videos scale with frames and pixels
_REPORT_MEDIA_COPIES = (919_860 + 1_629_844 + 3_445_823) / (919_860 + 1_629_844)  # the files and index.html
_PASSED: list = []  # the config last checked and its estimate (run() checks again what the main already checked)


@dataclass(frozen=True)
class WorkEstimate:
    """A run's work, from the config alone: output frames of one squeeze, particle-substeps summed over the run's
    objects x variants x seeds (particles bounded by each object's box / spacing^3), the largest artifact's bytes,
    the largest MPM grid (nodes from the grid spacing and the object's box, :func:`flows.preflight_settings.grid_dims`),
    the artifacts' bytes summed over the scenes, the report's bytes (:func:`report_bytes_per_scene` x scenes) and the
    expected wall time."""

    frames: int
    particles: int  # of the largest object
    substeps: int  # per frame
    particle_steps: float
    largest_bytes: float
    largest: str  # which artifact of which object
    objects: int = 1
    variants: int = 1
    seeds: int = 1
    backends: int = 1
    grid: tuple[int, int, int] = (0, 0, 0)  # nodes per axis of the largest scene's grid
    grid_bytes: float = 0.0
    grid_of: str = ""  # the object of the largest grid
    total_bytes: float = 0.0  # rollouts and g-buffers of every scene
    wall_seconds: float = 0.0
    report_bytes: float = 0.0  # the report's files under paths.reports (videos, figures, index.html, tables)

    @property
    def scenes(self) -> int:
        return self.objects * self.variants * self.seeds

    def line(self) -> str:
        """The one "work estimate: ..." line printed before a run's steps start."""
        from flows.preflight_settings import expected_wall, human_bytes

        plural = lambda n, w: f"{n} {w}{'s' if n != 1 else ''}"  # noqa: E731
        nodes = math.prod(self.grid)
        return (f"work estimate: {plural(self.scenes, 'scene')} ({plural(self.objects, 'object')} x "
                f"{plural(self.variants, 'variant')} x {plural(self.seeds, 'seed')}) x "
                f"{plural(self.backends, 'effect backend')}, {self.frames} frames each; largest grid "
                f"{'x'.join(map(str, self.grid))} = {nodes:,} nodes ({human_bytes(self.grid_bytes)}, {self.grid_of}); "
                f"about {self.particle_steps:.3g} particle-substeps, {human_bytes(self.total_bytes)} of artifacts; "
                f"expected wall time {expected_wall(self.wall_seconds)}")


def particle_bound(cfg: DictConfig, obj: DictConfig) -> int:
    """Particles an object can hold at most: its box over the particle spacing cubed (the object's share of a run's
    simulation work, known from the config alone)."""
    return int(math.prod(obj.geometry.size) / cfg.sampling.particle_spacing ** 3)


def report_bytes_per_scene(cfg: DictConfig, frames: int) -> float:
    """Bytes a run's report holds per scene (object x variant x seed) for ``frames`` output frames: text and tables,
    the figures, the videos (scaled from the measured one by frames and ``render.video_width`` x ``video_height``),
    the figures and videos again embedded in ``index.html``.  An upper bound from the largest one-scene report
    measured: a report of several scenes shares its per-object figures between the variants."""
    pixels = int(cfg.render.video_width) * int(cfg.render.video_height)
    media = _REPORT_IMAGE_BYTES + _REPORT_VIDEO_BYTES_PER_FRAME_PIXEL * frames * pixels
    return _REPORT_TEXT_BYTES + _REPORT_MEDIA_COPIES * media


def estimate_work(cfg: DictConfig, span: float) -> WorkEstimate:
    """The work of a run whose squeeze lasts ``span`` seconds (``signal.duration`` or the recording's span)."""
    from flows.preflight_settings import PARTICLE_STEPS_PER_WALL_SECOND, grid_bytes, grid_dims

    frames = int(span * cfg.control.smoothing.frame_rate) + 1
    m = cfg.mpm
    substeps = (math.ceil(1.0 / (cfg.control.smoothing.frame_rate * m.dt)) if m.dt
                else int(m.target_substeps_per_frame))  # the mass-scaled budget (unscaled runs: the CFL decides)
    n_variants = 1 if cfg.variant is not None else len(cfg.grid.variants)
    n_seeds = len(selected_seeds(cfg))
    r, points = cfg.render, int(cfg.sampling.surface_points)
    gbuffer = math.ceil(frames / r.frame_stride) * r.views * r.width * r.height * _GBUFFER_BYTES_PER_PIXEL
    steps, largest, particles_max, total = 0.0, (0.0, ""), 0, 0.0
    grid: tuple[int, tuple[int, int, int], str] = (0, (0, 0, 0), "")
    entries = object_entries(cfg)
    for key, obj in entries:
        particles = particle_bound(cfg, obj)
        particles_max = max(particles_max, particles)
        steps += n_seeds * n_variants * particles * substeps * frames
        rollout = frames * (particles * _ROLLOUT_BYTES_PER_PARTICLE + points * _ROLLOUT_BYTES_PER_POINT)
        total += n_seeds * n_variants * (rollout + gbuffer)
        for nbytes, what in ((rollout, f"mpm_rollout of {key}"), (gbuffer, f"gbuffer of {key}")):
            largest = max(largest, (float(nbytes), what))
        dims = grid_dims(cfg, obj)
        grid = max(grid, (math.prod(dims), dims, key))
    return WorkEstimate(frames, particles_max, substeps, steps, largest[0], largest[1], objects=len(entries),
                        variants=n_variants, seeds=n_seeds, backends=len(selected_backends(cfg)), grid=grid[1],
                        grid_bytes=float(grid_bytes(cfg, grid[0])), grid_of=grid[2], total_bytes=total,
                        wall_seconds=steps / PARTICLE_STEPS_PER_WALL_SECOND,
                        report_bytes=len(entries) * n_variants * n_seeds * report_bytes_per_scene(cfg, frames))


def check_work(cfg: DictConfig, est: WorkEstimate, span_from: str) -> None:
    """Refuse a run beyond ``limits`` with the estimate and the knobs to change (``SystemExit``)."""
    from flows.preflight_settings import GRID_BYTES_PER_NODE, human_bytes

    lim = cfg.limits
    if est.frames > lim.max_frames:
        raise SystemExit(f"work limit: {est.frames} frames per squeeze ({span_from} x control.smoothing.frame_rate "
                         f"{cfg.control.smoothing.frame_rate:g} Hz), above limits.max_frames={lim.max_frames}: shorten "
                         f"the squeeze or lower the frame rate (or raise limits.max_frames)")
    if est.grid_bytes > lim.max_grid_bytes:
        spacing = (f"mpm.dx={cfg.mpm.dx:g} m" if cfg.mpm.dx else
                   f"the grid spacing (sampling.particle_spacing {cfg.sampling.particle_spacing:g} m x cbrt of "
                   f"mpm.particles_per_cell {cfg.mpm.particles_per_cell:g})")
        fix = ("raise mpm.dx (unset: two particle spacings)" if cfg.mpm.dx else
               "raise sampling.particle_spacing or mpm.particles_per_cell")
        raise SystemExit(f"work limit: {spacing} gives {est.grid_of} a grid of {'x'.join(map(str, est.grid))} = "
                         f"{math.prod(est.grid):.3g} nodes, about {human_bytes(est.grid_bytes)} (up to "
                         f"{GRID_BYTES_PER_NODE} bytes per node), above limits.max_grid_bytes="
                         f"{lim.max_grid_bytes:.4g} ({human_bytes(lim.max_grid_bytes)}): {fix} (or raise the limit)")
    if est.particle_steps > lim.max_particle_steps:
        raise SystemExit(f"work limit: about {est.particle_steps:.3g} particle-substeps (up to {est.particles} "
                         f"particles x {est.substeps} substeps x {est.frames} frames per object and variant), above "
                         f"limits.max_particle_steps={lim.max_particle_steps:g}: raise sampling.particle_spacing, "
                         f"lower mpm.target_substeps_per_frame or run fewer objects (or raise the limit)")
    if est.largest_bytes > lim.max_artifact_bytes:
        raise SystemExit(f"work limit: the {est.largest} would hold about {est.largest_bytes / 2**30:.3g} GiB, above "
                         f"limits.max_artifact_bytes={lim.max_artifact_bytes:.4g} "
                         f"({lim.max_artifact_bytes / 2**30:.3g} GiB): shorten the squeeze, raise "
                         f"sampling.particle_spacing or render.frame_stride (or raise the limit)")
    if est.wall_seconds > lim.max_wall_hours * 3600:
        raise SystemExit(f"work limit: {est.scenes} scenes ({est.objects} objects x {est.variants} variants x "
                         f"{est.seeds} seed{'s' if est.seeds != 1 else ''}), about {est.particle_steps:.3g} particle-substeps, would take about "
                         f"{est.wall_seconds / 3600:.3g} h, above limits.max_wall_hours={lim.max_wall_hours:g}: run "
                         f"fewer seeds (grid.seeds), objects or variants (or raise limits.max_wall_hours)")


def _check_reach(cfg: DictConfig, tips: np.ndarray, time: np.ndarray) -> None:
    """Refuse a recording whose fingertips never come near a selected object (centred at the origin): it was
    recorded in another frame (e.g. the tracker's room coordinates) and would squeeze nothing."""
    for key, obj in object_entries(cfg):
        half = 0.5 * np.asarray(obj.geometry.size, float)
        gap = np.linalg.norm(np.maximum(np.abs(tips) - half, 0.0), axis=-1)  # (sample, finger) m to the box
        i = int(np.argmin(gap.min(axis=1)))
        near = max(_NEAR, 2 * float(np.max(obj.geometry.size)))
        if gap[i].min() > near:
            raise SystemExit(f"input error: signal.path: no fingertip comes within {near:g} m of {obj.name} ({key}; closest "
                             f"{gap[i].min():.3g} m, at t = {time[i]:.3g} s): nothing would be squeezed; write the "
                             f"positions in the object's frame (metres, object centred at the origin, z up)")


def _check_values(cfg: DictConfig) -> None:
    try:
        validate(cfg)
    except ConfigError as exc:
        raise SystemExit(f"config error: {exc}") from None
    check_settings(cfg)


def _read_once(seen: dict | None, key: tuple, read: Callable[[], Any]) -> Any:
    """``read()``; with ``seen`` (a sweep's files read so far, by ``key``) only the first time: each distinct file
    of a sweep is read once, and its refusal names the first job that uses it."""
    if seen is None:
        return read()
    if key not in seen:
        seen[key] = read()
    return seen[key]


def _file_key(path: Any) -> str:
    return os.path.abspath(os.path.expanduser(str(path))) if path else ""


def check_recording(cfg: DictConfig, seen: dict | None = None) -> tuple[float, str]:
    """2. The recording (``signal=csv``), read exactly as the squeeze_signals step reads it, and its reach; returns
    the squeeze's span (s) and where it comes from (``signal.duration`` without a recording)."""
    if cfg.signal.source != "csv":
        return float(cfg.signal.duration), f"signal.duration {cfg.signal.duration:g} s"
    from tasks.control.recording import SignalError, read_recording  # pandas only when a file is to be read

    rate = cfg.control.smoothing.frame_rate
    try:
        rec = _read_once(seen, ("recording", _file_key(cfg.signal.path), float(rate)),
                         lambda: read_recording(cfg.signal.path, frame_rate=rate))
    except SignalError as exc:
        raise SystemExit(f"input error: signal.path: {exc}") from None
    span = float(rec["time"][-1] - rec["time"][0])
    _check_reach(cfg, rec["fingertip_positions"], rec["time"])
    return span, f"the recording's {span:g} s"


def check_geometry_files(cfg: DictConfig, seen: dict | None = None, quiet: bool = False) -> None:
    """3. The selected objects' geometry files (``kind: mesh`` or ``ply``), with the loader the step uses, and their
    fit into ``geometry.size``; prints the fit's line unless ``quiet``."""
    for key, obj in object_entries(cfg):
        kind, path = obj.geometry.kind, obj.geometry.path
        if kind not in ("mesh", "ply"):
            continue
        from tasks.control.gaussian_ply import GaussianPlyError
        from tasks.control.object_config import ObjectModelError
        from tasks.control.sources.base import fit_statement
        from tasks.control.sources.by_kind import geometry_file_bounds

        try:
            lo, hi, what = _read_once(seen, ("geometry", kind, _file_key(path)),
                                      lambda: geometry_file_bounds(kind, path))
            fitted = fit_statement(what, lo, hi, list(obj.geometry.size))
        except (ObjectModelError, GaussianPlyError) as exc:
            raise SystemExit(f"input error: {key}.geometry.path: {exc}") from None
        if fitted and not quiet:
            print(f"{key}.geometry.path: {fitted}", flush=True)


def check_config(cfg: DictConfig, seen: dict | None = None) -> WorkEstimate:
    """What a ``-m`` sweep checks of every job before the first one runs (:class:`flows.hydra_checks.PreflightCallback`):
    the config's ranges and settings, its input files (the recording, the geometry files: each distinct file once
    across the jobs, ``seen`` holding what was read) and its work against ``limits``; the folders and environment
    are the sweep's own.  Returns the work estimate."""
    _check_values(cfg)
    span, span_from = check_recording(cfg, seen)
    est = estimate_work(cfg, span)
    check_work(cfg, est, span_from)
    check_geometry_files(cfg, seen, quiet=True)  # each job prints its fit when it runs
    return est


def preflight(cfg: DictConfig, read_only_ok: bool = False) -> None:
    """Refuse a bad config or input file with one line (``SystemExit``) before anything heavy starts; record the
    diffusion weights' identity in the config.  ``read_only_ok``: the caller can be served from a read-only
    artifacts cache (:func:`flows.preflight_env.check_folders`)."""
    if _PASSED and _PASSED[0] == OmegaConf.to_yaml(cfg):
        return
    # 1. config ranges, and values the steps would refuse late (sessions, kinds, patterns, interiors, eta, CUDA, oracle)
    _check_values(cfg)
    # 2. the recording, read exactly as the squeeze_signals step reads it
    span, span_from = check_recording(cfg)
    # 3. the work, before any geometry file is loaded; then the folders' free space for it, the caches, Prefect's API
    est = estimate_work(cfg, span)
    check_work(cfg, est, span_from)
    check_environment(cfg, est, read_only_ok)
    # 4. geometry files of the selected objects
    check_geometry_files(cfg)
    # 5. the LLM judge's endpoint settings (its requests come last, after the whole simulation)
    if cfg.llm_judge.url:
        from tasks.evaluation.llm_judge import JudgeConfig, LLMJudgeError, check_judge_config

        try:
            check_judge_config(JudgeConfig(**OmegaConf.to_container(cfg.llm_judge, resolve=True)))
        except LLMJudgeError as exc:
            raise SystemExit(f"config error: {exc}") from None
    # 6. diffusion weights
    if {"diffusers", "text_only"} & set(selected_backends(cfg)):
        from tasks.core.artifacts import digest_of
        from tasks.generation.components import (
            check_weights,
            diffusion_weights,
            missing_weights_message,
            weights_identity,
        )

        weights = diffusion_weights(cfg.generation)
        missing = check_weights(weights)
        if missing:
            raise SystemExit(f"input error: generation.weights: {missing_weights_message(missing)}")
        cfg.generation.weights_digest = digest_of(weights_identity(weights))
    # 7. the paper metrics' weight files
    if any(cfg.paper_metrics.get(k) for k in ("musiq_weights", "amt_weights", "videophy_weights", "videocon_weights")):
        from tasks.core.artifacts import digest_of
        from tasks.evaluation.paper_weights import weights_identity

        cfg.paper_metrics.weights_digest = digest_of(weights_identity(cfg.paper_metrics))
    _PASSED[:] = [OmegaConf.to_yaml(cfg), est]


def work_estimate(cfg: DictConfig) -> WorkEstimate:
    """The work estimate of the config :func:`preflight` passed last (checked again if it was another)."""
    preflight(cfg)
    return _PASSED[1]


def preflight_stability(cfg: DictConfig) -> list:
    """The stability suite's config (:func:`conf.study.stability_schema.validate_stability`) and its selected cases
    (``cases``, ``quick``), or one line (``SystemExit``) before any case runs.  Returns the cases."""
    from conf.study.stability_schema import validate_stability
    from tasks.verification.stability import select_cases

    try:
        validate_stability(cfg)
        return select_cases(list(cfg.cases), bool(cfg.quick))
    except ConfigError as exc:
        raise SystemExit(f"config error: {exc}") from None
    except ValueError as exc:  # an unknown case name
        raise SystemExit(f"config error: cases: {exc}") from None
