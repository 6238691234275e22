"""Evaluate a policy on AGNOSTOS tasks: ``python -m agnostos_mjx.eval``.

The protocol follows X-ICM's evaluation (see the spec, sections 6 and 9):
per task and seed a success rate over `--episodes` episodes; per task the
mean and population std (ddof=0) over seeds; Level-1 / Level-2 / All the
mean over that group's tasks per seed, then mean and population std over
seeds.

Episodes are reproducible and independent of batching: episode `e` of seed
`s` samples its scene from ``fold_in(PRNGKey(s), e)`` and, where the
variation is sampled, its variation from ``fold_in(that key, 1)``.  The
episodes of all seeds of a task are pooled and simulated `--batch` worlds at
a time.

Outputs in `--out` (default ``results/<policy>-<timestamp>``, created when the
run starts): episodes.jsonl (one JSON line per episode, appended and fsync'd as
each world finishes, the basis of --resume: an interrupted run keeps every
finished episode, and a torn last line is ignored), results.json (config,
versions, aggregates and the episode records), results.csv, results.md (the
table that is also printed) and results.png.

results.csv has one row per task, then one per group (Level-1, Level-2, All =
the unseen tasks, Seen), with these columns (success rates in percent)::

    name, kind (task | group), split (task rows; empty for groups),
    tasks (1, or the group's task count), seeds, episodes, successes,
    success_pct_mean, success_pct_std (population std over seeds),
    success_pct_seed<S> (one column per seed; empty where a task lacks it),
    mean_key_actions, mean_sim_steps (task rows),
    outcome_<label> (episode counts per outcome: success, max_steps, ...)

so ``pandas.read_csv`` or ``csv.DictReader`` load it without parsing strings.

Ctrl-C stops a run within seconds and prints the command that continues it
(the same options with ``--out DIR --resume``); a second Ctrl-C exits at once.

Examples::

    python -m agnostos_mjx.eval                                   # oracle, unseen tasks
    python -m agnostos_mjx.eval --tasks lamp_on --seeds 0 --episodes 4
    python -m agnostos_mjx.eval --policy my_pkg.agent:MyPolicy --policy-arg model=\"qwen\"
    python -m agnostos_mjx.eval --out results/run1 --resume      # finish an interrupted run
    python -m agnostos_mjx.eval --policy remote --policy-url ws://localhost:8000  # a served VLA
"""

from __future__ import annotations

import argparse
import collections
import concurrent.futures
import copy
import csv
import functools
import io
import json
import logging
import os
import re
import shlex
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.cli import (
    HelpFormatter,
    InterruptGuard,
    Progress,
    atomic_write,
    check_writable_dir,
    hard_exit,
    progress_bar,
    remove_empty_dirs,
    setup_logging,
    versions,
)
from agnostos_mjx.llm.client import DEFAULT_TIMEOUT_S
from agnostos_mjx.llm.server import KINDS as LLM_SERVER_KINDS

log = logging.getLogger("agnostos_mjx.eval")

VARIATION_STREAM = 1  # fold_in index of an episode key that draws its variation
VARIATION_MODES = ("protocol", "all", "zero")
EPISODES_FILE = "episodes.jsonl"
# Aggregate groups as in X-ICM's gather_score.py; "All" is the unseen tasks
# (X-ICM's 23-task average).  Seen tasks get their own group.
GROUPS: tuple[tuple[str, frozenset[str]], ...] = (
    ("Level-1", frozenset({"unseen_level1"})),
    ("Level-2", frozenset({"unseen_level2"})),
    ("All", frozenset({"unseen_level1", "unseen_level2"})),
    ("Seen", frozenset({"seen"})),
)


class UsageError(Exception):
    """A bad command line or output directory: reported in one line, exit code 2."""


# ---------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------
@dataclass
class EvalConfig:
    policy: str = "auto"
    policy_args: dict[str, Any] = field(default_factory=dict)
    tasks: str = "unseen"
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    episodes: int = 25
    batch: int = 75
    backend: str = "auto"
    variations: str = "protocol"
    out: str | None = None
    resume: bool = False
    fail_fast: bool = False
    quiet: bool = False
    llm_url: str | None = None
    llm_model: str | None = None
    llm_cache: str | None = None
    llm_concurrency: int | None = None
    llm_timeout: float = DEFAULT_TIMEOUT_S
    llm_server_kind: str = "auto"
    overlap_tasks: int = 3
    selection: str = "auto"
    num_demos: int = 18
    ddim_steps: int | None = None
    memory: str | None = None
    compare: str | None = None
    video: str | None = None
    video_cameras: str | None = None
    policy_url: str | None = None
    gpu_mem_fraction: float | None = None
    devices: int | None = None
    process_id: int = 0
    num_processes: int = 1
    coordinator: str | None = None
    merge: bool = False
    local_processes: int = 1


