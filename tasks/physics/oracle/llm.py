"""LLM backend of the material oracle (paper sec. 3.2: GPT-5 infers the object's materials).

Any OpenAI-compatible ``POST {llm_url}/chat/completions`` endpoint.  The answer must be JSON that validates
against :class:`LLMAnswer`; answers are cached on disk as JSON.  The API key comes from the environment variable
named by ``api_key_env`` and is never logged, cached or put in an error message.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import time
import uuid
from pathlib import Path
from typing import Any, Optional

from pydantic import ValidationError

from tasks.core.chat_client import (
    ChatEndpointError,
    EndpointWording,
    chat_content,
    display_url,
    post_chat,
    redact,
    snippet,
)
from tasks.physics.oracle.config import OracleSettings
from tasks.physics.oracle.schema import LLMAnswer, MaterialOracleError, one_line

log = logging.getLogger(__name__)

PROMPT_VERSION = "virsqueezer-material-oracle-v1"

_SYSTEM_PROMPT = """You are a materials engineer preparing inputs for a Material Point Method (MPM) simulation \
of an object squeezed by a human hand. From the object's name, description and interior, infer real physical \
properties in SI units and answer with ONE JSON object, no prose, that validates against this JSON schema:
{schema}
Rules:
- Units: Pa, kg/m^3, Pa s. Poisson's ratio 0 <= nu <= 0.49 (never 0.5). Give real measured values where \
they exist and name the handbook or paper in "source"; say "engineering choice" where you chose a value.
- "shell" is the visible body or wall; "interior" is what fills it (null when the object is hollow or solid).
- Models: fixed_corotated / neo_hookean (elastic), stvk_hencky_von_mises (elastoplastic, needs yield_stress), \
foam (viscoplastic, needs yield_stress), fluid (needs viscosity; give youngs_modulus = 3 K (1 - 2 nu) with \
nu = 0.49 so that K is the liquid's bulk modulus).
- "squeeze_threshold" is the compressive engineering strain (0..1) at the finger contact where rupture or \
overflow starts; null if the object never ruptures when squeezed by hand. Effects juice, cola_spray and \
stuffing_spill need a threshold; rebound, dent, buckle and none usually have null.
"""


def _prompt_messages(description: str, name: str, interior: Optional[str]) -> list[dict[str, str]]:
    schema = json.dumps(LLMAnswer.model_json_schema(), sort_keys=True)
    user = json.dumps({"name": name, "description": description, "interior": interior}, sort_keys=True)
    return [{"role": "system", "content": _SYSTEM_PROMPT.format(schema=schema)},
            {"role": "user", "content": f"Object (JSON): {user}"}]


def _cache_key(conf: OracleSettings, description: str, name: str,
               interior: Optional[str]) -> tuple[str, dict[str, Any]]:
    key = {"url": conf.llm_url, "model": conf.llm_model, "description": description, "name": name,
           "interior": interior, "prompt_version": PROMPT_VERSION}
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()
    return digest, key


def _cache_read(path: Path, key_display: dict[str, Any]) -> Optional[LLMAnswer]:
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        if record.get("key") != key_display:
            log.warning("material cache %s belongs to another request: ignored", path)
            return None
        return LLMAnswer.model_validate(record["answer"])
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError, ValidationError) as exc:
        log.warning("material cache %s is unreadable (%s): asking the endpoint again", path, type(exc).__name__)
        return None


def _cache_write(path: Path, key_display: dict[str, Any], answer: LLMAnswer) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"key": key_display, "answer": answer.model_dump(mode="json"),
              "created_unix": time.time(), "format": "virsqueezer-material-cache-v1"}
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex}.tmp")
    tmp.write_text(json.dumps(record, indent=1, sort_keys=True), encoding="utf-8")
    os.replace(tmp, path)


def llm_answer(description: str, name: str, interior: Optional[str], conf: OracleSettings) -> LLMAnswer:
    """The LLM backend of the oracle (paper sec. 3.2: an LLM infers the material): the validated answer of
    ``POST {conf.llm_url}/chat/completions`` for one object, read from / written to the JSON cache in
    ``conf.cache_dir`` when set.  Raises :class:`MaterialOracleError` (one line, API key redacted)."""
    if not conf.llm_url:
        raise MaterialOracleError("oracle.llm_url is not set: give the base URL of an OpenAI-compatible "
                                  "API (e.g. http://127.0.0.1:8000/v1) or use backend=table")
    if not conf.llm_url.startswith(("http://", "https://")):
        raise MaterialOracleError(f"oracle.llm_url {display_url(conf.llm_url)!r} must start with "
                                  "http:// or https://")
    digest, key = _cache_key(conf, description, name, interior)
    key_display = dict(key, url=display_url(conf.llm_url), url_sha256=hashlib.sha256(
        conf.llm_url.encode()).hexdigest())
    cache_path = Path(conf.cache_dir) / f"{digest}.json" if conf.cache_dir else None
    if cache_path is not None:
        cached = _cache_read(cache_path, key_display)
        if cached is not None:
            log.info("material oracle: cached LLM answer for %r (%s)", name, cache_path.name)
            return cached
    answer = _ask_llm(description, name, interior, conf)
    if cache_path is not None:
        _cache_write(cache_path, key_display, answer)
    return answer


def _ask_llm(description: str, name: str, interior: Optional[str], conf: OracleSettings) -> LLMAnswer:
    assert conf.llm_url is not None
    endpoint = conf.llm_url.rstrip("/") + "/chat/completions"
    shown = display_url(endpoint)
    secret = os.environ.get(conf.api_key_env) or None
    payload = {"model": conf.llm_model, "messages": _prompt_messages(description, name, interior),
               "response_format": {"type": "json_object"}, "temperature": 0}

    def fail(msg: str) -> MaterialOracleError:
        return MaterialOracleError(redact(msg, secret))

    log.info("material oracle: asking %s (model %s) about %r", shown, conf.llm_model, name)
    wording = EndpointWording("LLM endpoint", "raise oracle.timeout_s or use backend=table",
                              "start the server, fix oracle.llm_url or use backend=table", "not a material answer",
                              key_env=conf.api_key_env, status_fix="check oracle.llm_url and oracle.llm_model")
    try:
        status, text = post_chat(endpoint, payload, secret, conf.timeout_s, wording)
        content = chat_content(status, text, endpoint, secret, wording)
    except ChatEndpointError as exc:
        raise MaterialOracleError(str(exc)) from None
    if isinstance(content, str):
        stripped = content.strip()
        fence = re.fullmatch(r"```(?:json)?\s*(.*?)\s*```", stripped, flags=re.S)
        if fence:
            stripped = fence.group(1)
        try:
            data = json.loads(stripped)
        except ValueError as exc:
            raise fail(f"LLM endpoint {shown} answered invalid JSON in choices[0].message.content ({exc.msg} at "
                       f"char {exc.pos}): {snippet(stripped)}") from None
    elif isinstance(content, dict):
        data = content
    else:
        raise fail(f"LLM endpoint {shown} answered choices[0].message.content of type "
                   f"{type(content).__name__}: expected a JSON string")
    if not isinstance(data, dict):
        raise fail(f"LLM endpoint {shown} answered JSON {type(data).__name__}, expected an object")
    try:
        return LLMAnswer.model_validate(data)
    except ValidationError as exc:
        raise fail(f"LLM endpoint {shown} answered JSON that violates the material schema: {one_line(exc)}") \
            from None
