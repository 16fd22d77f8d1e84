"""LLM evaluation of one squeezing video (paper sec. 4.1.4, "Evaluation with Multiple LLMs"; Table 1's GPT-5 rows).

Following PhysGen3D and PhysDreamer as the paper does, a vision LLM sees the video (``frames`` images sampled
evenly in time) together with a rendering of the squeezing control signals, and scores visual quality, motion
realism and motion consistency (the effect's alignment with the controls) on a 5-point Likert scale
(1 = worst, 5 = best).

Any OpenAI-compatible ``POST {url}/chat/completions`` endpoint that takes ``image_url`` content parts.  The
answer must be one JSON object that validates against :class:`JudgeScores`; one repair request is sent when it
does not.  Valid answers are cached on disk as JSON keyed by a digest of (endpoint, model, prompt, images), so a
rerun does not ask again.  The API key comes from the environment variable named by ``api_key_env`` and is never
logged, cached or put in an error message.
"""
from __future__ import annotations

import base64
import hashlib
import json
import logging
import math
import os
import re
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import cv2
import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from tasks.core.chat_client import (
    ChatEndpointError,
    EndpointWording,
    chat_content,
    display_url,
    post_chat,
    redact,
    snippet,
)

log = logging.getLogger(__name__)

PROMPT_VERSION = "virsqueezer-llm-judge-v1"
CACHE_FORMAT = "virsqueezer-llm-judge-cache-v1"
QUESTIONS: tuple[str, ...] = ("visual_quality", "motion_realism", "motion_consistency")
JPEG_QUALITY = 90


class LLMJudgeError(ValueError):
    """The judge cannot give valid scores; the one-line message names the endpoint or input and the fix."""


