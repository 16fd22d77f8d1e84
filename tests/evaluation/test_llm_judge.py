"""Tests of the LLM judge (tasks/evaluation/llm_judge.py, paper sec. 4.1.4).

Every request goes to a REAL HTTP server on 127.0.0.1 (http.server in a thread) that answers like an
OpenAI-compatible vision endpoint; the first path segment selects its behaviour.  Nothing else is contacted.
"""
from __future__ import annotations

import base64
import json
import logging
import time

import cv2
import numpy as np
import pytest

from tasks.evaluation.llm_judge import (
    JudgeConfig,
    JudgeScores,
    LLMJudgeError,
    judge_video,
    sample_frame_indices,
)
from tests.chat_endpoint import KEY_ENV, SECRET, ChatEndpoint, assert_no_secret

VALID = {"visual_quality": 4, "motion_realism": 3, "motion_consistency": 5,
         "rationale": "Sharp frames; the juice follows the index finger's squeeze."}


def _judge_answer(mode: str, n: int, auth: str) -> tuple[int, str | None]:
    """The test endpoint's behaviour per mode (``n`` = the how-manieth request of the mode)."""
    if mode == "fenced":
        return 200, "```json\n" + json.dumps(VALID, indent=2) + "\n```"
    if mode == "badjson" or (mode == "repair" and n % 2 == 1):
        return 200, "Visual quality: 4/5, motion realism 3/5 " + auth
    if mode == "schema":
        return 200, json.dumps({**VALID, "visual_quality": 6, "mood": "good"})
    if mode == "echo":
        return 200, json.dumps({**VALID, "rationale": f"key was {auth}"})
    if mode == "slow":
        time.sleep(1.5)
    if mode == "unauthorized":
        return 401, None
    return 200, json.dumps(VALID)


@pytest.fixture(scope="module")
def server():
    s = ChatEndpoint(_judge_answer, lambda auth: {"error": {"message": f"invalid key {auth}"}})
    yield s
    s.close()



def _cfg(server, mode, tmp_path, **kw) -> JudgeConfig:
    kw = {"model": "test-vision", "timeout_s": 5.0, "frames": 4, "cache_dir": str(tmp_path / "cache"), **kw}
    return JudgeConfig(url=server.url(mode), api_key_env=KEY_ENV, **kw)


def _grey_ramp_video(n_frames=10, h=48, w=64) -> np.ndarray:
    """Frame t is a flat grey of value 20 t with a white square: each frame is identifiable after JPEG."""
    v = np.zeros((n_frames, h, w, 3), np.uint8)
    for t in range(n_frames):
        v[t] = 20 * t
        v[t, 8:24, 8:24] = 255
    return v


def _controls(h=40, w=80) -> np.ndarray:
    img = np.full((h, w, 3), 255, np.uint8)
    img[np.arange(h), np.linspace(0, w - 1, h).astype(int)] = (200, 30, 10)  # a red diagonal: the "force curve"
    return img


def _decode(url: str) -> tuple[str, np.ndarray]:
    head, data = url.split(",", 1)
    fmt = head.removeprefix("data:image/").removesuffix(";base64")
    bgr = cv2.imdecode(np.frombuffer(base64.b64decode(data), np.uint8), cv2.IMREAD_COLOR)
    return fmt, bgr[..., ::-1]



def test_sample_frame_indices_closed_form():
    assert sample_frame_indices(10, 4).tolist() == [0, 3, 6, 9]
    assert sample_frame_indices(49, 8).tolist() == [0, 7, 14, 21, 27, 34, 41, 48]
    assert sample_frame_indices(3, 8).tolist() == [0, 1, 2]
    assert sample_frame_indices(1, 1).tolist() == [0]
    with pytest.raises(LLMJudgeError, match=">= 1"):
        sample_frame_indices(0, 4)


