"""The paper's own video metrics of one object, variant and effect backend, where their weights are present (paper
sec. 4.1, Table 1): VBench imaging quality (MUSIQ, SPAQ weights; :mod:`tasks.evaluation.musiq`) and VBench motion
smoothness (AMT-S; :mod:`tasks.evaluation.amt` with the protocol of
:func:`tasks.evaluation.video_quality.vfi_smoothness`), by VBench's recipes, and VideoPhy-2 physical commonsense
(:mod:`tasks.evaluation.videophy`: VideoPhy-2's autorater as the share of videos rated >= 4 with its mean rating
beside it, VideoCon-Physics as P(Yes) / (P(Yes) + P(No)), both on the paper's [0, 1] scale), on the final video of each scored view
(``paper_metrics.views``), mean over the views.  The checkpoints are read from the files named in ``paper_metrics``
(:mod:`tasks.evaluation.paper_weights`); a metric whose file is absent is NaN with the report's "not computed:
weights not present (...)" line, and costs nothing.
"""
from __future__ import annotations

import functools
import math
import pickle
import time
from pathlib import Path
from typing import Any

import numpy as np

from tasks.core.artifacts import Array
from tasks.core.step import artifact_step, report_progress
from tasks.evaluation.amt import amt_midpoint, load_amt
from tasks.evaluation.metric_ranges import check_metrics
from tasks.evaluation.musiq import load_musiq, musiq_frame_scores
from tasks.evaluation.paper_weights import PAPER_WEIGHTS, RATING_COLUMN, absent_reason, present_weights
from tasks.evaluation.video_quality import to_srgb_uint8, vfi_smoothness
from tasks.evaluation.videophy import load_videophy, share_rated_at_least
from tasks.generation.final_video import final_video
from tasks.render.device import torch_device

# AMT-S's 4-level correlation pyramid at 1/8 resolution needs >= 2 cells per side at its coarsest level (frames padded
# to multiples of 16 of at least 128 px; smaller frames make the released model's lookup divide by zero)
AMT_MIN_SIDE_PX = 128

_FRAMES = ("Scored on the final frames as written (8-bit sRGB), not on frames decoded from the report's H.264 MP4 "
           "as VBench and VideoPhy-2 read their inputs: compression artefacts are not in the score.")
DEFINITIONS: dict[str, str] = {
    "imaging_quality_musiq": (
        "VBench imaging quality (1, in [0, 1], higher is better): MUSIQ with SPAQ weights on every frame (longer "
        "side resized to 512 px when longer, bilinear with antialiasing as torchvision's Resize, rounded to 8 bits; "
        "RGB / 255), mean over the frames / 100; mean over the scored views. " + _FRAMES),
    "motion_smoothness_amt": (
        "VBench motion smoothness (1, in [0, 1]): each odd frame predicted by AMT-S at t = 1/2 from its even "
        "neighbours (replicate padding to multiples of 16, uint8 by truncation), (255 - mean |odd - predicted|) / "
        "255 on uint8 RGB; mean over the scored views. " + _FRAMES),
    "physical_commonsense": (
        "Physical commonsense, VideoPhy-2 recipe (1, in [0, 1], the paper's scale): the share of scored videos (views) "
        "that the videophy_2_auto rater (mPLUG-Owl-Video 7B, bfloat16, layer norms in float32) rates >= 4 of 5 when "
        "asked whether the video adheres to the physical laws, on 32 frames at the centres of equal segments resized "
        "to 224 x 224 by torch (bicubic; the reference resizes with decord) (CLIP normalisation), greedy answer parsed "
        "for its rating (0 when none). " + _FRAMES),
    "physical_commonsense_rating": (
        "VideoPhy-2 autorater mean rating (1-5, higher is better): the mean over the scored views of the same "
        "ratings (VideoPhy-2's own scale, not the paper's). " + _FRAMES),
    "physical_commonsense_videocon": (
        "Physical commonsense, VideoCon-Physics recipe (1, in [0, 1], the paper's scale): P(Yes) / (P(Yes) + P(No)) "
        "of the next token after VideoPhy's prompt 'Does this video follow the physical laws?' (videocon_physics, "
        "same architecture and frames as above); mean over the scored views. " + _FRAMES),
}


@functools.cache
def _network(kind: str, path: Path, size: int, mtime_ns: int):
    """The loaded network of a checkpoint file or folder (cached per version within a process)."""
    return {"imaging_quality_musiq": load_musiq, "motion_smoothness_amt": load_amt,
            "physical_commonsense": load_videophy, "physical_commonsense_videocon": load_videophy}[kind](path)


