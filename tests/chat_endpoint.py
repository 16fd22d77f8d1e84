"""A real OpenAI-compatible chat endpoint on the loopback address, for the tests of the clients that call one
(the material oracle's LLM backend and the LLM judge).

The first path segment of a request selects the behaviour (``http://127.0.0.1:<port>/<mode>/v1``); the test passes
``answer(mode, n, auth) -> (status, content)`` (``n`` = the how-manieth request of that mode, ``auth`` = the
Authorization header).  A 200 answer wraps ``content`` as a chat completion; any other status sends
``error_body(auth)``.  Requests are recorded (mode, path, auth, raw body, parsed JSON) and counted per mode.
"""
from __future__ import annotations

import json
import threading
import traceback
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any, Callable

Answer = Callable[[str, int, str], tuple[int, "str | None"]]


class ChatEndpoint:
    """``ThreadingHTTPServer`` in a daemon thread answering ``POST <mode>/v1/chat/completions``."""

    def __init__(self, answer: Answer, error_body: Callable[[str], Any]) -> None:
        self.hits: dict[str, int] = {}
        self.requests: list[dict] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # keep test output clean
                pass

            def do_POST(self):  # noqa: N802
                mode = self.path.strip("/").split("/")[0]
                raw = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                n = outer.hits[mode] = outer.hits.get(mode, 0) + 1
                auth = self.headers.get("Authorization", "")
                outer.requests.append({"mode": mode, "path": self.path, "auth": auth, "raw": raw,
                                       "json": json.loads(raw)})
                status, content = answer(mode, n, auth)
                if status == 200:
                    payload = json.dumps({"id": "x", "object": "chat.completion", "choices": [
                        {"index": 0, "message": {"role": "assistant", "content": content},
                         "finish_reason": "stop"}]}).encode()
                else:
                    payload = json.dumps(error_body(auth)).encode()
                try:
                    self.send_response(status)
                    self.send_header("Content-Type", "application/json")
                    self.send_header("Content-Length", str(len(payload)))
                    self.end_headers()
                    self.wfile.write(payload)
                except OSError:  # the client gave up (timeout tests)
                    pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def url(self, mode: str) -> str:
        return f"http://127.0.0.1:{self.port}/{mode}/v1"

    def last(self, mode: str) -> dict:
        return [r for r in self.requests if r["mode"] == mode][-1]

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


SECRET = "sk-test-SECRET-0123456789abcdef"  # the API key the clients under test send; it must never leak
KEY_ENV = "VIRSQUEEZER_TEST_LLM_KEY"  # the environment variable the clients read it from


def assert_no_secret(exc: BaseException) -> None:
    """The key appears nowhere in an error the client raised: not in its message, repr or traceback."""
    assert SECRET not in str(exc) + repr(exc) + "".join(traceback.format_exception(exc))
