"""In-process vLLM engine (``--llm-url vllm:``, extra ``vllm``): all pending
prompts of a round are generated in one batched call, as the original served
its model, but batched.  Same interface as `ChatClient` (complete_batch,
preflight, stats, report, close) and the same on-disk cache."""

from __future__ import annotations

from dataclasses import asdict
from typing import Any

from agnostos_mjx.llm.cache import ResponseCache
from agnostos_mjx.llm.client import Completion, LLMConfig, LLMConfigError, Messages
from agnostos_mjx.llm.stats import LLMStats


class VLLMEngine:
    def __init__(self, config: LLMConfig, tensor_parallel_size: int | None = None,
                 gpu_memory_utilization: float = 0.8):
        try:
            import vllm
        except ImportError:
            raise LLMConfigError("--llm-url vllm: needs vLLM in this environment "
                                 "(pip install agnostos-mjx[vllm])") from None
        self.config = config
        self.cache = ResponseCache(config.cache_dir) if config.cache_dir else None
        kwargs = {"model": config.model, "gpu_memory_utilization": gpu_memory_utilization}
        if tensor_parallel_size:
            kwargs["tensor_parallel_size"] = tensor_parallel_size
        self._llm = vllm.LLM(**kwargs)
        s = config.sampling
        self._params = vllm.SamplingParams(temperature=s.temperature, top_p=s.top_p,
                                           repetition_penalty=s.repetition_penalty,
                                           max_tokens=s.max_tokens, seed=s.seed)
        self.stats = LLMStats()
        self.context_length = None  # vLLM truncates nothing: an over-long prompt errors

    def preflight(self) -> None:
        """The model loaded in __init__; nothing else can fail later."""

    def report(self) -> dict[str, Any]:
        s = self.config.sampling
        return {"server": {"url": "vllm:", "kind": "vllm", "software": "vLLM in-process"},
                "sampling_sent": asdict(s), **self.stats.as_dict()}

    def complete_batch(self, batch: list[Messages]) -> list[Completion]:
        numbers = [self.stats.next_number() for _ in batch]
        out: list[Completion | None] = [None] * len(batch)
        keys: list[str | None] = [None] * len(batch)
        todo = []
        for i, messages in enumerate(batch):
            if self.cache is not None:
                keys[i] = self.cache.key(self.config.model, messages, asdict(self.config.sampling))
                hit = self.cache.get(keys[i])
                if hit is not None:
                    self.stats.finish(numbers[i], {"ok": True, "cached": True})
                    out[i] = Completion(hit, cached=True)
                    continue
            todo.append(i)
        if todo:
            results = self._llm.chat([batch[i] for i in todo], self._params, use_tqdm=False)
            for i, result in zip(todo, results):
                text = result.outputs[0].text
                out[i] = Completion(text, attempts=1,
                                    finish_reason=result.outputs[0].finish_reason)
                self.stats.finish(numbers[i], {"ok": True, "attempts": 1,
                                               "finish_reason": out[i].finish_reason})
                if keys[i] is not None:
                    self.cache.put(keys[i], text)
        return out  # type: ignore[return-value]

    def close(self) -> None:
        self._llm = None