def _int_list(text: str) -> list[int]:
    try:
        values = [int(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}") from None
    if not values:
        raise argparse.ArgumentTypeError("expected at least one integer")
    return list(dict.fromkeys(values))


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _variation_mode(text: str) -> str:
    if text in VARIATION_MODES or text.isdigit():
        return text
    raise argparse.ArgumentTypeError(
        f"expected one of {', '.join(VARIATION_MODES)} or a variation number, got {text!r}")


def _policy_arg(text: str) -> tuple[str, Any]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def build_parser() -> argparse.ArgumentParser:
    from agnostos_mjx.physics import BACKENDS

    p = argparse.ArgumentParser(
        prog="python -m agnostos_mjx.eval",
        description="Evaluate a policy on AGNOSTOS tasks (X-ICM protocol) and write "
                    "episodes.jsonl, results.json, results.csv and results.md.",
        formatter_class=HelpFormatter)
    p.add_argument("--policy", default="auto",
                   help="auto (xicm when an LLM is configured, else retrieval), xicm, "
                        "retrieval, oracle, or 'module:attr' / 'file.py:attr' naming a Policy "
                        "class, factory or instance (see agnostos_mjx/policies/base.py)")
    p.add_argument("--policy-arg", action="append", type=_policy_arg, default=None,
                   metavar="KEY=VALUE",
                   help="keyword argument for the policy factory (VALUE parsed as JSON if it "
                        "can be); repeatable")
    p.add_argument("--policy-url", default=None, metavar="ws://HOST:PORT",
                   help="the policy server of --policy remote (openpi's websocket protocol; "
                        "default $AGNOSTOS_POLICY_URL); its adapter options (preset, keys, "
                        "timeout_s, action_index, quat_order, gripper, height, width) go in "
                        "--policy-arg, see agnostos_mjx/remote/adapter.py")
    p.add_argument("--gpu-mem-fraction", type=float, default=None, metavar="F",
                   help="cap JAX's GPU memory pool at F of the card, 0: no preallocation "
                        "(default $AGNOSTOS_GPU_MEM_FRACTION; 0.35 when the policy or LLM "
                        "server is on this machine; else JAX's 75%%); see agnostos_mjx/gpu.py")
    p.add_argument("--tasks", default="unseen",
                   help="comma-separated task names and/or split names (seen, unseen, "
                        "unseen_level1, unseen_level2, all)")
    p.add_argument("--seeds", type=_int_list, default="0,1,2",
                   help="comma-separated evaluation seeds")
    p.add_argument("--episodes", type=_positive_int, default=25, help="episodes per task and seed")
    p.add_argument("--batch", type=_positive_int, default=75,
                   help="worlds simulated at once; the episodes of all seeds of a task are "
                        "pooled and run in chunks of this size")
    p.add_argument("--backend", default="auto", choices=BACKENDS,
                   help="physics backend (auto: MJX-warp on a CUDA GPU for batches of >= 4096 "
                        "worlds, else native MuJoCo on all CPU threads, which is faster "
                        "below that and bit-reproducible)")
    p.add_argument("--variations", type=_variation_mode, default="protocol",
                   help="protocol: unseen tasks use variation 0, seen tasks sample one per "
                        "episode; all: sample for every task; zero: always 0; N: always N")
    p.add_argument("--out", default=None,
                   help="output directory; default results/<policy>-<timestamp>, <policy> "
                        "being the policy run (retrieval or xicm under auto)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out (required): skip episodes already in "
                        "its episodes.jsonl")
    p.add_argument("--fail-fast", action="store_true",
                   help="re-raise policy exceptions instead of recording policy_error")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar, warnings-only logging (the table is still printed)")
    p.add_argument("--video", default=None, metavar="first:N|failures[:N]",
                   help="MP4 per episode in <out>/videos for episodes 0..N-1 of each task and "
                        "seed, or the failures (see agnostos_mjx/video.py; needs PyAV)")
    p.add_argument("--video-cameras", default=None,
                   help="comma-separated cameras side by side (default front,overhead,wrist)")
    scale = p.add_argument_group("several devices and hosts (see README, Scale out)")
    scale.add_argument("--devices", type=_positive_int, default=None, metavar="N",
                       help="local accelerators a batch's worlds (MJX-jax) and the dynamics "
                            "features are sharded over (default: all)")
    scale.add_argument("--num-processes", type=_positive_int, default=1, metavar="N",
                       help="processes (hosts) sharing the run: process I runs tasks I, I+N, "
                            "... into --out/proc-I; then --merge")
    scale.add_argument("--process-id", type=int, default=0, metavar="I",
                       help="this process's index, 0..N-1")
    scale.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                       help="process 0's address: each process calls "
                            "jax.distributed.initialize with it (one JAX cluster; sharding "
                            "stays on each host's local devices); without it the processes "
                            "run independently")
    scale.add_argument("--local-processes", type=_positive_int, default=1, metavar="N",
                       help="run as N processes on this machine (each every N-th task, "
                            "sharing its GPU; logs in --out/proc-I.log), then merge: with "
                            "warp at batch 75 the GPU is mostly idle (H100 main job: 407 s "
                            "as 8 processes; see agnostos_mjx/local_processes.py)")
    scale.add_argument("--merge", action="store_true",
                       help="only merge --out/proc-*/episodes.jsonl into --out's results "
                            "files (episodes.jsonl, results.json/.csv/.md/.png)")
    llm = p.add_argument_group("X-ICM and retrieval")
    llm.add_argument("--llm-url", default=None,
                     help="OpenAI-compatible base URL, e.g. http://localhost:8000/v1, or "
                          "'vllm:' for an in-process vLLM engine (extra 'vllm') "
                          "(default: $AGNOSTOS_LLM_URL); the key comes from "
                          "$AGNOSTOS_LLM_API_KEY or $OPENAI_API_KEY")
    llm.add_argument("--llm-model", default=None,
                     help="model name on that server (default: $AGNOSTOS_LLM_MODEL)")
    llm.add_argument("--llm-cache", default=None,
                     help="response cache directory (default: <out>/llm_cache); reruns and "
                          "--resume reuse answers, a shipped cache replays a run offline")
    llm.add_argument("--llm-concurrency", type=_positive_int, default=None,
                     help="LLM requests in flight at once (default: the server's slot count "
                          "where it publishes one (llama.cpp: 1 unless started with "
                          "--parallel N), capping this flag too; else 64 for vLLM, which "
                          "batches on the GPU, and 8 for other servers)")
    llm.add_argument("--llm-timeout", type=_positive_float, default=DEFAULT_TIMEOUT_S,
                     help="seconds without a byte from the LLM server before a request is "
                          "given up (answers are streamed, so this is silence, not total "
                          "time; not retried, since the server may still be computing). "
                          "Covers prompt processing before the first token: seconds on a "
                          "GPU, up to minutes for long prompts on a CPU")
    llm.add_argument("--llm-server-kind", default="auto", choices=LLM_SERVER_KINDS,
                     help="which sampling field names to send: vllm (repetition_penalty; "
                          "also SGLang), llamacpp (repeat_penalty; llama.cpp and "
                          "llama-cpp-python), openai (no penalty field); auto detects it "
                          "in the start-up check")
    llm.add_argument("--overlap-tasks", type=_positive_int, default=3,
                     help="tasks evaluated at once when the policy waits on an LLM: while one "
                          "task's requests are in flight the others simulate (1: one task at "
                          "a time; results do not depend on it)")
    llm.add_argument("--selection", default="auto",
                     help="in-context demo selection: random, text (instruction trigrams), "
                          "dynamics features lang, vis.in, vis.out joined with '+', or auto "
                          "(lang+vis.out when the memory has dynamics features, else text)")
    llm.add_argument("--num-demos", type=_positive_int, default=18,
                     help="K, in-context demonstrations per prompt")
    llm.add_argument("--ddim-steps", type=_positive_int, default=None,
                     help="DDIM steps of a query's dynamics features (default 10: as good as "
                          "the original's 50 for selection and 5x cheaper, see "
                          "eval/reports/sampling_steps_h100)")
    llm.add_argument("--memory", default=None,
                     help="seen-demo memory .npz (default: the one shipped with the package)")
    llm.add_argument("--compare", default=None,
                     help="add a column of published numbers: 'X-ICM 7B', 'X-ICM 72B', pi0, "
                          "VoxPoser or RVT2")
    return p


