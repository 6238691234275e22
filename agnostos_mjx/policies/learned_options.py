"""The options of the built-in learned policies (retrieval, X-ICM, the reference VLA, the
dense replay), apart from the policies themselves, whose modules load JAX: the command
line checks and lists these before JAX starts (policies/options.py).

X-ICM's and retrieval's options that have flags of their own (``--selection``,
``--memory``, ``--ddim-steps``, ``--llm-url``, ...: EvalConfig's ``xicm`` part) are taken
from the run's config in `from_config`, the one place that maps those flags to them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from agnostos_mjx.llm.client import DEFAULT_TIMEOUT_S
from agnostos_mjx.llm.server import KINDS as LLM_SERVER_KINDS
from agnostos_mjx.policies.options import OptionsError, PolicyOptions, option

OBJECT_SOURCES = ("ground_truth", "segmented")


def _positive(options: PolicyOptions, *names: str) -> None:
    for name in names:
        value = getattr(options, name)
        if value is not None and value < 1:
            raise OptionsError(f"{name}={value}: must be an integer >= 1")


@dataclass
class RetrievalOptions(PolicyOptions):
    """The in-context demo selection (shared with X-ICM)."""

    selection: str = option(
        "auto", "demo selection: random, text, or lang, vis.in, vis.out joined with '+' "
                "(--selection)")
    memory: str | None = option(None, "seen-demo memory .npz (--memory; default: shipped)")
    sample_steps: int | None = option(
        None, "DDIM steps of a query's dynamics features (--ddim-steps; default 10)")

    def check(self) -> None:
        _positive(self, "sample_steps")

    @classmethod
    def from_config(cls, cfg: Any) -> dict[str, Any]:
        part = cfg.xicm
        return {"selection": part.selection, "memory": part.memory,
                "sample_steps": part.ddim_steps}


@dataclass
class XicmOptions(RetrievalOptions):
    """X-ICM's LLM client and prompt, besides the demo selection."""

    llm_url: str | None = option(
        None, "OpenAI-compatible base URL or 'vllm:' (--llm-url; default $AGNOSTOS_LLM_URL)")
    llm_model: str | None = option(None, "model name (--llm-model)")
    llm_cache: str | None = option(None, "response cache directory (--llm-cache)")
    num_demos: int = option(18, "in-context demonstrations per prompt (--num-demos)")
    concurrency: int | None = option(None, "requests in flight (--llm-concurrency)")
    timeout_s: float = option(DEFAULT_TIMEOUT_S, "seconds of silence before a request is "
                                                 "given up (--llm-timeout)")
    retries: int = option(4, "attempts after a failed request")
    server_kind: str = option("auto", f"sampling field names: {', '.join(LLM_SERVER_KINDS)} "
                                      "(--llm-server-kind)")
    temperature: float = option(0.1, "sampling temperature")
    top_p: float = option(0.001, "nucleus sampling mass")
    repetition_penalty: float = option(1.05, "repetition penalty (where the server has one)")
    max_tokens: int = option(256, "tokens of an answer at most")
    objects: str = option("ground_truth", "where the query's object poses come from: "
                                          "ground_truth or segmented (point clouds)")

    def check(self) -> None:
        super().check()
        _positive(self, "num_demos", "concurrency", "max_tokens")
        if self.objects not in OBJECT_SOURCES:
            raise OptionsError(f"objects={self.objects}: must be one of "
                               f"{', '.join(OBJECT_SOURCES)}")
        if self.server_kind not in LLM_SERVER_KINDS:
            raise OptionsError(f"server_kind={self.server_kind}: must be one of "
                               f"{', '.join(LLM_SERVER_KINDS)}")

    @classmethod
    def program_fields(cls) -> tuple[str, ...]:
        """The demo selection's options: the LLM's (its cache in the run's folder, say)
        compile nothing, so they leave the warm-up's marker alone."""
        return RetrievalOptions.program_fields()

    @classmethod
    def from_config(cls, cfg: Any) -> dict[str, Any]:
        part = cfg.xicm
        cache = part.llm_cache or str(Path(cfg.run.out or ".") / "llm_cache")
        return {**super().from_config(cfg), "llm_url": part.llm_url,
                "llm_model": part.llm_model, "llm_cache": cache,
                "concurrency": part.llm_concurrency, "timeout_s": part.llm_timeout,
                "server_kind": part.llm_server_kind, "num_demos": part.num_demos}


@dataclass
class ReferenceVLAOptions(PolicyOptions):
    """The reference VLA's checkpoint and how it runs."""

    checkpoint: str | None = option(
        None, "its run directory (python -m agnostos_mjx.train.vla --out RUN), required")
    renderer: str = option("auto", "its ObservationSpec.renderer: auto, cpu or warp")
    max_steps: int | None = option(
        None, "key actions before it gives up (default: the longest training demo's)")
    chunk: int = option(25, "worlds per forward pass (the last chunk padded)")

    def check(self) -> None:
        _positive(self, "max_steps", "chunk")


@dataclass
class DenseReplayOptions(PolicyOptions):
    """Which frames of the expert's demo the dense replay executes, and how."""

    every: int | str = option(
        "rlbench", "frames of the demo: every N physics steps, or rlbench (20 Hz), as the "
                   "export's --every")
    chunk: int = option(1, "rows per answer (an action chunk for --execute)")
    relative: bool = option(False, "rows as deltas of the previous tip pose")

    def check(self) -> None:
        _positive(self, "chunk")
