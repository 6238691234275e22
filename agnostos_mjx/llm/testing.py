"""A scripted OpenAI-compatible server on loopback, for tests and benchmarks.

It answers ``GET /v1/models`` and ``POST /v1/chat/completions`` (plain JSON
or, with ``"stream": true``, server-sent events) with text from a
`responder(messages) -> str`, and 404 at every other path.  It can pose as
a kind of server (`kind`): ``"vllm"`` (``/version``, ``owned_by: vllm``,
``max_model_len``, ``/tokenize``; honours ``repetition_penalty``),
``"llamacpp"`` (``/props`` with ``total_slots`` and ``n_ctx``, ``/tokenize``;
honours ``repeat_penalty``, default 1.1), ``"llama-cpp-python"`` (one slot,
``/openapi.json`` with ``/extras`` routes, publishes no context) or
``"openai"`` (publishes nothing; no penalty).

Behaviour of a slow server: at most `slots` requests are computed at once
(the others wait without a byte); each takes `latency_s`, during which a
stream sends a keepalive comment every `keepalive_s` (None: silence).  A
request is computed to its end even when its client has left, as real
servers do, so `computed` shows work done twice.  `context` (tokens, one
token per 4 characters) makes longer prompts fail with llama-cpp-python's
HTTP 400; a ``llama-cpp-python`` server, like the real one, answers such a
prompt in a stream with an empty 200 stream.

Faults: a `faults` callable gets the request number (0-based over the
server's life, not counting 1-token start-up probes) and the messages and
returns None or one of ``"timeout"`` (silence for `hang_s`, then the answer),
``"500"``, ``"429"`` (with Retry-After), ``"reset"`` (close the connection),
``"cut"`` (a stream that ends without a finish reason), ``"bad_json"`` (a 200
reply that is not JSON), ``"no_choices"``.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

Responder = Callable[[list[dict]], str]
Faults = Callable[[int, list[dict]], str | None]
KINDS = ("openai", "vllm", "llamacpp", "llama-cpp-python")
PENALTY = {"vllm": ("repetition_penalty", 1.0), "llamacpp": ("repeat_penalty", 1.1),
           "llama-cpp-python": ("repeat_penalty", 1.1), "openai": (None, 1.0)}


class _Server(ThreadingHTTPServer):
    request_queue_size = 256  # many clients connect at once


def count_tokens(messages: list[dict]) -> int:
    """The loopback server's 'tokenizer': 4 characters a token, 8 per message of template."""
    return sum(math.ceil(len(m.get("content", "")) / 4) + 8 for m in messages)