def parse_config(argv: Sequence[str] | None = None) -> EvalConfig:
    a = build_parser().parse_args(argv)
    return EvalConfig(policy=a.policy, policy_args=dict(a.policy_arg or []), tasks=a.tasks,
                      seeds=a.seeds, episodes=a.episodes, batch=a.batch, backend=a.backend,
                      variations=a.variations, out=a.out, resume=a.resume,
                      fail_fast=a.fail_fast, quiet=a.quiet, llm_url=a.llm_url,
                      llm_model=a.llm_model, llm_cache=a.llm_cache,
                      llm_concurrency=a.llm_concurrency, llm_timeout=a.llm_timeout,
                      llm_server_kind=a.llm_server_kind, overlap_tasks=a.overlap_tasks,
                      selection=a.selection,
                      num_demos=a.num_demos, ddim_steps=a.ddim_steps, memory=a.memory,
                      compare=a.compare, video=a.video, video_cameras=a.video_cameras,
                      policy_url=a.policy_url, gpu_mem_fraction=a.gpu_mem_fraction,
                      devices=a.devices, process_id=a.process_id,
                      num_processes=a.num_processes, coordinator=a.coordinator,
                      merge=a.merge, local_processes=a.local_processes)


def resolve_policy(cfg: EvalConfig) -> tuple[str, dict[str, Any], str]:
    """(policy spec, factory kwargs, a one-line explanation) for `cfg`; fills in
    the built-in policies' arguments from the command line."""
    from agnostos_mjx.llm.client import LLMConfig

    spec, note = cfg.policy, ""
    if spec == "auto":
        configured = LLMConfig.from_env(cfg.llm_url, cfg.llm_model) is not None
        spec = "xicm" if configured else "retrieval"
        note = ("an LLM is configured: running X-ICM" if configured else
                "no LLM configured (set --llm-url/--llm-model or AGNOSTOS_LLM_URL/"
                "AGNOSTOS_LLM_MODEL for X-ICM): running the retrieval baseline")
    kwargs: dict[str, Any] = {}
    if spec in ("xicm", "retrieval"):
        kwargs.update(selection=cfg.selection, memory=cfg.memory, sample_steps=cfg.ddim_steps)
    if spec == "xicm":
        cache = cfg.llm_cache or str(Path(cfg.out or ".") / "llm_cache")
        kwargs.update(llm_url=cfg.llm_url, llm_model=cfg.llm_model, llm_cache=cache,
                      concurrency=cfg.llm_concurrency, timeout_s=cfg.llm_timeout,
                      server_kind=cfg.llm_server_kind, num_demos=cfg.num_demos)
    if spec == "remote":
        kwargs["url"] = cfg.policy_url or os.environ.get("AGNOSTOS_POLICY_URL")
    kwargs.update(cfg.policy_args)
    return spec, kwargs, note


# ---------------------------------------------------------------------------------------
# Episode keys and variations
# ---------------------------------------------------------------------------------------
def episode_keys(seeds: np.ndarray, episodes: np.ndarray):
    """Scene keys ``fold_in(PRNGKey(seed), episode)``, shape (n, 2)."""
    import jax

    fold = lambda s, e: jax.random.fold_in(jax.random.PRNGKey(s), e)
    return jax.vmap(fold)(np.asarray(seeds, np.uint32), np.asarray(episodes, np.uint32))


def episode_variations(keys, num_variations: int, split: str, mode: str) -> np.ndarray:
    """Each episode's variation under `mode` (see --variations)."""
    import jax

    n = len(keys)
    if mode.isdigit():
        variation = int(mode)
        if variation >= num_variations:
            raise UsageError(f"variation {variation} out of range 0..{num_variations - 1}")
        return np.full(n, variation, np.int32)
    if mode == "zero" or (mode == "protocol" and split != "seen") or num_variations == 1:
        return np.zeros(n, np.int32)
    draw = lambda k: jax.random.randint(jax.random.fold_in(k, VARIATION_STREAM), (), 0,
                                        num_variations)
    return np.asarray(jax.vmap(draw)(keys), np.int32)


# ---------------------------------------------------------------------------------------
# Aggregation (pure)
# ---------------------------------------------------------------------------------------
def _mean_std(values: Iterable[float]) -> tuple[float, float]:
    v = np.asarray(list(values), np.float64)
    return float(v.mean()), float(v.std())  # population std, as X-ICM's np.std


def aggregate(records: Sequence[dict], tasks: Sequence[str] | None = None) -> dict:
    """Per-task and per-group success rates (in %) from episode records.

    Each record needs task, split, seed, success, outcome, key_actions and
    sim_steps.  Per task: success rate per seed, then mean and population
    std over seeds.  Per group (GROUPS): per seed the mean over the group's
    tasks that have that seed, then mean and population std over seeds.
    `tasks` fixes the order (and selection) of tasks; default record order."""
    by_task: dict[str, list[dict]] = defaultdict(list)
    for r in records:
        by_task[r["task"]].append(r)
    order = list(tasks) if tasks is not None else list(by_task)
    per_task: dict[str, dict] = {}
    for name in order:
        recs = by_task.get(name)
        if not recs:
            continue
        by_seed: dict[int, list[bool]] = defaultdict(list)
        for r in recs:
            by_seed[int(r["seed"])].append(bool(r["success"]))
        per_seed = {str(s): 100.0 * float(np.mean(v)) for s, v in sorted(by_seed.items())}
        mean, std = _mean_std(per_seed.values())
        outcomes = Counter(r["outcome"] for r in recs)
        per_task[name] = {
            "split": recs[0]["split"],
            "episodes": len(recs),
            "seeds": sorted(by_seed),
            "success_per_seed": per_seed,
            "success_mean": mean,
            "success_std": std,
            "mean_key_actions": float(np.mean([r["key_actions"] for r in recs])),
            "mean_sim_steps": float(np.mean([r["sim_steps"] for r in recs])),
            "outcomes": dict(sorted(outcomes.items(), key=lambda kv: (-kv[1], kv[0]))),
        }
    groups: dict[str, dict] = {}
    for group, splits in GROUPS:
        members = [n for n, t in per_task.items() if t["split"] in splits]
        if not members:
            continue
        seeds = sorted({s for n in members for s in per_task[n]["success_per_seed"]}, key=int)
        per_seed = {}
        for s in seeds:
            vals = [per_task[n]["success_per_seed"][s] for n in members
                    if s in per_task[n]["success_per_seed"]]
            per_seed[s] = float(np.mean(vals))
        mean, std = _mean_std(per_seed.values())
        groups[group] = {"tasks": members, "success_per_seed": per_seed,
                         "success_mean": mean, "success_std": std}
    return {"tasks": per_task, "groups": groups}