def network(kind: str, path: Path):
    """MUSIQ (``kind`` = imaging_quality_musiq), AMT-S (motion_smoothness_amt) or the VideoPhy-2 rater
    (physical_commonsense, a folder) loaded strictly from ``path``; RuntimeError naming the config key and file when
    it is not such a checkpoint."""
    stat = (path / "config.json" if path.is_dir() else path).stat()
    try:
        return _network(kind, path, stat.st_size, stat.st_mtime_ns)
    except (KeyError, RuntimeError, ValueError, OSError, ImportError, pickle.UnpicklingError) as exc:
        key = next(s.key for s in PAPER_WEIGHTS if s.metric == kind)
        raise RuntimeError(f"{key}: {path} is not a loadable {kind} checkpoint ({type(exc).__name__}: "
                           f"{str(exc).splitlines()[0][:200]}); download the file named in the report again") from None


def _on_device(net, device):
    """The network (or the VideoPhy-2 rater's network) moved to ``device`` (a no-op when it is there)."""
    (net.net if hasattr(net, "net") else net).to(device)
    return net


def paper_metrics(final: np.ndarray, cfg: dict[str, Any], scene: str = "this scene"
                  ) -> tuple[dict[str, float], dict[str, str], np.ndarray | None, dict[str, float]]:
    """The paper's metrics of one scene.  final: (view, frame, y, x, 3) uint8 sRGB or float linear RGB; cfg: the
    ``paper_metrics`` group.  Returns (values, reasons for NaN values, MUSIQ frame scores (view, frame) or None,
    seconds spent per metric); a value outside its documented range is a bug named with ``scene``
    (:func:`tasks.evaluation.metric_ranges.check_metrics`)."""
    values: dict[str, float] = {}
    reasons: dict[str, str] = {}
    seconds: dict[str, float] = {}
    present = present_weights(cfg)
    device = torch_device(cfg.get("device", "auto"))
    views = range(final.shape[0]) if cfg["views"] == "all" else [0]
    frame_scores = None
    for spec in PAPER_WEIGHTS:
        values[spec.metric] = math.nan
        if spec.metric == "physical_commonsense":
            values[RATING_COLUMN[0]] = math.nan
        if spec.metric not in present:
            reasons[spec.metric] = absent_reason(cfg, spec)
            if spec.metric == "physical_commonsense":
                reasons[RATING_COLUMN[0]] = reasons[spec.metric]
            continue
        if spec.metric == "motion_smoothness_amt" and min(-(-n // 16) * 16 for n in final.shape[2:4]) < AMT_MIN_SIDE_PX:
            reasons[spec.metric] = (f"not computed: frames of {final.shape[3]} x {final.shape[2]} px are below AMT-S's "
                                    f"{AMT_MIN_SIDE_PX} px minimum after padding to multiples of 16 "
                                    "(render.width/height)")
            continue
        t0 = time.perf_counter()
        net = _on_device(network(spec.metric, present[spec.metric]), device)
        scores = []
        for i, v in enumerate(views):
            video = to_srgb_uint8(final[v])
            if spec.metric == "imaging_quality_musiq":
                scores.append(musiq_frame_scores(video, net))
            elif spec.metric == "physical_commonsense":
                scores.append(net.rate(video)[0])
            elif spec.metric == "physical_commonsense_videocon":
                scores.append(net.p_yes(video))
            else:
                scores.append(vfi_smoothness(video, functools.partial(amt_midpoint, net)))
            report_progress(i + 1, len(views), unit="view")
        if spec.metric == "imaging_quality_musiq":
            frame_scores = np.stack(scores)
            values[spec.metric] = float(frame_scores.mean(axis=1).mean() / 100.0)
        elif spec.metric == "physical_commonsense":  # the paper's [0, 1] scale, and VideoPhy-2's 1-5 beside it
            values[spec.metric] = share_rated_at_least(scores, 4)
            values[RATING_COLUMN[0]] = float(np.mean(scores))
        else:
            values[spec.metric] = float(np.mean(scores))
        seconds[spec.metric] = time.perf_counter() - t0
    check_metrics(values, scene)
    return values, reasons, frame_scores, seconds


@artifact_step("paper_metrics", inputs=("gbuffer", "effect"), reads=("paper_metrics",),
               outputs=("musiq_frame_score?",))
def paper_metrics_step(inputs, params):
    """Table 1's VBench imaging quality and motion smoothness and VideoPhy-2 physical commonsense of one scene, or
    why they were not computed."""
    torch_device(params["paper_metrics"].get("device", "auto"))  # thread count
    g, effect = inputs["gbuffer"], inputs["effect"]
    final = final_video(effect, g)
    values, reasons, frame_scores, seconds = paper_metrics(final, dict(params["paper_metrics"]),
                                                           f"{effect.ref.scope} ({effect.attrs.get('backend')} effect)")
    arrays = {}
    if frame_scores is not None:
        arrays["musiq_frame_score"] = Array(frame_scores, ("view", "frame"), "1",
                                            "MUSIQ-SPAQ score per frame (0..100 MOS scale)")
    attrs = {"metrics": {k: (None if math.isnan(v) else v) for k, v in values.items()}, "reasons": reasons,
             "seconds": seconds, "definitions": DEFINITIONS}
    return arrays, attrs