class JudgeScores(BaseModel):
    """The judge's answer: three 1-5 Likert scores (1 = worst, 5 = best) and a short rationale."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    visual_quality: int = Field(strict=True, ge=1, le=5, description="image quality of the frames")
    motion_realism: int = Field(strict=True, ge=1, le=5, description="physical plausibility of the motion")
    motion_consistency: int = Field(strict=True, ge=1, le=5,
                                    description="alignment of the deformation and effect with the controls")
    rationale: str = Field(min_length=1, max_length=1000, description="one or two sentences")


@dataclass(frozen=True)
class JudgeConfig:
    """Settings of the LLM judge (config group ``llm_judge``).

    url: base URL of the OpenAI-compatible API (e.g. ``https://api.openai.com/v1``); ``/chat/completions`` is
    appended.  model: the vision model's name.  api_key_env: name of the environment variable holding the key
    (an unset or empty variable sends no Authorization header).  timeout_s: seconds allowed per request.
    frames: number of video frames sent, sampled evenly in time.  cache_dir: folder of the answer cache (None:
    ask every time).  max_image_px: longest side, pixels, of every image sent (larger ones are downscaled).
    """

    url: str
    model: str = "gpt-5"
    api_key_env: str = "VIRSQUEEZER_LLM_API_KEY"
    timeout_s: float = 120.0
    frames: int = 8
    cache_dir: Optional[str] = None
    max_image_px: int = 512


_SYSTEM_PROMPT = """You are an expert rater of generated videos of a human hand squeezing an object. You get \
one image plotting the squeezing control signals over time (per finger: flexion and force coefficient, \
thumb, index, middle, ring, pinky), then frames sampled evenly in time from the generated video, in order. \
Rate the video on a 5-point Likert scale (1 = worst, 5 = best) on three questions:
- visual_quality: how sharp, clean and artefact-free the frames look (blur, noise, distortions, flicker);
- motion_realism: how physically plausible the object's deformation and any released material (juice, \
spray, stuffing) move;
- motion_consistency: how well the deformation and effect follow the control signals (which fingers squeeze, \
when and how strongly; no motion where the controls are idle).
Answer with ONE JSON object, no prose, that validates against this JSON schema:
{schema}"""


def sample_frame_indices(n_video_frames: int, n_samples: int) -> np.ndarray:
    """Indices of ``n_samples`` frames spread evenly over a video of ``n_video_frames`` frames, first and last
    included: ``round(linspace(0, T - 1, N))`` (all frames when T <= N).  Returns (sample,) int64, ascending."""
    if n_video_frames < 1 or n_samples < 1:
        raise LLMJudgeError(f"cannot sample {n_samples} of {n_video_frames} frames: both must be >= 1")
    if n_video_frames <= n_samples:
        return np.arange(n_video_frames, dtype=np.int64)
    return np.round(np.linspace(0, n_video_frames - 1, n_samples)).astype(np.int64)


def encode_image(rgb: np.ndarray, image_format: str, max_px: int) -> str:
    """One image as a ``data:`` URL for an ``image_url`` content part.

    rgb: (y, x, channel=3) uint8 sRGB.  image_format: "png" (lossless; the control plot) or "jpeg" (quality 90;
    video frames).  max_px: the longest side in pixels after downscaling with area averaging (aspect kept)."""
    h, w = rgb.shape[:2]
    scale = max_px / max(h, w)
    if scale < 1.0:
        rgb = cv2.resize(rgb, (max(1, round(w * scale)), max(1, round(h * scale))), interpolation=cv2.INTER_AREA)
    params = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if image_format == "jpeg" else []
    ok, buf = cv2.imencode(f".{image_format}", np.ascontiguousarray(rgb[..., ::-1]), params)
    if not ok:
        raise LLMJudgeError(f"OpenCV could not encode a {w}x{h} image as {image_format}")
    return f"data:image/{image_format};base64,{base64.b64encode(buf.tobytes()).decode('ascii')}"


def judge_messages(frame_urls: list[str], controls_url: str, object_name: str, effect: str,
                   frame_indices: np.ndarray, n_video_frames: int) -> list[dict[str, Any]]:
    """The chat messages of one judge request (paper sec. 4.1.4): system prompt with the answer schema, then
    the object, the controls image and the frames (``data:`` URLs from :func:`encode_image`), in time order."""
    schema = json.dumps(JudgeScores.model_json_schema(), sort_keys=True)
    intro = (f"Object: {object_name}. Expected squeezing effect: {effect}. First image: the control signals. "
             f"Then {len(frame_urls)} frames of the {n_video_frames}-frame video (frame indices "
             f"{', '.join(str(int(i)) for i in frame_indices)}), in time order.")
    content: list[dict[str, Any]] = [{"type": "text", "text": intro},
                                     {"type": "image_url", "image_url": {"url": controls_url}}]
    content += [{"type": "image_url", "image_url": {"url": u}} for u in frame_urls]
    return [{"role": "system", "content": _SYSTEM_PROMPT.format(schema=schema)}, {"role": "user", "content": content}]


def judge_video(frames: np.ndarray, controls_image: np.ndarray, object_name: str, effect: str,
                cfg: JudgeConfig) -> JudgeScores:
    """LLM scores of one squeezing video (paper sec. 4.1.4; Table 1's LLM-evaluation columns).

    frames: (frame, y, x, channel=3) uint8 sRGB, the whole video; ``cfg.frames`` of them are sent
    (:func:`sample_frame_indices`).  controls_image: (y, x, channel=3) uint8 sRGB plot of the control signals
    (flexion and force coefficient per finger over the video's time span).  object_name, effect: words shown to
    the judge (e.g. "tomato", "juice").  Returns the validated :class:`JudgeScores`, from the cache in
    ``cfg.cache_dir`` when the same request was answered before.  Raises :class:`LLMJudgeError` (one line, API
    key redacted)."""
    # 1. check the inputs and the config
    check_judge_config(cfg)
    _check_image(frames, "frames", 4)
    _check_image(controls_image, "controls_image", 3)
    # 2. the request: sampled frames (JPEG) and the control plot (PNG) as data URLs
    indices = sample_frame_indices(frames.shape[0], cfg.frames)
    frame_urls = [encode_image(frames[i], "jpeg", cfg.max_image_px) for i in indices]
    controls_url = encode_image(controls_image, "png", cfg.max_image_px)
    messages = judge_messages(frame_urls, controls_url, object_name, effect, indices, frames.shape[0])
    # 3. the cache, keyed by endpoint, model, prompt and images
    key = {"format": CACHE_FORMAT, "prompt_version": PROMPT_VERSION, "url": display_url(cfg.url),
           "url_sha256": _sha256(cfg.url), "model": cfg.model,
           "prompt_sha256": _sha256(json.dumps(messages, sort_keys=True)),
           "image_sha256": [_sha256(u) for u in [controls_url, *frame_urls]],
           "object": object_name, "effect": effect, "frame_indices": [int(i) for i in indices]}
    cache_path = Path(cfg.cache_dir) / f"{_sha256(json.dumps(key, sort_keys=True))}.json" if cfg.cache_dir else None
    if cache_path is not None:
        cached = _cache_read(cache_path, key)
        if cached is not None:
            log.info("LLM judge: cached scores for %r (%s)", object_name, cache_path.name)
            return cached
    # 4. ask, with one repair request on a malformed answer
    scores = _ask_with_repair(messages, cfg)
    if cache_path is not None:
        _cache_write(cache_path, key, scores)
    return scores


def check_judge_config(cfg: JudgeConfig) -> None:
    """Refuse endpoint settings that cannot work (:class:`LLMJudgeError`, one line naming the key); also run by
    :mod:`flows.preflight` before the flow starts."""
    if not cfg.url or not str(cfg.url).startswith(("http://", "https://")):
        raise LLMJudgeError(f"llm_judge.url {display_url(str(cfg.url or ''))!r} must be the http:// or https:// "
                            "base URL of an OpenAI-compatible API (e.g. http://127.0.0.1:8000/v1)")
    if not (isinstance(cfg.timeout_s, (int, float)) and math.isfinite(cfg.timeout_s) and cfg.timeout_s > 0):
        raise LLMJudgeError(f"llm_judge.timeout_s {cfg.timeout_s!r} must be a number of seconds > 0")
    if not (isinstance(cfg.frames, int) and cfg.frames >= 1):
        raise LLMJudgeError(f"llm_judge.frames {cfg.frames!r} must be an integer >= 1 (e.g. 8)")
    if not (isinstance(cfg.max_image_px, int) and cfg.max_image_px >= 16):
        raise LLMJudgeError(f"llm_judge.max_image_px {cfg.max_image_px!r} must be an integer >= 16 (e.g. 512)")


def _check_image(a: Any, name: str, ndim: int) -> None:
    shape = "(frame, y, x, 3)" if ndim == 4 else "(y, x, 3)"
    if not isinstance(a, np.ndarray) or a.dtype != np.uint8 or a.ndim != ndim or a.shape[-1] != 3 or 0 in a.shape:
        got = f"{a.dtype} {a.shape}" if isinstance(a, np.ndarray) else type(a).__name__
        raise LLMJudgeError(f"{name} must be a non-empty uint8 sRGB array {shape}, got {got}: convert it first")


def _ask_with_repair(messages: list[dict[str, Any]], cfg: JudgeConfig) -> JudgeScores:
    shown = display_url(_endpoint(cfg))
    content = _post_chat(messages, cfg)
    try:
        return _parse_scores(content)
    except _Malformed as first:
        log.warning("LLM judge: %s answered a malformed score (%s): asking once more", shown, first)
        repair = messages + [{"role": "assistant", "content": content},
                             {"role": "user", "content": f"That answer is invalid ({first}). Answer again with "
                                                         "ONE JSON object, no prose, that validates against the "
                                                         "schema in the system message."}]
        try:
            return _parse_scores(_post_chat(repair, cfg))
        except _Malformed as second:
            raise LLMJudgeError(redact(
                f"LLM judge endpoint {shown} answered malformed scores twice ({second}): use a model that follows "
                f"JSON instructions and takes images, or set llm_judge.model",
                os.environ.get(cfg.api_key_env) or None)) from None


class _Malformed(Exception):
    """An answer that is not a valid :class:`JudgeScores` JSON object (worth one repair request)."""


def _parse_scores(content: str) -> JudgeScores:
    text = content.strip()
    fence = re.fullmatch(r"```(?:json)?\s*(.*?)\s*```", text, flags=re.S)
    if fence:
        text = fence.group(1)
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise _Malformed(f"invalid JSON: {exc.msg} at char {exc.pos}: {snippet(text, 60)}") from None
    if not isinstance(data, dict):
        raise _Malformed(f"JSON {type(data).__name__}, expected an object")
    try:
        return JudgeScores.model_validate(data)
    except ValidationError as exc:
        parts = [f"{'.'.join(str(x) for x in e['loc']) or '<root>'}: {e['msg']}"
                 for e in exc.errors(include_url=False, include_input=False)]
        raise _Malformed("schema violation: " + "; ".join(parts)) from None


def _endpoint(cfg: JudgeConfig) -> str:
    return cfg.url.rstrip("/") + "/chat/completions"


def _post_chat(messages: list[dict[str, Any]], cfg: JudgeConfig) -> str:
    """``choices[0].message.content`` of one chat completion (temperature 0, JSON answer requested)."""
    # 1. request with the key in the Authorization header only
    endpoint = _endpoint(cfg)
    shown = display_url(endpoint)
    secret = os.environ.get(cfg.api_key_env) or None
    payload = {"model": cfg.model, "messages": messages, "response_format": {"type": "json_object"},
               "temperature": 0}

    def fail(msg: str) -> LLMJudgeError:
        return LLMJudgeError(redact(msg, secret))

    log.info("LLM judge: asking %s (model %s)", shown, cfg.model)
    # 2. streamed read under one overall deadline (tasks.core.chat_client)
    wording = EndpointWording("LLM judge endpoint", "raise llm_judge.timeout_s or check that the server is up",
                              "start the server or fix llm_judge.url", "not a chat completion; check llm_judge.url",
                              key_env=cfg.api_key_env, status_fix="check llm_judge.url/model")
    try:
        status, text = post_chat(endpoint, payload, secret, cfg.timeout_s, wording)
        # 3. the OpenAI envelope
        content = chat_content(status, text, endpoint, secret, wording)
    except ChatEndpointError as exc:
        raise LLMJudgeError(str(exc)) from None
    if not isinstance(content, str):
        raise fail(f"LLM judge endpoint {shown} answered choices[0].message.content of type "
                   f"{type(content).__name__}: expected text")
    return redact(content, secret)


def _sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _cache_read(path: Path, key: dict[str, Any]) -> Optional[JudgeScores]:
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        if record.get("key") != key:
            log.warning("LLM judge cache %s belongs to another request: ignored", path)
            return None
        return JudgeScores.model_validate(record["scores"])
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as exc:  # ValidationError is a ValueError
        log.warning("LLM judge cache %s is unreadable (%s): asking the endpoint again", path, type(exc).__name__)
        return None


def _cache_write(path: Path, key: dict[str, Any], scores: JudgeScores) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"key": key, "scores": scores.model_dump(mode="json"), "created_unix": time.time()}
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    tmp.write_text(json.dumps(record, indent=1, sort_keys=True), encoding="utf-8")
    os.replace(tmp, path)
