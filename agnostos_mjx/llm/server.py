"""What kind of OpenAI-compatible server is behind a URL, and what it can take.

Servers differ in ways that matter to X-ICM: the name of the repetition
penalty they honour (vLLM/SGLang ``repetition_penalty``, llama.cpp
``repeat_penalty``; plain OpenAI has neither and rejects unknown fields),
how many requests they compute at once (llama.cpp publishes its slots,
llama-cpp-python computes one and cuts a stream short when another request
waits), their context length, and whether they tokenize.  `detect` reads what
each publishes; nothing here sends a generation request.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from agnostos_mjx.llm.http import BadReply, HTTPStatusError

KINDS = ("auto", "vllm", "llamacpp", "openai")
PENALTY_FIELD = {"vllm": "repetition_penalty", "llamacpp": "repeat_penalty", "openai": None}
# Requests in flight when the server publishes no slot count: vLLM batches continuously on
# a GPU; an unknown OpenAI-compatible server gets a moderate number.
DEFAULT_CONCURRENCY = {"vllm": 64, "llamacpp": 1, "openai": 8}
CHARS_PER_TOKEN = 3  # conservative estimate when the server cannot tokenize
ENDPOINT_SUFFIXES = ("/chat/completions", "/completions", "/models")
CONTEXT_RE = re.compile(r"context (?:length|window|size)\D{0,12}(\d+)", re.I)

GetJSON = Callable[[str], Any]  # url -> JSON (raises HTTPStatusError, OSError, BadReply)
PostJSON = Callable[[str, dict], Any]


@dataclass
class ServerInfo:
    """What the start-up check learned; recorded in results.json."""

    url: str
    kind: str  # vllm | llamacpp | openai: decides the sampling field names
    software: str = "unknown OpenAI-compatible server"
    detected_by: str = "nothing recognisable"
    slots: int | None = None  # requests it computes at once, where published
    context: int | None = None  # tokens per request, where published
    tokenizer: str | None = None  # vllm | llamacpp | llama-cpp-python
    models: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def normalise_url(url: str) -> tuple[str, list[str]]:
    """The API base for a URL as people paste it: a trailing endpoint path such as
    ``/v1/chat/completions`` is dropped (and said)."""
    base, notes = url.strip().rstrip("/"), []
    for suffix in ENDPOINT_SUFFIXES:
        if base.endswith(suffix):
            base = base[:-len(suffix)].rstrip("/")
            notes.append(f"dropped {suffix} from the URL (it takes the API base)")
            break
    return base, notes


def base_candidates(base: str) -> list[str]:
    """The given base, then with ``/v1`` added (a URL of only host and port is common)."""
    return [base] if base.endswith("/v1") else [base, base + "/v1"]


def server_root(base: str) -> str:
    return base[:-3] if base.endswith("/v1") else base


def _positive_int(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) and value > 0 else None


def _try(fetch: Callable[[], Any]) -> Any:
    try:
        return fetch()
    except (HTTPStatusError, OSError, BadReply, ValueError):
        return None


def detect(base: str, listing: dict | None, get: GetJSON) -> ServerInfo:
    """Recognise the server from what it publishes: llama.cpp's ``/props``,
    vLLM's ``/version`` or ``owned_by``, llama-cpp-python's ``/extras`` routes."""
    root = server_root(base)
    entries = [m for m in (listing or {}).get("data", []) if isinstance(m, dict)]
    info = ServerInfo(url=base, kind="openai", models=[str(m.get("id")) for m in entries])
    owners = {str(m.get("owned_by", "")).lower() for m in entries}
    props = _try(lambda: get(root + "/props"))
    if isinstance(props, dict) and ("total_slots" in props or "default_generation_settings" in props):
        settings = props.get("default_generation_settings") or {}
        info.kind, info.software, info.detected_by = "llamacpp", "llama.cpp server", "GET /props"
        info.slots = _positive_int(props.get("total_slots"))
        info.context = _positive_int(settings.get("n_ctx")) or _positive_int(props.get("n_ctx"))
        info.tokenizer = "llamacpp"
        return info
    version = None if "vllm" in owners else _try(lambda: get(root + "/version"))
    if "vllm" in owners or (isinstance(version, dict) and "version" in version):
        info.kind, info.tokenizer = "vllm", "vllm"
        info.software = "vLLM" + (f" {version['version']}" if isinstance(version, dict) else "")
        info.detected_by = "owned_by vllm" if "vllm" in owners else "GET /version"
        info.context = next((_positive_int(m.get("max_model_len")) for m in entries
                             if _positive_int(m.get("max_model_len"))), None)
        return info
    if "llamacpp" in owners:
        info.kind, info.software, info.detected_by = "llamacpp", "llama.cpp", "owned_by llamacpp"
        info.tokenizer = "llamacpp"
        return info
    spec = _try(lambda: get(root + "/openapi.json"))
    if isinstance(spec, dict) and "/extras/tokenize/count" in (spec.get("paths") or {}):
        # One model behind one lock: a second request waits, and (interrupt_requests, on by
        # default) cuts the running stream short.
        info.kind, info.software = "llamacpp", "llama-cpp-python"
        info.detected_by, info.slots, info.tokenizer = "GET /openapi.json", 1, "llama-cpp-python"
        return info
    return info


def resolve_kind(info: ServerInfo, override: str) -> None:
    if override not in KINDS:
        raise ValueError(f"server kind {override!r}: expected one of {', '.join(KINDS)}")
    if override != "auto" and override != info.kind:
        info.notes.append(f"server kind {override} (--llm-server-kind; detected {info.kind})")
        info.kind = override


def resolve_concurrency(info: ServerInfo, requested: int | None) -> int:
    """Requests in flight: the server's slot count where published (a larger request is
    capped, since extra requests would only queue silently in the server), else the
    flag, else a default for the kind of server."""
    if info.slots:
        if requested and requested > info.slots:
            info.notes.append(f"--llm-concurrency {requested} capped at the server's "
                              f"{info.slots} slot(s)")
        return min(requested or info.slots, info.slots)
    return requested or DEFAULT_CONCURRENCY[info.kind]


def sampling_fields(kind: str, temperature: float, top_p: float, repetition_penalty: float,
                    max_tokens: int, seed: int | None) -> dict[str, Any]:
    """The sampling part of a request, under the names `kind` honours.  Plain OpenAI
    gets no penalty: its frequency_penalty is additive and counts differently, so it is
    not the same knob (use --llm-server-kind vllm for SGLang and other vLLM-like servers)."""
    body: dict[str, Any] = {"temperature": temperature, "top_p": top_p, "max_tokens": max_tokens}
    name = PENALTY_FIELD[kind]
    if name is not None and repetition_penalty != 1.0:
        body[name] = repetition_penalty
    if seed is not None:
        body["seed"] = seed
    return body


def count_tokens(info: ServerInfo, model: str, messages: list[dict[str, str]],
                 post: PostJSON) -> tuple[int, str]:
    """(tokens, how counted) of a prompt: the server's tokenizer where it has one, else
    characters / CHARS_PER_TOKEN rounded up."""
    root = server_root(info.url)
    text = "\n".join(m["content"] for m in messages)
    overhead = 8 * len(messages)  # chat-template tokens around each message
    try:
        if info.tokenizer == "vllm":
            reply = post(root + "/tokenize", {"model": model, "messages": messages})
            return int(reply["count"]), "the server's /tokenize"
        if info.tokenizer == "llamacpp":
            reply = post(root + "/tokenize", {"content": text})
            return len(reply["tokens"]) + overhead, "the server's /tokenize"
        if info.tokenizer == "llama-cpp-python":
            reply = post(root + "/extras/tokenize/count", {"input": text, "model": model})
            return int(reply["count"]) + overhead, "the server's /extras/tokenize/count"
    except (HTTPStatusError, OSError, BadReply, KeyError, TypeError, ValueError):
        pass
    return math.ceil(len(text) / CHARS_PER_TOKEN) + overhead, \
        f"an estimate (characters / {CHARS_PER_TOKEN})"


def context_from_error(message: str) -> int | None:
    """The context length a server names in its error (llama-cpp-python, vLLM, OpenAI:
    "maximum context length is 2048 tokens")."""
    match = CONTEXT_RE.search(message)
    return int(match.group(1)) if match else None


def context_advice(context: int | None = None) -> str:
    size = f" (the server's context is {context} tokens)" if context else ""
    return (f"prompts too long for the server{size}: use fewer demos (--num-demos) or serve "
            "a larger context (llama.cpp --n_ctx / -c, vLLM --max-model-len)")
