"""LLM access for X-ICM: an OpenAI-compatible asynchronous client with retries
and an on-disk cache, an optional in-process vLLM engine, and a scripted
loopback server for tests and benchmarks."""

from agnostos_mjx.llm.client import (
    ChatClient,
    Completion,
    LLMConfig,
    LLMConfigError,
    LLMError,
    SamplingParams,
)

__all__ = ["ChatClient", "Completion", "LLMConfig", "LLMConfigError", "LLMError",
           "SamplingParams"]
