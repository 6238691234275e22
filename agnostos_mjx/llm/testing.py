"""A scripted OpenAI-compatible server on loopback, for tests and benchmarks.

It answers ``GET /models`` and ``POST /chat/completions`` with text from a
`responder(messages) -> str`, after `latency_s`, and can inject faults:
a `faults` callable gets the request number (0-based, over the server's
life) and the messages and returns None or one of ``"timeout"`` (sleep past
the client's timeout), ``"500"``, ``"429"`` (with Retry-After), ``"bad_json"``
(a 200 reply that is not JSON), ``"no_choices"``.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

Responder = Callable[[list[dict]], str]
Faults = Callable[[int, list[dict]], str | None]


class _Server(ThreadingHTTPServer):
    request_queue_size = 256  # many clients connect at once


class ScriptedLLMServer:
    def __init__(self, responder: Responder, model: str = "scripted", latency_s: float = 0.0,
                 faults: Faults | None = None, api_key: str | None = None,
                 hang_s: float = 5.0, retry_after_s: float = 0.05):
        self.responder, self.model, self.latency_s = responder, model, latency_s
        self.faults, self.api_key, self.hang_s = faults, api_key, hang_s
        self.retry_after_s = retry_after_s
        self.requests: list[dict] = []
        # (arrival, answered) monotonic times per request number: shows what overlapped
        self.times: dict[int, tuple[float, float]] = {}
        self._lock = threading.Lock()
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args) -> None:  # keep test output clean
                pass

            def _send(self, status: int, body: bytes, headers: dict | None = None) -> None:
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                for k, v in (headers or {}).items():
                    self.send_header(k, v)
                self.end_headers()
                self.wfile.write(body)

            def _authorised(self) -> bool:
                if server.api_key is None:
                    return True
                if self.headers.get("Authorization") == f"Bearer {server.api_key}":
                    return True
                self._send(401, b'{"error": "bad key"}')
                return False

            def do_GET(self) -> None:  # noqa: N802
                if not self._authorised():
                    return
                if self.path.rstrip("/").endswith("/models"):
                    body = {"object": "list", "data": [{"id": server.model, "object": "model"}]}
                    self._send(200, json.dumps(body).encode())
                else:
                    self._send(404, b'{"error": "not found"}')

            def do_POST(self) -> None:  # noqa: N802
                length = int(self.headers.get("Content-Length", 0))
                payload = json.loads(self.rfile.read(length) or b"{}")
                if not self._authorised():
                    return
                arrival = time.monotonic()
                with server._lock:
                    number = len(server.requests)
                    server.requests.append(payload)
                try:
                    self._answer(number, payload)
                finally:
                    server.times[number] = (arrival, time.monotonic())

            def _answer(self, number: int, payload: dict) -> None:
                messages = payload.get("messages", [])
                fault = server.faults(number, messages) if server.faults else None
                time.sleep(server.latency_s)
                if payload.get("model") != server.model:
                    self._send(404, json.dumps({"error": f"model {payload.get('model')!r} "
                                                         "not found"}).encode())
                elif fault == "timeout":
                    time.sleep(server.hang_s)
                    self._send(200, b"{}")
                elif fault == "500":
                    self._send(500, b'{"error": "internal"}')
                elif fault == "429":
                    self._send(429, b'{"error": "slow down"}',
                               {"Retry-After": f"{server.retry_after_s}"})
                elif fault == "bad_json":
                    self._send(200, b"<html>proxy error</html>")
                elif fault == "no_choices":
                    self._send(200, b'{"choices": []}')
                else:
                    try:
                        text = server.responder(messages)
                    except Exception as err:  # a broken script is a server error, visibly
                        self._send(500, json.dumps({"error": repr(err)}).encode())
                        return
                    body = {"id": f"cmpl-{number}", "object": "chat.completion",
                            "model": server.model,
                            "choices": [{"index": 0, "finish_reason": "stop",
                                         "message": {"role": "assistant", "content": text}}]}
                    self._send(200, json.dumps(body).encode())

        self._httpd = _Server(("127.0.0.1", 0), Handler)
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, daemon=True)

    @property
    def url(self) -> str:
        host, port = self._httpd.server_address[:2]
        return f"http://{host}:{port}/v1"

    def __enter__(self) -> ScriptedLLMServer:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()