class ScriptedLLMServer:
    def __init__(self, responder: Responder, model: str = "scripted", latency_s: float = 0.0,
                 faults: Faults | None = None, api_key: str | None = None,
                 hang_s: float = 5.0, retry_after_s: float = 0.05, kind: str = "openai",
                 slots: int | None = None, keepalive_s: float | None = None,
                 context: int | None = None):
        if kind not in KINDS:
            raise ValueError(f"kind {kind!r}: expected one of {KINDS}")
        self.responder, self.model, self.latency_s = responder, model, latency_s
        self.faults, self.api_key, self.hang_s = faults, api_key, hang_s
        self.retry_after_s, self.kind, self.keepalive_s = retry_after_s, kind, keepalive_s
        self.slots = 1 if kind == "llama-cpp-python" and slots is None else slots
        self.context = context
        self.requests: list[dict] = []  # chat-completion payloads, in arrival order
        self.probes: list[dict] = []  # the client's 1-token start-up checks
        self.paths: list[tuple[str, str]] = []  # (method, path) of every request
        self.computed: list[str] = []  # last message of every generation computed
        self.penalty_used: list[float] = []  # the repetition penalty each generation used
        # (arrival, answered) monotonic times per request number: shows what overlapped
        self.times: dict[int, tuple[float, float]] = {}
        self.running = 0
        self.max_running = 0  # most generations computed at once
        self._lock = threading.Lock()
        self._slots = threading.Semaphore(self.slots) if self.slots else None
        self._httpd = _Server(("127.0.0.1", 0), self._handler())
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

    # ---- what the server publishes ------------------------------------------------------
    def _get_routes(self) -> dict[str, Callable[[], dict]]:
        entry = {"id": self.model, "object": "model",
                 "owned_by": {"vllm": "vllm", "llamacpp": "llamacpp",
                              "llama-cpp-python": "me"}.get(self.kind, "system")}
        if self.kind == "vllm" and self.context:
            entry["max_model_len"] = self.context
        routes = {"/v1/models": lambda: {"object": "list", "data": [entry]}}
        if self.kind == "llamacpp":
            routes["/props"] = lambda: {"total_slots": self.slots or 1,
                                        "default_generation_settings": {"n_ctx": self.context}}
        if self.kind == "vllm":
            routes["/version"] = lambda: {"version": "0.8.5.post1"}
        if self.kind == "llama-cpp-python":
            routes["/openapi.json"] = lambda: {"paths": {"/v1/chat/completions": {},
                                                         "/extras/tokenize/count": {}}}
        return routes

    def _tokenize(self, path: str, payload: dict) -> dict | None:
        if self.kind in ("llamacpp", "vllm") and path == "/tokenize":
            if "messages" in payload:
                n = count_tokens(payload["messages"])
                return {"count": n, "max_model_len": self.context, "tokens": list(range(n))}
            return {"tokens": list(range(math.ceil(len(payload.get("content", "")) / 4)))}
        if self.kind == "llama-cpp-python" and path == "/extras/tokenize/count":
            return {"count": math.ceil(len(payload.get("input", "")) / 4)}
        return None

    # ---- HTTP ---------------------------------------------------------------------------
    def _handler(self) -> type[BaseHTTPRequestHandler]:
        server = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args) -> None:  # keep test output clean
                pass

            def _send(self, status: int, body: bytes | dict, headers: dict | None = None) -> None:
                if isinstance(body, dict):
                    body = json.dumps(body).encode()
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
                self._send(401, {"error": "bad key"})
                return False

            def do_GET(self) -> None:  # noqa: N802
                server.paths.append(("GET", self.path))
                if not self._authorised():
                    return
                route = server._get_routes().get(self.path.rstrip("/"))
                if route is None:
                    self._send(404, {"error": "not found"})
                else:
                    self._send(200, route())

            def do_POST(self) -> None:  # noqa: N802
                server.paths.append(("POST", self.path))
                length = int(self.headers.get("Content-Length", 0))
                payload = json.loads(self.rfile.read(length) or b"{}")
                if not self._authorised():
                    return
                path = self.path.rstrip("/")
                if path != "/v1/chat/completions":
                    answer = server._tokenize(path, payload)
                    self._send(*((200, answer) if answer is not None else
                                 (404, {"error": "not found"})))
                    return
                if payload.get("max_tokens") == 1:  # the start-up probe
                    server.probes.append(payload)
                    self._answer(-1, payload)
                    return
                arrival = time.monotonic()
                with server._lock:
                    number = len(server.requests)
                    server.requests.append(payload)
                try:
                    self._answer(number, payload)
                except (BrokenPipeError, ConnectionResetError):
                    pass  # the client left; the work was done anyway (see computed)
                finally:
                    server.times[number] = (arrival, time.monotonic())

            def _answer(self, number: int, payload: dict) -> None:
                messages = payload.get("messages", [])
                if payload.get("model") != server.model and server.kind in ("vllm", "openai"):
                    self._send(404, {"error": {"message": f"The model `{payload.get('model')}` "
                                                          "does not exist."}})
                    return
                fault = server.faults(number, messages) if server.faults and number >= 0 \
                    else None
                tokens = count_tokens(messages) + int(payload.get("max_tokens") or 0)
                stream = bool(payload.get("stream"))
                if server.context and tokens > server.context and stream \
                        and server.kind == "llama-cpp-python":
                    self._start_stream()  # the error is raised after the headers went out
                    self._chunk(b"")
                    return
                if server.context and tokens > server.context:
                    self._send(400, {"error": {"message": (
                        f"This model's maximum context length is {server.context} tokens, "
                        f"however you requested {tokens} tokens. Please reduce your prompt."),
                        "type": "invalid_request_error"}})
                    return
                if fault in ("500", "429", "bad_json", "no_choices", "reset"):
                    self._fault(fault)
                    return
                if fault == "timeout":
                    time.sleep(server.hang_s)
                if server._slots is not None:
                    server._slots.acquire()  # queued: not a byte until a slot is free
                try:
                    self._generate(number, payload, stream, cut=fault == "cut")
                finally:
                    if server._slots is not None:
                        server._slots.release()

            def _fault(self, fault: str) -> None:
                if fault == "500":
                    self._send(500, {"error": "internal"})
                elif fault == "429":
                    self._send(429, {"error": "slow down"},
                               {"Retry-After": f"{server.retry_after_s}"})
                elif fault == "bad_json":
                    self._send(200, b"<html>proxy error</html>")
                elif fault == "no_choices":
                    self._send(200, {"choices": []})
                else:  # reset: drop the connection without a reply
                    self.close_connection = True
                    self.connection.shutdown(2)

            def _generate(self, number: int, payload: dict, stream: bool, cut: bool) -> None:
                with server._lock:
                    server.running += 1
                    server.max_running = max(server.max_running, server.running)
                try:
                    if stream:
                        self._start_stream()
                    self._compute(stream)
                    text = self._text(payload) if number >= 0 else "OK"  # probe: any text
                finally:
                    with server._lock:
                        server.running -= 1
                if number >= 0:
                    with server._lock:
                        server.computed.append(payload["messages"][-1]["content"])
                        name, default = PENALTY[server.kind]
                        server.penalty_used.append(payload.get(name, default) if name
                                                   else default)
                if text is None and not stream:
                    self._send(500, {"error": "the responder raised"})
                elif text is None:
                    self._event({"error": {"message": "the responder raised"}})
                    self._chunk(b"")
                elif not stream:
                    self._send(200, {"id": f"cmpl-{number}", "object": "chat.completion",
                                     "model": server.model,
                                     "choices": [{"index": 0, "finish_reason": "stop",
                                                  "message": {"role": "assistant",
                                                              "content": text}}]})
                else:
                    half = len(text) // 2
                    for piece in (text[:half], text[half:]):
                        self._event({"choices": [{"index": 0, "delta": {"content": piece},
                                                  "finish_reason": None}]})
                    if not cut:
                        self._event({"choices": [{"index": 0, "delta": {},
                                                  "finish_reason": "stop"}]})
                    self._chunk(b"data: [DONE]\n\n")
                    self._chunk(b"")

            def _compute(self, stream: bool) -> None:
                """latency_s of work; a stream gets keepalive comments meanwhile."""
                end = time.monotonic() + server.latency_s
                while (left := end - time.monotonic()) > 0:
                    if stream and server.keepalive_s:
                        time.sleep(min(left, server.keepalive_s))
                        self._chunk(b": keepalive\n\n")
                    else:
                        time.sleep(left)

            def _text(self, payload: dict) -> str | None:
                try:
                    return server.responder(payload.get("messages", []))
                except Exception:  # a broken script is a server error, visibly
                    return None

            def _start_stream(self) -> None:
                self.send_response(200)
                self.send_header("Content-Type", "text/event-stream")
                self.send_header("Transfer-Encoding", "chunked")
                self.end_headers()

            def _event(self, data: dict) -> None:
                self._chunk(b"data: " + json.dumps(data).encode() + b"\n\n")

            def _chunk(self, data: bytes) -> None:
                try:
                    self.wfile.write(f"{len(data):x}\r\n".encode() + data + b"\r\n")
                    self.wfile.flush()
                except OSError:
                    pass  # the client left; the server works on regardless

        return Handler
