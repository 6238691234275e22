"""From episode records to the reported numbers: results.json, .csv, .md and .png.

Per task and seed a success rate; per task the mean and population std (ddof=0) over
seeds; Level-1 / Level-2 / All the mean over that group's tasks per seed, then mean and
population std over seeds (X-ICM's protocol, spec sections 6 and 9).

results.csv has one row per task, then one per group (Level-1, Level-2, All = the unseen
tasks, Seen), with these columns (success rates in percent)::

    name, kind (task | group), split (task rows; empty for groups),
    tasks (1, or the group's task count), seeds, episodes, successes,
    success_pct_mean, success_pct_std (population std over seeds),
    success_pct_ci_low, success_pct_ci_high (Wilson 95 % interval of the pooled episodes:
    with 75 episodes a task's rate is known to about +-10 points, which the std over 3
    seeds does not show),
    success_pct_seed<S> (one column per seed; empty where a task lacks it),
    mean_key_actions, mean_sim_steps (task rows),
    outcome_<label> (episode counts per outcome: success, max_steps, ...)

so ``pandas.read_csv`` or ``csv.DictReader`` load it without parsing strings.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import sys
from collections import Counter, defaultdict
from collections.abc import Iterable, Sequence
from dataclasses import asdict
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from agnostos_mjx.evaluation.config import EvalConfig, UsageError
from agnostos_mjx.evaluation.protocol import GROUPS, group_label
from agnostos_mjx.evaluation.records import EPISODES_FILE, jsonl, load_records, record_key
from agnostos_mjx.infra.cli import atomic_write
from agnostos_mjx.infra.stats import wilson_interval

log = logging.getLogger("agnostos_mjx.eval")

CSV_COLUMNS = ("name", "kind", "split", "tasks", "seeds", "episodes", "successes",
               "success_pct_mean", "success_pct_std", "success_pct_ci_low", "success_pct_ci_high",
               "mean_key_actions", "mean_sim_steps")


# ---- aggregation (pure) ------------------------------------------------------------------
def _mean_std(values: Iterable[float]) -> tuple[float, float]:
    v = np.asarray(list(values), np.float64)
    return float(v.mean()), float(v.std())  # population std, as X-ICM's np.std


def wilson_pct(successes: int, episodes: int) -> list[float]:
    """Wilson 95 % interval of a success count, in percent (stats.wilson_interval)."""
    low, high = wilson_interval(successes, episodes)
    return [round(100.0 * low, 2), round(100.0 * high, 2)]


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
            "successes": int(outcomes.get("success", 0)),
            "wilson95": wilson_pct(int(outcomes.get("success", 0)), len(recs)),
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
        successes = sum(per_task[n]["successes"] for n in members)
        episodes = sum(per_task[n]["episodes"] for n in members)
        groups[group] = {"tasks": members, "success_per_seed": per_seed,
                         "success_mean": mean, "success_std": std, "episodes": episodes,
                         "successes": successes, "wilson95": wilson_pct(successes, episodes)}
    return {"tasks": per_task, "groups": groups}


# ---- formats -----------------------------------------------------------------------------
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
    ci = lambda item: "[{:.1f}, {:.1f}]".format(*item["wilson95"])  # noqa: E731
    lines += [f"| task | split | success % mean (std){extra} | 95% CI (Wilson) | key actions "
              "| sim steps | failures |", f"|---|---|---{sep}|---|---|---|---|"]
    for name, t in summary["tasks"].items():
        lines.append(f"| {name} | {t['split']} | {t['success_mean']:.1f} ({t['success_std']:.1f})"
                     f"{ref(name)} | {ci(t)} | {t['mean_key_actions']:.2f} "
                     f"| {t['mean_sim_steps']:.0f} | {_failures(t['outcomes'])} |")
    if summary["groups"]:
        lines += ["", f"| group | tasks | success % mean (std){extra} | 95% CI (Wilson, pooled "
                  "episodes) | per seed |", f"|---|---|---{sep}|---|---|"]
        for name, g in summary["groups"].items():
            per_seed = ", ".join(f"{s}: {v:.1f}" for s, v in g["success_per_seed"].items())
            lines.append(f"| {group_label(name)} | {len(g['tasks'])} | {g['success_mean']:.1f} "
                         f"({g['success_std']:.1f}){ref(name)} | {ci(g)} | {per_seed} |")
    return "\n".join(lines) + "\n"


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
            "success_pct_ci_low": item["wilson95"][0],
            "success_pct_ci_high": item["wilson95"][1],
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


# ---- files -------------------------------------------------------------------------------
def write_outputs(out_dir: Path, meta: dict, records: Sequence[dict], tasks: Sequence[str],
                  cfg: EvalConfig, wall_s: float, final: bool, extra: dict | None = None,
                  plot: bool = True) -> dict:
    """results.json/.csv/.md (and .png when `final` and `plot`) of `records` over `tasks`
    (their order); shared by a run and by `merge`.  Returns results.json's dict +
    markdown."""
    records = sorted(records, key=lambda r: (list(tasks).index(r["task"]), r["seed"],
                                             r["episode"]))
    summary = aggregate(records, tasks)
    seeds, episodes, compare_with = cfg.protocol.seeds, cfg.protocol.episodes, cfg.run.compare
    out_dir.mkdir(parents=True, exist_ok=True)
    results = {**meta, "finished": datetime.now().isoformat(timespec="seconds") if final
               else None, "wall_s": round(wall_s, 2),
               "complete": len(records) == len(tasks) * len(seeds) * episodes,
               "summary": summary, "episodes": records, **(extra or {})}
    atomic_write(out_dir / "results.json", json.dumps(results, indent=1) + "\n")
    atomic_write(out_dir / "results.csv", format_csv(summary))
    title = (f"policy {meta['policy']['name']}, backend {meta['backend']}, seeds "
             f"{','.join(map(str, seeds))}, {episodes} episodes per seed")
    compare = None
    if compare_with:
        from agnostos_mjx.evaluation.paper import published

        compare = published(compare_with)
    results["markdown"] = format_markdown(summary, title, compare, compare_with or "")
    atomic_write(out_dir / "results.md", results["markdown"])
    if final and plot:
        from agnostos_mjx.evaluation.report_plot import plot_summary

        plot_summary(summary, out_dir / "results.png", title, compare, compare_with or "")
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
    # Each "config" nested by part, or flat as written before the parts.
    configs = [EvalConfig.from_dict(m["config"]) for m in metas]
    cfg = configs[0].with_options(process_id=0, num_processes=1, coordinator=None,
                                  merge=False, resume=False)
    expected = configs[0].run.num_processes
    missing = sorted(set(range(expected)) - {c.run.process_id for c in configs})
    if missing:
        log.warning("%s: no results yet from process %s", out, ", ".join(map(str, missing)))
    records: dict[tuple, dict] = {}
    for p in parts:
        for r in load_records(p.parent / EPISODES_FILE):
            records.setdefault(record_key(r), r)
    merged = list(records.values())
    meta = {k: first.get(k) for k in ("config", "policy", "backend", "renderer", "versions",
                                      "tasks")}
    meta["config"] = asdict(cfg)
    meta["started"] = min(m["started"] for m in metas)
    meta["processes"] = [{"process_id": c.run.process_id, "wall_s": m["wall_s"],
                          "finished": m["finished"], "episodes": len(m["episodes"])}
                         for c, m in zip(configs, metas)]
    failed = {t: e for m in metas for t, e in m.get("failed_tasks", {}).items()}
    tasks = first["tasks"]
    atomic_write(out / EPISODES_FILE, jsonl(sorted(merged, key=lambda r: (
        tasks.index(r["task"]), r["seed"], r["episode"]))))
    return write_outputs(out, meta, merged, tasks, cfg, max(m["wall_s"] for m in metas),
                         final=True, extra={"failed_tasks": failed} if failed else None)


def merge_main(out: str | None) -> int:
    """``--merge``: write `out`'s results from its proc-* folders and print the table;
    the exit code (2: nothing to merge)."""
    try:
        if out is None:
            raise UsageError("--merge needs --out DIR, the folder the processes shared")
        results = merge(Path(out))
    except UsageError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(results["markdown"], end="", flush=True)
    if not results["complete"]:
        log.warning("%s: episodes are missing (a process has not finished); merge again "
                    "once it has", out)
    return max(policy_error_summary(results), failed_task_summary(results))


def failed_task_summary(results: dict) -> int:
    """Name the tasks that raised (their error is in results.json's ``failed_tasks`` and
    the traceback in the log); the exit code: 1 when any did."""
    failed = results.get("failed_tasks") or {}
    for task, error in failed.items():
        print(f"error: task {task} failed: {error}", file=sys.stderr, flush=True)
    if failed:
        print(f"error: {len(failed)} task(s) failed and the others finished; --resume with "
              "the same --out runs the missing episodes again", file=sys.stderr, flush=True)
    return 1 if failed else 0


# ---- requests to servers -----------------------------------------------------------------
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


def policy_error_summary(results: dict) -> int:
    """Say how many episodes ended as policy_error (the policy raised: a crash, not a
    decision, e.g. out of GPU memory); the exit code: 3 when more than half did, since
    the table then measures the crash (seen: 16 reference-VLA processes on one GPU, every
    episode out of memory, a table of zeros with exit 0)."""
    episodes = results.get("episodes") or []
    failed = sum(r.get("outcome") == "policy_error" for r in episodes)
    if not failed:
        return 0
    text = (f"{failed} of {len(episodes)} episodes ended as policy_error: the policy raised "
            f"(the traceback is in the log{'s' if results.get('processes') else ''}; "
            "--fail-fast stops at the first)")
    if failed * 2 > len(episodes):
        print(f"error: {text}; the table measures that failure, not the policy",
              file=sys.stderr, flush=True)
        return 3
    log.warning("%s", text)
    return 0


def request_summaries(results: dict) -> int:
    """Print the requests of a run's policy (LLM, policy server); the exit code."""
    return max(llm_summary(results.get("llm")), remote_summary(results.get("remote")))
