"""OpenAI-compatible chat-completions client: asynchronous, bounded, retrying, cached.

One client serves vLLM, SGLang, llama.cpp's server, llama-cpp-python, Ollama
and hosted APIs (anything that speaks ``POST {url}/chat/completions``).
Requests run on a thread pool behind asyncio (the standard library only),
so hundreds of episodes can wait on the LLM while at most `concurrency`
requests are in flight: the server's slot count where it publishes one, else
``--llm-concurrency``, else a default for the kind of server.

Answers are streamed and the timeout is on silence (`http.chat`), so a
slow server is waited for, not abandoned and asked again.  Only failures a
retry can fix are retried (refused or broken connections, HTTP 429, 5xx);
every request's attempts and causes are recorded (`LLMStats`).  A request
that still fails becomes the episode outcome ``llm_error``.  `preflight()`
proves the endpoint with a 1-token completion before any simulation starts,
fixes the usual URL mistakes, and learns the server's kind, slots and
context length (`server.detect`).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import random
import threading
import time
from dataclasses import asdict, dataclass, field
from typing import Any

from agnostos_mjx.infra import settings
from agnostos_mjx.llm import server as srv
from agnostos_mjx.llm.cache import ResponseCache
from agnostos_mjx.llm.http import (
    BadReply,
    EmptyStream,
    HTTPStatusError,
    chat,
    classify,
    one_line,
    request_json,
)
from agnostos_mjx.llm.stats import LLMStats

log = logging.getLogger("agnostos_mjx.llm")

Messages = list[dict[str, str]]
DEFAULT_TIMEOUT_S = 300.0  # of silence; see --llm-timeout


class LLMError(Exception):
    """A request that failed for good (after its retries, or not retryable)."""


class LLMConfigError(LLMError):
    """The LLM cannot be used at all: unreachable server, bad key, unknown model."""


@dataclass(frozen=True)
class SamplingParams:
    """X-ICM's sampling settings by default (effectively greedy decoding)."""

    temperature: float = 0.1
    top_p: float = 0.001
    repetition_penalty: float = 1.05
    max_tokens: int = 256
    seed: int | None = 0


@dataclass(frozen=True)
class LLMConfig:
    url: str
    model: str
    api_key: str | None = None
    concurrency: int | None = None  # None: the server's slots, else a default for its kind
    timeout_s: float = DEFAULT_TIMEOUT_S  # seconds without a byte from the server
    server_kind: str = "auto"  # auto | vllm | llamacpp | openai (sampling field names)
    retries: int = 4
    backoff_s: float = 1.0
    max_backoff_s: float = 30.0
    sampling: SamplingParams = field(default_factory=SamplingParams)
    cache_dir: str | None = None

    @classmethod
    def from_env(cls, url: str | None = None, model: str | None = None, **kwargs: Any
                 ) -> LLMConfig | None:
        """Flags first, then AGNOSTOS_LLM_URL / AGNOSTOS_LLM_MODEL; the key from
        AGNOSTOS_LLM_API_KEY or OPENAI_API_KEY.  None when no URL is configured."""
        url = url or settings.LLM_URL.get()
        if not url:
            return None
        model = model or settings.LLM_MODEL.get()
        if not model:
            raise LLMConfigError(f"an LLM URL is set ({url}) but no model: pass --llm-model "
                                 "or set AGNOSTOS_LLM_MODEL")
        key = settings.LLM_API_KEY.get() or os.environ.get("OPENAI_API_KEY")
        return cls(url=url.rstrip("/"), model=model, api_key=key, **kwargs)


@dataclass
class Completion:
    """One answer: the text, or the error (and its cause) that ended its request."""

    text: str | None
    error: str | None = None
    cached: bool = False
    attempts: int = 0
    latency_s: float = 0.0
    cause: str | None = None
    finish_reason: str | None = None


