"""X-ICM: an LLM predicts key actions for an unseen task from K textualised
seen-task demonstrations (spec: xicm_reference.md §3-4).

Every world that needs a plan sends its request in the same round; the
client keeps up to `concurrency` requests in flight, so a batch of 75
episodes costs about one LLM latency per round instead of 75.  Every prompt,
answer and parse result is kept in the episode record, every request's
attempts and causes in the run's `report` (results.json's ``llm``).  Before the run, prompts of
`num_demos` demos are measured against the server's context length where it
publishes one, so a too-small context is one clear error, not a run of
``llm_error`` episodes.
"""

from __future__ import annotations

import logging

import numpy as np

from agnostos_mjx.llm.client import (
    ChatClient,
    LLMConfig,
    LLMConfigError,
    SamplingParams,
)
from agnostos_mjx.llm.server import context_advice
from agnostos_mjx.policies.base import Round
from agnostos_mjx.policies.demo_selection import demo_selection, queries_for, warm_selection
from agnostos_mjx.policies.learned_options import XicmOptions
from agnostos_mjx.policies.planning import PlanningPolicy, PlanResult
from agnostos_mjx.runtime.observation import CAMERAS, ObservationSpec
from agnostos_mjx.sim.textualise import decode_action
from agnostos_mjx.xicm.prompt import messages, parse_actions
from agnostos_mjx.xicm.scene_text import query_texts, segmented_object_voxels

log = logging.getLogger("agnostos_mjx.xicm")

# X-ICM's cameras and resolution (xicm_reference.md 3): what its object positions come from.
SEGMENTED_SPEC = ObservationSpec(cameras=CAMERAS, height=128, width=128,
                                 modalities=("point_cloud", "segmentation"))


class XICMPolicy(PlanningPolicy):
    """Privileged: the query's text holds the scene's object poses, from the simulator
    (``objects="ground_truth"``) or from its segmented point clouds, as X-ICM's harness."""

    name = "xicm"
    privileged = True

    def __init__(self, options: XicmOptions | None = None, client: ChatClient | None = None
                 ) -> None:
        """`client`: an LLM client to use instead of the one the options describe."""
        super().__init__()
        o = options or XicmOptions()
        self.objects = o.objects
        if client is None:
            config = LLMConfig.from_env(
                o.llm_url, o.llm_model, concurrency=o.concurrency, timeout_s=o.timeout_s,
                retries=o.retries, server_kind=o.server_kind, cache_dir=o.llm_cache,
                sampling=SamplingParams(o.temperature, o.top_p, o.repetition_penalty,
                                        o.max_tokens))
            if config is None:
                raise LLMConfigError("X-ICM needs an LLM: pass --llm-url and --llm-model or set "
                                     "AGNOSTOS_LLM_URL and AGNOSTOS_LLM_MODEL")
            if config.url.startswith("vllm:"):
                from agnostos_mjx.llm.vllm_engine import VLLMEngine

                client = VLLMEngine(config)
            else:
                client = ChatClient(config)
            client.preflight()
        self.client = client
        self.memory, self.selection, self.selector = demo_selection(o)
        self.num_demos = o.num_demos
        self.name = f"xicm[{self.selection},k={o.num_demos}]"
        self.check_context()

    @classmethod
    def warm_up(cls, options: XicmOptions, batch: int) -> bool:
        return warm_selection(options)

    def check_context(self) -> None:
        """Measure prompts of `num_demos` demos (of median length, and the longest) against
        the server's context: an error when typical prompts cannot fit, a warning when
        only the longest cannot.  Skipped where the server publishes no context length."""
        context = getattr(self.client, "context_length", None)
        count = getattr(self.client, "count_tokens", None)
        if not context or count is None or len(self.memory) == 0:
            return
        texts = [str(t) for t in self.memory.text]
        order = np.argsort([len(t) for t in texts], kind="stable")
        k = min(self.num_demos, len(texts))
        middle = order[max(0, len(order) // 2 - k // 2):][:k]
        query = texts[order[-1]].split(">", 1)[0] + ">"  # the observation of a long demo
        answer = self.client.config.sampling.max_tokens
        typical, how = count(messages([texts[i] for i in middle], query))
        longest, _ = count(messages([texts[i] for i in order[-k:]], query))
        bare, _ = count(messages([], query))
        per_demo = max(1.0, (typical - bare) / k)
        fitting = max(0, int((context - answer - bare) // per_demo))
        log.info("prompts of %d demos: about %d tokens (longest %d), counted by %s, + %d to "
                 "answer; context %d", k, typical, longest, how, answer, context)
        if typical + answer > context:
            fix = (f"--num-demos {fitting} fits" if fitting else "even no demos do not fit")
            raise LLMConfigError(
                f"prompts of {k} demos need about {typical} tokens + {answer} to answer "
                f"(counted by {how}) but the server's context is {context} tokens ({fix}): "
                + context_advice())
        if longest + answer > context:
            log.warning("the longest prompts of %d demos (about %d tokens + %d) exceed the "
                        "server's context of %d tokens; some requests will fail: %s", k,
                        longest, answer, context, context_advice())

    def report(self) -> dict:
        """The run's LLM requests, for results.json (``llm``) and the console summary."""
        report = getattr(self.client, "report", None)
        return {"llm": report() if report is not None else {}}

    def plan_steps(self, view: Round, worlds: np.ndarray):
        from agnostos_mjx.runtime.outcome import Outcome

        episodes, env = view.episodes, view.env
        variations = env.variation[worlds]
        obs = type(env.obs)(env.obs.data[worlds], env.obs.layout, env.obs.attached[worlds])
        voxels = None
        if self.objects == "segmented":  # as the original: 5 cameras' segmented point clouds
            observation = episodes.observe(env, SEGMENTED_SPEC)
            voxels = segmented_object_voxels(observation, worlds)
        query_lines = query_texts(episodes.task, obs, variations, voxels)
        selected = self.selector.submit(queries_for(self, view, worlds, self.selection),
                                        self.num_demos)
        yield selected  # the evaluator runs other tasks while the features are computed
        chosen = selected.result()
        batch = [messages([str(self.memory.text[i]) for i in idx], q)
                 for idx, q in zip(chosen, query_lines)]
        submit = getattr(self.client, "submit_batch", None)
        if submit is None:  # e.g. the in-process vLLM engine: one blocking batch
            answers = self.client.complete_batch(batch)
        else:
            future = submit(batch)
            yield future  # the evaluator runs other tasks until the answers are in
            answers = future.result()
        results = []
        for idx, msgs, answer in zip(chosen, batch, answers):
            info = {"selected": [f"{self.memory.task[i]}#{i}" for i in idx],
                    "prompt": msgs[1]["content"], "response": answer.text,
                    "error": answer.error, "cause": answer.cause, "cached": answer.cached,
                    "attempts": answer.attempts, "finish_reason": answer.finish_reason}
            if answer.text is None:
                results.append(PlanResult(end_reason=Outcome.LLM_ERROR, info=info))
                continue
            parsed = parse_actions(answer.text)
            info["parsed"] = parsed.summary()
            if len(parsed.actions) == 0:
                results.append(PlanResult(end_reason=Outcome.BAD_LLM_OUTPUT, info=info))
                continue
            pos, quat, grip = map(np.asarray, decode_action(parsed.actions))
            results.append(PlanResult(pos, quat, grip, info=info))
        return results
