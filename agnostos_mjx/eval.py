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

Outputs in `--out`: episodes.jsonl (one record per episode, rewritten
atomically after every batch, the basis of --resume), results.json (config,
versions, aggregates and the episode records), results.csv (a row per task)
and results.md (the table that is also printed).

Examples::

    python -m agnostos_mjx.eval                                   # oracle, unseen tasks
    python -m agnostos_mjx.eval --tasks lamp_on --seeds 0 --episodes 4
    python -m agnostos_mjx.eval --policy my_pkg.agent:MyPolicy --policy-arg model=\"qwen\"
    python -m agnostos_mjx.eval --out results/run1 --resume      # finish an interrupted run
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
import re
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
    Progress,
    atomic_write,
    progress_bar,
    setup_logging,
    versions,
)

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
    llm_concurrency: int = 64
    overlap_tasks: int = 3
    selection: str = "auto"
    num_demos: int = 18
    ddim_steps: int | None = None
    memory: str | None = None
    compare: str | None = None
    video: str | None = None
    video_cameras: str | None = None


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
                   help="output directory; default results/<policy>-<timestamp>")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out: skip episodes already in episodes.jsonl")
    p.add_argument("--fail-fast", action="store_true",
                   help="re-raise policy exceptions instead of recording policy_error")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar, warnings-only logging (the table is still printed)")
    p.add_argument("--video", default=None, metavar="first:N|failures[:N]",
                   help="MP4 per episode in <out>/videos for episodes 0..N-1 of each task and "
                        "seed, or the failures (see agnostos_mjx/video.py; needs PyAV)")
    p.add_argument("--video-cameras", default=None,
                   help="comma-separated cameras side by side (default front,overhead,wrist)")
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
    llm.add_argument("--llm-concurrency", type=_positive_int, default=64,
                     help="LLM requests in flight at once")
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
                      llm_concurrency=a.llm_concurrency, overlap_tasks=a.overlap_tasks,
                      selection=a.selection,
                      num_demos=a.num_demos, ddim_steps=a.ddim_steps, memory=a.memory,
                      compare=a.compare, video=a.video, video_cameras=a.video_cameras)


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
                      concurrency=cfg.llm_concurrency, num_demos=cfg.num_demos)
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


def format_csv(summary: dict) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["task", "split", "episodes", "seeds", "success_mean", "success_std",
                "success_per_seed", "mean_key_actions", "mean_sim_steps", "outcomes"])
    for name, t in summary["tasks"].items():
        w.writerow([name, t["split"], t["episodes"], " ".join(map(str, t["seeds"])),
                    f"{t['success_mean']:.4f}", f"{t['success_std']:.4f}",
                    " ".join(f"{s}:{v:.4f}" for s, v in t["success_per_seed"].items()),
                    f"{t['mean_key_actions']:.4f}", f"{t['mean_sim_steps']:.2f}",
                    " ".join(f"{k}:{v}" for k, v in t["outcomes"].items())])
    return buf.getvalue()


# ---------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------
def load_records(path: Path) -> list[dict]:
    """Episode records of an earlier run (unreadable lines are skipped with a warning)."""
    records = []
    if not path.exists():
        return records
    for i, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            log.warning("%s:%d is not valid JSON; ignored", path, i)
    return records


def _jsonl(records: Sequence[dict]) -> str:
    return "".join(json.dumps(r, sort_keys=False) + "\n" for r in records)


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
             on_batch, progress: Progress | None = None, done_before: int = 0) -> list[dict]:
    """Run `pending` (seed, episode) pairs of one task in chunks of cfg.batch;
    `on_batch(records)` is called after every chunk.  Returns the records."""
    from agnostos_mjx.policies.planning import run_blocking

    tick = None if progress is None else (lambda n: progress.update(done_before + n))
    return run_blocking(task_steps(task, policy, pending, cfg, on_batch, tick))


