"""Checks of the config and of every input file, run before the flow starts (no Prefect server, no step).

A bad input stops the run with one line naming the input (its config key) and the fix, and no traceback:
:func:`preflight` raises ``SystemExit(line)``.  What is checked:

1. the config's ranges (:func:`conf.schema.validate`);
2. the SenseGlove recording (``signal=csv``): it exists, is at most ``MAX_RECORDING_BYTES``, and parses
   completely (columns, numbers, ranges, truncation, units), with the reader the step uses; some fingertip comes
   near every selected object (the recording is in the object's frame);
3. every selected object's geometry file (``kind: mesh`` or ``ply``): it exists and is a closed, non-flat,
   consistently wound, self-intersection-free mesh without NaN vertices, or a 3DGS PLY in the Inria layout with
   enough Gaussians, visible ones, smaller than the object (:mod:`tasks.control.splat_content`), with the loader the
   step uses, and its fit into ``geometry.size`` is a plausible scale (a line states the factor when it is not 1);
4. the run's work (:func:`estimate_work`: frames, particle-substeps, bytes of the largest artifact) against
   ``limits``: a run beyond one is refused with the estimate and the knob to change;
5. the LLM judge's endpoint settings when ``llm_judge.url`` is set;
6. the diffusion weights when a diffusion backend runs: every model present in ``generation.weights`` (a message
   naming each missing model, the folder expected and how to fetch it); their identity (configs + file digests)
   is recorded in ``generation.weights_digest``, which is part of the effect step's cache key;
7. the paper metrics' weight files named in ``paper_metrics`` (absent ones are reported "not computed" by the
   step): the present files' digests are recorded in ``paper_metrics.weights_digest`` (cache key).

The stability suite (``python -m flows.studies.stability``) has its own config: :func:`preflight_stability` checks it
the same way (its simulation groups and catalog, and the case names) before any case runs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from omegaconf import DictConfig, OmegaConf

from conf.schema import ConfigError, validate
from flows.selection import object_entries, selected_backends

# A hand's fingertips come closer than this to the object they squeeze (m; or twice the object's largest size)
_NEAR = 0.25
# bytes per frame and particle / surface point / pixel of the two largest artifacts (mpm_rollout: float32
# positions, J, von Mises, plastic strain; Gaussian positions, covariances, rotations; gbuffer: sRGB + 4 float32 maps)
_ROLLOUT_BYTES_PER_PARTICLE, _ROLLOUT_BYTES_PER_POINT, _GBUFFER_BYTES_PER_PIXEL = 24, 52, 19
_PASSED: list[str] = []  # the config last checked (run() checks again what the main already checked)


@dataclass(frozen=True)
class WorkEstimate:
    """A run's work, from the config alone: output frames of one squeeze, particle-substeps summed over the run's
    objects x variants (particles bounded by each object's box / spacing^3), and the largest artifact's bytes."""

    frames: int
    particles: int  # of the largest object
    substeps: int  # per frame
    particle_steps: float
    largest_bytes: float
    largest: str  # which artifact of which object


def particle_bound(cfg: DictConfig, obj: DictConfig) -> int:
    """Particles an object can hold at most: its box over the particle spacing cubed (the object's share of a run's
    simulation work, known from the config alone)."""
    return int(math.prod(obj.geometry.size) / cfg.sampling.particle_spacing ** 3)


def estimate_work(cfg: DictConfig, span: float) -> WorkEstimate:
    """The work of a run whose squeeze lasts ``span`` seconds (``signal.duration`` or the recording's span)."""
    frames = int(span * cfg.control.smoothing.frame_rate) + 1
    m = cfg.mpm
    substeps = (math.ceil(1.0 / (cfg.control.smoothing.frame_rate * m.dt)) if m.dt
                else int(m.target_substeps_per_frame))  # the mass-scaled budget (unscaled runs: the CFL decides)
    n_variants = 1 if cfg.variant is not None else len(cfg.grid.variants)
    r, points = cfg.render, int(cfg.sampling.surface_points)
    gbuffer = math.ceil(frames / r.frame_stride) * r.views * r.width * r.height * _GBUFFER_BYTES_PER_PIXEL
    steps, largest, particles_max = 0.0, (0.0, ""), 0
    for key, obj in object_entries(cfg):
        particles = particle_bound(cfg, obj)
        particles_max = max(particles_max, particles)
        steps += n_variants * particles * substeps * frames
        rollout = frames * (particles * _ROLLOUT_BYTES_PER_PARTICLE + points * _ROLLOUT_BYTES_PER_POINT)
        for nbytes, what in ((rollout, f"mpm_rollout of {key}"), (gbuffer, f"gbuffer of {key}")):
            largest = max(largest, (float(nbytes), what))
    return WorkEstimate(frames, particles_max, substeps, steps, largest[0], largest[1])


def check_work(cfg: DictConfig, est: WorkEstimate, span_from: str) -> None:
    """Refuse a run beyond ``limits`` with the estimate and the knobs to change (``SystemExit``)."""
    lim = cfg.limits
    if est.frames > lim.max_frames:
        raise SystemExit(f"work limit: {est.frames} frames per squeeze ({span_from} x control.smoothing.frame_rate "
                         f"{cfg.control.smoothing.frame_rate:g} Hz), above limits.max_frames={lim.max_frames}: shorten "
                         f"the squeeze or lower the frame rate (or raise limits.max_frames)")
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


def preflight(cfg: DictConfig) -> None:
    """Refuse a bad config or input file with one line (``SystemExit``) before anything heavy starts; record the
    diffusion weights' identity in the config."""
    if _PASSED and _PASSED[0] == OmegaConf.to_yaml(cfg):
        return
    # 1. config ranges
    try:
        validate(cfg)
    except ConfigError as exc:
        raise SystemExit(f"config error: {exc}") from None
    # 2. the recording, read exactly as the squeeze_signals step reads it
    span, span_from = float(cfg.signal.duration), f"signal.duration {cfg.signal.duration:g} s"
    if cfg.signal.source == "csv":  # imported here: pandas (and Prefect, below) only when a file is to be read
        from tasks.control.recording import SignalError, read_recording

        try:
            rec = read_recording(cfg.signal.path, frame_rate=cfg.control.smoothing.frame_rate)
        except SignalError as exc:
            raise SystemExit(f"input error: signal.path: {exc}") from None
        span = float(rec["time"][-1] - rec["time"][0])
        span_from = f"the recording's {span:g} s"
        _check_reach(cfg, rec["fingertip_positions"], rec["time"])
    # 3. the work, before any geometry file is loaded
    check_work(cfg, estimate_work(cfg, span), span_from)
    # 4. geometry files of the selected objects
    for key, obj in object_entries(cfg):
        if obj.geometry.kind in ("mesh", "ply"):
            from tasks.control.gaussian_ply import GaussianPlyError
            from tasks.control.object_config import ObjectModelError
            from tasks.control.sources.by_kind import check_geometry_file

            try:
                fitted = check_geometry_file(obj.geometry.kind, obj.geometry.path, list(obj.geometry.size))
            except (ObjectModelError, GaussianPlyError) as exc:
                raise SystemExit(f"input error: {key}.geometry.path: {exc}") from None
            if fitted:
                print(f"{key}.geometry.path: {fitted}", flush=True)
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
    _PASSED[:] = [OmegaConf.to_yaml(cfg)]


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