def test_valid_answer_request_images_key_and_cache(server, tmp_path, key_env):
    frames, controls = _grey_ramp_video(), _controls()
    cfg = _cfg(server, "good", tmp_path)
    scores = judge_video(frames, controls, "tomato", "juice", cfg)
    assert scores == JudgeScores(**VALID) and server.hits["good"] == 1
    req = server.last("good")
    # the key travels in the Authorization header only
    assert req["path"] == "/good/v1/chat/completions" and req["auth"] == f"Bearer {SECRET}"
    assert SECRET.encode() not in req["raw"]
    body = req["json"]
    assert body["model"] == "test-vision" and body["response_format"] == {"type": "json_object"}
    assert "motion_consistency" in body["messages"][0]["content"]  # the schema is in the system prompt
    parts = body["messages"][1]["content"]
    assert parts[0]["type"] == "text" and "tomato" in parts[0]["text"] and "juice" in parts[0]["text"]
    images = [_decode(p["image_url"]["url"]) for p in parts[1:]]
    assert [p["type"] for p in parts[1:]] == ["image_url"] * 5
    # the controls image first, lossless; then frames 0, 3, 6, 9 in time order
    assert images[0][0] == "png" and np.array_equal(images[0][1], controls)
    for (fmt, img), t in zip(images[1:], [0, 3, 6, 9]):
        assert fmt == "jpeg" and img.shape == frames[t].shape
        assert np.abs(img.astype(int) - frames[t]).mean() < 3.0
    # a second identical call is served from the cache; the cache file is JSON without the key
    assert judge_video(frames, controls, "tomato", "juice", cfg) == scores and server.hits["good"] == 1
    files = list((tmp_path / "cache").glob("*.json"))
    assert len(files) == 1 and SECRET not in files[0].read_text()
    record = json.loads(files[0].read_text())
    assert record["key"]["model"] == "test-vision" and record["scores"] == VALID
    # another video, another model or another object is a new request
    judge_video(frames[::-1].copy(), controls, "tomato", "juice", cfg)
    judge_video(frames, controls, "tomato", "juice", _cfg(server, "good", tmp_path, model="other"))
    judge_video(frames, controls, "orange", "juice", cfg)
    assert server.hits["good"] == 4 and len(list((tmp_path / "cache").glob("*.json"))) == 4
    # a corrupted cache file is ignored and rewritten
    files[0].write_text("{not json")
    assert judge_video(frames, controls, "tomato", "juice", cfg) == scores and server.hits["good"] == 5
    assert json.loads(files[0].read_text())["scores"] == VALID


def test_images_are_downscaled_to_max_image_px(server, tmp_path, key_env):
    cfg = _cfg(server, "fenced", tmp_path, max_image_px=32, frames=2, cache_dir=None)
    scores = judge_video(_grey_ramp_video(5, 48, 64), _controls(40, 80), "clay", "dent", cfg)
    assert scores.motion_consistency == 5  # (a ```json fence around the answer is accepted)
    shapes = [_decode(p["image_url"]["url"])[1].shape for p in server.last("fenced")["json"]["messages"][1]
              ["content"][1:]]
    assert shapes == [(16, 32, 3), (24, 32, 3), (24, 32, 3)]


def test_one_repair_request_after_a_malformed_answer(server, tmp_path, key_env):
    cfg = _cfg(server, "repair", tmp_path)
    assert judge_video(_grey_ramp_video(), _controls(), "can", "cola_spray", cfg) == JudgeScores(**VALID)
    assert server.hits["repair"] == 2
    messages = server.last("repair")["json"]["messages"]
    assert [m["role"] for m in messages] == ["system", "user", "assistant", "user"]
    assert "***" in messages[2]["content"] and SECRET not in json.dumps(messages)  # echoed key redacted
    assert "invalid JSON" in messages[3]["content"]
    assert judge_video(_grey_ramp_video(), _controls(), "can", "cola_spray", cfg) == JudgeScores(**VALID)
    assert server.hits["repair"] == 2  # cached


@pytest.mark.parametrize("mode,fragment", [("badjson", "invalid JSON"),
                                           ("schema", "visual_quality: Input should be less than or equal to 5")])