class ChatClient:
    """Chat completions against one OpenAI-compatible server."""

    def __init__(self, config: LLMConfig):
        self.config = config
        self.cache = ResponseCache(config.cache_dir) if config.cache_dir else None
        base, notes = srv.normalise_url(config.url)
        # Until preflight() learns better: the kind given, else vLLM's field names.
        kind = "vllm" if config.server_kind == "auto" else config.server_kind
        self.server = srv.ServerInfo(url=base, kind=kind, notes=notes)
        self.concurrency = srv.resolve_concurrency(self.server, config.concurrency)
        self._pool: concurrent.futures.ThreadPoolExecutor | None = None
        self._pool_lock = threading.Lock()
        # Runs whole batches in the background (submit_batch); the requests themselves
        # share the bounded pool.
        self._batches = concurrent.futures.ThreadPoolExecutor(max_workers=8,
                                                              thread_name_prefix="llm-batch")
        self.stats = LLMStats()

    @property
    def url(self) -> str:
        return self.server.url

    @property
    def context_length(self) -> int | None:
        return self.server.context

    @property
    def sampling_sent(self) -> dict[str, Any]:
        """The sampling fields every request carries, under the server's names."""
        s = self.config.sampling
        return srv.sampling_fields(self.server.kind, s.temperature, s.top_p,
                                   s.repetition_penalty, s.max_tokens, s.seed)

    def _headers(self) -> dict[str, str]:
        key = self.config.api_key
        return {"Authorization": f"Bearer {key}"} if key else {}

    def _get(self, url: str) -> Any:
        return request_json("GET", url, None, self._headers(), self.config.timeout_s)

    def _post(self, url: str, body: dict) -> Any:
        return request_json("POST", url, body, self._headers(), self.config.timeout_s)

    def payload(self, messages: Messages) -> dict:
        return {"model": self.config.model, "messages": messages, **self.sampling_sent}

    def _pool_for_requests(self) -> concurrent.futures.ThreadPoolExecutor:
        with self._pool_lock:  # made on first use, after preflight() set the concurrency
            if self._pool is None:
                self._pool = concurrent.futures.ThreadPoolExecutor(
                    max_workers=self.concurrency, thread_name_prefix="llm")
            return self._pool

    # ---- one request (blocking, runs on the pool) ----------------------------------------
    def _backoff(self, attempt: int, retry_after: float | None) -> None:
        cfg = self.config
        if retry_after is not None:
            time.sleep(retry_after)
        else:
            time.sleep(min(cfg.max_backoff_s, cfg.backoff_s * 2 ** attempt)
                       * (0.5 + random.random() / 2))

    def _complete_blocking(self, messages: Messages, number: int) -> Completion:
        cfg = self.config
        t0 = time.perf_counter()
        causes: list[str] = []
        record: dict[str, Any] = {"prompt_chars": sum(len(m["content"]) for m in messages)}
        stream = True
        for attempt in range(cfg.retries + 1):
            try:
                reply = chat(self.url + "/chat/completions", self.payload(messages),
                             self._headers(), cfg.timeout_s, stream=stream)
            except Exception as err:  # noqa: BLE001 - classified, recorded, never lost
                cause, message, retryable = classify(err, cfg.timeout_s)
                causes.append(cause)
                if isinstance(err, EmptyStream):
                    retryable, stream = stream, False  # once more, unstreamed: the real error
                if self.stats.error_seen(cause, message):
                    log.warning("LLM request failed (%s%s): %s", cause,
                                ", will retry" if retryable and attempt < cfg.retries else "",
                                message)
                    if cause == "http_400" and "context" in message:
                        log.warning("%s", srv.context_advice(srv.context_from_error(message)))
                if not retryable or attempt == cfg.retries:
                    break
                self.stats.retried(cause)
                if cause != "empty_stream":
                    self._backoff(attempt, getattr(err, "retry_after", None))
                continue
            latency = time.perf_counter() - t0
            self.stats.finish(number, {
                **record, "ok": True, "attempts": attempt + 1, "causes": causes, "stream": stream,
                "latency_s": round(latency, 3), "first_token_s": None if reply.first_token_s
                is None else round(reply.first_token_s, 3), "finish_reason": reply.finish_reason,
                "usage": reply.usage})
            return Completion(reply.text, attempts=attempt + 1, latency_s=latency,
                              finish_reason=reply.finish_reason)
        latency = time.perf_counter() - t0
        self.stats.finish(number, {**record, "ok": False, "attempts": len(causes),
                                   "causes": causes, "cause": causes[-1], "error": message,
                                   "latency_s": round(latency, 3)})
        return Completion(None, error=message, attempts=len(causes), latency_s=latency,
                          cause=causes[-1])

    # ---- async API ------------------------------------------------------------------------
    async def complete(self, messages: Messages) -> Completion:
        """One chat completion (from the cache when this exact request was answered)."""
        number = self.stats.next_number()
        key = None
        if self.cache is not None:
            key = self.cache.key(self.config.model, messages, asdict(self.config.sampling))
            hit = self.cache.get(key)
            if hit is not None:
                self.stats.finish(number, {"ok": True, "cached": True})
                return Completion(hit, cached=True)
        loop = asyncio.get_running_loop()
        result = await loop.run_in_executor(self._pool_for_requests(), self._complete_blocking,
                                            messages, number)
        if key is not None and result.text is not None:
            self.cache.put(key, result.text)
        return result

    async def complete_many(self, batch: list[Messages]) -> list[Completion]:
        return list(await asyncio.gather(*(self.complete(m) for m in batch)))

    def complete_batch(self, batch: list[Messages]) -> list[Completion]:
        """Blocking helper: all requests in flight at once (bounded by the pool)."""
        return asyncio.run(self.complete_many(batch))

    def submit_batch(self, batch: list[Messages]) -> concurrent.futures.Future:
        """`complete_batch` in the background: the evaluator simulates other tasks while
        this batch waits on the server (the future's result is the list of Completions)."""
        return self._batches.submit(self.complete_batch, batch)

    # ---- start-up check ---------------------------------------------------------------------
    def preflight(self) -> srv.ServerInfo:
        """Prove the endpoint before any simulation: find the API base (the given URL,
        else with /v1 added), check key and model, complete one token, then learn the
        server's kind, slots and context length.  Raises LLMConfigError with one line."""
        cfg = self.config
        given, notes = self.server.url, list(self.server.notes)
        tried = []
        for base in srv.base_candidates(given):
            tried.append(base)
            listing = self._listing(base)
            try:
                self._probe(base, listing)
            except HTTPStatusError as err:
                if err.status == 404 and listing is None:
                    continue  # no API here; try the next form of the URL
                raise LLMConfigError(self._explain(err, base)) from None
            break
        else:
            raise LLMConfigError(
                f"no OpenAI-compatible API at {cfg.url}: {' and '.join(tried)} answered HTTP "
                "404 to /models and /chat/completions; pass the API base, e.g. "
                "http://HOST:PORT/v1")
        if base != given:
            notes.append(f"added /v1 to the URL (nothing answered at {given})")
        info = srv.detect(base, listing, self._get)
        info.notes = notes + info.notes
        srv.resolve_kind(info, cfg.server_kind)
        self.server = info
        self.concurrency = srv.resolve_concurrency(info, cfg.concurrency)
        for note in info.notes:  # a corrected URL is worth fixing in the command line
            log.log(logging.WARNING if "URL" in note else logging.INFO, "LLM: %s", note)
        log.info("LLM: %s at %s (kind %s, by %s); %d request(s) at a time%s; sending %s",
                 info.software, info.url, info.kind, info.detected_by, self.concurrency,
                 f"; context {info.context} tokens" if info.context else "",
                 ", ".join(f"{k}={v}" for k, v in self.sampling_sent.items()))
        return info

    def _listing(self, base: str) -> dict | None:
        """GET /models: the served models, or None where the server has no such route."""
        cfg = self.config
        try:
            listing = self._get(base + "/models")
        except HTTPStatusError as err:
            if err.status == 404:
                return None
            raise LLMConfigError(self._explain(err, base)) from None
        except OSError as err:
            raise LLMConfigError(f"LLM server {cfg.url} is unreachable "
                                 f"({one_line(str(getattr(err, 'reason', err)))})") from None
        except BadReply:
            return None  # e.g. an HTML page: not the API base
        if not isinstance(listing, dict):
            return None
        served = [str(m.get("id")) for m in listing.get("data", []) if isinstance(m, dict)]
        if served and cfg.model not in served:
            raise LLMConfigError(f"{base} does not serve model {cfg.model!r}; it serves "
                                 f"{', '.join(served)} (--llm-model)")
        return listing

    def _probe(self, base: str, listing: dict | None) -> None:
        """One streamed 1-token completion; transient failures are retried like any request."""
        cfg = self.config
        body = {"model": cfg.model, "max_tokens": 1,
                "messages": [{"role": "user", "content": "Say OK."}]}
        stream = True
        for attempt in range(cfg.retries + 1):
            try:
                chat(base + "/chat/completions", body, self._headers(), cfg.timeout_s, stream)
                return
            except HTTPStatusError as err:
                if not (err.status == 429 or err.status >= 500) or attempt == cfg.retries:
                    raise
                self._backoff(attempt, err.retry_after)
            except (OSError, BadReply, EmptyStream) as err:
                cause, message, retryable = classify(err, cfg.timeout_s)
                if isinstance(err, EmptyStream):
                    retryable, stream = stream, False
                if not retryable or attempt == cfg.retries:
                    raise LLMConfigError(f"the test request to {base}/chat/completions "
                                         f"failed ({cause}): {message}") from None
                self._backoff(attempt, None)

    def _explain(self, err: HTTPStatusError, base: str) -> str:
        cfg = self.config
        if err.status in (401, 403):
            return (f"{base} rejected the API key (HTTP {err.status}); set "
                    "AGNOSTOS_LLM_API_KEY or OPENAI_API_KEY")
        if err.status == 404:
            return (f"{base}/chat/completions answered HTTP 404 for model {cfg.model!r} "
                    f"(--llm-model): {err.body}")
        return (f"the test request (model {cfg.model!r}, 1 token) to {base}/chat/completions "
                f"failed: {err}")

    # ---- context ------------------------------------------------------------------------------
    def count_tokens(self, messages: Messages) -> tuple[int, str]:
        """Prompt tokens (the server's tokenizer where it has one, else an estimate)."""
        return srv.count_tokens(self.server, self.config.model, messages, self._post)

    def report(self) -> dict[str, Any]:
        """For results.json: the server, what was sent, and every request."""
        return {"server": asdict(self.server), "concurrency": self.concurrency,
                "timeout_s": self.config.timeout_s, "retries_allowed": self.config.retries,
                "sampling_sent": self.sampling_sent, **self.stats.as_dict()}

    def close(self) -> None:
        self._batches.shutdown(wait=False, cancel_futures=True)
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