def group_label(name: str) -> str:
    """How reports name a group (All covers the unseen tasks only)."""
    return "All (unseen)" if name == "All" else name


def _failures(outcomes: dict[str, int]) -> str:
    bad = [f"{k}: {v}" for k, v in outcomes.items() if k != "success"]
    return ", ".join(bad) if bad else "-"


def format_markdown(summary: dict, title: str = "", compare: dict[str, float] | None = None,
                    compare_label: str = "") -> str:
    """A readable Markdown report: one row per task, then the groups; with
    `compare`, a column of published numbers (task/group name -> %)."""
    ref = (lambda name: f" | {compare[name]:.1f}" if name in compare else " | -") if compare \
        else (lambda name: "")
    extra = f" | {compare_label} (published)" if compare else ""
    sep = "|---" if compare else ""
    lines = [f"## {title}", ""] if title else []
    lines += [f"| task | split | success % mean (std){extra} | key actions | sim steps | failures |",
              f"|---|---|---{sep}|---|---|---|"]
    for name, t in summary["tasks"].items():
        lines.append(f"| {name} | {t['split']} | {t['success_mean']:.1f} ({t['success_std']:.1f})"
                     f"{ref(name)} | {t['mean_key_actions']:.2f} | {t['mean_sim_steps']:.0f}"
                     f" | {_failures(t['outcomes'])} |")
    if summary["groups"]:
        lines += ["", f"| group | tasks | success % mean (std){extra} | per seed |",
                  f"|---|---|---{sep}|---|"]
        for name, g in summary["groups"].items():
            per_seed = ", ".join(f"{s}: {v:.1f}" for s, v in g["success_per_seed"].items())
            lines.append(f"| {group_label(name)} | {len(g['tasks'])} | {g['success_mean']:.1f} "
                         f"({g['success_std']:.1f}){ref(name)} | {per_seed} |")
    return "\n".join(lines) + "\n"


CSV_COLUMNS = ("name", "kind", "split", "tasks", "seeds", "episodes", "successes",
               "success_pct_mean", "success_pct_std", "mean_key_actions", "mean_sim_steps")


def csv_rows(summary: dict) -> list[dict[str, Any]]:
    """results.csv as dicts: a row per task, then a row per group (see the module
    docstring for the columns).  Numbers stay numbers; absent values are None."""
    tasks, groups = summary["tasks"], summary["groups"]
    seeds = sorted({s for t in tasks.values() for s in t["success_per_seed"]}, key=int)
    labels = sorted({k for t in tasks.values() for k in t["outcomes"]})

    def row(name: str, kind: str, split: str | None, members: list[str], item: dict
            ) -> dict[str, Any]:
        counts = {k: sum(tasks[m]["outcomes"].get(k, 0) for m in members) for k in labels}
        per_seed = item["success_per_seed"]
        single = tasks[members[0]] if kind == "task" else None
        return {
            "name": name, "kind": kind, "split": split, "tasks": len(members),
            "seeds": len(per_seed), "episodes": sum(tasks[m]["episodes"] for m in members),
            "successes": counts.get("success", 0),
            "success_pct_mean": round(item["success_mean"], 4),
            "success_pct_std": round(item["success_std"], 4),
            **{f"success_pct_seed{s}": round(per_seed[s], 4) if s in per_seed else None
               for s in seeds},
            "mean_key_actions": round(single["mean_key_actions"], 4) if single else None,
            "mean_sim_steps": round(single["mean_sim_steps"], 2) if single else None,
            **{f"outcome_{k}": counts[k] for k in labels},
        }

    return ([row(n, "task", t["split"], [n], t) for n, t in tasks.items()]
            + [row(n, "group", None, g["tasks"], g) for n, g in groups.items()])


def format_csv(summary: dict) -> str:
    """results.csv: `csv_rows` with a header (the columns of the first row)."""
    rows = csv_rows(summary)
    if not rows:
        return ",".join(CSV_COLUMNS) + "\n"
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


# ---------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------
def record_key(record: dict) -> tuple[str, int, int]:
    return record["task"], int(record["seed"]), int(record["episode"])


def load_records(path: Path) -> list[dict]:
    """Episode records of an earlier run, first of each (task, seed, episode).  A torn
    last line (the process died while appending) is dropped; other unreadable lines
    are skipped with a warning."""
    if not path.exists():
        return []
    text = path.read_text(encoding="utf-8", errors="replace")
    lines = text.split("\n")
    records: dict[tuple, dict] = {}
    for i, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            record = json.loads(line)
            key = record_key(record)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            if i == len(lines):  # no newline after it: an append cut short
                log.info("%s: ignoring the incomplete last line", path)
            else:
                log.warning("%s:%d is not a valid episode record; ignored", path, i)
            continue
        records.setdefault(key, record)
    return list(records.values())


def repair_records(path: Path) -> list[dict]:
    """`load_records`, then rewrite the file (atomically) if it held anything else, so
    appends start on a line of their own."""
    records = load_records(path)
    if path.exists() and path.read_bytes() != _jsonl(records).encode("utf-8"):
        atomic_write(path, _jsonl(records))
    return records


def append_records(path: Path, records: Sequence[dict]) -> None:
    """Append whole lines in one write, then fsync: a crash tears at most the last line,
    which `load_records` drops.  Creates the folder (the run has really started)."""
    data = _jsonl(records).encode("utf-8")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)


def _jsonl(records: Sequence[dict]) -> str:
    return "".join(json.dumps(r, sort_keys=False) + "\n" for r in records)