def task_steps(task, policy, pending: list[tuple[int, int]], cfg: EvalConfig, on_batch,
               tick=None):
    """`run_task` as a generator that yields the futures the policy waits on (see
    PlanningPolicy.act_steps), so `run_interleaved` can simulate other tasks meanwhile.
    `tick(episodes_done)` reports progress within the task."""
    from agnostos_mjx.episode import Episodes, Outcome
    from agnostos_mjx.observation import act as policy_act
    from agnostos_mjx.video import EpisodeVideos

    t0 = time.perf_counter()
    runner = Episodes(task, cfg.backend)
    videos = EpisodeVideos.for_task(cfg, runner)
    log.info("%s: %d episodes on backend %s (runner built in %.1f s)", task.name, len(pending),
             runner.backend_name, time.perf_counter() - t0)
    chunk = min(cfg.batch, len(pending))
    # MJX recompiles for every new batch shape: pad the last chunk there.
    pad = runner.backend_name != "native"
    out: list[dict] = []
    for start in range(0, len(pending), chunk):
        part = pending[start:start + chunk]
        n = len(part)
        run_part = part + [part[-1]] * (chunk - n) if pad else part
        seeds = np.array([s for s, _ in run_part])
        eps = np.array([e for _, e in run_part])
        t_batch = time.perf_counter()
        keys = episode_keys(seeds, eps)
        variations = episode_variations(keys, task.num_variations, task.split.value,
                                        cfg.variations)
        instructions = [task.descriptions(int(v))[0] for v in variations]
        env = runner.reset(keys, variations)
        videos.start(env, part)
        try:
            if _accepts(policy.reset, "episode_seeds"):
                policy.reset(runner, env, instructions,
                             episode_seeds=[int(s) * 100_003 + int(e) for s, e in run_part])
            else:
                policy.reset(runner, env, instructions)
            for _ in range(task.max_key_actions):
                if env.done.all():
                    break
                if hasattr(policy, "act_steps"):
                    actions = yield from policy.act_steps(runner, env)
                else:  # with observation= when the policy declares an ObservationSpec
                    actions = policy_act(policy, runner, env)
                running = env.outcome == Outcome.RUNNING
                env, _ = runner.step(env, actions)
                videos.capture(env)
                # A policy may say why a world got no action (bad LLM output, LLM error).
                reasons = getattr(policy, "end_reasons", None)
                if reasons is not None:
                    ended = running & (env.outcome == Outcome.NO_ACTION) & (reasons > 0)
                    env.outcome = np.where(ended, reasons, env.outcome)
                if tick is not None:
                    tick(len(out) + int(env.done[:n].sum()))
        except Exception:
            if cfg.fail_fast:
                raise
            log.exception("%s: the policy raised; running episodes of this batch end as "
                          "policy_error", task.name)
            env.outcome = np.where(env.done, env.outcome, Outcome.POLICY_ERROR)
        outcome = np.where(env.done, env.outcome, Outcome.MAX_STEPS)
        wall = time.perf_counter() - t_batch
        records = []
        for i, (seed, episode) in enumerate(part):
            records.append({
                "task": task.name, "split": task.split.value, "seed": int(seed),
                "episode": int(episode), "variation": int(variations[i]),
                "instruction": instructions[i], "policy": policy.name,
                "success": bool(outcome[i] == Outcome.SUCCESS),
                "outcome": Outcome(int(outcome[i])).label,
                "key_actions": int(env.key_actions[i]), "sim_steps": int(env.sim_steps[i]),
                "backend": runner.backend_name, "batch_size": len(run_part),
                "batch_wall_s": round(wall, 4),
            })
            if hasattr(policy, "episode_info"):
                records[-1]["policy_info"] = policy.episode_info(i)
        out += records
        videos.write(records)
        on_batch(records)
        if tick is not None:
            tick(len(out))
        rate = 100.0 * np.mean([r["success"] for r in records])
        log.info("%s: batch of %d done in %.1f s, success %.0f%%", task.name, n, wall, rate)
    return out


