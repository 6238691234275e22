"""OpenAI-compatible chat-completions client: asynchronous, bounded, retrying, cached.

One client serves vLLM, SGLang, llama.cpp's server, Ollama and hosted APIs
(anything that speaks ``POST {url}/chat/completions``).  Requests run on a
thread pool behind an asyncio semaphore (the standard library only, no
extra dependency), so hundreds of episodes can wait on the LLM at once while
at most `concurrency` requests are in flight.

Failures: timeouts, HTTP 429 and 5xx and broken connections are retried with
exponential backoff (honouring ``Retry-After``); anything else (400, 401,
404, a reply that is not chat-completions JSON) fails at once.  A request
that still fails raises `LLMError`, which the X-ICM policy turns into the
episode outcome ``llm_error``.  `preflight()` checks the server, the key and
the model name once, before any simulation starts.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import json
import logging
import os
import random
import time
import urllib.error
import urllib.request
from dataclasses import asdict, dataclass, field
from typing import Any

from agnostos_mjx.llm.cache import ResponseCache

log = logging.getLogger("agnostos_mjx.llm")

Messages = list[dict[str, str]]
RETRY_STATUS = frozenset({408, 409, 429, 500, 502, 503, 504})


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
    concurrency: int = 64
    timeout_s: float = 60.0
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
        url = url or os.environ.get("AGNOSTOS_LLM_URL")
        if not url:
            return None
        model = model or os.environ.get("AGNOSTOS_LLM_MODEL")
        if not model:
            raise LLMConfigError(f"an LLM URL is set ({url}) but no model: pass --llm-model "
                                 "or set AGNOSTOS_LLM_MODEL")
        key = os.environ.get("AGNOSTOS_LLM_API_KEY") or os.environ.get("OPENAI_API_KEY")
        return cls(url=url.rstrip("/"), model=model, api_key=key, **kwargs)


@dataclass
class Completion:
    """One answer: the text, or the error that ended its request."""

    text: str | None
    error: str | None = None
    cached: bool = False
    attempts: int = 0
    latency_s: float = 0.0


class _HTTPStatus(Exception):
    def __init__(self, status: int, body: str, retry_after: float | None):
        super().__init__(f"HTTP {status}: {body[:200]}")
        self.status, self.retry_after = status, retry_after


def _retry_after(headers) -> float | None:
    value = headers.get("Retry-After") if headers is not None else None
    try:
        return max(0.0, float(value)) if value is not None else None
    except ValueError:
        return None


class ChatClient:
    """Chat completions against one OpenAI-compatible server."""

    def __init__(self, config: LLMConfig):
        self.config = config
        self.cache = ResponseCache(config.cache_dir) if config.cache_dir else None
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=config.concurrency,
                                                           thread_name_prefix="llm")
        # Runs whole batches in the background (submit_batch); the requests themselves
        # still share the bounded pool above.
        self._batches = concurrent.futures.ThreadPoolExecutor(max_workers=8,
                                                              thread_name_prefix="llm-batch")
        self.stats = {"requests": 0, "cache_hits": 0, "retries": 0, "failures": 0}

    # ---- HTTP (blocking, runs on the pool) --------------------------------------------
    def _http(self, method: str, path: str, body: dict | None = None) -> dict:
        headers = {"Content-Type": "application/json"}
        if self.config.api_key:
            headers["Authorization"] = f"Bearer {self.config.api_key}"
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.config.url + path, data=data, headers=headers,
                                     method=method)
        try:
            with urllib.request.urlopen(req, timeout=self.config.timeout_s) as resp:
                raw = resp.read().decode("utf-8", errors="replace")
        except urllib.error.HTTPError as err:
            body_text = err.read().decode("utf-8", errors="replace") if err.fp else ""
            raise _HTTPStatus(err.code, body_text, _retry_after(err.headers)) from None
        try:
            return json.loads(raw)
        except json.JSONDecodeError:
            raise LLMError(f"{self.config.url}{path} answered with non-JSON: {raw[:200]!r}") from None

    def payload(self, messages: Messages) -> dict:
        s = self.config.sampling
        body = {"model": self.config.model, "messages": messages, "temperature": s.temperature,
                "top_p": s.top_p, "max_tokens": s.max_tokens}
        if s.repetition_penalty != 1.0:
            body["repetition_penalty"] = s.repetition_penalty  # vLLM/SGLang extension
        if s.seed is not None:
            body["seed"] = s.seed
        return body

    def _complete_blocking(self, messages: Messages) -> Completion:
        cfg = self.config
        t0 = time.perf_counter()
        last = "no attempt"
        for attempt in range(cfg.retries + 1):
            wait = None
            try:
                reply = self._http("POST", "/chat/completions", self.payload(messages))
                text = reply["choices"][0]["message"]["content"]
                if not isinstance(text, str):
                    raise TypeError("content is not a string")
                return Completion(text, attempts=attempt + 1, latency_s=time.perf_counter() - t0)
            except _HTTPStatus as err:
                last = str(err)
                if err.status not in RETRY_STATUS:
                    break
                wait = err.retry_after
            except (urllib.error.URLError, TimeoutError, ConnectionError) as err:
                last = f"{type(err).__name__}: {getattr(err, 'reason', err)}"
            except (KeyError, IndexError, TypeError) as err:
                last = f"reply is not a chat completion ({type(err).__name__}: {err})"
                break
            except LLMError as err:
                last = str(err)
                break
            if attempt < cfg.retries:
                self.stats["retries"] += 1
                backoff = min(cfg.max_backoff_s, cfg.backoff_s * 2 ** attempt)
                time.sleep(wait if wait is not None else backoff * (0.5 + random.random() / 2))
        self.stats["failures"] += 1
        return Completion(None, error=last, attempts=attempt + 1,
                          latency_s=time.perf_counter() - t0)

    # ---- async API ------------------------------------------------------------------------
    async def complete(self, messages: Messages) -> Completion:
        """One chat completion (from the cache when this exact request was answered)."""
        self.stats["requests"] += 1
        key = None
        if self.cache is not None:
            key = self.cache.key(self.config.model, messages, asdict(self.config.sampling))
            hit = self.cache.get(key)
            if hit is not None:
                self.stats["cache_hits"] += 1
                return Completion(hit, cached=True)
        loop = asyncio.get_running_loop()
        result = await loop.run_in_executor(self._pool, self._complete_blocking, messages)
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

    def preflight(self) -> None:
        """Fail early and clearly: server reachable, key accepted, model served."""
        cfg = self.config
        try:
            listing = self._http("GET", "/models")
        except _HTTPStatus as err:
            if err.status in (401, 403):
                raise LLMConfigError(
                    f"{cfg.url} rejected the API key (HTTP {err.status}); set "
                    "AGNOSTOS_LLM_API_KEY or OPENAI_API_KEY") from None
            if err.status == 404:
                return  # some servers have no /models; the first request will tell
            raise LLMConfigError(f"{cfg.url}/models failed: {err}") from None
        except (urllib.error.URLError, TimeoutError, ConnectionError) as err:
            raise LLMConfigError(f"LLM server {cfg.url} is unreachable "
                                 f"({getattr(err, 'reason', err)})") from None
        except LLMError as err:
            raise LLMConfigError(str(err)) from None
        served = [m.get("id") for m in listing.get("data", []) if isinstance(m, dict)]
        if served and cfg.model not in served:
            raise LLMConfigError(f"{cfg.url} does not serve model {cfg.model!r}; it serves "
                                 f"{', '.join(map(str, served))}")

    def close(self) -> None:
        self._batches.shutdown(wait=False, cancel_futures=True)
        self._pool.shutdown(wait=False, cancel_futures=True)