def resume_command(argv: Sequence[str], out: Path) -> str:
    """The command that continues this run: the same options, then --out OUT --resume."""
    args, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--out":
            skip = True
        elif not (a.startswith("--out=") or a == "--resume"):
            args.append(a)
    return shlex.join(["python", "-m", "agnostos_mjx.eval", *args, "--out", str(out),
                       "--resume"])


def interrupted_message(out_dir: Path, argv: Sequence[str], out: Path | None = None) -> str:
    """What Ctrl-C prints: what is kept in `out_dir`, and the command that continues the
    run (whose --out is `out`, the shared folder of a multi-process run; default out_dir)."""
    kept = len(load_records(out_dir / EPISODES_FILE))
    where = (f"{kept} finished episode{'s' * (kept != 1)} saved in {out_dir / EPISODES_FILE}"
             if kept else "no episode had finished")
    return f"\ninterrupted; {where}; to continue: {resume_command(argv, out or out_dir)}"


def latest_run(root: Path = Path("results")) -> Path | None:
    """The most recently changed run folder (one with episodes.jsonl) under `root`."""
    runs = [p.parent for p in root.glob(f"*/{EPISODES_FILE}")]
    return max(runs, key=lambda p: (p / EPISODES_FILE).stat().st_mtime, default=None)


def process_dir(out: Path, cfg: EvalConfig) -> Path:
    """Where this process writes: `out` itself, or out/proc-I when several processes share
    it, so each keeps its own episodes.jsonl (and --resume) with no file locking."""
    return out / f"proc-{cfg.process_id}" if cfg.num_processes > 1 else out


def resolve_out(cfg: EvalConfig, spec: str) -> Path:
    """Sets cfg.out (default results/<policy>-<timestamp>) and checks, before anything
    is loaded or created, that the run can write there."""
    if cfg.out is None and cfg.num_processes > 1:
        raise UsageError("--num-processes needs --out DIR, the folder the processes share")
    if cfg.out is None:
        if cfg.resume:
            latest = latest_run()
            hint = f" (the latest run is {latest})" if latest else ""
            raise UsageError(f"--resume needs --out DIR, the folder of the run to continue"
                             f"{hint}")
        cfg.out = str(_default_out(spec))
    if not 0 <= cfg.process_id < cfg.num_processes:
        raise UsageError(f"--process-id {cfg.process_id}: expected 0..{cfg.num_processes - 1}")
    out_dir = process_dir(Path(cfg.out), cfg)
    problem = check_writable_dir(out_dir)
    if problem:
        raise UsageError(f"--out: {problem}")
    if (out_dir / EPISODES_FILE).exists() and not cfg.resume:
        raise UsageError(f"{out_dir / EPISODES_FILE} exists; pass --resume to continue that "
                         f"run or choose another --out")
    return out_dir


# ---------------------------------------------------------------------------------------
# Running
# ---------------------------------------------------------------------------------------
def _accepts(func, name: str) -> bool:
    import inspect

    try:
        return name in inspect.signature(func).parameters
    except (TypeError, ValueError):
        return False


def _default_out(policy: str) -> Path:
    tag = re.sub(r"[^A-Za-z0-9_.-]+", "_", policy.split(":")[-1]).strip("_") or "policy"
    return Path("results") / f"{tag}-{datetime.now():%Y%m%d-%H%M%S}"


def run_task(task, policy, pending: list[tuple[int, int]], cfg: EvalConfig,
             on_records, progress: Progress | None = None, done_before: int = 0) -> list[dict]:
    """Run `pending` (seed, episode) pairs of one task in chunks of cfg.batch;
    `on_records(records)` is called as episodes finish.  Returns the records."""
    from agnostos_mjx.policies.planning import run_blocking

    tick = None if progress is None else (
        lambda n, partial=0.0, detail=None: progress.update(done_before + n, partial=partial,
                                                            detail=detail))
    return run_blocking(task_steps(task, policy, pending, cfg, on_records, tick))


def episode_records(task, policy, backend: str, part: Sequence[tuple[int, int]],
                    variations: np.ndarray, instructions: list[str], env, outcome: np.ndarray,
                    worlds: Iterable[int], wall_s: float, batch_size: int) -> list[dict]:
    """The records of the finished `worlds` of a batch (episodes.jsonl's lines)."""
    from agnostos_mjx.runtime.outcome import Outcome

    records = []
    for i in worlds:
        seed, episode = part[i]
        record = {
            "task": task.name, "split": task.split.value, "seed": int(seed),
            "episode": int(episode), "variation": int(variations[i]),
            "instruction": instructions[i], "policy": policy.name,
            "success": bool(outcome[i] == Outcome.SUCCESS),
            "outcome": Outcome(int(outcome[i])).label,
            "key_actions": int(env.key_actions[i]), "sim_steps": int(env.sim_steps[i]),
            "backend": backend, "batch_size": batch_size, "wall_s": round(wall_s, 4),
        }
        if hasattr(policy, "episode_info"):
            record["policy_info"] = policy.episode_info(int(i))
        records.append(record)
    return records


