"""One POST to an OpenAI-compatible chat-completions endpoint, shared by the material oracle's LLM backend (paper
sec. 3.2) and the LLM judge (sec. 4.1.4).

The API key is read from an environment variable by the caller and sent in the Authorization header only; it is
replaced by ``***`` in every message this module builds.  The client ignores proxies and netrc from the environment
(``trust_env=False``: only the configured URL is contacted), follows no redirects, reads the answer as a stream
under one overall deadline and refuses answers above ``MAX_RESPONSE_BYTES``.  Failures raise
:class:`ChatEndpointError` with one line naming the endpoint and the caller's fix.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass
from typing import Any, Optional

import httpx

MAX_RESPONSE_BYTES = 2_000_000


class ChatEndpointError(RuntimeError):
    """The endpoint did not give a chat completion; the message is one line, key redacted."""


@dataclass(frozen=True)
class EndpointWording:
    """How a caller names the endpoint and the fixes in its messages, e.g. ``"LLM endpoint"`` and
    ``"raise oracle.timeout_s or use backend=table"``."""

    name: str
    timeout_fix: str
    unreachable_fix: str
    oversize_fix: str = ""
    key_env: str = ""  # the environment variable holding the API key (named on HTTP 401/403)
    status_fix: str = ""  # the fix for any other HTTP error or a body that is not a chat completion


def display_url(url: str) -> str:
    """The URL without user info, query string and fragment (they may hold credentials)."""
    try:
        return str(httpx.URL(url).copy_with(username=None, password=None, query=None, fragment=None))
    except Exception:  # noqa: BLE001 - a malformed URL is shown as given, minus anything after '?'
        return url.split("?", 1)[0]


def snippet(text: str, limit: int = 160) -> str:
    """The start of ``text`` on one line, quoted, for an error message."""
    text = " ".join(text.split())
    return repr(text[:limit] + ("..." if len(text) > limit else ""))


def redact(text: str, secret: Optional[str]) -> str:
    """``text`` with the API key replaced by ``***``."""
    return text.replace(secret, "***") if secret else text


def post_chat(endpoint: str, payload: dict[str, Any], secret: Optional[str], timeout_s: float,
              wording: EndpointWording) -> tuple[int, str]:
    """POST ``payload`` as JSON to ``endpoint``; returns (HTTP status, body text).  Raises
    :class:`ChatEndpointError` on a timeout, an unreachable endpoint or an oversized answer."""
    shown = display_url(endpoint)
    headers = {"Content-Type": "application/json", "Accept": "application/json"}
    if secret:
        headers["Authorization"] = f"Bearer {secret}"
    timeout_msg = f"{wording.name} {shown} timed out after {timeout_s:g} s: {wording.timeout_fix}"
    deadline = time.monotonic() + timeout_s
    try:
        with httpx.Client(timeout=httpx.Timeout(timeout_s), trust_env=False, follow_redirects=False) as client:
            with client.stream("POST", endpoint, json=payload, headers=headers) as resp:
                chunks, size = [], 0
                for chunk in resp.iter_bytes():
                    chunks.append(chunk)
                    size += len(chunk)
                    if time.monotonic() > deadline:
                        raise ChatEndpointError(redact(timeout_msg, secret))
                    if size > MAX_RESPONSE_BYTES:
                        raise ChatEndpointError(redact(f"{wording.name} {shown} answered more than "
                                                       f"{MAX_RESPONSE_BYTES} bytes: {wording.oversize_fix}",
                                                       secret))
                return resp.status_code, b"".join(chunks).decode("utf-8", errors="replace")
    except httpx.TimeoutException:
        raise ChatEndpointError(redact(timeout_msg, secret)) from None
    except httpx.HTTPError as exc:
        raise ChatEndpointError(redact(f"{wording.name} {shown} is unreachable ({type(exc).__name__}): "
                                       f"{wording.unreachable_fix}", secret)) from None


def chat_content(status: int, text: str, endpoint: str, secret: Optional[str], wording: EndpointWording) -> Any:
    """``choices[0].message.content`` of the answer of :func:`post_chat` (text, or an object when a server sends
    one).  Raises :class:`ChatEndpointError` (one line, key redacted) for an HTTP error status, a body that is not
    an OpenAI-compatible chat completion, or a refusal."""
    shown = display_url(endpoint)

    def fail(msg: str) -> ChatEndpointError:
        return ChatEndpointError(redact(msg, secret))

    if status != 200:
        fix = f"check the API key in ${wording.key_env}" if status in (401, 403) else wording.status_fix
        raise fail(f"{wording.name} {shown} answered HTTP {status} ({fix}): {snippet(text)}")
    try:
        message = json.loads(text)["choices"][0]["message"]
        content = message.get("content")
    except (ValueError, KeyError, IndexError, TypeError, AttributeError):
        raise fail(f"{wording.name} {shown} answered without choices[0].message (not an OpenAI-compatible chat "
                   f"completion; {wording.status_fix}): {snippet(text)}") from None
    if content is None and message.get("refusal"):
        raise fail(f"{wording.name} {shown} refused: {snippet(str(message['refusal']))}")
    return content
