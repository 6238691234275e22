"""Blocking HTTP for the LLM client (standard library only), and what each failure means.

Chat completions are streamed (``"stream": true``, server-sent events) so that
the client's timeout measures *silence*, not total time: urllib's socket
timeout applies to every read, and a streaming server sends tokens (and
llama.cpp-python keepalive comments) while it works.  A server that is slow
but alive is therefore never abandoned, and nothing it is still computing is
sent again.  A stream that closes without an event is asked once more
without streaming, where such a server reports its error.  `classify` decides which failures a retry can fix: a refused or
broken connection, HTTP 429 and 5xx; not a timeout (the server may still be
computing), not other 4xx (the same request fails the same way).
"""

from __future__ import annotations

import http.client
import json
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from typing import Any


class HTTPStatusError(Exception):
    """A non-2xx answer, with its body (one line, shortened) and Retry-After."""

    def __init__(self, status: int, body: str, retry_after: float | None = None):
        self.status, self.body, self.retry_after = status, one_line(body), retry_after
        super().__init__(f"HTTP {status}: {self.body}")


class BadReply(Exception):
    """A 2xx answer that is not what the endpoint should return (not JSON, no choices)."""


class EmptyStream(Exception):
    """A 200 stream that closed without one event.  llama-cpp-python does this when a
    prompt exceeds its context (the error is raised after the headers went out); asked
    without streaming, the same server answers with the HTTP error and its message."""


class StreamCut(ConnectionError):
    """The stream ended before ``[DONE]`` or a finish reason: the server stopped
    working on it (crash, restart, or llama-cpp-python's interrupt_requests)."""


def one_line(text: str, limit: int = 300) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _retry_after(headers: Any) -> float | None:
    value = headers.get("Retry-After") if headers is not None else None
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None


def open_url(method: str, url: str, body: dict | None, headers: dict[str, str],
             timeout_s: float) -> http.client.HTTPResponse:
    """urlopen that turns HTTP errors into `HTTPStatusError` (the caller closes)."""
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(url, data=data, method=method,
                                 headers={"Content-Type": "application/json", **headers})
    try:
        return urllib.request.urlopen(req, timeout=timeout_s)
    except urllib.error.HTTPError as err:
        text = err.read().decode("utf-8", errors="replace") if err.fp else ""
        raise HTTPStatusError(err.code, text, _retry_after(err.headers)) from None


def request_json(method: str, url: str, body: dict | None, headers: dict[str, str],
                 timeout_s: float) -> Any:
    with open_url(method, url, body, headers, timeout_s) as resp:
        raw = resp.read().decode("utf-8", errors="replace")
    try:
        return json.loads(raw)
    except json.JSONDecodeError:
        raise BadReply(f"{url} answered with non-JSON: {one_line(raw, 200)!r}") from None


@dataclass
class Reply:
    """One chat completion as received."""

    text: str
    finish_reason: str | None
    usage: dict | None
    first_token_s: float | None  # time to the first content token (streams only)
    streamed: bool


def _message_text(reply: Any) -> tuple[str, str | None]:
    try:
        choice = reply["choices"][0]
        text = choice["message"]["content"]
    except (KeyError, IndexError, TypeError) as err:
        raise BadReply(f"reply is not a chat completion ({type(err).__name__}: {err}): "
                       f"{one_line(json.dumps(reply), 200)}") from None
    if not isinstance(text, str):
        raise BadReply("reply content is not a string")
    return text, choice.get("finish_reason")


def chat(url: str, body: dict, headers: dict[str, str], timeout_s: float,
         stream: bool = True) -> Reply:
    """POST a chat completion, by default with ``stream: true``, collecting the deltas.

    `timeout_s` bounds each wait for bytes, so keepalive comments and tokens
    keep a long generation alive.  A server that ignores ``stream`` and answers
    plain JSON is accepted as well."""
    t0 = time.perf_counter()
    with open_url("POST", url, {**body, "stream": stream}, headers, timeout_s) as resp:
        if "text/event-stream" not in resp.headers.get("Content-Type", ""):
            raw = resp.read().decode("utf-8", errors="replace")
            try:
                reply = json.loads(raw)
            except json.JSONDecodeError:
                raise BadReply(f"{url} answered with non-JSON: {one_line(raw, 200)!r}") from None
            text, finish = _message_text(reply)
            return Reply(text, finish, reply.get("usage"), None, streamed=False)
        parts: list[str] = []
        finish, usage, first, done, events = None, None, None, False, 0
        for raw_line in resp:
            line = raw_line.decode("utf-8", errors="replace").strip()
            if not line.startswith("data:"):
                continue  # keepalive comments (": ping"), event:, id:, blank separators
            data = line[5:].strip()
            events += 1
            if data == "[DONE]":
                done = True
                break
            try:
                chunk = json.loads(data)
            except json.JSONDecodeError:
                raise BadReply(f"stream event is not JSON: {one_line(data, 200)!r}") from None
            if isinstance(chunk, dict) and chunk.get("error"):
                raise HTTPStatusError(500, f"error inside the stream: {json.dumps(chunk)}")
            usage = chunk.get("usage") or usage
            for choice in chunk.get("choices") or []:
                piece = (choice.get("delta") or {}).get("content")
                if piece:
                    if first is None:
                        first = time.perf_counter() - t0
                    parts.append(piece)
                finish = choice.get("finish_reason") or finish
    if events == 0:
        raise EmptyStream("the server closed the stream without sending anything")
    if finish is None:
        raise StreamCut("the stream ended before a finish reason" + (
            " (the server sent [DONE] early)" if done else " (connection closed)"))
    return Reply("".join(parts), finish, usage, first, streamed=True)


def classify(err: BaseException, timeout_s: float) -> tuple[str, str, bool]:
    """(cause, one-line message, whether a retry can fix it) for a failed request."""
    if isinstance(err, HTTPStatusError):
        return f"http_{err.status}", str(err), err.status == 429 or err.status >= 500
    reason = getattr(err, "reason", err) if isinstance(err, urllib.error.URLError) else err
    if isinstance(reason, TimeoutError):
        return ("timeout", f"no bytes from the server for {timeout_s:g} s (--llm-timeout); "
                           "not retried: the server may still be computing it", False)
    if isinstance(reason, (ConnectionError, OSError, http.client.HTTPException)):
        return "connection", f"{type(reason).__name__}: {one_line(str(reason))}", True
    if isinstance(err, EmptyStream):  # retried once without streaming (see ChatClient)
        return "empty_stream", str(err), True
    if isinstance(err, BadReply):
        return "bad_reply", one_line(str(err)), False
    return "error", f"{type(err).__name__}: {one_line(str(err))}", False