def task_steps(task, policy, pending: list[tuple[int, int]], cfg: EvalConfig, on_records,
               tick=None):
    """`run_task` as a generator that yields the futures the policy waits on (see
    PlanningPolicy.act_steps), so `run_interleaved` can simulate other tasks meanwhile.
    `tick(episodes_done, partial, detail)` reports progress within the task."""
    from agnostos_mjx.runtime.env import Episodes
    from agnostos_mjx.video import EpisodeVideos

    t0 = time.perf_counter()
    runner = Episodes(task, cfg.backend)
    videos = EpisodeVideos.for_task(cfg, runner)
    log.info("%s: %d episodes on backend %s (runner built in %.1f s)", task.name, len(pending),
             runner.backend_name, time.perf_counter() - t0)
    chunk = min(cfg.batch, len(pending))
    batches = -(-len(pending) // chunk)
    # MJX recompiles for every new batch shape: pad the last chunk there.
    pad = runner.backend_name != "native"
    out: list[dict] = []
    for b, start in enumerate(range(0, len(pending), chunk)):
        part = pending[start:start + chunk]
        t_batch = time.perf_counter()
        label = f"{task.name} batch {b + 1}/{batches}"
        out += yield from batch_steps(task, policy, runner, part, chunk if pad else len(part),
                                      cfg, on_records, tick, len(out), label, videos)
        rate = 100.0 * np.mean([r["success"] for r in out[-len(part):]])
        log.info("%s: batch of %d done in %.1f s, success %.0f%%", task.name, len(part),
                 time.perf_counter() - t_batch, rate)
    return out


def batch_steps(task, policy, runner, part: list[tuple[int, int]], size: int, cfg: EvalConfig,
                on_records, tick=None, done_before: int = 0, label: str = "", videos=None):
    """One batch of `task_steps`: `part` padded to `size` worlds.  Each episode goes to
    `on_records` as soon as its world finishes, so an interrupted run keeps it; `tick`
    also gets the finished key-action rounds of the unfinished episodes (`partial`)."""
    from agnostos_mjx.observation import act as policy_act
    from agnostos_mjx.runtime.outcome import Outcome

    n = len(part)
    run_part = part + [part[-1]] * (size - n)
    t_batch = time.perf_counter()
    keys = episode_keys(np.array([s for s, _ in run_part]), np.array([e for _, e in run_part]))
    variations = episode_variations(keys, task.num_variations, task.split.value, cfg.variations)
    instructions = [task.descriptions(int(v))[0] for v in variations]
    recorded = np.zeros(n, bool)
    out: list[dict] = []

    def record(env, outcome: np.ndarray) -> None:
        new = (outcome[:n] != Outcome.RUNNING) & ~recorded
        if new.any():
            records = episode_records(task, policy, runner.backend_name, part, variations,
                                      instructions, env, outcome, np.nonzero(new)[0],
                                      time.perf_counter() - t_batch, len(run_part))
            recorded[new] = True
            out.extend(records)
            on_records(records)

    def report(rounds: int) -> None:
        if tick is not None:
            tick(done_before + len(out), (n - recorded.sum()) * rounds / task.max_key_actions,
                 f"{label} key action {min(rounds + 1, task.max_key_actions)}"
                 f"/{task.max_key_actions}")

    report(0)
    env = runner.reset(keys, variations)
    if videos is not None:
        videos.start(env, part)
    try:
        if _accepts(policy.reset, "episode_seeds"):
            policy.reset(runner, env, instructions,
                         episode_seeds=[int(s) * 100_003 + int(e) for s, e in run_part])
        else:
            policy.reset(runner, env, instructions)
        for rounds in range(task.max_key_actions):
            if env.done.all():
                break
            if hasattr(policy, "act_steps"):
                actions = yield from policy.act_steps(runner, env)
            else:  # with observation= when the policy declares an ObservationSpec
                actions = policy_act(policy, runner, env)
            running = env.outcome == Outcome.RUNNING
            env, _ = runner.step(env, actions)
            if videos is not None:
                videos.capture(env)
            # A policy may say why a world got no action (bad LLM output, LLM error).
            reasons = getattr(policy, "end_reasons", None)
            if reasons is not None:
                ended = running & (env.outcome == Outcome.NO_ACTION) & (reasons > 0)
                env = env.replace(outcome=np.where(ended, reasons, env.outcome))
            record(env, np.where(env.done, env.outcome, Outcome.RUNNING))
            report(rounds + 1)
    except Exception:
        if cfg.fail_fast:
            raise
        log.exception("%s: the policy raised; running episodes of this batch end as "
                      "policy_error", task.name)
        env = env.replace(outcome=np.where(env.done, env.outcome, Outcome.POLICY_ERROR))
    record(env, np.where(env.done, env.outcome, Outcome.MAX_STEPS))
    if videos is not None:
        by_episode = {(r["seed"], r["episode"]): r for r in out}
        videos.write([by_episode[int(s), int(e)] for s, e in part])
    if tick is not None:
        tick(done_before + len(out))
    return out


def run_interleaved(jobs: Sequence, limit: int, on_done=None) -> list:
    """Run generators of futures (task_steps) with up to `limit` started at once: whenever
    one waits on a future, the next ready one runs.  Everything runs on the calling thread
    (physics and JAX stay single-threaded); only the awaited work (LLM requests) runs
    elsewhere.  `on_done(index, value)` is called as each finishes; returns the values."""
    pending = collections.deque(enumerate(jobs))
    active: list[list] = []  # [index, generator, future or None]
    values: list = [None] * len(jobs)
    try:
        while pending or active:
            while pending and len(active) < limit:
                active.append([*pending.popleft(), None])
            ready = [slot for slot in active if slot[2] is None or slot[2].done()]
            if not ready:
                concurrent.futures.wait([slot[2] for slot in active],
                                        return_when=concurrent.futures.FIRST_COMPLETED)
                continue
            for slot in ready:
                try:
                    slot[2] = slot[1].send(None)
                except StopIteration as stop:
                    values[slot[0]] = stop.value
                    active.remove(slot)
                    if on_done is not None:
                        on_done(slot[0], stop.value)
    except BaseException:  # Ctrl-C or a failure: cancel the work still waited on
        for _, steps, future in active:
            if future is not None:
                future.cancel()
            steps.close()
        raise
    return values


def evaluate(cfg: EvalConfig) -> dict:
    """Run the evaluation described by `cfg`, write the outputs, return results.json's dict."""
    from agnostos_mjx.physics import resolve_backend
    from agnostos_mjx.policies import make_policy
    from agnostos_mjx.tasks import parse_tasks

    try:
        tasks = parse_tasks(cfg.tasks)
    except KeyError as e:
        raise UsageError(e.args[0] if e.args else str(e)) from None
    if not tasks:
        raise UsageError(f"--tasks {cfg.tasks!r} selects no registered task")
    all_tasks = [t.name for t in tasks]
    if cfg.variations.isdigit():
        for t in tasks:
            if int(cfg.variations) >= t.num_variations:
                raise UsageError(f"--variations {cfg.variations}: {t.name} has variations "
                                 f"0..{t.num_variations - 1}")
    if cfg.video:
        from agnostos_mjx.video import VideoSpec

        try:
            VideoSpec.parse(cfg.video, cfg.video_cameras)
        except ValueError as e:
            raise UsageError(str(e)) from None
    out_dir = resolve_out(cfg, resolve_policy(cfg)[0])
    episodes_path = out_dir / EPISODES_FILE
    from agnostos_mjx import sharding

    sharding.configure(cfg.devices)
    tasks = tasks[cfg.process_id::cfg.num_processes]  # this process's share (all when one)
    if cfg.num_processes > 1:
        log.info("process %d of %d: %s", cfg.process_id, cfg.num_processes,
                 ", ".join(t.name for t in tasks) or "no task")
    if cfg.compare:
        from agnostos_mjx.paper import published

        try:
            published(cfg.compare)
        except KeyError as e:
            raise UsageError(f"--compare: {e.args[0]}") from None
    from agnostos_mjx.llm.client import LLMConfigError
    from agnostos_mjx.xicm.memory import MemoryFileError

    spec, kwargs, note = resolve_policy(cfg)
    if note:
        log.info("%s", note)
    try:
        policy = make_policy(spec, **kwargs)
    except (LLMConfigError, MemoryFileError) as e:
        raise UsageError(str(e)) from None
    except (KeyError, ImportError, ValueError, TypeError) as e:
        raise UsageError(f"cannot load policy {spec!r}: "
                         f"{e.args[0] if isinstance(e, KeyError) else e}") from None
    policy_name = getattr(policy, "name", cfg.policy)
    log.info("policy %s (%s.%s)", policy_name, type(policy).__module__, type(policy).__qualname__)
    backend = resolve_backend(cfg.backend, cfg.batch)

    all_records = repair_records(episodes_path) if cfg.resume else []
    if all_records:
        earlier = {r.get("policy") for r in all_records} - {None}
        if earlier and earlier != {policy_name}:
            log.warning("%s holds episodes of policy %s; continuing with %s", out_dir,
                        ", ".join(sorted(earlier)), policy_name)
    recorded = {record_key(r) for r in all_records}
    plan = {t.name: [(s, e) for s in cfg.seeds for e in range(cfg.episodes)
                     if (t.name, s, e) not in recorded] for t in tasks}
    total = sum(map(len, plan.values()))
    skipped = len(tasks) * len(cfg.seeds) * cfg.episodes - total
    log.info("%d tasks (%s), seeds %s, %d episodes each: %d to run%s", len(tasks),
             ", ".join(t.name for t in tasks), ",".join(map(str, cfg.seeds)), cfg.episodes,
             total, f", {skipped} already recorded" if skipped else "")

    started = datetime.now().isoformat(timespec="seconds")
    t0 = time.perf_counter()
    meta = {"config": asdict(cfg), "policy": {"spec": spec, "name": policy_name, "note": note,
                                              "class": f"{type(policy).__module__}."
                                                       f"{type(policy).__qualname__}"},
            "backend": backend, "versions": versions(), "started": started,
            "tasks": all_tasks}

    def selected() -> list[dict]:
        names, seeds = {t.name for t in tasks}, set(cfg.seeds)
        return [r for r in all_records if r["task"] in names and int(r["seed"]) in seeds
                and int(r["episode"]) < cfg.episodes]

    def write_results(final: bool) -> dict:
        extra = {}
        if hasattr(policy, "llm_report"):  # requests, retries, failures, what was sent
            extra["llm"] = policy.llm_report()
        if hasattr(policy, "remote_report"):  # requests to a policy server, failures
            extra["remote"] = policy.remote_report()
        return write_outputs(out_dir, meta, selected(), [t.name for t in tasks], cfg,
                             time.perf_counter() - t0, final, extra)

    def on_records(records: list[dict]) -> None:
        append_records(episodes_path, records)
        all_records.extend(records)

    todo = [t for t in tasks if plan[t.name]]
    # One policy copy per task running at once: copies share the heavy parts (LLM client,
    # memory, selector); reset() gives each its own per-episode state.
    overlap = cfg.overlap_tasks if hasattr(policy, "act_steps") else 1
    with progress_bar(total, enabled=not cfg.quiet) as progress:
        done = {t.name: (0, 0.0) for t in todo}

        def tick(name: str, n: int, partial: float = 0.0, detail: str | None = None) -> None:
            done[name] = (n, partial)
            progress.update(sum(d for d, _ in done.values()),
                            partial=sum(p for _, p in done.values()), detail=detail)

        run_cfg = replace(cfg, backend=backend)  # every task on the resolved one
        jobs = [task_steps(t, copy.copy(policy) if overlap > 1 else policy, plan[t.name], run_cfg,
                           on_records, functools.partial(tick, t.name)) for t in todo]
        run_interleaved(jobs, overlap, on_done=lambda i, _: write_results(final=False))
    return write_results(final=True)


def write_outputs(out_dir: Path, meta: dict, records: Sequence[dict], tasks: Sequence[str],
                  cfg: EvalConfig, wall_s: float, final: bool, extra: dict | None = None
                  ) -> dict:
    """results.json/.csv/.md (and .png when `final`) of `records` over `tasks` (their
    order); shared by a run and by `merge`.  Returns results.json's dict + markdown."""
    records = sorted(records, key=lambda r: (list(tasks).index(r["task"]), r["seed"],
                                             r["episode"]))
    summary = aggregate(records, tasks)
    out_dir.mkdir(parents=True, exist_ok=True)
    results = {**meta, "finished": datetime.now().isoformat(timespec="seconds") if final
               else None, "wall_s": round(wall_s, 2),
               "complete": len(records) == len(tasks) * len(cfg.seeds) * cfg.episodes,
               "summary": summary, "episodes": records, **(extra or {})}
    atomic_write(out_dir / "results.json", json.dumps(results, indent=1) + "\n")
    atomic_write(out_dir / "results.csv", format_csv(summary))
    title = (f"policy {meta['policy']['name']}, backend {meta['backend']}, seeds "
             f"{','.join(map(str, cfg.seeds))}, {cfg.episodes} episodes per seed")
    compare = None
    if cfg.compare:
        from agnostos_mjx.paper import published

        compare = published(cfg.compare)
    results["markdown"] = format_markdown(summary, title, compare, cfg.compare or "")
    atomic_write(out_dir / "results.md", results["markdown"])
    if final:
        from agnostos_mjx.report_plot import plot_summary

        plot_summary(summary, out_dir / "results.png", title, compare, cfg.compare or "")
    return results


def merge(out: Path) -> dict:
    """Merge the per-process runs in out/proc-* (``--num-processes``) into out's
    episodes.jsonl and results files, as one process running every task would have
    written them.  Returns results.json's dict; "complete" is false while episodes are
    missing (a process not yet finished); merging again later completes it."""
    parts = sorted(out.glob("proc-*/results.json"))
    if not parts:
        raise UsageError(f"{out}: no proc-*/results.json to merge (run the processes with "
                         f"--num-processes N --out {out} first)")
    metas = [json.loads(p.read_text(encoding="utf-8")) for p in parts]
    first = metas[0]
    cfg = EvalConfig(**{**first["config"], "process_id": 0, "num_processes": 1,
                        "coordinator": None, "merge": False, "resume": False})
    expected = first["config"]["num_processes"]
    missing = sorted(set(range(expected)) - {m["config"]["process_id"] for m in metas})
    if missing:
        log.warning("%s: no results yet from process %s", out, ", ".join(map(str, missing)))
    records: dict[tuple, dict] = {}
    for p in parts:
        for r in load_records(p.parent / EPISODES_FILE):
            records.setdefault(record_key(r), r)
    merged = list(records.values())
    meta = {k: first[k] for k in ("config", "policy", "backend", "versions", "tasks")}
    meta["config"] = asdict(cfg)
    meta["started"] = min(m["started"] for m in metas)
    meta["processes"] = [{"process_id": m["config"]["process_id"], "wall_s": m["wall_s"],
                          "finished": m["finished"], "episodes": len(m["episodes"])}
                         for m in metas]
    tasks = first["tasks"]
    atomic_write(out / EPISODES_FILE, _jsonl(sorted(merged, key=lambda r: (
        tasks.index(r["task"]), r["seed"], r["episode"]))))
    return write_outputs(out, meta, merged, tasks, cfg, max(m["wall_s"] for m in metas),
                         final=True)


def main(argv: Sequence[str] | None = None, guard: InterruptGuard | None = None) -> int:
    """Command-line entry point; returns the exit code (2 for usage errors, 1 for file
    errors, 130 when interrupted).  `guard` (the command line's) bounds Ctrl-C's delay."""
    argv = list(sys.argv[1:] if argv is None else argv)
    cfg = parse_config(argv)
    if cfg.merge:
        return merge_main(cfg)
    if cfg.local_processes > 1:
        return local_processes_main(cfg, argv)
    try:
        spec, _, note = resolve_policy(cfg)
    except Exception as e:  # e.g. an LLM URL without a model
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"agnostos_mjx.eval: policy {spec}" + (f" ({note})" if note else ""), flush=True)
    setup_logging(cfg.quiet)
    from agnostos_mjx.gpu import apply_memory_limit

    servers = {"remote": cfg.policy_url or os.environ.get("AGNOSTOS_POLICY_URL"),
               "xicm": cfg.llm_url or os.environ.get("AGNOSTOS_LLM_URL")}
    try:  # before JAX starts its backend
        apply_memory_limit(cfg.gpu_mem_fraction, [servers.get(spec)])
    except ValueError as e:
        print(f"error: --gpu-mem-fraction: {e}", file=sys.stderr)
        return 2
    if cfg.coordinator:  # before anything touches a device
        import jax

        jax.distributed.initialize(cfg.coordinator, cfg.num_processes, cfg.process_id)
    out_dir = None
    try:
        out_dir = resolve_out(cfg, spec)
        existed = out_dir.exists()
        message = functools.partial(interrupted_message, out_dir, argv, Path(cfg.out))
        if guard is not None:
            guard.message = message
        results = evaluate(cfg)
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        if guard is not None:
            guard.announce()
        else:
            print(message(), file=sys.stderr)
        return 130
    except OSError as e:  # e.g. the disk filled up
        print(f"error: {e}", file=sys.stderr)
        return 1
    finally:
        if out_dir is not None and not existed:
            remove_empty_dirs(out_dir)  # a run that failed before its first result
    print(results["markdown"], end="", flush=True)
    log.info("wrote %s", cfg.out)
    return max(llm_summary(results.get("llm")), remote_summary(results.get("remote")))