def test_two_malformed_answers_are_a_one_line_error(server, tmp_path, key_env, mode, fragment):
    with pytest.raises(LLMJudgeError) as info:
        judge_video(_grey_ramp_video(), _controls(), "can", "cola_spray", _cfg(server, mode, tmp_path))
    msg = str(info.value)
    assert msg.startswith(f"LLM judge endpoint {server.url(mode)}/chat/completions answered malformed scores "
                          "twice (")
    assert fragment in msg and "llm_judge.model" in msg and "\n" not in msg
    assert server.hits[mode] == 2 and not list((tmp_path / "cache").glob("*.json"))
    assert_no_secret(info.value)


def test_timeout_is_a_one_line_error_naming_the_url(server, tmp_path, key_env):
    t0 = time.monotonic()
    with pytest.raises(LLMJudgeError) as info:
        judge_video(_grey_ramp_video(), _controls(), "can", "cola_spray", _cfg(server, "slow", tmp_path, timeout_s=0.3))
    assert time.monotonic() - t0 < 1.4
    assert str(info.value) == (f"LLM judge endpoint {server.url('slow')}/chat/completions timed out after 0.3 s: "
                               "raise llm_judge.timeout_s or check that the server is up")


def test_http_401_names_the_variable_and_leaks_no_key(server, tmp_path, key_env, caplog, capfd):
    caplog.set_level(logging.DEBUG)  # every logger, httpx and httpcore included
    cfg = _cfg(server, "unauthorized", tmp_path)
    with pytest.raises(LLMJudgeError) as info:
        judge_video(_grey_ramp_video(), _controls(), "can", "cola_spray", cfg)
    logging.getLogger("virsqueezer").error("step failed", exc_info=info.value)  # as Prefect logs a failure
    msg = str(info.value)
    assert "HTTP 401" in msg and f"${KEY_ENV}" in msg and "***" in msg and "\n" not in msg
    assert server.last("unauthorized")["auth"] == f"Bearer {SECRET}"  # the key was sent and echoed back
    assert_no_secret(info.value)
    # a valid answer that echoes the key: the cached rationale holds "***"
    echoed = judge_video(_grey_ramp_video(), _controls(), "can", "cola_spray", _cfg(server, "echo", tmp_path))
    assert echoed.rationale == "key was Bearer ***"
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    assert files and [p for p in files if SECRET.encode() in p.read_bytes()] == []
    out, err = capfd.readouterr()
    assert "step failed" in caplog.text and SECRET not in caplog.text + out + err


def test_bad_inputs_and_config(server, tmp_path, key_env):
    good = _cfg(server, "good", tmp_path)
    with pytest.raises(LLMJudgeError, match=r"frames must be a non-empty uint8 sRGB array \(frame, y, x, 3\), "
                                            r"got float32 \(4, 8, 8, 3\)"):
        judge_video(np.zeros((4, 8, 8, 3), np.float32), _controls(), "can", "x", good)
    with pytest.raises(LLMJudgeError, match=r"controls_image must be .* \(y, x, 3\)"):
        judge_video(_grey_ramp_video(), _grey_ramp_video(), "can", "x", good)
    with pytest.raises(LLMJudgeError, match="llm_judge.url 'ftp://host/v1' must be"):
        judge_video(_grey_ramp_video(), _controls(), "can", "x", JudgeConfig(url="ftp://host/v1"))
    with pytest.raises(LLMJudgeError, match="llm_judge.frames 0 must be"):
        judge_video(_grey_ramp_video(), _controls(), "can", "x", _cfg(server, "good", tmp_path, frames=0))
    # a closed port: unreachable, one line, the fix named
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(LLMJudgeError, match="unreachable .*start the server or fix llm_judge.url") as info:
        judge_video(_grey_ramp_video(), _controls(), "can", "x", JudgeConfig(url=f"http://127.0.0.1:{port}/v1",
                                                                  api_key_env=KEY_ENV, timeout_s=2.0))
    assert_no_secret(info.value)
