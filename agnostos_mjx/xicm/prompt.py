"""X-ICM's prompt and the parsing of the LLM's answer (spec: xicm_reference.md §4).

The user prompt is one line: each selected demo as
``['instruction': ..., {objects}]>[[7 ints], ...], `` most similar first,
then the query ``['instruction': ..., {objects}]>``.

Parsing never raises.  Like the original's ``re_match`` it takes the
innermost bracket groups that contain a digit and keeps groups of exactly 7
integers; unlike the original, one malformed group (a float, a word) does not
throw away the whole answer (the original then fell back to 26 home-pose
actions), and groups whose integers are out of range are dropped too.  An
answer with no valid group yields an empty plan; the policy ends that
episode with ``bad_llm_output``.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

SYSTEM_PROMPT = (
    "You are a Franka Panda robot with a parallel gripper. We provide you with some demos "
    "from some seen tasks, in the format of [task_instruction, observation]>[ 7-dim "
    "action_1, 7-dim action_2, ..., 7-dim action_N ]. Then you will receive an unseen task "
    "instruction with a new observation, and you need to output a list of 7-dim actions that "
    "match the trends in the demos. Do not output anything else."
)
MAX_PLAN = 26  # the original truncates a parsed plan to 26 actions
_GROUP = re.compile(r"\[([^\[\]]+\d[^\[\]]*)\]")
_INT = re.compile(r"^[+-]?\d+$")


def user_prompt(demo_texts: Sequence[str], query: str) -> str:
    """Demos (already in descending similarity order, each ending in ", ") + query."""
    return "".join(demo_texts) + query


def messages(demo_texts: Sequence[str], query: str) -> list[dict[str, str]]:
    return [{"role": "system", "content": SYSTEM_PROMPT},
            {"role": "user", "content": user_prompt(demo_texts, query)}]


@dataclass(frozen=True)
class ParsedPlan:
    actions: np.ndarray  # (n, 7) int32, every row in range
    groups: int  # bracket groups with a digit
    rejected: tuple[str, ...]  # groups dropped, and why

    def summary(self) -> dict:
        return {"actions": self.actions.tolist(), "groups": self.groups,
                "rejected": list(self.rejected)}


def _in_range(a: list[int]) -> bool:
    return (all(0 <= v <= 99 for v in a[:3]) and all(0 <= v <= 71 for v in a[3:6])
            and a[6] in (0, 1))


def parse_actions(text: object, limit: int = MAX_PLAN) -> ParsedPlan:
    """The valid 7-integer actions in an LLM answer, in order (never raises)."""
    if not isinstance(text, str):
        return ParsedPlan(np.zeros((0, 7), np.int32), 0, (f"not text: {type(text).__name__}",))
    rows, rejected = [], []
    groups = _GROUP.findall(text)
    for group in groups:
        parts = [p.strip() for p in group.split(",")]
        if len(parts) != 7:
            rejected.append(f"[{group}]: {len(parts)} values")
        elif not all(_INT.match(p) for p in parts):
            rejected.append(f"[{group}]: not all integers")
        elif not _in_range(values := [int(p) for p in parts]):
            rejected.append(f"[{group}]: out of range")
        else:
            rows.append(values)
    if len(rows) > limit:
        rejected.append(f"{len(rows) - limit} actions beyond {limit}")
        rows = rows[:limit]
    actions = np.asarray(rows, np.int32).reshape(-1, 7)
    return ParsedPlan(actions, len(groups), tuple(rejected))