def run_interleaved(jobs: Sequence, limit: int, on_done=None) -> list:
    """Run generators of futures (task_steps) with up to `limit` started at once: whenever
    one waits on a future, the next ready one runs.  Everything runs on the calling thread
    (physics and JAX stay single-threaded); only the awaited work (LLM requests) runs
    elsewhere.  `on_done(index, value)` is called as each finishes; returns the values."""
    pending = collections.deque(enumerate(jobs))
    active: list[list] = []  # [index, generator, future or None]
    values: list = [None] * len(jobs)
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
    out_dir = Path(cfg.out) if cfg.out else _default_out(cfg.policy)
    cfg.out = str(out_dir)
    episodes_path = out_dir / EPISODES_FILE
    if episodes_path.exists() and not cfg.resume:
        raise UsageError(f"{episodes_path} exists; pass --resume to continue that run or "
                         f"choose another --out")
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

    out_dir.mkdir(parents=True, exist_ok=True)
    all_records = load_records(episodes_path) if cfg.resume else []
    if all_records:
        earlier = {r.get("policy") for r in all_records} - {None}
        if earlier and earlier != {policy_name}:
            log.warning("%s holds episodes of policy %s; continuing with %s", out_dir,
                        ", ".join(sorted(earlier)), policy_name)
    recorded = {(r["task"], int(r["seed"]), int(r["episode"])) for r in all_records}
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
            "backend": backend, "versions": versions(), "started": started}

    def selected() -> list[dict]:
        names, seeds = {t.name for t in tasks}, set(cfg.seeds)
        return [r for r in all_records if r["task"] in names and int(r["seed"]) in seeds
                and int(r["episode"]) < cfg.episodes]

    def write_results(final: bool) -> dict:
        records = sorted(selected(), key=lambda r: ([t.name for t in tasks].index(r["task"]),
                                                    r["seed"], r["episode"]))
        summary = aggregate(records, [t.name for t in tasks])
        results = {**meta, "finished": datetime.now().isoformat(timespec="seconds") if final
                   else None, "wall_s": round(time.perf_counter() - t0, 2),
                   "complete": len(records) == len(tasks) * len(cfg.seeds) * cfg.episodes,
                   "summary": summary, "episodes": records}
        atomic_write(out_dir / "results.json", json.dumps(results, indent=1) + "\n")
        atomic_write(out_dir / "results.csv", format_csv(summary))
        title = (f"policy {policy_name}, backend {backend}, seeds "
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

    def on_batch(records: list[dict]) -> None:
        all_records.extend(records)
        atomic_write(episodes_path, _jsonl(all_records))

    todo = [t for t in tasks if plan[t.name]]
    # One policy copy per task running at once: copies share the heavy parts (LLM client,
    # memory, selector); reset() gives each its own per-episode state.
    overlap = cfg.overlap_tasks if hasattr(policy, "act_steps") else 1
    with progress_bar(total, enabled=not cfg.quiet) as progress:
        done = {t.name: 0 for t in todo}

        def tick(name: str, n: int) -> None:
            done[name] = n
            progress.update(sum(done.values()))

        run_cfg = replace(cfg, backend=backend)  # every task on the resolved one
        jobs = [task_steps(t, copy.copy(policy) if overlap > 1 else policy, plan[t.name], run_cfg,
                           on_batch, functools.partial(tick, t.name)) for t in todo]
        run_interleaved(jobs, overlap, on_done=lambda i, _: write_results(final=False))
    return write_results(final=True)


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit code (2 for usage errors)."""
    cfg = parse_config(argv)
    try:
        spec, _, note = resolve_policy(cfg)
    except Exception as e:  # e.g. an LLM URL without a model
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"agnostos_mjx.eval: policy {spec}" + (f" ({note})" if note else ""), flush=True)
    setup_logging(cfg.quiet)
    try:
        results = evaluate(cfg)
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"\ninterrupted; finished batches are in {cfg.out}; rerun with --resume",
              file=sys.stderr)
        return 130
    print(results["markdown"], end="", flush=True)
    log.info("wrote %s", cfg.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