def local_processes_main(cfg: EvalConfig, argv: Sequence[str]) -> int:
    """``--local-processes N``: the run as N processes on this machine, then merged."""
    from agnostos_mjx import local_processes

    setup_logging(cfg.quiet)
    if cfg.out is None:
        print("error: --local-processes needs --out DIR, the folder the processes share",
              file=sys.stderr)
        return 2
    if cfg.num_processes > 1 or cfg.coordinator:
        print("error: --local-processes starts its own processes; drop --num-processes, "
              "--process-id and --coordinator", file=sys.stderr)
        return 2
    return local_processes.run(argv, cfg.local_processes, Path(cfg.out), cfg.quiet,
                               cfg.gpu_mem_fraction)


def merge_main(cfg: EvalConfig) -> int:
    """``--merge``: write --out's results from its proc-* folders and print the table."""
    setup_logging(cfg.quiet)
    try:
        if cfg.out is None:
            raise UsageError("--merge needs --out DIR, the folder the processes shared")
        results = merge(Path(cfg.out))
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(results["markdown"], end="", flush=True)
    if not results["complete"]:
        log.warning("%s: episodes are missing (a process has not finished); merge again "
                    "once it has", cfg.out)
    return 0


def remote_summary(report: dict | None) -> int:
    """Print the requests to the policy server and their failures; the exit code: 3 when
    more than half of the requests failed (the table then measures the failures)."""
    if not report:
        return 0
    failed = sum(report["failures"].values())
    causes = ", ".join(f"{k}: {v}" for k, v in report["failures"].items()) or "none"
    print(f"policy server {report['url']}: {report['requests']} requests, {failed} failed "
          f"({causes}), mean round trip {report['mean_round_trip_ms']:.1f} ms", flush=True)
    return 3 if failed * 2 > report["requests"] else 0


def llm_summary(report: dict | None) -> int:
    """Print the run's LLM requests, retries and failures by cause; the exit code: 3
    when more than half of the requests failed (the table then measures the failures)."""
    from agnostos_mjx.llm.stats import mostly_failed, summary_lines

    if not report:
        return 0
    print("\n".join(summary_lines(report)), flush=True)
    return 3 if mostly_failed(report) else 0


if __name__ == "__main__":
    with InterruptGuard() as _guard:
        try:
            _code = main(guard=_guard)
        except KeyboardInterrupt:  # outside the run (printing the table, say)
            _guard.announce()
            _code = 130
    if _code == 130:
        hard_exit(_code)  # threads in native code must not delay the exit
    sys.exit(_code)
